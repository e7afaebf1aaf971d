"""DIAYN checkpoints, written by ``recipes/diayn.py``: one file per seed (``"umrl.diayn.v1"``) and the program's
state (``"umrl.diayn_seeds.v1"``).

A run of seeds ``[s, ...]`` in ``<output_dir>`` writes, at every checkpoint:

- ``<output_dir>/seed<s>/checkpoints/step_<frames>.safetensors`` for each seed, format ``"umrl.diayn.v1"``, a dict
  (stored by :mod:`umrl.checkpoints.file`) of
  ``"format"``; ``"meta"``: ``env`` (name), ``obs_dim``, ``act_dim``, ``num_skills``, ``hidden`` (actor/Q widths),
  ``discriminator_hidden``, ``discriminator_observation_key`` (``["observation"]``: D was trained on s_t;
  ``["next", "observation"]`` in checkpoints written before DIAYN scored s_t), ``discriminator_input_dims``
  (``None``: D reads the whole observation; a list: only those dims; absent in checkpoints written before the key);
  ``"actor"``: state dict of :func:`umrl.modules.sac.make_skill_actor` ``(obs_dim, num_skills, act_dim,
  hidden=hidden)``: reads ``"observation"`` and one-hot ``"skill"``, writes a tanh-Gaussian ``"action"`` in [-1, 1];
  ``"discriminator"``: state dict of :func:`umrl.modules.discriminator.make_discriminator` ``(obs_dim, num_skills,
  hidden=discriminator_hidden, input_dims=discriminator_input_dims)``; ``"counters"``: ``frames`` (env steps of the
  seed), ``updates``, ...; ``"config"``: the run's resolved config with ``seed`` set to this seed (also beside it as
  ``config.yaml``). Every loader here, the MAML recipe's ``diayn_checkpoint`` and the suite read these.
- ``<output_dir>/checkpoints/step_<frames>.safetensors``, format ``"umrl.diayn_seeds.v1"``, for ``resume=true``:
  ``"meta"`` (the above and ``seeds``), ``"loss"`` (the state dict of the
  :class:`~umrl.objectives.stacked_diayn.StackedDIAYNLoss`: every seed's networks stacked, targets, alpha),
  ``"optimizers"`` (``{"actor", "qvalue", "discriminator"[, "alpha"]}`` Adam state dicts), ``"counters"``
  (``frames``, ``updates``, ``next_eval``, ``next_log``, ``next_checkpoint``, ``update_credit``),
  ``"random_metrics"``, ``"replay"`` (:func:`umrl.resume_state.replay_buffer_state` of the rows ``[S]``), ``"rng"``
  (:func:`umrl.rng.rng_state` with each seed's generator), ``"envs"`` (``{"train"}``:
  :func:`umrl.resume_state.env_state` with ``episodes=True``: MuJoCo's reset noise per seed and the copies' physics
  where the env gives it), ``"episodes"`` (the episodes in progress, :meth:`DIAYNTrainer.state_dict
  <umrl.trainers.diayn.DIAYNTrainer.state_dict>`: the env's last output, each copy's pseudo-return so far, the
  logging interval's pending steps), ``"config"``. A program checkpoint without the episodes (written before umrl
  kept them) resumes with them restarted.

A single DIAYN checkpoint written before multi-seed runs (``"umrl.diayn.v1"`` with ``loss``, ``optimizers`` and
``replay``) still loads everywhere a seed's file does. The loaders take a seed's file or folder, or a run's
``output_dir`` when it holds one seed (:func:`seed_run_dir`).

:func:`export_diayn_skills` copies a seed's skills (:data:`SKILL_ENTRIES`) into a file of the same format elsewhere.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor

from umrl.checkpoints.folder import Checkpointer
from umrl.checkpoints.format import CheckpointFormat, Network
from umrl.modules.discriminator import make_discriminator
from umrl.modules.sac import make_skill_actor
from umrl.validation import check_writable_dir


def _discriminator(meta: Mapping[str, Any]) -> TensorDictModule:
    return make_discriminator(meta["obs_dim"], meta["num_skills"], hidden=meta["discriminator_hidden"],
                              input_dims=meta.get("discriminator_input_dims"))  # absent before the key


def _discriminator_widths(meta: Mapping[str, Any]) -> list:
    input_dims = meta.get("discriminator_input_dims")
    return [len(input_dims) if input_dims else meta["obs_dim"], *meta["discriminator_hidden"], meta["num_skills"]]


DIAYN_FORMAT = CheckpointFormat(
    "umrl.diayn.v1", "DIAYN",
    meta_keys=("env", "obs_dim", "act_dim", "num_skills", "hidden", "discriminator_hidden",
               "discriminator_observation_key", "discriminator_input_dims"),
    networks=(
        Network("actor", lambda m: make_skill_actor(m["obs_dim"], m["num_skills"], m["act_dim"], hidden=m["hidden"]),
                lambda m: [m["obs_dim"] + m["num_skills"], *m["hidden"], 2 * m["act_dim"]]),
        Network("discriminator", _discriminator, _discriminator_widths),
    ),
    weights=("loss",),  # the single-run checkpoints written before multi-seed runs hold their SAC loss
    locate=lambda path: resolve_seed_run(path),  # a one-seed run's output_dir holds the program state beside it
)
DIAYN_SEEDS_FORMAT = CheckpointFormat("umrl.diayn_seeds.v1", "multi-seed DIAYN",
                                      meta_keys=(*DIAYN_FORMAT.meta_keys, "seeds"), weights=("loss",))

SKILL_ENTRIES = ("actor", "discriminator", "counters")
"""What :func:`export_diayn_skills` keeps besides ``format``, ``meta`` and ``config``."""

__all__ = ["DIAYN_FORMAT", "DIAYN_SEEDS_FORMAT", "SKILL_ENTRIES", "export_diayn_skills",
           "load_diayn_checkpoint", "load_discriminator", "load_skill_policy", "save_diayn_checkpoint", "seed_run_dir",
           "skill_policy"]


def seed_run_dir(output_dir: str | os.PathLike, seed: int) -> Path:
    """Seed ``seed``'s folder in a DIAYN run's ``output_dir``: ``<output_dir>/seed<seed>``."""
    return Path(output_dir) / f"seed{seed}"


def resolve_seed_run(path: str | os.PathLike) -> Path:
    """``path``, or the seed's folder when ``path`` is (the ``checkpoints/`` folder of) a DIAYN run's ``output_dir``
    holding one seed; ``ValueError`` naming the seed folders when it holds several."""
    path = Path(path)
    root = path.parent if path.name == "checkpoints" else path
    if not root.is_dir():
        return path
    seeds = sorted(p for p in root.glob("seed*") if (p / "checkpoints").is_dir())
    if len(seeds) == 1:
        return seeds[0]
    if len(seeds) > 1:
        raise ValueError(f"{root} is a DIAYN run of {len(seeds)} seeds: point to one seed's folder, one of "
                         f"{[str(p) for p in seeds]}.")
    return path


def save_diayn_checkpoint(
    checkpointer: Checkpointer,
    *,
    meta: Mapping[str, Any],
    actor: torch.nn.Module,
    discriminator: torch.nn.Module,
    counters: Mapping[str, int | float],
    config: Any,
) -> Path:
    """Write one seed's skills (the format above) as ``step_<counters["frames"]>.safetensors``."""
    return DIAYN_FORMAT.save(checkpointer, counters["frames"], meta, config, actor=actor.state_dict(),
                             discriminator=discriminator.state_dict(), counters=dict(counters))


