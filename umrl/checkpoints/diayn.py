"""DIAYN checkpoints, written by ``recipes/diayn.py`` (format ``"umrl.diayn.v1"``).

A checkpoint is a dict (stored by :mod:`umrl.checkpoint_file`):

- ``"format"``: ``"umrl.diayn.v1"``;
- ``"meta"``: ``env`` (name), ``obs_dim``, ``act_dim``, ``num_skills``, ``hidden`` (actor/Q widths),
  ``discriminator_hidden``, ``discriminator_observation_key`` (``["observation"]``: D was trained on s_t; ``["next", "observation"]`` in
  checkpoints written before DIAYN scored s_t),
  ``discriminator_input_dims`` (``None``: D reads the whole observation; a list: only those dims; absent in
  checkpoints written before the key, which read the whole observation);
- ``"actor"``: state dict of :func:`umrl.modules.sac.make_skill_actor` ``(obs_dim, num_skills, act_dim,
  hidden=hidden)``: reads ``"observation"`` and one-hot ``"skill"``, writes a tanh-Gaussian ``"action"`` in [-1, 1];
- ``"discriminator"``: state dict of :func:`umrl.modules.discriminator.make_discriminator` ``(obs_dim,
  num_skills, hidden=discriminator_hidden, input_dims=discriminator_input_dims)``;
- ``"loss"``: state dict of the :class:`~umrl.objectives.diayn.DIAYNLoss` (actor, twin Q-networks and their targets,
  discriminator, alpha), ``"optimizers"``: ``{"actor", "qvalue", "discriminator"[, "alpha"]}`` Adam state dicts;
- ``"counters"``: ``frames`` (env steps), ``updates``, ``next_eval``, ``next_checkpoint``, ``update_credit``;
- ``"random_metrics"``: the ``eval/random_*`` metrics of a uniformly random policy, scored by the run's initial
  discriminator (a resumed run reports these instead of rescoring with the trained one; absent in checkpoints written
  before the key);
- ``"replay"``: :func:`umrl.runtime.replay_buffer_state` (TorchRL's ``state_dict``: sampler, writer, and the storage
  cut to its filled rows);
- ``"rng"``: :func:`umrl.runtime.rng_state` (torch, numpy, python); ``"envs"``: ``{"train", "eval"}``
  :func:`umrl.runtime.env_state` (MuJoCo reset noise, transforms); ``"collector"``: ``{"traj_pool": {"traj_id"}}``,
  the TorchRL collector's next trajectory id (the replay's ``("collector", "traj_ids")`` continue from it; absent in
  checkpoints written before the key), all for a bit-identical ``resume=true`` (every tensor of the checkpoint);
- ``"config"``: the resolved recipe config (also written beside it as ``config.yaml``).

Files are ``<output_dir>/checkpoints/step_<frames>.pt``; the final one of a run is the latest.

:func:`export_diayn_skills` copies a run's trained skills into a checkpoint of the same format that keeps only
``format``, ``meta``, ``actor``, ``discriminator``, ``counters`` and ``config`` (≈ 1 MB for 2×300 networks, against
tens of MB with the replay buffer): every loader reads it, ``resume=true`` refuses it.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor

from umrl.checkpoints.format import CheckpointFormat
from umrl.modules.discriminator import make_discriminator
from umrl.modules.sac import make_skill_actor
from umrl.runtime import Checkpointer

DIAYN_FORMAT = CheckpointFormat(
    "umrl.diayn.v1", "DIAYN",
    meta_keys=("env", "obs_dim", "act_dim", "num_skills", "hidden", "discriminator_hidden",
               "discriminator_observation_key", "discriminator_input_dims"),
)

SKILL_ENTRIES = ("actor", "discriminator", "counters")
"""What :func:`export_diayn_skills` keeps besides ``format``, ``meta`` and ``config``."""

__all__ = ["DIAYN_FORMAT", "SKILL_ENTRIES", "check_resumable", "export_diayn_skills", "load_diayn_checkpoint",
           "load_discriminator", "load_skill_policy", "save_diayn_checkpoint", "skill_policy"]


def save_diayn_checkpoint(
    checkpointer: Checkpointer,
    *,
    meta: Mapping[str, Any],
    actor: torch.nn.Module,
    discriminator: torch.nn.Module,
    loss: torch.nn.Module,
    optimizers: Mapping[str, torch.optim.Optimizer],
    counters: Mapping[str, int | float],
    random_metrics: Mapping[str, float],
    replay: Mapping[str, Any],
    rng: Mapping[str, Any],
    envs: Mapping[str, Any],
    collector: Mapping[str, Any],
    config: Any,
) -> Path:
    """Write the DIAYN state above as ``step_<counters["frames"]>.pt`` (``replay``, ``rng`` and ``envs`` as taken by
    ``ReplayBuffer.state_dict``, :func:`~umrl.runtime.rng_state` and :func:`~umrl.runtime.env_state`; ``collector``:
    ``{"traj_pool": Collector.state_dict()["traj_pool"]}``)."""
    return DIAYN_FORMAT.save(
        checkpointer, counters["frames"], meta, config,
        actor=actor.state_dict(), discriminator=discriminator.state_dict(), loss=loss.state_dict(),
        optimizers={k: o.state_dict() for k, o in optimizers.items()}, counters=dict(counters),
        random_metrics=dict(random_metrics), replay=dict(replay), rng=dict(rng), envs=dict(envs),
        collector=dict(collector),
    )


def load_diayn_checkpoint(path: str | os.PathLike) -> dict:
    """Load a DIAYN checkpoint: a ``step_*.pt`` file, a ``checkpoints/`` folder or a run's output_dir (latest)."""
    return DIAYN_FORMAT.load(path)


