"""The benchmark suite's command line: does unsupervised meta-learning make RL faster here?

    python benchmarks/suite.py profile=tiny                      # every method at toy budgets (~140 CPU-seconds)
    python benchmarks/suite.py profile=quick                     # point_nav, reduced budgets, minutes on 2 cores
    python benchmarks/suite.py profile=reference envs=[point_nav]  # the reference code's settings
    python benchmarks/suite.py profile=quick launcher.ray_address=auto   # jobs as Ray tasks on a cluster
    python benchmarks/suite.py profile=quick device=auto         # pre-training and meta-test on a GPU if there is one

A Hydra main over :func:`umrl.suite.run_suite` (what a suite runs and reports is documented in :mod:`umrl.suite`);
every value is a config override (``benchmarks/config/``: ``suite.yaml`` and the ``profile/`` presets).
"""
from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

from umrl.process import tune_process
from umrl.suite import run_suite
from umrl.trainers.config import register_help_text


@hydra.main(version_base="1.3", config_path="config", config_name="suite")
def main(cfg: DictConfig) -> None:
    tune_process(num_threads=cfg.launcher.threads)  # as each worker (umrl.launch): jobs of workers=0 run here
    run_suite(cfg, log=logging.getLogger(__name__).info)  # also into hydra/suite.log


if __name__ == "__main__":
    register_help_text(Path(__file__).resolve().parent / "config")
    main()
