"""VIME checkpoints, written by ``recipes/vime.py`` (format ``"umrl.vime.v1"``).

A dict (stored by :mod:`umrl.checkpoints.file`), files ``<output_dir>/checkpoints/step_<iteration>.safetensors``
(the final one of a run is the latest), with

- ``"format"``: ``"umrl.vime.v1"``;
- ``"meta"``: ``env`` (name), ``obs_dim``, ``act_dim``, ``policy_hidden``, ``policy_init_std``, ``dynamics_hidden``,
  ``prior_std``, ``likelihood_std``;
- ``"policy"``: state dict of :func:`umrl.modules.policy.make_gaussian_policy` ``(obs_dim, act_dim,
  hidden=policy_hidden, init_std=policy_init_std)`` (reads ``"observation"``, writes ``"loc"``, ``"scale"``,
  ``"action"``, ``"action_log_prob"``);
- ``"dynamics"``: state dict of :class:`~umrl.modules.bnn.BayesianDynamics` (posterior and running statistics);
- ``"dynamics_optimizer"``: Adam state; ``"median_history"``: the bonus normaliser's recent medians;
- ``"replay"`` / ``"holdout"``: the dynamics model's transition buffers (:func:`umrl.resume_state.replay_buffer_state`:
  TorchRL's state dict with the storage cut to its filled rows) or ``None`` (``checkpoint.save_replay=false``: a resume is then not faithful);
- ``"counters"``: ``iteration``, ``frames``; ``"initial_coverage"``: coverage of the untrained policy;
  ``"initial_states"``: the untrained policy's visited states (the coverage figure's baseline); ``"visited"``: the
  cells (or velocity range) visited so far;
  ``"rng"``: :func:`umrl.rng.rng_state` (torch, numpy, python); ``"env"``: :func:`umrl.resume_state.env_state`
  (MuJoCo reset noise); ``"config"``: the resolved recipe config (also beside it as ``config.yaml``).
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
from umrl.modules.bnn import BayesianDynamics
from umrl.modules.policy import make_gaussian_policy

VIME_FORMAT = CheckpointFormat(
    "umrl.vime.v1", "VIME",
    meta_keys=("env", "obs_dim", "act_dim", "policy_hidden", "policy_init_std", "dynamics_hidden", "prior_std",
               "likelihood_std"),
    networks=(
        Network("policy", lambda m: make_gaussian_policy(m["obs_dim"], m["act_dim"], hidden=m["policy_hidden"],
                                                         init_std=m["policy_init_std"]),
                lambda m: [m["obs_dim"], *m["policy_hidden"], m["act_dim"]]),
        Network("dynamics", lambda m: BayesianDynamics(m["obs_dim"], m["act_dim"], hidden=m["dynamics_hidden"],
                                                       prior_std=m["prior_std"], likelihood_std=m["likelihood_std"]),
                lambda m: [m["obs_dim"] + m["act_dim"], *m["dynamics_hidden"], m["obs_dim"]]),
    ),
)

__all__ = ["VIME_FORMAT", "load_vime_checkpoint", "load_vime_dynamics", "load_vime_policy", "save_vime_checkpoint",
           "vime_policy"]


def save_vime_checkpoint(
    checkpointer: Checkpointer,
    *,
    meta: Mapping[str, Any],
    policy: torch.nn.Module,
    dynamics: BayesianDynamics,
    dynamics_optimizer: torch.optim.Optimizer,
    median_history: torch.Tensor,
    replay: Mapping[str, Any] | None,
    holdout: Mapping[str, Any] | None,
    counters: Mapping[str, int],
    initial_coverage: Mapping[str, float],
    initial_states: torch.Tensor | None,
    visited: torch.Tensor | None,
    rng: Mapping[str, Any],
    env: Mapping[str, Any],
    config: Any,
) -> Path:
    """Write the VIME state above as ``step_<counters["iteration"]>.safetensors``."""
    return VIME_FORMAT.save(
        checkpointer, counters["iteration"], meta, config,
        policy=policy.state_dict(), dynamics=dynamics.state_dict(),
        dynamics_optimizer=dynamics_optimizer.state_dict(), median_history=median_history.clone(),
        replay=replay, holdout=holdout, counters=dict(counters), initial_coverage=dict(initial_coverage),
        initial_states=initial_states, visited=visited, rng=dict(rng), env=dict(env),
    )


def load_vime_checkpoint(path: str | os.PathLike) -> dict:
    """Load a VIME checkpoint: a ``step_*.safetensors`` (or ``.pt``) file, a ``checkpoints/`` folder or a run's
    output_dir (latest)."""
    return VIME_FORMAT.load(path)


def load_vime_policy(path: str | os.PathLike) -> ProbabilisticActor:
    """The VIME-pre-trained 2x300 Gaussian policy (trainable, for fine-tuning; the VIME-init baseline).

    Reads ``"observation"``, writes ``"loc"``, ``"scale"``, ``"action"`` and ``"action_log_prob"``, exactly like
    :func:`umrl.modules.policy.make_gaussian_policy`.
    """
    return vime_policy(load_vime_checkpoint(path))


def vime_policy(state: Mapping[str, Any]) -> ProbabilisticActor:
    """:func:`load_vime_policy`'s policy from a checkpoint already loaded (and checked)."""
    return VIME_FORMAT.build(state, "policy")


def load_vime_dynamics(path: str | os.PathLike) -> BayesianDynamics:
    """The trained Bayesian dynamics model (with its running statistics), e.g. to score transitions."""
    return VIME_FORMAT.build(load_vime_checkpoint(path), "dynamics")
