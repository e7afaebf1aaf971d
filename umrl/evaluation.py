"""Meta-test evaluation: one adaptation protocol shared by every method (PROTOCOL.md, "Meta-test").

For a policy initialisation and a set of held-out tasks ``[T, task_dim]``:

1. every task gets its own copy of the policy parameters (a TensorDict with a leading task dim ``[T]``);
2. at each adaptation step ``k = 0 … K`` the env batch ``T × N`` (``N`` trajectories per task, task-major) is rolled
   out for ``H`` steps with each task's parameters, and the mean undiscounted return per task is recorded;
3. unless ``k = K``, one policy-gradient update is taken on that fresh batch: the per-task VPG losses of
   :mod:`umrl.objectives.policy_gradient` (linear feature baseline, GAE) are summed and differentiated w.r.t. the
   stacked parameters, so row ``t`` of the gradient is task ``t``'s gradient. ``optimizer="sgd"`` is vanilla PG at
   the MAML inner learning rate (UML-DIAYN, UML-random, oracle); ``optimizer="adam"`` is REINFORCE with Adam
   (scratch, DIAYN-init, VIME-init). Adam is element-wise, so one Adam over the stacked parameters equals one Adam
   per task.

All tasks adapt in one batched run. Results are a tidy table with columns :data:`COLUMNS` (one row per method, env,
seed, task and step), written as CSV.

DIAYN-init first picks, for every task, the skill whose rollouts earn the highest task return
(:func:`select_skills`), then fine-tunes the skill-conditioned policy with that skill pinned.
"""
from __future__ import annotations

import csv
import json
import math
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import TransformedEnv

from umrl.envs import make_env, make_task_env
from umrl.envs.tasks import get_task_family
from umrl.modules.policy import make_gaussian_policy
from umrl.objectives.policy_gradient import compute_advantages, episode_returns, vpg_loss
from umrl.plots import Curve
from umrl.rollout import FunctionalPolicy, collect
from umrl.runtime import check_finite, seed_everything
from umrl.stats import auc, bootstrap_ci, summarize
from umrl.transforms.skill import SkillTransform

#: Columns of the tidy results table.
COLUMNS = ("method", "env", "seed", "task", "step", "return")
OPTIMIZERS = ("sgd", "adam")
#: Offset added to the cell seed to draw learning-rate sweep tasks (never the held-out evaluation tasks).
SWEEP_SEED_OFFSET = 7919


@dataclass(frozen=True)
class AdaptationConfig:
    """The meta-test protocol's knobs (PROTOCOL.md defaults).

    Attributes:
        num_steps: ``K``, the number of updates; returns are recorded at ``k = 0 … K``.
        num_trajectories: ``N`` fresh trajectories per task at every step.
        horizon: ``H`` env steps per trajectory.
        gamma, lmbda: discount and GAE λ of the advantages.
        normalize_advantage: standardise each task's advantages (rllab's ``center_adv``, as MAML's inner step).
    """

    num_steps: int = 10
    num_trajectories: int = 40
    horizon: int = 100
    gamma: float = 0.99
    lmbda: float = 1.0
    normalize_advantage: bool = True

    def __post_init__(self):
        if self.num_steps < 0 or self.num_trajectories < 1 or self.horizon < 1:
            raise ValueError(
                f"need num_steps >= 0, num_trajectories >= 1 and horizon >= 1, got {self.num_steps}, "
                f"{self.num_trajectories} and {self.horizon}."
            )


