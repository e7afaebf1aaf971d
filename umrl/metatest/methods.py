"""The compared methods, what each hands to meta-test, and one suite cell = (method, env, seed).

* :data:`METHODS` — name -> :class:`Method`: the :class:`Pretraining` run that produces its initialisation (typed:
  recipe + proposal, never parsed out of a string) and its update rule at meta-test.
* :func:`load_initialisation` — the policy a method starts meta-test from.
* :class:`CellSpec` — every setting of one cell, typed, with its defaults in this one place, validated on
  construction; :func:`run_cell` evaluates it and writes its tidy CSV (the suite's unit of work, picklable).
"""
from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from umrl.atomic_write import write_text_atomic
from umrl.checkpoints import DIAYN_FORMAT, MAML_FORMAT, VIME_FORMAT, maml_policy, skill_policy, vime_policy
from umrl.envs import get_env_spec
from umrl.envs.tasks import get_task_family
from umrl.metatest.cache import write_json_atomic
from umrl.metatest.method_table import METHODS, RECIPES, Method, Pretraining, get_method
from umrl.metatest.protocol import (
    AdaptationConfig,
    TaskAdapter,
    make_eval_env,
    select_skills,
    sweep_learning_rate,
    sweep_tasks,
)
from umrl.metatest.provenance import relative_path
from umrl.metatest.results import cell_finished, csv_text, text_sha256, to_rows
from umrl.modules.policy import make_gaussian_policy
from umrl.objectives.policy_gradient import episode_lengths, episode_mean
from umrl.proposals import PROPOSALS
from umrl.rng import seed_everything
from umrl.validation import (
    DEVICES,
    InvalidType,
    InvalidValue,
    check_bool,
    check_choice,
    check_int,
    check_list,
    check_positive,
    check_str,
    check_writable_dir,
    resolve_device,
)


@dataclass
class Initialisation:
    """A policy to adapt, its update rule and (DIAYN-init) the skill count; ``lr`` is the SGD step of MAML inits."""

    policy: TensorDictModuleBase
    optimizer: str
    lr: float | None = None
    num_skills: int | None = None


def load_initialisation(method: str, env_name: str, checkpoint: str | os.PathLike | None, *,
                        seed: int, device: torch.device | str = "cpu") -> Initialisation:
    """The policy ``method`` starts meta-test from (see :data:`METHODS`); ``checkpoint`` is its pre-training output.

    scratch draws a fresh 2x300 Gaussian policy from ``seed`` (on the CPU: the same weights on every device); the
    MAML inits return the SGD step size they were meta-trained with as ``lr``. The policy is moved to ``device``
    (checkpoints load on the CPU first, so one written on a GPU loads anywhere).
    """
    init = _load_initialisation(method, env_name, checkpoint, seed=seed)
    init.policy = init.policy.to(device)
    return init


def _load_initialisation(method: str, env_name: str, checkpoint: str | os.PathLike | None, *,
                         seed: int) -> Initialisation:
    spec = get_method(method)
    pretraining = spec.pretraining
    if pretraining is None:  # the draw MAML's and VIME's initialisations start from for this seed
        env = get_env_spec(env_name)
        return Initialisation(make_gaussian_policy(env.obs_dim, env.act_dim, seed=seed), spec.optimizer)
    if checkpoint is None:
        raise ValueError(f"method {method!r} needs the checkpoint of its {pretraining.kind} pre-training.")
    recipe_format = {"diayn": DIAYN_FORMAT, "maml": MAML_FORMAT, "vime": VIME_FORMAT}[pretraining.recipe]
    proposal = {} if pretraining.proposal is None else {"proposal": pretraining.proposal}
    state = recipe_format.check_run(recipe_format.load(checkpoint), "checkpoint", checkpoint,
                                    f"method {method!r} on {env_name}", env=env_name, **proposal)
    if pretraining.recipe == "vime":
        return Initialisation(vime_policy(state), spec.optimizer)
    if pretraining.recipe == "diayn":
        actor, num_skills, _ = skill_policy(state)
        return Initialisation(actor, spec.optimizer, num_skills=num_skills)
    policy, inner_lr = maml_policy(state)
    return Initialisation(policy, spec.optimizer, lr=inner_lr)


