"""What every recipe needs around its training loop: seeding, loggers, checkpoints.

Loggers are TorchRL's (:func:`torchrl.record.loggers.get_logger`): ``wandb`` in offline mode by default (runs land in
``./wandb/offline-run-*``; publish them later with ``wandb sync``), ``csv`` as a dependency-free alternative, ``none``
for tests. Checkpoints are ``torch.save`` files written atomically, with the resolved config beside them (their
formats, saving and checked loading live in :mod:`umrl.checkpoints`).
"""
from __future__ import annotations

import math
import os
import random
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.record.loggers import Logger, get_logger

LOGGER_BACKENDS = ("wandb", "csv", "none")


def seed_everything(seed: int) -> torch.Generator:
    """Seed Python, NumPy and torch; return a torch generator seeded with ``seed`` for explicit sampling."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)


def to_container(config: Any) -> dict:
    """A plain, resolved ``dict`` from a Hydra/OmegaConf config (or a mapping)."""
    if isinstance(config, DictConfig):
        return OmegaConf.to_container(config, resolve=True)
    return dict(config)


def make_logger(logger_cfg: Mapping, *, exp_name: str, config: Any = None, log_dir: str | os.PathLike = ".") -> Logger | None:
    """Build the TorchRL logger named by ``logger_cfg["backend"]`` and log ``config`` as hyperparameters.

    ``logger_cfg`` keys: ``backend`` (``wandb`` | ``csv`` | ``none``), optional ``project``, ``group``, ``mode``
    (wandb: ``offline`` by default, ``online`` to stream, ``disabled``; the ``WANDB_MODE`` environment variable wins).
    CSV logs go to ``<log_dir>/csv/<exp_name>/``; wandb runs to ``$WANDB_DIR`` or ``./wandb``.
    """
    backend = logger_cfg.get("backend", "wandb")
    if backend not in LOGGER_BACKENDS:
        raise ValueError(f"unknown logger backend {backend!r}; valid choices: {list(LOGGER_BACKENDS)}.")
    if backend == "none":
        return None
    if backend == "csv":
        logger = get_logger("csv", logger_name=str(Path(log_dir) / "csv"), experiment_name=exp_name)
    else:
        mode = os.environ.get("WANDB_MODE", logger_cfg.get("mode", "offline"))
        logger = get_logger(
            "wandb",
            logger_name=os.environ.get("WANDB_DIR", "."),
            experiment_name=exp_name,
            wandb_kwargs={
                "project": logger_cfg.get("project", "umrl"),
                "group": logger_cfg.get("group"),
                "offline": mode == "offline",
                "mode": mode,
            },
        )
    if config is not None:
        logger.log_hparams(to_container(config))
    return logger


def log_metrics(logger: Logger | None, metrics: Mapping[str, float], step: int) -> None:
    """Log scalar ``metrics`` at ``step``; non-finite values are logged too (they are what needs seeing)."""
    if logger is None:
        return
    for name, value in metrics.items():
        value = float(value)
        logger.log_scalar(name, value if math.isfinite(value) else float("nan"), step=step)


def log_image(logger: Logger | None, name: str, path: str | os.PathLike, step: int) -> None:
    """Log a PNG file to wandb (other backends keep the file on disk only)."""
    experiment = getattr(logger, "experiment", None)
    if experiment is None or not hasattr(experiment, "log"):
        return
    import wandb

    experiment.log({name: wandb.Image(str(path)), "step": step})


def check_finite(losses: Mapping[str, torch.Tensor], where: str) -> None:
    """Fail fast with the names of the non-finite entries of ``losses``."""
    bad = [k for k, v in losses.items() if torch.is_tensor(v) and not torch.isfinite(v).all()]
    if bad:
        raise FloatingPointError(
            f"non-finite {bad} in {where}: lower the learning rate or check the inputs; the last checkpoint is intact."
        )


class Checkpointer:
    """Saves ``state`` dicts as ``<directory>/step_<N>.pt`` with the resolved config in ``<directory>/config.yaml``.

    Args:
        directory: where checkpoints go (created on first save).
        keep_all: keep every checkpoint (meta-training ablations evaluate them all); otherwise only the newest.
    """

    _pattern = re.compile(r"step_(\d+)\.pt$")

    def __init__(self, directory: str | os.PathLike, keep_all: bool = False):
        self.directory = Path(directory)
        self.keep_all = keep_all

    def all(self) -> list[Path]:
        """Every checkpoint on disk, oldest step first."""
        if not self.directory.is_dir():
            return []
        found = [(int(m.group(1)), p) for p in self.directory.iterdir() if (m := self._pattern.search(p.name))]
        return [p for _, p in sorted(found)]

    def latest(self) -> Path | None:
        """The checkpoint with the largest step, or ``None``."""
        found = self.all()
        return found[-1] if found else None

    def save(self, state: Mapping[str, Any], step: int, config: Any = None) -> Path:
        """Write ``state`` for ``step`` atomically (a killed save never leaves a broken newest file)."""
        self.directory.mkdir(parents=True, exist_ok=True)
        path = self.directory / f"step_{step}.pt"
        tmp = path.with_suffix(".pt.tmp")
        torch.save(dict(state), tmp)
        os.replace(tmp, path)
        if config is not None:
            (self.directory / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(to_container(config))))
        if not self.keep_all:
            for old in self.all():
                if old != path:
                    old.unlink()
        return path

    def load(self, path: str | os.PathLike | None = None) -> dict:
        """Load ``path`` (default: the latest checkpoint)."""
        target = Path(path) if path is not None else self.latest()
        if target is None or not target.is_file():
            where = target if target is not None else self.directory
            raise FileNotFoundError(
                f"no checkpoint at {where}: run the recipe once without resume=true, or point to an existing .pt file."
            )
        return torch.load(target, map_location="cpu", weights_only=False)


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """``path`` if it is a checkpoint file, else the latest ``step_*.pt`` inside the directory ``path`` (or its
    ``checkpoints/`` subfolder). Raises ``FileNotFoundError`` saying what was looked for."""
    path = Path(path)
    if path.is_file():
        return path
    for directory in (path, path / "checkpoints"):
        latest = Checkpointer(directory).latest()
        if latest is not None:
            return latest
    raise FileNotFoundError(f"no checkpoint file at {path} (looked for step_*.pt in it and in {path / 'checkpoints'}).")