def make_eval_env(env_name: str, tasks: torch.Tensor, num_trajectories: int, *, seed: int, horizon: int,
                  skills: torch.Tensor | None = None, num_skills: int | None = None) -> TransformedEnv:
    """Task env with batch ``T × N`` (task-major: copy ``t * N + n`` solves ``tasks[t]``).

    With ``skills`` (LongTensor ``[T]``) a :class:`SkillTransform` of ``num_skills`` is appended and copy
    ``t * N + n`` runs skill ``skills[t]``.
    """
    env = make_task_env(env_name, tasks.repeat_interleave(num_trajectories, 0), seed=seed, horizon=horizon)
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
        lr: learning rate (> 0).
        config: the protocol (:class:`AdaptationConfig`).

    Attributes:
        params: per-task parameters, a TensorDict with batch size ``[T]`` whose leaves the optimizer updates.
    """

    def __init__(self, policy: TensorDictModuleBase, env: TransformedEnv, num_tasks: int, *, optimizer: str,
                 lr: float, config: AdaptationConfig = AdaptationConfig()):
        if optimizer not in OPTIMIZERS:
            raise ValueError(f"unknown optimizer {optimizer!r}; valid choices: {list(OPTIMIZERS)}.")
        if not lr > 0:
            raise ValueError(f"lr must be positive, got {lr}.")
        if env.batch_size.numel() != num_tasks * config.num_trajectories:
            raise ValueError(
                f"env batch {tuple(env.batch_size)} != {num_tasks} tasks x {config.num_trajectories} trajectories."
            )
        self.policy, self.env, self.num_tasks, self.config = policy, env, num_tasks, config
        self.functional = FunctionalPolicy(policy)  # loop or vmap over tasks, by per-task batch size
        base = TensorDict.from_module(policy).detach()
        self.params = base.expand(num_tasks).clone()
        leaves = [p.requires_grad_() for p in self.params.values(True, True) if p.is_floating_point()]
        cls = torch.optim.SGD if optimizer == "sgd" else torch.optim.Adam
        self.optimizer = cls(leaves, lr=lr)

    def collect(self) -> TensorDictBase:
        """Roll out ``N`` trajectories per task with each task's current parameters: a ``[T, N, H]`` TensorDict."""
        with torch.no_grad():
            return collect(self.env, self.policy, num_tasks=self.num_tasks, horizon=self.config.horizon,
                           params=self.params.detach())

    def step(self, batch: TensorDictBase) -> torch.Tensor:
        """One update from ``batch`` ``[T, N, H]``; returns the per-task losses ``[T]`` (detached)."""
        batch = compute_advantages(batch, gamma=self.config.gamma, lmbda=self.config.lmbda,
                                   normalize=self.config.normalize_advantage)
        log_prob = self.functional.log_prob(self.params, batch)
        losses = vpg_loss(log_prob, batch)
        check_finite({"loss_objective": losses}, "meta-test adaptation")
        self.optimizer.zero_grad()
        losses.sum().backward()
        self.optimizer.step()
        return losses.detach()

    def run(self) -> torch.Tensor:
        """Returns ``[K + 1, T]``: the mean undiscounted return of each task before each update and after the last."""
        returns = []
        for k in range(self.config.num_steps + 1):
            batch = self.collect()
            returns.append(episode_returns(batch).mean(-1))
            if k < self.config.num_steps:
                self.step(batch)
        return torch.stack(returns)


def select_skills(policy: TensorDictModuleBase, env_name: str, tasks: torch.Tensor, num_skills: int, *,
                  num_trajectories: int, seed: int, horizon: int = 100) -> tuple[torch.Tensor, torch.Tensor]:
    """DIAYN-init's skill choice: roll out every skill on every task, keep the best.

    The env batch is ``T × K × n`` (``n = num_trajectories``); one policy call per step.

    Returns:
        ``(best [T] long, returns [T, K])``: the skill with the highest mean task return per task and all means.
    """
    num_tasks = tasks.shape[0]
    # one (task, skill) pair per "task" of the eval env: pair t * K + k solves tasks[t] with skill k
    env = make_eval_env(env_name, tasks.repeat_interleave(num_skills, 0), num_trajectories, seed=seed, horizon=horizon,
                        skills=torch.arange(num_skills).repeat(num_tasks), num_skills=num_skills)
    batch = collect(env, policy, num_tasks=num_tasks * num_skills, horizon=horizon)
    env.close()
    returns = episode_returns(batch).mean(-1).reshape(num_tasks, num_skills)
    return returns.argmax(-1), returns


