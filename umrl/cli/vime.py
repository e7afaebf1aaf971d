"""``umrl vime`` (``python recipes/vime.py``): VIME pre-training, TRPO on the information-gain bonus alone (the
VIME-init baseline's policy).

    umrl vime env.name=point_nav                     # 30 iterations of 40 x 100 steps
    umrl vime env.name=half_cheetah logger.backend=csv
    umrl vime env.name=point_nav resume=true         # continue from the latest checkpoint

A Hydra app over :func:`umrl.trainers.vime.train`: the config in ``umrl/configs/vime.yaml`` (``--cfg job`` prints the
resolved one), process tuning (:func:`umrl.process.tune_process`: ``num_threads``), then training; logging,
checkpoints and resumption are the library's.
"""
from __future__ import annotations

import logging

import hydra
from omegaconf import DictConfig

from umrl.cli.errors import refuses_bad_config
from umrl.cli.recipe import train_and_summarize
from umrl.trainers.config import CONFIG_DIR
from umrl.trainers.vime import train

__all__ = ["CONFIG_DIR", "CONFIG_NAME", "main"]  # what umrl.cli.run reads

CONFIG_NAME = "vime"
SUMMARY_KEYS = ("train/frames", "bonus/info_gain_median", "dynamics/heldout_log_likelihood", "coverage/cumulative_area",
                "coverage/cumulative_velocity_range")
"""What the command line prints when a run ends (every metric is in the logs)."""


@hydra.main(version_base="1.3", config_path="pkg://umrl.configs", config_name=CONFIG_NAME)
@refuses_bad_config
def main(cfg: DictConfig) -> None:
    train_and_summarize("vime", cfg, train, SUMMARY_KEYS, logging.getLogger(__name__))
