"""Schema of ``recipes/config/maml.yaml`` (MAML meta-training: UML-DIAYN, UML-random, oracle, and the
``random_arena`` ablation)."""
# ruff: noqa: RUF009  (the field helpers of umrl.configs.validate return dataclasses.field(...) objects)
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from umrl.configs.common import (
    CheckpointConfig,
    EnvConfig,
    PolicyConfig,
    RunConfig,
    TRPOConfig,
    cudagraphs_errors,
)
from umrl.configs.validate import boolean, checked, choice, group, integer, number, string
from umrl.envs import get_env_spec
from umrl.proposals import PROPOSALS
from umrl.validation import InvalidValue, check_bool, check_path_exists

COMPILE_UNSUPPORTED = (
    "torch.compile cannot differentiate a compiled graph twice, and MAML's meta-gradient and KL Hessian-vector "
    "products are second derivatives through the inner step"
)
"""Why ``compile=true`` is refused."""

HVP_MODES = ("gauss_newton", "analytic", "exact")
"""``trpo.hvp``: ``gauss_newton`` (J^T F J through the inner step, by autograd), ``analytic`` (the same product
derived by hand for the ReLU MLP policy: equal to float rounding, faster) or ``exact`` (the KL's Hessian)."""


@dataclass
class MAMLEnvConfig(EnvConfig):
    """:class:`EnvConfig` plus ``arena`` (null or > 0): point_nav's position bound during meta-training."""

    arena: float | None = number(gt=0)


@dataclass
class InnerConfig:
    """``maml`` group: inner step size and count, FOMAML switch, per-task loop (true) / vmap (false) / auto (null)."""

    inner_lr: float = number(gt=0)
    num_inner_steps: int = integer(min=1)
    first_order: bool = boolean()
    task_loop: bool | None = boolean()


@dataclass
class AdvantageConfig:
    gamma: float = number(ge=0, le=1)
    lmbda: float = number(ge=0, le=1)
    normalize: bool = boolean()


@dataclass
class MetaTRPOConfig(TRPOConfig):
    """:class:`TRPOConfig` plus the Hessian-vector product (``hvp``) and the batch share it uses (in (0, 1])."""

    hvp: str = choice(HVP_MODES)
    hvp_fraction: float = number(gt=0, le=1)


def hvp_errors(cfg: Mapping) -> list[str]:
    """``trpo.hvp`` against the inner step it differentiates (a composed MAML config, also checked by the suite before
    its pre-training runs start): a Gauss–Newton product needs one inner step, ``analytic`` also the task-batched
    MLP (``maml.task_loop=null``)."""
    errors, hvp, inner = [], cfg["trpo"]["hvp"], cfg["maml"]
    if hvp != "exact" and inner["num_inner_steps"] != 1:
        errors.append(InvalidValue("maml.num_inner_steps", inner["num_inner_steps"],
                                   f"1 with trpo.hvp={hvp} (it differentiates one inner step; trpo.hvp=exact "
                                   "takes any number)").message())
    if hvp == "analytic" and inner["task_loop"] is not None:
        errors.append(InvalidValue("maml.task_loop", inner["task_loop"],
                                   "null with trpo.hvp=analytic (it differentiates the task-batched MLP; "
                                   "trpo.hvp=gauss_newton takes any)").message())
    return errors


def _compile_off(name: str, value) -> bool:
    """``compile`` must be false (a field check, so a suite's ``pretrain.maml.overrides`` is refused at start too)."""
    if check_bool(name, value):
        raise InvalidValue(name, True, "false (set compile=false)", COMPILE_UNSUPPORTED)
    return False


@dataclass
class MAMLConfig(RunConfig):
    """Every key of ``recipes/config/maml.yaml`` (:class:`RunConfig`'s and these); the yaml's comments say what each does."""

    env: MAMLEnvConfig = group(MAMLEnvConfig)
    proposal: str = choice(PROPOSALS)
    diayn_checkpoint: str = string()
    num_skills: int | None = integer(min=2)
    meta_batch_size: int | None = integer(min=1)
    trajectories_per_task: int = integer(min=1)
    iterations: int | None = integer(min=1)
    policy: PolicyConfig = group(PolicyConfig)
    maml: InnerConfig = group(InnerConfig)
    advantage: AdvantageConfig = group(AdvantageConfig)
    trpo: MetaTRPOConfig = group(MetaTRPOConfig)
    checkpoint: CheckpointConfig = group(CheckpointConfig)
    compile: bool = checked(_compile_off)
    cudagraphs: bool = boolean()

    @staticmethod
    def fill_env_defaults(cfg: dict) -> None:
        """Null ``iterations``: the env's ``EnvSpec.maml_iterations`` (the MAML reference code's run length)."""
        if cfg["iterations"] is None:
            cfg["iterations"] = get_env_spec(cfg["env"]["name"]).maml_iterations

    @staticmethod
    def cross_check(cfg: dict) -> list[str]:
        """``proposal=diayn`` needs an existing ``diayn_checkpoint``; CUDA graphs run on a CUDA device (``device`` is
        resolved here; which envs they can record is checked when the env exists, see
        :func:`umrl.rollout.check_cudagraphs`); ``trpo.hvp`` other than ``exact`` needs one inner step, and
        ``analytic`` the batched policy (``maml.task_loop=null``)."""
        errors = cudagraphs_errors(cfg["cudagraphs"], cfg["device"], "cudagraphs")
        errors += hvp_errors(cfg)
        if cfg["proposal"] == "diayn":
            try:
                check_path_exists("diayn_checkpoint", cfg["diayn_checkpoint"])
            except InvalidValue as e:
                e.expected += " (a DIAYN run directory or step_*.pt file: proposal=diayn needs it)"
                errors.append(e.message())
        return errors
