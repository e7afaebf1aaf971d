"""DIAYN on a reward-free env: skill-conditioned SAC + a skill discriminator (the UMRL task proposal).

    python recipes/diayn.py env.name=point_nav                       # 50 skills, docs/protocol.md defaults
    python recipes/diayn.py env.name=half_cheetah logger.backend=csv
    python recipes/diayn.py env.name=point_nav resume=true           # continue from the latest checkpoint
    python recipes/diayn.py env.name=half_cheetah seeds=[0,1,2]      # three seeds in one program

A Hydra main over :func:`umrl.trainers.diayn.train`: configs in ``umrl/configs/diayn.yaml`` (``--cfg job`` prints the resolved
one), process tuning (:func:`umrl.process.tune_process`: ``num_threads``), then training; logging, checkpoints and
resumption are the library's (:mod:`umrl.trainers.diayn`).
"""
from __future__ import annotations

import logging

import hydra
from omegaconf import DictConfig

from umrl.configs.diayn import resolve_seeds
from umrl.process import tune_process
from umrl.runtime import log_location, run_summary
from umrl.trainers.config import register_help_text
from umrl.trainers.diayn import train

SUMMARY_KEYS = ("train/frames", "train/updates", "train/discriminator_accuracy", "eval/final_state_accuracy",
                "eval/random_final_state_accuracy")
"""What the command line prints when a run ends, for each seed (every metric is in the logs)."""


@hydra.main(version_base="1.3", config_path="pkg://umrl.configs", config_name="diayn")
def main(cfg: DictConfig) -> None:
    tune_process(num_threads=cfg.num_threads)  # this process is the run's: umrl's process-wide settings
    result = train(cfg)
    keys = [f"{prefix}{key}" for prefix in ["", *(f"seed{s}/" for s in resolve_seeds(cfg))] for key in SUMMARY_KEYS]
    logging.getLogger(__name__).info(run_summary(f"diayn {cfg.env.name} finished", result, keys,
                                                 log_location(cfg.logger, cfg.output_dir)))
    logging.getLogger(__name__).info("skills (one folder per seed): " + ", ".join(result["runs"]))


if __name__ == "__main__":
    register_help_text()
    main()
