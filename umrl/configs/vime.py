"""Schema of ``umrl/configs/vime.yaml`` (VIME pre-training, the VIME-init baseline)."""
# ruff: noqa: RUF009  (the field helpers of umrl.configs.validate return dataclasses.field(...) objects)
from __future__ import annotations

from dataclasses import dataclass

from umrl.configs.common import (
    BatchedEnvConfig,
    CheckpointConfig,
    GAEConfig,
    PolicyConfig,
    RunConfig,
    TRPOConfig,
)
from umrl.configs.memory import Allocation, allocation_errors, step_bytes
from umrl.configs.validate import boolean, group, int_list, integer, number


@dataclass
class DynamicsConfig:
    """The Bayesian dynamics model and its training (``holdout_fraction`` in (0, 1))."""

    hidden: list[int] = int_list(min=1, min_len=1)
    prior_std: float = number(gt=0)
    likelihood_std: float = number(gt=0)
    init_std: float | None = number(gt=0)
    num_samples: int = integer(min=1)
    lr: float = number(gt=0)
    batch_size: int = integer(min=1)
    updates_per_iteration: int = integer(min=1)
    replay_size: int = integer(min=1)
    holdout_fraction: float = number(gt=0, lt=1)
    holdout_size: int = integer(min=1)


@dataclass
class BonusConfig:
    eta: float = number(ge=0)
    num_samples: int = integer(min=1)
    median_window: int = integer(min=1)
    shuffle: bool = boolean()


@dataclass
class CoverageConfig:
    cell_size: float | None = number(gt=0)


@dataclass
class VIMECheckpointConfig(CheckpointConfig):
    """:class:`CheckpointConfig` plus ``save_replay`` (store the dynamics data so a resume is faithful)."""

    save_replay: bool = boolean()


@dataclass
class VIMEConfig(RunConfig):
    """Every key of ``umrl/configs/vime.yaml`` (:class:`RunConfig`'s and these); the yaml's comments say what each does."""

    iterations: int = integer(min=1)
    env: BatchedEnvConfig = group(BatchedEnvConfig)
    policy: PolicyConfig = group(PolicyConfig)
    dynamics: DynamicsConfig = group(DynamicsConfig)
    bonus: BonusConfig = group(BonusConfig)
    trpo: TRPOConfig = group(TRPOConfig)
    advantage: GAEConfig = group(GAEConfig)
    coverage: CoverageConfig = group(CoverageConfig)
    checkpoint: VIMECheckpointConfig = group(VIMECheckpointConfig)

    @staticmethod
    def cross_check(cfg: dict) -> list[str]:
        """The batch and the dynamics model's data fit in memory (:func:`memory_errors`; ``device`` is resolved)."""
        return memory_errors(cfg)


def memory_errors(cfg: dict) -> list[str]:
    """A batch of ``env.num_envs`` trajectories and the dynamics model's ``replay_size`` + ``holdout_size`` transitions
    against the memory of ``device`` (:mod:`umrl.configs.memory`)."""
    name, horizon, dyn = cfg["env"]["name"], cfg["env"]["horizon"], cfg["dynamics"]
    transition = step_bytes(name)
    return allocation_errors([
        Allocation("env.num_envs", cfg["env"]["num_envs"], horizon * transition,
                   f"{horizon}-step trajectories", f"with env.horizon={horizon} and env.name={name}"),
        Allocation("dynamics.replay_size", dyn["replay_size"], transition, "dynamics replay", f"with env.name={name}"),
        Allocation("dynamics.holdout_size", dyn["holdout_size"], transition, "held-out transitions",
                   f"with env.name={name}"),
    ], cfg["device"])
