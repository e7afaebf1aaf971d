"""Training as library objects, one module per algorithm, built from a config composed by name.

- :mod:`umrl.trainers.maml`: :class:`MAMLTrainer` (meta-training on proposed tasks; ``step``, ``state_dict`` /
  ``load_state_dict``, ``save``, ``log``, ``train``) and the meta-iteration's parts (:func:`~umrl.trainers.maml.build`,
  :func:`~umrl.trainers.maml.meta_batch`, :func:`~umrl.trainers.maml.meta_step`).
- :mod:`umrl.trainers.diayn`, :mod:`umrl.trainers.vime`: ``train(cfg)`` for DIAYN and VIME pre-training.
- :mod:`umrl.trainers.config`: :func:`compose` (defaults in ``umrl/configs/<name>.yaml`` plus Hydra overrides).

The recipes (``recipes/<name>.py``) are their command lines. From Python::

    from umrl.trainers import MAMLTrainer, compose

    trainer = MAMLTrainer(compose("maml", ["proposal=random", "iterations=10", "logger.backend=none"]))
    result = trainer.train()

or in one call ``umrl.trainers.train("maml", [...])``.
"""
from __future__ import annotations

import importlib
from collections.abc import Sequence

from umrl.trainers.config import CONFIG_DIR, TRAINERS, check_name, compose, config_dir
from umrl.trainers.maml import MAMLTrainer

__all__ = ["CONFIG_DIR", "TRAINERS", "MAMLTrainer", "compose", "config_dir", "train"]


def train(name: str, overrides: Sequence[str] = ()) -> dict:
    """Run trainer ``name`` in this process on ``compose(name, overrides)``: ``umrl.trainers.<name>.train(cfg)``
    (the final metrics and the ``"checkpoint"`` path). Pickles by reference: the suite's pre-training job."""
    check_name(name)
    return importlib.import_module(f"umrl.trainers.{name}").train(compose(name, overrides))
