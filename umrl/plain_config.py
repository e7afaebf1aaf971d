"""A resolved config as plain Python containers, the form loggers and checkpoints store."""
from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf


def to_container(config: Any) -> dict:
    """A plain, resolved ``dict`` from a Hydra/OmegaConf config (or a mapping).

    >>> to_container(OmegaConf.create({"lr": 0.1, "copy": "${lr}"}))
    {'lr': 0.1, 'copy': 0.1}
    """
    if isinstance(config, DictConfig):
        return OmegaConf.to_container(config, resolve=True)
    return dict(config)