def meta_test(init: Initialisation, env_name: str, tasks: torch.Tensor, *, lr: float, seed: int,
              config: AdaptationConfig, skill_trajectories: int, device: torch.device | str = "cpu",
              observe: Callable[[int, TensorDictBase], None] | None = None) -> tuple[torch.Tensor, dict]:
    """Adapt ``init`` on ``tasks`` ``[T, task_dim]``; returns (returns ``[K + 1, T]`` on the CPU, info).

    The envs, the per-task parameters and the batches live on ``device`` (``init.policy`` must be there too, as
    :func:`load_initialisation` leaves it). DIAYN-init first picks each task's best skill from
    ``skill_trajectories`` rollouts per (task, skill); ``info["skills"]`` lists them and
    ``info["skill_choice_env_steps"]`` counts the env steps per task that choice took (before k = 0, on no curve:
    skills × ``skill_trajectories`` × horizon). ``observe`` is passed to
    :meth:`TaskAdapter.run` (it sees every step's batch).
    """
    seed_everything(seed)
    info: dict = {}
    skills = None
    if init.num_skills is not None:
        skills, _ = select_skills(init.policy, env_name, tasks, init.num_skills, num_trajectories=skill_trajectories,
                                  seed=seed, horizon=config.horizon, device=device)
        info["skills"] = skills.tolist()
        # env steps per task that no curve shows: every skill rolled out before k = 0
        info["skill_choice_env_steps"] = init.num_skills * skill_trajectories * config.horizon
    env = make_eval_env(env_name, tasks, config.num_trajectories, seed=seed, horizon=config.horizon, skills=skills,
                        num_skills=init.num_skills, device=device)
    adapter = TaskAdapter(init.policy, env, tasks.shape[0], optimizer=init.optimizer, lr=lr, config=config)
    returns = adapter.run(observe)
    env.close()
    return returns.cpu(), info


@dataclass(frozen=True)
class SweepConfig:
    """Step-size sweeps on ``num_tasks`` non-evaluation tasks, each adapted for ``num_steps`` steps, keeping the
    best mean AUC: the Adam methods' learning rate over ``lrs`` (``enabled=False``: use ``CellSpec.adam_lr``), and
    for the ``"swept"`` SGD schedule (always swept) the factor of ``α`` after the first update over
    ``later_factors``."""

    enabled: bool = False
    lrs: tuple[float, ...] = (1e-4, 3e-4, 1e-3, 3e-3, 1e-2)
    later_factors: tuple[float, ...] = (0.0625, 0.125, 0.25, 0.5)
    num_tasks: int = 5
    num_steps: int = 5

    def __post_init__(self):
        check_bool("sweep.enabled", self.enabled)
        lrs = check_list("sweep.lrs", self.lrs, check_positive, min_len=1, what="learning rates > 0")
        object.__setattr__(self, "lrs", tuple(lrs))
        factors = check_list("sweep.later_factors", self.later_factors, check_positive, min_len=1,
                             what="factors > 0")
        object.__setattr__(self, "later_factors", tuple(factors))
        for key in ("num_tasks", "num_steps"):
            check_int(f"sweep.{key}", getattr(self, key), min=1)


