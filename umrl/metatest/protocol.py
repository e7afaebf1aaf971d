"""The meta-test adaptation protocol shared by every method (docs/protocol.md, "Meta-test").

For a policy initialisation and a set of held-out tasks ``[T, task_dim]``:

1. every task gets its own copy of the policy parameters (a TensorDict with a leading task dim ``[T]``);
2. at each adaptation step ``k = 0 … K`` the env batch ``T × N`` (``N`` trajectories per task, task-major) is rolled
   out for ``H`` steps with each task's parameters, and the mean undiscounted return per task is recorded (with
   ``AdaptationConfig.env_steps`` set, each task's batch is instead its first episodes up to that many env steps,
   as the MAML reference code samples: :func:`umrl.rollout.collect_env_steps`);
3. unless ``k = K``, one policy-gradient update is taken on that fresh batch: the per-task VPG losses of
   :mod:`umrl.objectives.policy_gradient` (linear feature baseline, GAE) are summed and differentiated w.r.t. the
   stacked parameters, so row ``t`` of the gradient is task ``t``'s gradient. ``optimizer="sgd"`` is vanilla PG at
   the MAML inner learning rate (UML-DIAYN, UML-random, oracle); ``optimizer="adam"`` is REINFORCE with Adam
   (scratch, DIAYN-init, VIME-init). Adam is element-wise, so one Adam over the stacked parameters equals one Adam
   per task.

SGD follows ``AdaptationConfig.sgd_schedule`` (:func:`sgd_lr_factor`): ``"constant"`` takes every step at ``α``;
``"reference"`` is the MAML reference code's test-time schedule, ``α`` for the first step and ``α / 2`` for every
later one; ``"swept"`` (an ablation, not the paper's protocol) takes ``α`` first and ``f · α`` later, with ``f``
(``AdaptationConfig.sgd_later_factor``) picked per cell on the sweep tasks. Adam always runs at a constant learning
rate.

DIAYN-init first picks, for every task, the skill whose rollouts earn the highest task return
(:func:`select_skills`); the learning-rate sweep (:func:`sweep_learning_rate`) runs on tasks drawn apart from the
held-out set (:func:`sweep_tasks`).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import TransformedEnv

from umrl.envs import make_task_env
from umrl.envs.tasks import get_task_family
from umrl.metatest.stats import auc
from umrl.objectives.policy_gradient import compute_advantages, episode_mean, episode_returns, vpg_loss
from umrl.rollout import FunctionalPolicy, collect, collect_env_steps
from umrl.transforms.skill import SkillTransform
from umrl.validation import check_choice, check_int, check_not_diverged, check_positive, check_probability

OPTIMIZERS = ("sgd", "adam")
#: SGD step-size schedules at meta-test (see :func:`sgd_lr_factor`).
SGD_SCHEDULES = ("constant", "reference", "swept")
#: The SGD schedule of maml_rl's test scripts, umrl's default; tables name an SGD arm after its method alone under it.
DEFAULT_SGD_SCHEDULE = "reference"
#: Offset added to the cell seed to draw learning-rate sweep tasks (never the held-out evaluation tasks).
SWEEP_SEED_OFFSET = 7919


def sgd_lr_factor(schedule: str, step: int, later_factor: float = 0.5) -> float:
    """Multiplier of the SGD learning rate ``α`` for update ``step`` (0-based) under ``schedule``.

    ``"constant"``: 1 for every step. ``"reference"`` (the MAML reference code at test time): 1 for step 0, then 0.5.
    ``"swept"``: 1 for step 0, then ``later_factor``.
    """
    if schedule not in SGD_SCHEDULES:
        raise ValueError(f"sgd_schedule must be one of {list(SGD_SCHEDULES)}, got {schedule!r}.")
    check_positive("later_factor", later_factor)
    if schedule == "constant" or step == 0:
        return 1.0
    return 0.5 if schedule == "reference" else later_factor


@dataclass(frozen=True)
class AdaptationConfig:
    """The meta-test protocol's knobs (docs/protocol.md defaults).

    Attributes:
        num_steps: ``K``, the number of updates; returns are recorded at ``k = 0 … K``.
        num_trajectories: ``N`` fresh trajectories per task at every step.
        horizon: ``H`` env steps per trajectory.
        gamma, lmbda: discount and GAE λ of the advantages.
        normalize_advantage: standardise each task's advantages (rllab's ``center_adv``, as MAML's inner step).
        sgd_schedule: ``"reference"`` (default: maml_rl's ``maml_examples/test_maml_*.py``), ``"constant"`` or
            ``"swept"`` (:func:`sgd_lr_factor`); applies to ``optimizer="sgd"``.
        sgd_later_factor: ``"swept"``'s factor of ``α`` after the first update (> 0); a suite cell replaces it with
            the best of ``sweep.later_factors`` on the sweep tasks. Ignored by the other schedules.
        env_steps: ``None`` (docs/protocol.md): every batch is ``num_trajectories`` trajectories per task. An integer
            ``S`` >= 1: every batch is each task's first episodes up to ``S`` env steps, the last one whole, rolled out
            ``num_trajectories`` at a time (:func:`umrl.rollout.collect_env_steps`), and the recorded return is the
            mean over those episodes: the MAML reference code's test-time sampler (``test_maml_point.py``:
            ``batch_size=4000``, i.e. ``S = 4000``). Where episodes end early, a batch then holds more of them.
    """

    num_steps: int = 20
    num_trajectories: int = 40
    horizon: int = 100
    gamma: float = 0.99
    lmbda: float = 1.0
    normalize_advantage: bool = True
    sgd_schedule: str = DEFAULT_SGD_SCHEDULE
    sgd_later_factor: float = 0.5
    env_steps: int | None = None

    def __post_init__(self):
        check_int("protocol.num_steps", self.num_steps, min=0)
        check_int("protocol.num_trajectories", self.num_trajectories, min=1)
        check_int("protocol.horizon", self.horizon, min=1)
        check_probability("protocol.gamma", self.gamma)
        check_probability("protocol.lmbda", self.lmbda)
        check_choice("protocol.sgd_schedule", self.sgd_schedule, SGD_SCHEDULES)
        check_positive("protocol.sgd_later_factor", self.sgd_later_factor)
        if self.env_steps is not None:
            check_int("protocol.env_steps", self.env_steps, min=1)


def make_eval_env(env_name: str, tasks: torch.Tensor, num_trajectories: int, *, seed: int, horizon: int,
                  skills: torch.Tensor | None = None, num_skills: int | None = None,
                  device: torch.device | str = "cpu") -> TransformedEnv:
    """Task env with batch ``T × N`` (task-major: copy ``t * N + n`` solves ``tasks[t]``) whose tensors live on
    ``device`` (MuJoCo physics stays on CPU threads; its outputs move once per step).

    With ``skills`` (LongTensor ``[T]``) a :class:`SkillTransform` of ``num_skills`` is appended and copy
    ``t * N + n`` runs skill ``skills[t]``.
    """
    env = make_task_env(env_name, tasks.repeat_interleave(num_trajectories, 0), seed=seed, horizon=horizon,
                        device=device)
    if skills is not None:
        if num_skills is None:
            raise ValueError("num_skills is required when skills are pinned.")
        if skills.shape != (tasks.shape[0],):
            raise ValueError(f"give one skill per task: skills {tuple(skills.shape)} vs {tasks.shape[0]} tasks.")
        skill_transform = SkillTransform(num_skills)
        env.append_transform(skill_transform)
        skill_transform.pin(skills.repeat_interleave(num_trajectories, 0))
    return env


class TaskAdapter:
    """Adapts per-task copies of ``policy``'s parameters on ``T`` tasks at once.

    Args:
        policy: a TorchRL probabilistic actor (writes ``"action"``; ``get_dist`` gives the action distribution).
        env: env whose batch is ``T × N`` task-major (see :func:`make_eval_env`).
        num_tasks: ``T``.

    Keyword Args:
        optimizer: ``"sgd"`` (vanilla PG, MAML initialisations) or ``"adam"`` (REINFORCE + Adam).
        lr: learning rate (> 0); for SGD the base ``α`` of ``config.sgd_schedule``.
        config: the protocol (:class:`AdaptationConfig`).

    The per-task parameters, the optimizer state and every batch live on ``env.device``.

    Attributes:
        params: per-task parameters, a TensorDict with batch size ``[T]`` whose leaves the optimizer updates.
        scheduler: a ``torch.optim.lr_scheduler.LambdaLR`` applying ``config.sgd_schedule`` (SGD only, else None).
    """

    def __init__(self, policy: TensorDictModuleBase, env: TransformedEnv, num_tasks: int, *, optimizer: str,
                 lr: float, config: AdaptationConfig = AdaptationConfig()):
        if optimizer not in OPTIMIZERS:
            raise ValueError(f"unknown optimizer {optimizer!r}; valid choices: {list(OPTIMIZERS)}.")
        check_positive("lr", lr)
        if env.batch_size.numel() != num_tasks * config.num_trajectories:
            raise ValueError(
                f"env batch {tuple(env.batch_size)} != {num_tasks} tasks x {config.num_trajectories} trajectories."
            )
        self.policy, self.env, self.num_tasks, self.config = policy, env, num_tasks, config
        self.functional = FunctionalPolicy(policy)  # all tasks batched: one baddbmm per layer
        base = TensorDict.from_module(policy).detach().to(env.device)
        self.params = base.expand(num_tasks).clone()
        leaves = [p.requires_grad_() for p in self.params.values(True, True) if p.is_floating_point()]
        cls = torch.optim.SGD if optimizer == "sgd" else torch.optim.Adam
        self.optimizer = cls(leaves, lr=lr)
        self.scheduler = None
        if optimizer == "sgd":
            schedule, later = config.sgd_schedule, config.sgd_later_factor
            self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer,
                                                               lambda k: sgd_lr_factor(schedule, k, later))

    def collect(self) -> TensorDictBase:
        """Roll out ``N`` trajectories per task with each task's current parameters: a ``[T, N, H]`` TensorDict
        (with ``config.env_steps``, each task's first episodes up to that many steps: ``[T, M, H]``)."""
        rollout = {"num_tasks": self.num_tasks, "horizon": self.config.horizon, "params": self.params.detach()}
        with torch.no_grad():
            if self.config.env_steps is None:
                return collect(self.env, self.policy, **rollout)
            return collect_env_steps(self.env, self.policy, env_steps=self.config.env_steps, **rollout)

    def step(self, batch: TensorDictBase) -> torch.Tensor:
        """One update from ``batch`` ``[T, N, H]``; returns the per-task losses ``[T]`` (detached)."""
        batch = compute_advantages(batch, gamma=self.config.gamma, lmbda=self.config.lmbda,
                                   normalize=self.config.normalize_advantage)
        log_prob = self.functional.log_prob(self.params, batch)
        losses = vpg_loss(log_prob, batch)
        check_not_diverged({"loss_objective": losses}, "meta-test adaptation")
        self.optimizer.zero_grad()
        losses.sum().backward()
        self.optimizer.step()
        if self.scheduler is not None:
            self.scheduler.step()
        return losses.detach()

    def run(self, observe: Callable[[int, TensorDictBase], None] | None = None) -> torch.Tensor:
        """Returns ``[K + 1, T]``: the mean undiscounted return of each task before each update and after the last.

        ``observe(k, batch)``, if given, sees each step's ``[T, N, H]`` batch before the update it feeds (average
        per-trajectory figures over it with :func:`umrl.objectives.policy_gradient.episode_mean`).
        """
        returns = []
        for k in range(self.config.num_steps + 1):
            batch = self.collect()
            returns.append(episode_mean(episode_returns(batch), batch))
            if observe is not None:
                observe(k, batch)
            if k < self.config.num_steps:
                self.step(batch)
        return torch.stack(returns)


def select_skills(policy: TensorDictModuleBase, env_name: str, tasks: torch.Tensor, num_skills: int, *,
                  num_trajectories: int, seed: int, horizon: int = 100,
                  device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """DIAYN-init's skill choice: roll out every skill on every task, keep the best.

    The env batch is ``T × K × n`` (``n = num_trajectories``); one policy call per step. The env runs on ``device``,
    where ``policy`` must live; both outputs are on ``device``.

    Returns:
        ``(best [T] long, returns [T, K])``: the skill with the highest mean task return per task and all means.
    """
    num_tasks = tasks.shape[0]
    # one (task, skill) pair per "task" of the eval env: pair t * K + k solves tasks[t] with skill k
    env = make_eval_env(env_name, tasks.repeat_interleave(num_skills, 0), num_trajectories, seed=seed, horizon=horizon,
                        skills=torch.arange(num_skills).repeat(num_tasks), num_skills=num_skills, device=device)
    batch = collect(env, policy, num_tasks=num_tasks * num_skills, horizon=horizon)
    env.close()
    returns = episode_returns(batch).mean(-1).reshape(num_tasks, num_skills)
    return returns.argmax(-1), returns


def sweep_learning_rate(run: Callable[[float, torch.Tensor], torch.Tensor], lrs: Sequence[float],
                        tasks: torch.Tensor) -> tuple[float, dict[float, float]]:
    """Pick the step size whose adaptation has the largest mean AUC on ``tasks`` (never the evaluation tasks): the
    Adam learning rate, or the ``"swept"`` SGD schedule's later-step factor.

    Args:
        run: ``run(value, tasks) -> returns [K + 1, T]`` (a full adaptation from the initialisation).
        lrs: the grid.
        tasks: sweep tasks ``[T', task_dim]``.

    Returns:
        ``(best_lr, {lr: mean AUC})``.
    """
    if not lrs:
        raise ValueError("the learning-rate sweep needs at least one value.")
    scores = {}
    for lr in lrs:
        returns = run(float(lr), tasks).cpu().numpy()
        score = float(auc(returns.T).mean())
        scores[float(lr)] = score if math.isfinite(score) else -math.inf
    return max(scores, key=scores.get), scores


def sweep_tasks(env_name: str, num_tasks: int, seed: int) -> torch.Tensor:
    """Tasks for the learning-rate sweep: drawn from the family with a seed unrelated to the held-out set."""
    generator = torch.Generator().manual_seed(seed + SWEEP_SEED_OFFSET)
    return get_task_family(env_name).sample(num_tasks, generator)
