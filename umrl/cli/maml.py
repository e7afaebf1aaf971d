"""``umrl maml`` (``python recipes/maml.py``): MAML meta-training on proposed tasks, UML-DIAYN, UML-random or the
oracle task family.

    umrl maml proposal=oracle                                     # hand-designed goals (upper bound)
    umrl maml proposal=diayn diayn_checkpoint=outputs/diayn/point_nav/seed0
    umrl maml proposal=random resume=true                         # continue from the latest checkpoint

A Hydra app over :func:`umrl.trainers.maml.train` (:class:`~umrl.trainers.maml.MAMLTrainer`): the config in
``umrl/configs/maml.yaml`` (``--cfg job`` prints the resolved one), process tuning (:func:`umrl.process.tune_process`:
``num_threads``), then training; logging, checkpoints and resumption are the library's.
"""
from __future__ import annotations

import logging

import hydra
from omegaconf import DictConfig

from umrl.cli.errors import refuses_bad_config
from umrl.cli.recipe import train_and_summarize
from umrl.trainers.config import CONFIG_DIR
from umrl.trainers.maml import train

__all__ = ["CONFIG_DIR", "CONFIG_NAME", "main"]  # what umrl.cli.run reads

CONFIG_NAME = "maml"
SUMMARY_KEYS = ("iteration", "train/return_pre", "train/return_post", "train/kl", "time/learn_s")
"""What the command line prints when a run ends (every metric is in the logs)."""


@hydra.main(version_base="1.3", config_path="pkg://umrl.configs", config_name=CONFIG_NAME)
@refuses_bad_config
def main(cfg: DictConfig) -> None:
    train_and_summarize("maml", cfg, train, SUMMARY_KEYS, logging.getLogger(__name__))
