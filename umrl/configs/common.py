"""Config groups shared by several schemas: env, logger, checkpoint, TRPO and policy settings."""
# ruff: noqa: RUF009  (the field helpers of umrl.configs.validate return dataclasses.field(...) objects)
from __future__ import annotations

from dataclasses import dataclass

from umrl.configs.validate import (
    boolean,
    checked,
    choice,
    device,
    group,
    int_list,
    integer,
    name,
    number,
    seed,
    string,
    writable_dir,
)
from umrl.envs import BACKENDS
from umrl.envs.user_envs import check_env_name, import_env_module
from umrl.loggers import check_logger_backend
from umrl.validation import MAX_THREADS, InvalidValue

LOGGER_MODES = ("offline", "online", "disabled")


@dataclass
class EnvConfig:
    """``module`` (null, or a module or ``.py`` file imported first: it may register envs), ``name`` (one of
    :data:`umrl.envs.ENV_NAMES`, read after ``module``), ``horizon`` (steps per episode, >= 1)."""

    module: str | None = checked(import_env_module)  # before name: the registry it reads may grow
    name: str = checked(check_env_name)
    horizon: int = integer(min=1)


@dataclass
class BatchedEnvConfig(EnvConfig):
    """:class:`EnvConfig` plus ``num_envs`` (copies stepped as one batch) and the MuJoCo ``backend``."""

    num_envs: int = integer(min=1)
    backend: str = choice(BACKENDS)


@dataclass
class LoggerConfig:
    """``backend`` wandb | csv | none, wandb ``project``, ``group`` (null: none) and ``mode``."""

    backend: str = checked(check_logger_backend)  # a $WANDB_DIR wandb could not write is refused
    project: str = string()
    group: str | None = string()
    mode: str = choice(LOGGER_MODES)


@dataclass
class RunLoggerConfig(LoggerConfig):
    """:class:`LoggerConfig` plus the run's ``exp_name``."""

    exp_name: str = name()  # a folder name under <output_dir>/csv


@dataclass
class RunConfig:
    """The keys every recipe has: ``seed`` (in [0, 2**63 - 1]), ``device`` (cpu | cuda | auto), ``num_threads``
    (torch intra-op threads, >= 1), the run's ``logger``, ``output_dir`` (a writable directory), ``resume`` and
    ``progress`` (the tqdm bar). Each recipe's schema extends it."""

    seed: int = seed()
    device: str = device()
    num_threads: int = integer(min=1, max=MAX_THREADS)
    logger: RunLoggerConfig = group(RunLoggerConfig)
    output_dir: str = writable_dir()
    resume: bool = boolean()
    progress: bool = boolean()


@dataclass
class CheckpointConfig:
    """``every`` (iterations or frames between checkpoints, >= 1) and ``keep_all`` (else only the latest)."""

    every: int = integer(min=1)
    keep_all: bool = boolean()


@dataclass
class PolicyConfig:
    """The Gaussian policy: ``hidden`` layer widths (non-empty, each >= 1) and ``init_std`` (> 0)."""

    hidden: list[int] = int_list(min=1, min_len=1)
    init_std: float = number(gt=0)


@dataclass
class GAEConfig:
    """Advantages by GAE: discount ``gamma`` and ``lmbda`` (TorchRL's name for GAE's λ), each in [0, 1]."""

    gamma: float = number(ge=0, le=1)
    lmbda: float = number(ge=0, le=1)


@dataclass
class TRPOConfig:
    """TRPO step: ``max_kl`` > 0, ``damping`` >= 0, ``cg_iters`` >= 1, ``backtrack_ratio`` in (0, 1),
    ``max_backtracks`` >= 0."""

    max_kl: float = number(gt=0)
    damping: float = number(ge=0)
    cg_iters: int = integer(min=1)
    backtrack_ratio: float = number(gt=0, lt=1)
    max_backtracks: int = integer(min=0)


def cudagraphs_errors(cudagraphs: bool, device: str, key: str) -> list[str]:
    """The error of a CUDA-graph switch ``key`` set true on a device other than CUDA (``device`` resolved:
    ``cpu``/``cuda``)."""
    return _cuda_only_errors(key, cudagraphs, device, "CUDA graphs need device=cuda, or auto on a machine with a GPU")


def _cuda_only_errors(key: str, value: bool, device: str, why: str) -> list[str]:
    if value and device != "cuda":
        return [InvalidValue(key, True, f"false with device={device} ({why})").message()]
    return []
