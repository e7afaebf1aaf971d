"""MAML meta-training on proposed tasks: UML-DIAYN, UML-random, or the oracle task family.

    python recipes/maml.py proposal=oracle                                   # hand-designed goals (upper bound)
    python recipes/maml.py proposal=diayn diayn_checkpoint=outputs/diayn/point_nav/seed0
    python recipes/maml.py proposal=random resume=true                       # continue from the latest checkpoint

A Hydra main over :class:`umrl.trainers.maml.MAMLTrainer`: configs in ``umrl/configs/maml.yaml`` (``--cfg job``
prints the resolved one), process tuning (:func:`umrl.process.tune_process`: ``num_threads``), then training; logging, checkpoints and
resumption are the library's (:mod:`umrl.trainers.maml`).
"""
from __future__ import annotations

import logging

import hydra
from omegaconf import DictConfig

from umrl.process import tune_process
from umrl.runtime import log_location, run_summary
from umrl.trainers.config import register_help_text
from umrl.trainers.maml import train

SUMMARY_KEYS = ("iteration", "train/return_pre", "train/return_post", "train/kl", "time/learn_s")
"""What the command line prints when a run ends (every metric is in the logs)."""


@hydra.main(version_base="1.3", config_path="pkg://umrl.configs", config_name="maml")
def main(cfg: DictConfig) -> None:
    tune_process(num_threads=cfg.num_threads)  # this process is the run's: umrl's process-wide settings
    result = train(cfg)  # umrl.trainers.maml.MAMLTrainer(cfg).train(), then closed
    logging.getLogger(__name__).info(run_summary(f"maml {cfg.env.name} finished", result, SUMMARY_KEYS,
                                                 log_location(cfg.logger, cfg.output_dir)))


if __name__ == "__main__":
    register_help_text()
    main()
