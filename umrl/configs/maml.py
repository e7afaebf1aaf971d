"""Schema of ``umrl/configs/maml.yaml`` (MAML meta-training: UML-DIAYN, UML-random, oracle, and the
``random_arena`` ablation)."""
# ruff: noqa: RUF009  (the field helpers of umrl.configs.validate return dataclasses.field(...) objects)
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from umrl.configs.common import (
    CheckpointConfig,
    EnvConfig,
    GAEConfig,
    PolicyConfig,
    RunConfig,
    TRPOConfig,
    cudagraphs_errors,
)
from umrl.configs.memory import Allocation, allocation_errors, step_bytes
from umrl.configs.validate import boolean, checked, choice, group, int_list, integer, number, string
from umrl.optim.meta_hvp import META_HVPS
from umrl.proposals import PROPOSALS
from umrl.rollout import SAMPLE_BY
from umrl.validation import InvalidValue, check_bool, check_path_exists

COMPILE_UNSUPPORTED = (
    "torch.compile cannot differentiate a compiled graph twice, and MAML's meta-gradient and KL Hessian-vector "
    "products are second derivatives through the inner step"
)
"""Why ``compile=true`` is refused."""

HVP_MODES = tuple(META_HVPS)
"""``trpo.hvp``: ``gauss_newton`` (J^T F J through the inner step, by autograd), ``analytic`` (the same product
derived by hand for the ReLU MLP policy: equal to float rounding, faster) or ``exact`` (the KL's Hessian); the
strategies are :data:`umrl.optim.meta_hvp.META_HVPS`."""


@dataclass
class MAMLEnvConfig(EnvConfig):
    """:class:`EnvConfig` plus ``arena`` (null or > 0): point_nav's position bound during meta-training."""

    arena: float | None = number(gt=0)


@dataclass
class MAMLPolicyConfig(PolicyConfig):
    """:class:`PolicyConfig` plus ``learn_std``: false keeps the std at ``init_std`` in the inner step, the TRPO
    step and the meta-test's adaptation (an ablation; maml_rl's ``MAMLGaussianMLPPolicy`` learns it,
    ``learn_std=True`` at ``sandbox/rocky/tf/policies/maml_minimal_gauss_mlp_policy.py`` line 33)."""

    learn_std: bool = boolean()


@dataclass
class InnerConfig:
    """``maml`` group: inner step size and count, FOMAML switch, per-task loop (true) / vmap (false) / auto (null)."""

    inner_lr: float = number(gt=0)
    num_inner_steps: int = integer(min=1)
    first_order: bool = boolean()
    task_loop: bool | None = boolean()


@dataclass
class AdvantageConfig(GAEConfig):
    """:class:`GAEConfig` plus ``normalize`` (standardise each task's advantages)."""

    normalize: bool = boolean()


@dataclass
class MetaTRPOConfig(TRPOConfig):
    """:class:`TRPOConfig` plus the Hessian-vector product (``hvp``) and the batch share it uses (in (0, 1])."""

    hvp: str = choice(HVP_MODES)
    hvp_fraction: float = number(gt=0, le=1)


def hvp_errors(cfg: Mapping) -> list[str]:
    """``trpo.hvp`` against the inner step it differentiates (a composed MAML config, also checked by the suite before
    its pre-training runs start): a Gauss–Newton product needs one inner step, ``analytic`` also the task-batched
    MLP (``maml.task_loop=null``) and a learned std (it differentiates the log-std by hand)."""
    errors, hvp, inner = [], cfg["trpo"]["hvp"], cfg["maml"]
    if hvp != "exact" and inner["num_inner_steps"] != 1:
        errors.append(InvalidValue("maml.num_inner_steps", inner["num_inner_steps"],
                                   f"1 with trpo.hvp={hvp} (it differentiates one inner step; trpo.hvp=exact "
                                   "takes any number)").message())
    if hvp == "analytic" and inner["task_loop"] is not None:
        errors.append(InvalidValue("maml.task_loop", inner["task_loop"],
                                   "null with trpo.hvp=analytic (it differentiates the task-batched MLP; "
                                   "trpo.hvp=gauss_newton takes any)").message())
    if hvp == "analytic" and not cfg["policy"]["learn_std"]:
        errors.append(InvalidValue("trpo.hvp", hvp, "gauss_newton or exact with policy.learn_std=false (analytic "
                                   "differentiates a learned log-std by hand)").message())
    return errors


