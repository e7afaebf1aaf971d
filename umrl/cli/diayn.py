"""``umrl diayn`` (``python recipes/diayn.py``): DIAYN on a reward-free env, skill-conditioned SAC and a skill
discriminator (the UMRL task proposal).

    umrl diayn env.name=point_nav                       # 50 skills, docs/protocol.md defaults
    umrl diayn env.name=half_cheetah logger.backend=csv
    umrl diayn env.name=point_nav resume=true           # continue from the latest checkpoint
    umrl diayn env.name=half_cheetah seeds=[0,1,2]      # three seeds in one program

A Hydra app over :func:`umrl.trainers.diayn.train`: the config in ``umrl/configs/diayn.yaml`` (``--cfg job`` prints
the resolved one), process tuning (:func:`umrl.process.tune_process`: ``num_threads``), then training; logging,
checkpoints and resumption are the library's.
"""
from __future__ import annotations

import logging

import hydra
from omegaconf import DictConfig

from umrl.cli.errors import refuses_bad_config
from umrl.cli.recipe import train_and_summarize
from umrl.configs.diayn import resolve_seeds
from umrl.trainers.config import CONFIG_DIR
from umrl.trainers.diayn import train

__all__ = ["CONFIG_DIR", "CONFIG_NAME", "main"]  # what umrl.cli.run reads

CONFIG_NAME = "diayn"
SUMMARY_KEYS = ("train/frames", "train/updates", "train/discriminator_accuracy", "eval/final_state_accuracy",
                "eval/random_final_state_accuracy")
"""What the command line prints when a run ends, for each seed (every metric is in the logs)."""


@hydra.main(version_base="1.3", config_path="pkg://umrl.configs", config_name=CONFIG_NAME)
@refuses_bad_config
def main(cfg: DictConfig) -> None:
    keys = [f"{prefix}{key}" for prefix in ["", *(f"seed{s}/" for s in resolve_seeds(cfg))] for key in SUMMARY_KEYS]
    result = train_and_summarize("diayn", cfg, train, keys, logging.getLogger(__name__))
    logging.getLogger(__name__).info("skills (one folder per seed): " + ", ".join(result["runs"]))
