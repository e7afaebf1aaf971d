"""One record per environment: :class:`EnvSpec` and the registry every table of per-env facts reads from.

An env is added by one :func:`register_env` call (the built-in ones are in :mod:`umrl.envs.builtin`); everything
that depends on the env's physics or tasks (``make_env``, task families and rewards, the coverage metrics of DIAYN
and VIME, the recipes' ``env.name`` choices) reads its :class:`EnvSpec`. The recipes' per-env hyperparameters
(DIAYN's skill count, episode length, budget and widths; MAML's iterations) are config, not env facts: they live in
the recipes' groups, ``umrl/configs/<recipe>_env/<env>.yaml`` (:mod:`umrl.configs.env_groups`)::

    register_env(EnvSpec(name="my_env", make=MyEnv, obs_dim=4, act_dim=2,
                         task_family=TaskFamily("my_env", 2, -1.0, 1.0, reward_fn=my_reward),
                         physics_keys={"position": 2}, coverage_key="position"))
"""
from __future__ import annotations

from collections.abc import Callable, KeysView, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from torchrl.envs import EnvBase

if TYPE_CHECKING:  # tasks.py reads the registry: the type alone avoids an import cycle
    from umrl.envs.tasks import TaskFamily

COVERAGE_REDUCTIONS = ("last", "mean")

__all__ = ["COVERAGE_REDUCTIONS", "ENV_NAMES", "EnvSpec", "check_observation_size", "get_env_spec", "register_env",
           "unregister_env"]


@dataclass(frozen=True)
class EnvSpec:
    """The physics and task facts umrl needs to know about one reward-free environment (CMP).

    Attributes:
        name: the ``env.name`` of the recipes.
        make: ``make(num_envs, *, seed, device, backend) -> EnvBase``: the CMP with batch size ``[num_envs]``, no time
            limit (``make_env`` adds the horizon), zero ``("next", "reward")``, float32 ``"observation"``
            ``[B, obs_dim]``, an ``"action"`` in ``[-1, 1]^act_dim`` and the :attr:`physics_keys` at every step.
        obs_dim, act_dim: observation and action sizes.
        task_family: the hand-designed tasks (oracle meta-training, meta-test) and their reward.
        physics_keys: ``{key: width}`` written into every step's ``"next"`` (what task rewards and coverage read).
        coverage_key: the physics key whose values show where the agent went (x-y position, forward velocity).
        coverage_reduction: ``"last"`` (a skill's end point is its final value: positions) or ``"mean"`` (the
            episode mean: velocities).
        coverage_cell: grid cell side for VIME's state-coverage counts of a 2-D :attr:`coverage_key`; ``None`` for
            1-D coverage (velocity ranges).
        horizon: default episode length of meta-training and meta-test (the paper's path length, 100).
        num_eval_tasks: how many held-out evaluation tasks :meth:`eval_tasks` returns.
    """

    name: str
    make: Callable[..., EnvBase]
    obs_dim: int
    act_dim: int
    task_family: TaskFamily
    physics_keys: Mapping[str, int]
    coverage_key: str
    coverage_reduction: str = "last"
    coverage_cell: float | None = None
    horizon: int = 100
    num_eval_tasks: int = 20

    def __post_init__(self) -> None:
        positive = {"obs_dim": self.obs_dim, "act_dim": self.act_dim, "horizon": self.horizon,
                    "num_eval_tasks": self.num_eval_tasks}
        bad = {k: v for k, v in positive.items() if not (isinstance(v, int) and v > 0)}
        if bad:
            raise ValueError(f"EnvSpec {self.name!r}: these fields must be positive integers, got {bad}.")
        if self.coverage_key not in self.physics_keys:
            raise ValueError(f"EnvSpec {self.name!r}: coverage_key {self.coverage_key!r} is not one of its "
                             f"physics_keys {sorted(self.physics_keys)}.")
        if self.coverage_reduction not in COVERAGE_REDUCTIONS:
            raise ValueError(f"EnvSpec {self.name!r}: coverage_reduction must be one of {list(COVERAGE_REDUCTIONS)}, "
                             f"got {self.coverage_reduction!r}.")
        if (self.coverage_cell is None) != (self.physics_keys[self.coverage_key] == 1):
            raise ValueError(f"EnvSpec {self.name!r}: coverage_cell is needed for a 2-D coverage_key and must be None "
                             f"for a 1-D one (got {self.coverage_cell!r} for a width-"
                             f"{self.physics_keys[self.coverage_key]} key).")
        if self.task_family.env_name != self.name:
            raise ValueError(f"EnvSpec {self.name!r} carries the task family of {self.task_family.env_name!r}.")

    def eval_tasks(self):
        """The held-out evaluation tasks, ``task_family.eval_tasks(num_eval_tasks)``: a fixed ``[num_eval_tasks,
        task_dim]`` tensor (goals, target velocities) in the coordinates of :attr:`coverage_key`."""
        return self.task_family.eval_tasks(self.num_eval_tasks)


_REGISTRY: dict[str, EnvSpec] = {}


def register_env(spec: EnvSpec, *, overwrite: bool = False) -> EnvSpec:
    """Add ``spec`` to the registry (``overwrite=True`` replaces a record of the same name) and return it."""
    if spec.name in _REGISTRY and not overwrite:
        raise ValueError(f"env {spec.name!r} is already registered; pass overwrite=True to replace it.")
    _REGISTRY[spec.name] = spec
    return spec


def unregister_env(name: str) -> EnvSpec:
    """Remove and return the record of ``name`` (e.g. a test's toy env)."""
    return _REGISTRY.pop(get_env_spec(name).name)


def get_env_spec(name: str) -> EnvSpec:
    """The record of env ``name``; ``ValueError`` lists the registered names."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown env {name!r}; valid choices: {list(_REGISTRY)}.") from None


def check_observation_size(env_name: str, obs_dim: int, source: str) -> None:
    """Refuse networks built for ``obs_dim``-D observations (``source``: e.g. a checkpoint) on env ``env_name`` when
    its observation has another size: a clear ``ValueError`` before any work, not a shape error inside a matmul."""
    expected = get_env_spec(env_name).obs_dim
    if obs_dim != expected:
        raise ValueError(
            f"observation size: got {obs_dim} ({source}); expected {expected}, the observation size of env "
            f"{env_name!r}: they were trained on another observation (another env, or an earlier version of this one: "
            f"ant's was 107-D before it excluded the x-y position); train them again."
        )


#: Names of the registered envs, in registration order: a live view of the registry (an env registered later is in
#: it): ``"point_nav" in ENV_NAMES``, ``list(ENV_NAMES)``.
ENV_NAMES: KeysView[str] = _REGISTRY.keys()