@dataclass(frozen=True)
class CellSpec:
    """Everything one meta-test cell (method, env, seed) needs; defaults here are the only defaults.

    Attributes:
        method: a key of :data:`METHODS`.
        env: env name (:func:`umrl.envs.make_env`).
        seed: meta-test seed (>= 0): env sampling, scratch's initial weights, the sweep tasks.
        output: the cell's CSV path; a JSON of the same stem records lr, sweep scores, skills and timing.
        checkpoint: the pre-training output (run dir or ``step_*.safetensors``); None only for scratch.
        protocol: the adaptation protocol (:class:`AdaptationConfig`).
        num_tasks: held-out evaluation tasks (the family's first ``num_tasks`` eval tasks).
        adam_lr: REINFORCE + Adam learning rate when the sweep is off.
        sgd_lr: SGD step of MAML inits; None: the checkpoint's meta-trained inner lr.
        sweep: the Adam learning-rate sweep (:class:`SweepConfig`).
        skill_trajectories: DIAYN-init rollouts per (task, skill) when choosing each task's skill.
        threads: torch threads of the job.
        device: ``cpu`` | ``cuda`` | ``auto`` (:func:`umrl.validation.resolve_device`, at the start of
            :func:`run_cell`: ``cuda`` on a machine without a GPU fails there, naming the choices).
        extra: constant columns added to every row (e.g. the ablation's ``iteration``).
    """

    method: str
    env: str
    seed: int
    output: str
    checkpoint: str | None = None
    protocol: AdaptationConfig = field(default_factory=AdaptationConfig)
    num_tasks: int = 20
    adam_lr: float = 1e-3
    sgd_lr: float | None = None
    sweep: SweepConfig = field(default_factory=SweepConfig)
    skill_trajectories: int = 4
    threads: int = 1
    device: str = "cpu"
    extra: Mapping = field(default_factory=dict)

    def __post_init__(self):
        check_choice("method", self.method, METHODS)
        check_str("env", self.env)
        check_int("seed", self.seed, min=0)
        for key in ("num_tasks", "skill_trajectories", "threads"):
            check_int(key, getattr(self, key), min=1)
        check_choice("device", self.device, DEVICES)
        check_positive("adam_lr", self.adam_lr)
        if self.sgd_lr is not None:
            check_positive("sgd_lr", self.sgd_lr)  # null: the checkpoint's inner lr
        if (self.checkpoint is None) != (METHODS[self.method].pretraining is None):
            raise InvalidValue("checkpoint", self.checkpoint, f"a pre-training output for {self.method!r}"
                               if self.checkpoint is None else "null for scratch")
        if not isinstance(self.protocol, AdaptationConfig):
            raise InvalidType("protocol", self.protocol, "an AdaptationConfig")
        if not isinstance(self.sweep, SweepConfig):
            raise InvalidType("sweep", self.sweep, "a SweepConfig")

    @classmethod
    def from_mapping(cls, values: Mapping) -> CellSpec:
        """Build from plain nested mappings (``protocol`` and ``sweep`` as dicts); unknown keys are rejected."""
        values = dict(values)
        _check_keys("", values, cls)
        if isinstance(values.get("protocol"), Mapping):
            _check_keys("protocol.", values["protocol"], AdaptationConfig)
            values["protocol"] = AdaptationConfig(**values["protocol"])
        if isinstance(values.get("sweep"), Mapping):
            _check_keys("sweep.", values["sweep"], SweepConfig)
            values["sweep"] = SweepConfig(**values["sweep"])
        return cls(**values)

    def settings(self) -> dict:
        """What the cell's JSON records as its settings, and :meth:`finished` compares: every field but ``output``,
        as plain JSON values, the checkpoint relative to ``output``'s folder (so results moved or committed together
        with their runs still count as finished)."""
        values = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "output"}
        values.update(protocol=asdict(self.protocol), sweep=asdict(self.sweep), extra=dict(self.extra))
        if self.checkpoint is not None:
            values["checkpoint"] = relative_path(self.checkpoint, self.output)
        return json.loads(json.dumps(values, default=str))

    def finished(self) -> bool:
        """Whether ``output`` holds this cell's finished result (:func:`~umrl.metatest.results.cell_finished`: a
        stale file is named and removed, a folder there refused)."""
        return cell_finished(self.output, self.settings())

    @property
    def lr_schedule(self) -> str:
        """The cell's step-size schedule: ``protocol.sgd_schedule`` for SGD methods, ``"constant"`` for Adam."""
        return self.protocol.sgd_schedule if METHODS[self.method].optimizer == "sgd" else "constant"


def _check_keys(prefix: str, values: Mapping, cls) -> None:
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"cell spec: unknown keys {[prefix + k for k in unknown]}; accepted: {sorted(known)}.")


