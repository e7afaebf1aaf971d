"""``umrl suite`` (``python benchmarks/suite.py``): does unsupervised meta-learning make RL faster here?

    umrl suite profile=tiny                      # every method at toy budgets (~140 CPU-seconds)
    umrl suite profile=quick                     # point_nav, reduced budgets, minutes on 2 cores
    umrl suite profile=reference envs=[point_nav]  # the reference code's settings
    umrl suite profile=quick launcher.ray_address=auto   # jobs as Ray tasks on a cluster
    umrl suite profile=quick device=auto         # pre-training and meta-test on a GPU if there is one

A Hydra app over :func:`umrl.suite.run_suite` (what a suite runs and reports is documented in :mod:`umrl.suite`);
every value is a config override (:data:`umrl.suite.CONFIG_DIR`, ``umrl/suite/config/``: ``suite.yaml`` and the
``profile/`` presets).
"""
from __future__ import annotations

import logging

import hydra
from omegaconf import DictConfig

from umrl.cli.errors import refuses_bad_config
from umrl.process import tune_process
from umrl.suite import CONFIG_DIR, run_suite

__all__ = ["CONFIG_DIR", "CONFIG_NAME", "main"]  # what umrl.cli.run reads

CONFIG_NAME = "suite"


@hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name=CONFIG_NAME)
@refuses_bad_config
def main(cfg: DictConfig) -> None:
    tune_process(num_threads=cfg.launcher.threads)  # as each worker (umrl.launch): jobs of workers=0 run here
    run_suite(cfg, log=logging.getLogger(__name__).info)  # also into hydra/suite.log
