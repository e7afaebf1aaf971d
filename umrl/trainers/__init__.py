"""Training as library objects, one module per algorithm, built from a config composed by name.

Each trainer is a :class:`~umrl.trainers.base.Trainer`, built from its config without I/O: ``setup()`` (run by
the first ``step()`` or ``train()``) opens the logger and writes what a run starts with, ``step()`` advances
it and returns the step's metrics, ``state_dict()`` / ``load_state_dict()`` hold what a resumed run needs,
``save()`` writes a checkpoint, ``log(metrics)`` sends metrics to the configured logger, ``train()`` runs to
the budget (logged, evaluated, checkpointed), ``register_op(point, op)`` adds a hook
(:mod:`umrl.trainers.base` lists the points) and ``close()`` releases the envs; each module's ``train(cfg)``
does all of it in one call.

- :mod:`umrl.trainers.base`: :class:`~umrl.trainers.base.Trainer` (the loop, the hook points, setup and
closing).
- :mod:`umrl.trainers.maml`: :class:`MAMLTrainer` (meta-training on proposed tasks) and the meta-iteration's
  parts (:func:`~umrl.trainers.maml.build`, :func:`~umrl.trainers.maml.meta_batch`,
  :func:`~umrl.trainers.maml.meta_step`).
- :mod:`umrl.trainers.diayn`: :class:`DIAYNTrainer` (skill discovery, the task proposal; ``step`` is one collector
  batch, ``save`` keeps the episodes in progress: they go on, also after a resume).
- :mod:`umrl.trainers.vime`: :class:`VIMETrainer` (VIME pre-training, the VIME-init baseline).
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

from omegaconf import read_write

from umrl.folder_lock import reserve_folder
from umrl.run_folders import named_keys, place_default_run
from umrl.trainers.config import CONFIG_DIR, RECIPES, check_name, compose, config_dir
from umrl.trainers.diayn import DIAYNTrainer
from umrl.trainers.maml import MAMLTrainer
from umrl.trainers.vime import VIMETrainer

__all__ = ["CONFIG_DIR", "RECIPES", "DIAYNTrainer", "MAMLTrainer", "VIMETrainer", "compose", "config_dir", "train"]


def train(name: str, overrides: Sequence[str] = ()) -> dict:
    """Run trainer ``name`` in this process on ``compose(name, overrides)``: ``umrl.trainers.<name>.train(cfg)``
    (the final metrics and the ``"checkpoint"`` path). Pickles by reference: the suite's pre-training job.

    As on the command line, ``overrides`` that leave ``output_dir`` at its default put a rerun in a folder of its own
    (``<folder>-2``, ...; :mod:`umrl.run_folders`, with the line saying so printed) and ``resume=true`` continues the
    latest run; a named ``output_dir`` is used as it is."""
    check_name(name)
    cfg = compose(name, overrides)
    with read_write(cfg):
        lock, notes = place_default_run(cfg, named_keys(overrides))
    for note in notes:
        print(note, flush=True)
    try:
        if lock is not None:
            reserve_folder(lock)  # the trainer takes this lock over
        return importlib.import_module(f"umrl.trainers.{name}").train(cfg)
    finally:
        if lock is not None:
            lock.release()