def run_cell(spec: CellSpec) -> str:
    """Evaluate one (method, env, seed) cell and write its tidy CSV; the suite's unit of work.

    A JSON file beside the CSV records the learning rate used, the sweep scores, DIAYN-init's skills and timings.
    Returns the CSV path. A finished cell of the same settings (:meth:`CellSpec.finished`) is left untouched and not
    recomputed; any other file at ``output`` is named in a warning and replaced, a folder there refused before any
    work, as is an ``output`` in a folder this process cannot create or write.
    """
    if not isinstance(spec, CellSpec):
        raise TypeError(f"run_cell takes a CellSpec, got {type(spec).__name__}.")
    output = Path(spec.output)
    if spec.finished():
        return str(output)
    check_writable_dir("output's folder", str(output.absolute().parent))
    device = torch.device(resolve_device("device", spec.device))
    start = time.perf_counter()
    config = spec.protocol
    init = load_initialisation(spec.method, spec.env, spec.checkpoint, seed=spec.seed, device=device)
    checkpoint = None if spec.checkpoint is None else relative_path(spec.checkpoint, output)  # no machine path
    info: dict = {"method": spec.method, "env": spec.env, "seed": spec.seed, "checkpoint": checkpoint,
                  "num_tasks": spec.num_tasks, "skill_trajectories": spec.skill_trajectories}
    sweep_config = replace(config, num_steps=spec.sweep.num_steps)

    def trial(trial_lr: float, trial_config: AdaptationConfig, tasks: torch.Tensor) -> torch.Tensor:
        # meta_test adapts copies of init's parameters and reseeds: one init serves every trial
        return meta_test(init, spec.env, tasks, lr=trial_lr, seed=spec.seed, config=trial_config,
                         skill_trajectories=spec.skill_trajectories, device=device)[0]

    tasks_of_sweep = sweep_tasks(spec.env, spec.sweep.num_tasks, spec.seed)
    if init.optimizer == "sgd":
        lr = float(spec.sgd_lr) if spec.sgd_lr is not None else init.lr
        if config.sgd_schedule == "swept":
            factor, info["later_factor_scores"] = sweep_learning_rate(
                lambda f, tasks: trial(lr, replace(sweep_config, sgd_later_factor=f), tasks),
                list(spec.sweep.later_factors), tasks_of_sweep)
            config = replace(config, sgd_later_factor=factor)
    else:
        lr = float(spec.adam_lr)
        if spec.sweep.enabled:
            lr, info["sweep_scores"] = sweep_learning_rate(
                lambda trial_lr, tasks: trial(trial_lr, sweep_config, tasks), list(spec.sweep.lrs), tasks_of_sweep)
    tasks = get_task_family(spec.env).eval_tasks(spec.num_tasks)
    lengths = []  # [K + 1] x [T]: mean episode length per task at each step, beside the returns

    def record_lengths(step: int, batch: TensorDictBase) -> None:
        lengths.append(episode_mean(episode_lengths(batch).float(), batch).cpu())

    returns, extra_info = meta_test(init, spec.env, tasks, lr=lr, seed=spec.seed, config=config,
                                    skill_trajectories=spec.skill_trajectories, device=device,
                                    observe=record_lengths)
    info.update(extra_info, lr=lr, optimizer=init.optimizer, lr_schedule=spec.lr_schedule,
                protocol=asdict(config), seconds=time.perf_counter() - start, mean_return=returns.mean(-1).tolist())
    rows = to_rows(returns, torch.stack(lengths), method=spec.method, env=spec.env, seed=spec.seed,
                   lr_schedule=spec.lr_schedule, **dict(spec.extra))
    text = csv_text(rows)
    write_json_atomic(output.with_suffix(".json"), {**info, "settings": spec.settings(), "csv_sha256": text_sha256(text)})
    write_text_atomic(output, text)  # last: the CSV's existence marks the cell finished
    return str(output)


__all__ = [
    "METHODS",
    "PROPOSALS",
    "RECIPES",
    "CellSpec",
    "Initialisation",
    "Method",
    "Pretraining",
    "SweepConfig",
    "get_method",
    "load_initialisation",
    "meta_test",
    "run_cell",
]