def sweep_learning_rate(run: Callable[[float, torch.Tensor], torch.Tensor], lrs: Sequence[float],
                        tasks: torch.Tensor) -> tuple[float, dict[float, float]]:
    """Pick the learning rate whose adaptation has the largest mean AUC on ``tasks`` (never the evaluation tasks).

    Args:
        run: ``run(lr, tasks) -> returns [K + 1, T]`` (a full adaptation from the initialisation).
        lrs: the grid.
        tasks: sweep tasks ``[T', task_dim]``.

    Returns:
        ``(best_lr, {lr: mean AUC})``.
    """
    if not lrs:
        raise ValueError("the learning-rate sweep needs at least one value.")
    scores = {}
    for lr in lrs:
        returns = run(float(lr), tasks).numpy()
        score = float(auc(returns.T).mean())
        scores[float(lr)] = score if math.isfinite(score) else -math.inf
    return max(scores, key=scores.get), scores


def sweep_tasks(env_name: str, num_tasks: int, seed: int) -> torch.Tensor:
    """Tasks for the learning-rate sweep: drawn from the family with a seed unrelated to the held-out set."""
    generator = torch.Generator().manual_seed(seed + SWEEP_SEED_OFFSET)
    return get_task_family(env_name).sample(num_tasks, generator)


# ----------------------------------------------------------------------------------------------------------------
# Methods: what each one hands to meta-test, and one cell = (method, env, seed).

#: Method name -> (pre-training that produces its initialisation, update rule at meta-test).
METHODS = {
    "uml_diayn": ("maml_diayn", "sgd"),
    "uml_random": ("maml_random", "sgd"),
    "oracle": ("maml_oracle", "sgd"),
    "vime_init": ("vime", "adam"),
    "diayn_init": ("diayn", "adam"),
    "scratch": (None, "adam"),
}


@dataclass
class Initialisation:
    """A policy to adapt, its update rule and (DIAYN-init) the skill count; ``lr`` is the SGD step of MAML inits."""

    policy: TensorDictModuleBase
    optimizer: str
    lr: float | None = None
    num_skills: int | None = None


def env_dims(env_name: str) -> tuple[int, int]:
    """``(obs_dim, act_dim)`` of an env (builds one copy)."""
    env = make_env(env_name, 1)
    dims = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    env.close()
    return dims