def export_diayn_skills(source: str | os.PathLike, destination: str | os.PathLike) -> Path:
    """Write the trained skills of the DIAYN checkpoint at ``source`` (a file, ``checkpoints/`` folder or run
    directory: the latest) to ``<destination>/checkpoints/step_<frames>.pt``, with its ``config.yaml``.

    The copy keeps :data:`SKILL_ENTRIES` (the skill policy, the discriminator, the counters) and drops the loss,
    optimisers, replay buffer, RNG and env states: :func:`load_discriminator`, :func:`load_skill_policy`, the MAML
    recipe's ``diayn_checkpoint`` and the suite's ``pretrain.diayn.reuse`` read it as they read the source;
    ``resume=true`` cannot continue from it. Returns the written file.
    """
    state = load_diayn_checkpoint(source)
    return DIAYN_FORMAT.save(Checkpointer(Path(destination) / "checkpoints"), state["counters"]["frames"],
                             state["meta"], state["config"], **{key: state[key] for key in SKILL_ENTRIES})


def check_resumable(state: Mapping[str, Any], source: str | os.PathLike | None) -> None:
    """Raise ``ValueError`` naming ``source`` if ``state`` is a skills-only copy (:func:`export_diayn_skills`): it has
    no loss, optimisers or replay buffer to resume from."""
    if "replay" not in state:
        raise ValueError(f"resume=true: {source} holds a run's skills only (written by "
                         "umrl.checkpoints.export_diayn_skills, without loss, optimisers and replay buffer); resume "
                         "the run it was exported from, or train afresh with resume=false.")


def load_discriminator(path: str | os.PathLike) -> tuple[TensorDictModule, int, int]:
    """``(discriminator, num_skills, obs_dim)``: the trained D(z|s), frozen (``requires_grad=False``, eval mode).

    It reads ``"observation"`` [*B, obs_dim] and writes ``"skill_logits"`` [*B, num_skills]; wrap it in
    :class:`~umrl.transforms.discriminator_reward.DiscriminatorReward` for the UML-DIAYN task proposal.
    """
    state = load_diayn_checkpoint(path)
    meta = state["meta"]
    discriminator = make_discriminator(meta["obs_dim"], meta["num_skills"], hidden=meta["discriminator_hidden"],
                                       input_dims=meta.get("discriminator_input_dims"))  # absent before the key
    discriminator.load_state_dict(state["discriminator"])
    return discriminator.eval().requires_grad_(False), meta["num_skills"], meta["obs_dim"]


def load_skill_policy(path: str | os.PathLike) -> tuple[ProbabilisticActor, int, int]:
    """``(actor, num_skills, obs_dim)``: the trained skill-conditioned policy pi(a|s,z) (trainable, for fine-tuning).

    Reads ``"observation"`` and a one-hot ``"skill"`` [*B, num_skills] (pin one with
    :meth:`~umrl.transforms.skill.SkillTransform.pin`), writes ``"action"`` and ``"action_log_prob"``.
    """
    return skill_policy(load_diayn_checkpoint(path))


def skill_policy(state: Mapping[str, Any]) -> tuple[ProbabilisticActor, int, int]:
    """:func:`load_skill_policy`'s ``(actor, num_skills, obs_dim)`` from a checkpoint already loaded (and checked)."""
    meta = state["meta"]
    actor = make_skill_actor(meta["obs_dim"], meta["num_skills"], meta["act_dim"], hidden=meta["hidden"])
    actor.load_state_dict(state["actor"])
    return actor, meta["num_skills"], meta["obs_dim"]
