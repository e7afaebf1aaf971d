"""MAML checkpoints, written by ``recipes/maml.py`` (format ``"umrl.maml.v1"``).

A checkpoint is a dict (stored by :mod:`umrl.checkpoints.file`):

- ``"format"``: ``"umrl.maml.v1"``;
- ``"meta"``: ``env``, ``proposal`` (diayn | random | oracle), ``obs_dim``, ``act_dim``, ``hidden``, ``init_std``
  (arguments of :func:`umrl.modules.policy.make_gaussian_policy`), ``inner_lr``, ``num_inner_steps``,
  ``first_order``, ``num_tasks``, ``trajectories_per_task``, ``horizon``, ``num_skills`` (None for oracle), and
  ``learn_std: False`` only for a run whose std was not learned (absent: learned);
- ``"policy"``: state dict of the meta-trained initialisation θ;
- ``"iteration"`` (meta-iterations done), ``"env_steps"``; ``"rng"`` (:func:`umrl.rng.rng_state`: torch, numpy,
  python and ``generators["task"]``, the generator that draws meta-batches) and ``"env"`` (the proposal env's
  :func:`umrl.resume_state.env_state`: MuJoCo reset noise), for a bit-identical ``resume=true``;
- ``"config"``: the resolved recipe config (also written beside it as ``config.yaml``).

Files are ``<output_dir>/checkpoints/step_<iteration>.safetensors``, all kept by default (meta-training ablation);
the latest is the final initialisation.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torchrl.modules import ProbabilisticActor

from umrl.checkpoints.folder import Checkpointer
from umrl.checkpoints.format import CheckpointFormat, Network
from umrl.modules.policy import make_gaussian_policy

MAML_FORMAT = CheckpointFormat(
    "umrl.maml.v1", "MAML",
    meta_keys=("env", "proposal", "obs_dim", "act_dim", "hidden", "init_std", "inner_lr", "num_inner_steps",
               "first_order", "num_tasks", "trajectories_per_task", "horizon", "num_skills"),
    networks=(Network("policy",
                      lambda m: make_gaussian_policy(m["obs_dim"], m["act_dim"], hidden=m["hidden"],
                                                     init_std=m["init_std"],
                                                     learn_std=m.get("learn_std", True)),
                      lambda m: [m["obs_dim"], *m["hidden"], m["act_dim"]]),),
)

__all__ = ["MAML_FORMAT", "load_maml_checkpoint", "load_maml_policy", "maml_policy", "save_maml_checkpoint"]


def save_maml_checkpoint(
    checkpointer: Checkpointer,
    *,
    meta: Mapping[str, Any],
    policy: torch.nn.Module,
    iteration: int,
    env_steps: int,
    rng: Mapping[str, Any],
    env: Mapping[str, Any],
    config: Any,
) -> Path:
    """Write the MAML state above as ``step_<iteration>.safetensors``."""
    return MAML_FORMAT.save(
        checkpointer, iteration, meta, config,
        policy=policy.state_dict(), iteration=iteration, env_steps=env_steps, rng=dict(rng), env=dict(env),
    )


def load_maml_checkpoint(path: str | os.PathLike) -> dict:
    """Load a MAML checkpoint: a ``step_*.safetensors`` (or ``.pt``) file, a ``checkpoints/`` folder or a run's
    output_dir (latest)."""
    return MAML_FORMAT.load(path)


def load_maml_policy(path: str | os.PathLike) -> tuple[ProbabilisticActor, float]:
    """``(policy, inner_lr)``: the meta-trained Gaussian policy and the SGD step size it was meta-trained for."""
    return maml_policy(load_maml_checkpoint(path))


def maml_policy(state: Mapping[str, Any]) -> tuple[ProbabilisticActor, float]:
    """:func:`load_maml_policy`'s ``(policy, inner_lr)`` from a checkpoint already loaded (and checked)."""
    return MAML_FORMAT.build(state, "policy"), float(state["meta"]["inner_lr"])