def load_initialisation(method: str, env_name: str, checkpoint: str | os.PathLike | None, *,
                        seed: int) -> Initialisation:
    """The policy ``method`` starts meta-test from (see :data:`METHODS`); ``checkpoint`` is its pre-training output.

    scratch draws a fresh 2x300 Gaussian policy from ``seed``; the MAML inits return the SGD step size they were
    meta-trained with as ``lr``.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; valid choices: {list(METHODS)}.")
    pretraining, rule = METHODS[method]
    if pretraining is not None and checkpoint is None:
        raise ValueError(f"method {method!r} needs the checkpoint of its {pretraining} pre-training.")
    if method == "scratch":
        seed_everything(seed)
        return Initialisation(make_gaussian_policy(*env_dims(env_name)), rule)
    if method == "vime_init":
        from umrl.objectives.vime import load_vime_policy

        return Initialisation(load_vime_policy(checkpoint), rule)
    if method == "diayn_init":
        from umrl.diayn_checkpoint import load_skill_policy

        actor, num_skills, _ = load_skill_policy(checkpoint)
        return Initialisation(actor, rule, num_skills=num_skills)
    from umrl.maml_checkpoint import load_maml_policy

    policy, inner_lr = load_maml_policy(checkpoint)
    return Initialisation(policy, rule, lr=inner_lr)


def meta_test(init: Initialisation, env_name: str, tasks: torch.Tensor, *, lr: float, seed: int,
              config: AdaptationConfig, skill_trajectories: int = 4) -> tuple[torch.Tensor, dict]:
    """Adapt ``init`` on ``tasks`` ``[T, task_dim]``; returns (returns ``[K + 1, T]``, info).

    DIAYN-init first picks each task's best skill from ``skill_trajectories`` rollouts per (task, skill);
    ``info["skills"]`` lists them.
    """
    seed_everything(seed)
    info: dict = {}
    skills = None
    if init.num_skills is not None:
        skills, _ = select_skills(init.policy, env_name, tasks, init.num_skills, num_trajectories=skill_trajectories,
                                  seed=seed, horizon=config.horizon)
        info["skills"] = skills.tolist()
    env = make_eval_env(env_name, tasks, config.num_trajectories, seed=seed, horizon=config.horizon, skills=skills,
                        num_skills=init.num_skills)
    returns = TaskAdapter(init.policy, env, tasks.shape[0], optimizer=init.optimizer, lr=lr, config=config).run()
    env.close()
    return returns, info


def run_cell(spec: Mapping) -> str:
    """Evaluate one (method, env, seed) cell and write its tidy CSV; the suite's unit of work (picklable input).

    ``spec`` keys: ``method``, ``env``, ``seed``, ``checkpoint`` (path or None), ``output`` (CSV path),
    ``protocol`` (:class:`AdaptationConfig` fields), ``num_tasks``, ``adam_lr``, ``sgd_lr`` (None: the MAML
    checkpoint's inner lr), ``sweep`` (``enabled``, ``lrs``, ``num_tasks``, ``num_steps``), ``skill_trajectories``,
    ``threads``, optional ``extra`` (constant columns added to every row, e.g. the ablation's ``iteration``).
    A JSON file beside the CSV records the learning rate used, the sweep scores, DIAYN-init's skills and timings.
    Returns the CSV path; an existing CSV is left untouched (finished cells are never recomputed).
    """
    output = Path(spec["output"])
    if output.exists():
        return str(output)
    torch.set_num_threads(int(spec.get("threads", 1)))
    start = time.perf_counter()
    method, env_name, seed = spec["method"], spec["env"], int(spec["seed"])
    config = AdaptationConfig(**spec["protocol"])
    init = load_initialisation(method, env_name, spec.get("checkpoint"), seed=seed)
    info: dict = {"method": method, "env": env_name, "seed": seed, "checkpoint": spec.get("checkpoint")}
    if init.optimizer == "sgd":
        lr = float(spec["sgd_lr"]) if spec.get("sgd_lr") is not None else init.lr
    else:
        lr = float(spec["adam_lr"])
        sweep = spec.get("sweep") or {}
        if sweep.get("enabled"):
            sweep_config = replace(config, num_steps=int(sweep.get("num_steps", config.num_steps)))

            def trial(trial_lr: float, tasks: torch.Tensor) -> torch.Tensor:
                fresh = load_initialisation(method, env_name, spec.get("checkpoint"), seed=seed)
                return meta_test(fresh, env_name, tasks, lr=trial_lr, seed=seed, config=sweep_config,
                                 skill_trajectories=int(spec.get("skill_trajectories", 4)))[0]

            lr, info["sweep_scores"] = sweep_learning_rate(
                trial, list(sweep["lrs"]), sweep_tasks(env_name, int(sweep.get("num_tasks", 5)), seed))
    tasks = get_task_family(env_name).eval_tasks(int(spec.get("num_tasks", 20)))
    returns, extra_info = meta_test(init, env_name, tasks, lr=lr, seed=seed, config=config,
                                    skill_trajectories=int(spec.get("skill_trajectories", 4)))
    info.update(extra_info, lr=lr, optimizer=init.optimizer, seconds=time.perf_counter() - start,
                mean_return=returns.mean(-1).tolist())
    rows = to_rows(returns, method=method, env=env_name, seed=seed, **dict(spec.get("extra") or {}))
    output.with_suffix(".json").parent.mkdir(parents=True, exist_ok=True)
    output.with_suffix(".json").write_text(json.dumps(info, indent=1))
    write_rows(rows, output)  # last: the CSV's existence marks the cell finished
    return str(output)


# ----------------------------------------------------------------------------------------------------------------
# Tidy results: rows, CSV, curves and the summary table.


def to_rows(returns: torch.Tensor | np.ndarray, *, method: str, env: str, seed: int, **extra) -> list[dict]:
    """Tidy rows (:data:`COLUMNS` plus ``extra`` columns) from returns ``[K + 1, T]``."""
    returns = np.asarray(returns)
    return [
        {"method": method, "env": env, "seed": int(seed), "task": int(t), "step": int(k),
         "return": float(returns[k, t]), **extra}
        for k in range(returns.shape[0]) for t in range(returns.shape[1])
    ]


def write_rows(rows: Sequence[Mapping], path: str | os.PathLike) -> Path:
    """Write rows as CSV atomically (a killed write never leaves a partial file under ``path``)."""
    if not rows:
        raise ValueError(f"no rows to write to {path}.")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)
    return path


def read_rows(paths: Iterable[str | os.PathLike]) -> list[dict]:
    """Rows of one or more CSV files, with ``seed``/``task``/``step`` as int and ``return`` as float."""
    rows = []
    for path in paths:
        with Path(path).open(newline="") as f:
            for row in csv.DictReader(f):
                row.update(seed=int(row["seed"]), task=int(row["task"]), step=int(row["step"]),
                           **{"return": float(row["return"])})
                rows.append(row)
    return rows


def run_matrix(rows: Iterable[Mapping], *, env: str, method: str) -> np.ndarray:
    """``[runs, K + 1]`` returns of one (env, method): one row per (seed, task), sorted."""
    table: dict[tuple[int, int], dict[int, float]] = {}
    for row in rows:
        if row["env"] == env and row["method"] == method:
            table.setdefault((row["seed"], row["task"]), {})[row["step"]] = row["return"]
    if not table:
        raise ValueError(f"no results for method {method!r} on env {env!r}.")
    steps = sorted(next(iter(table.values())))
    return np.array([[table[run][k] for k in steps] for run in sorted(table)])


def curves_from_rows(rows: Sequence[Mapping], *, methods: Sequence[str] | None = None,
                     confidence: float = 0.95) -> dict[str, dict[str, Curve]]:
    """``{env: {method: Curve}}``: mean return per step over (seed, task) runs with bootstrap CI bands.

    Methods come in the order of ``methods`` (others after them, sorted).
    """
    order = {m: i for i, m in enumerate(methods or [])}
    pairs = sorted({(r["env"], r["method"]) for r in rows}, key=lambda p: (p[0], order.get(p[1], len(order)), p[1]))
    curves: dict[str, dict[str, Curve]] = {}
    for env, method in pairs:
        matrix = run_matrix(rows, env=env, method=method)
        bands = np.array([bootstrap_ci(matrix[:, k], confidence=confidence) for k in range(matrix.shape[1])])
        curves.setdefault(env, {})[method] = Curve(np.arange(matrix.shape[1]), matrix.mean(0), bands[:, 0],
                                                   bands[:, 1])
    return curves


def summary_table(rows: Sequence[Mapping], *, steps: Sequence[int] = (0, 1, 5), methods: Sequence[str] | None = None,
                  confidence: float = 0.95) -> tuple[str, list[dict]]:
    """Markdown table and records: return at ``k ∈ steps ∪ {K}`` and AUC per (env, method).

    Every cell is the IQM over (seed, task) runs with its bootstrap CI; the AUC is also given as a mean with CI.
    Returns ``(markdown, records)``; each record holds ``env``, ``method``, ``metric`` and :func:`summarize`'s keys.
    """
    records = []
    envs = sorted({r["env"] for r in rows})
    lines = []
    for env in envs:
        present = sorted({r["method"] for r in rows if r["env"] == env})
        order = [m for m in (methods or present) if m in present] + [m for m in present if methods and m not in methods]
        num_steps = run_matrix(rows, env=env, method=order[0]).shape[1] - 1
        ks = sorted({k for k in steps if k <= num_steps} | {num_steps})
        header = ["method"] + [f"k={k} IQM [95% CI]" for k in ks] + ["AUC IQM [95% CI]", "AUC mean [95% CI]", "runs"]
        lines += [f"### {env}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for method in order:
            matrix = run_matrix(rows, env=env, method=method)
            cells = []
            for k in ks:
                s = summarize(matrix[:, k], confidence=confidence)
                records.append({"env": env, "method": method, "metric": f"return_k{k}", **s})
                cells.append(f"{s['iqm']:.2f} [{s['iqm_low']:.2f}, {s['iqm_high']:.2f}]")
            s = summarize(auc(matrix), confidence=confidence)
            records.append({"env": env, "method": method, "metric": "auc", **s})
            cells.append(f"{s['iqm']:.1f} [{s['iqm_low']:.1f}, {s['iqm_high']:.1f}]")
            cells.append(f"{s['mean']:.1f} [{s['mean_low']:.1f}, {s['mean_high']:.1f}]")
            lines.append(f"| {method} | " + " | ".join(cells) + f" | {matrix.shape[0]} |")
        lines.append("")
    return "\n".join(lines), records