def load_diayn_checkpoint(path: str | os.PathLike) -> dict:
    """Load a seed's DIAYN checkpoint: a ``step_*.safetensors`` (or ``.pt``) file, a ``checkpoints/`` folder, a
    seed's folder or the ``output_dir`` of a run of one seed (the latest file)."""
    return DIAYN_FORMAT.load(path)


def export_diayn_skills(source: str | os.PathLike, destination: str | os.PathLike) -> Path:
    """Write the trained skills of the DIAYN checkpoint at ``source`` (a file, ``checkpoints/`` folder or run
    directory: the latest) to ``<destination>/checkpoints/step_<frames>.safetensors``, with its ``config.yaml``.

    The copy keeps :data:`SKILL_ENTRIES` (the skill policy, the discriminator, the counters) and drops the loss,
    optimisers, replay buffer, RNG and env states: :func:`load_discriminator`, :func:`load_skill_policy`, the MAML
    recipe's ``diayn_checkpoint`` and the suite's ``pretrain.diayn.reuse`` read it as they read the source;
    ``resume=true`` cannot continue from it. Returns the written file. A ``destination`` that cannot be a writable
    folder (a file, a name too long) is refused before the source is read.
    """
    check_writable_dir("destination", str(destination))
    state = load_diayn_checkpoint(source)
    return DIAYN_FORMAT.save(Checkpointer(Path(destination) / "checkpoints"), state["counters"]["frames"],
                             state["meta"], state["config"], **{key: state[key] for key in SKILL_ENTRIES})


def load_discriminator(path: str | os.PathLike) -> tuple[TensorDictModule, int, int]:
    """``(discriminator, num_skills, obs_dim)``: the trained D(z|s), frozen (``requires_grad=False``, eval mode).

    It reads ``"observation"`` [*B, obs_dim] and writes ``"skill_logits"`` [*B, num_skills]; wrap it in
    :class:`~umrl.transforms.discriminator_reward.DiscriminatorReward` for the UML-DIAYN task proposal.
    """
    state = load_diayn_checkpoint(path)
    discriminator = DIAYN_FORMAT.build(state, "discriminator")
    return discriminator.eval().requires_grad_(False), state["meta"]["num_skills"], state["meta"]["obs_dim"]


def load_skill_policy(path: str | os.PathLike) -> tuple[ProbabilisticActor, int, int]:
    """``(actor, num_skills, obs_dim)``: the trained skill-conditioned policy pi(a|s,z) (trainable, for fine-tuning).

    Reads ``"observation"`` and a one-hot ``"skill"`` [*B, num_skills] (pin one with
    :meth:`~umrl.transforms.skill.SkillTransform.pin`), writes ``"action"`` and ``"action_log_prob"``.
    """
    return skill_policy(load_diayn_checkpoint(path))


def skill_policy(state: Mapping[str, Any]) -> tuple[ProbabilisticActor, int, int]:
    """:func:`load_skill_policy`'s ``(actor, num_skills, obs_dim)`` from a checkpoint already loaded (and checked)."""
    return DIAYN_FORMAT.build(state, "actor"), state["meta"]["num_skills"], state["meta"]["obs_dim"]
