"""Schema of ``umrl/configs/vime.yaml`` (VIME pre-training, the VIME-init baseline)."""
# ruff: noqa: RUF009  (the field helpers of umrl.configs.validate return dataclasses.field(...) objects)
from __future__ import annotations

from dataclasses import dataclass

from umrl.configs.common import (
    BatchedEnvConfig,
    CheckpointConfig,
    PolicyConfig,
    RunConfig,
    TRPOConfig,
)
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
class VIMETRPOConfig(TRPOConfig):
    """:class:`TRPOConfig` plus the discount and GAE lambda (each in [0, 1])."""

    gamma: float = number(ge=0, le=1)
    gae_lambda: float = number(ge=0, le=1)


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
    trpo: VIMETRPOConfig = group(VIMETRPOConfig)
    coverage: CoverageConfig = group(CoverageConfig)
    checkpoint: VIMECheckpointConfig = group(VIMECheckpointConfig)