SKILL_COUNT_SOURCE = {
    "diayn": "the skill count comes from the DIAYN checkpoint",
    "oracle": "the oracle proposes the env's tasks, not skills; meta_batch_size sets how many",
}
"""The proposals that take no ``num_skills``, and where their task count comes from instead."""


def num_skills_errors(proposal: str, num_skills: int | None, key: str = "num_skills") -> list[str]:
    """The error of a ``num_skills`` (config key ``key``) set with a proposal that has no use for it
    (:data:`SKILL_COUNT_SOURCE`): it would be ignored."""
    if num_skills is None or proposal not in SKILL_COUNT_SOURCE:
        return []
    return [InvalidValue(key, num_skills, f"null with proposal={proposal} ({SKILL_COUNT_SOURCE[proposal]})").message()]


def memory_errors(cfg: Mapping) -> list[str]:
    """The meta-batch's rollouts, held together for the meta-gradient (``maml.num_inner_steps`` + 1 batches of
    tasks x ``trajectories_per_task`` x ``env.horizon`` steps), against the memory of ``device``
    (:mod:`umrl.configs.memory`). With ``proposal=diayn`` and a null ``meta_batch_size`` the task count is the DIAYN
    checkpoint's, unread here: one task is counted."""
    name, horizon, batches = cfg["env"]["name"], cfg["env"]["horizon"], cfg["maml"]["num_inner_steps"] + 1
    tasks = cfg["meta_batch_size"] or (1 if cfg["proposal"] == "diayn" else cfg["num_skills"]
                                       or cfg["default_num_skills"])
    trajectory = tasks * horizon * batches * step_bytes(name)
    what = f"rollouts: {tasks} tasks x {horizon} steps x {batches} batches (pre-update, after each inner step)"
    given = f"with {tasks} tasks, env.horizon={horizon} and env.name={name}"
    return allocation_errors([Allocation("trajectories_per_task", cfg["trajectories_per_task"], trajectory, what, given)],
                             cfg["device"])


def _compile_off(name: str, value) -> bool:
    """``compile`` must be false (a field check, so a suite's ``pretrain.maml.overrides`` is refused at start too)."""
    if check_bool(name, value):
        raise InvalidValue(name, True, "false (set compile=false)", COMPILE_UNSUPPORTED)
    return False


@dataclass
class MAMLConfig(RunConfig):
    """Every key of ``umrl/configs/maml.yaml`` (:class:`RunConfig`'s and these); the yaml's comments say what each does."""

    env: MAMLEnvConfig = group(MAMLEnvConfig)
    proposal: str = choice(PROPOSALS)
    diayn_checkpoint: str = string()
    num_skills: int | None = integer(min=2)
    meta_batch_size: int | None = integer(min=1)
    default_num_skills: int = integer(min=2)
    discriminator_hidden: list[int] = int_list(min=1, min_len=1)
    trajectories_per_task: int = integer(min=1)
    sample_by: str = choice(SAMPLE_BY)
    iterations: int = integer(min=1)
    policy: MAMLPolicyConfig = group(MAMLPolicyConfig)
    maml: InnerConfig = group(InnerConfig)
    advantage: AdvantageConfig = group(AdvantageConfig)
    trpo: MetaTRPOConfig = group(MetaTRPOConfig)
    checkpoint: CheckpointConfig = group(CheckpointConfig)
    compile: bool = checked(_compile_off)
    cudagraphs: bool = boolean()

    @staticmethod
    def cross_check(cfg: dict) -> list[str]:
        """``proposal=diayn`` needs an existing ``diayn_checkpoint``; CUDA graphs run on a CUDA device (``device`` is
        resolved here; which envs they can record is checked when the env exists, see
        :func:`umrl.rollout.check_cudagraphs`); ``trpo.hvp`` other than ``exact`` needs one inner step, and
        ``analytic`` the batched policy (``maml.task_loop=null``); ``num_skills`` only with a proposal that uses it
        (:func:`num_skills_errors`); the rollouts fit in memory (:func:`memory_errors`)."""
        errors = cudagraphs_errors(cfg["cudagraphs"], cfg["device"], "cudagraphs")
        errors += hvp_errors(cfg) + num_skills_errors(cfg["proposal"], cfg["num_skills"]) + memory_errors(cfg)
        if cfg["proposal"] == "diayn":
            try:
                check_path_exists("diayn_checkpoint", cfg["diayn_checkpoint"])
            except InvalidValue as e:
                e.expected += " (a DIAYN run directory or step_*.safetensors file: proposal=diayn needs it)"
                errors.append(e.message())
        return errors
