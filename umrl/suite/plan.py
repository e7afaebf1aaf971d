"""The suite's plan: which pre-training runs and meta-test cells a validated suite config asks for, as
:class:`umrl.launch.Job` lists keyed by their resolved configs and the code version (:mod:`umrl.metatest.cache`).

Pre-training runs are ``umrl.trainers.train(recipe, overrides)`` jobs, cells :func:`umrl.metatest.run_cell` jobs;
every recipe config is composed (:func:`umrl.trainers.compose`) and checked against its schema while planning, so
every bad key or value is listed before any work starts.
"""
from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

import umrl.trainers
from umrl.checkpoints import DIAYN_FORMAT, MAML_FORMAT, VIME_FORMAT
from umrl.checkpoints.diayn import seed_run_dir
from umrl.checkpoints.folder import Checkpointer
from umrl.configs import ConfigError
from umrl.configs.maml import hvp_errors
from umrl.configs.suite import RECIPE_SCHEMAS, needed_pretraining, pretrain_seeds, reuse_dir
from umrl.configs.validate import check_partial
from umrl.launch import Job
from umrl.metatest import CellSpec, Pretraining, default_lr_schedule, get_method, run_cell
from umrl.metatest.cache import config_key, keyed_config, mark_done, run_finished
from umrl.plain_config import to_container
from umrl.validation import InvalidValue

__all__ = ["BUDGET_KEYS", "PretrainRun", "cell_spec", "checkpoint_identity", "hydra_overrides", "job_key", "keyed_cell",
           "plan", "plan_ablation", "plan_pretraining", "pretrain_key", "sgd_schedules"]

RUN_FORMATS = {"diayn": DIAYN_FORMAT, "maml": MAML_FORMAT, "vime": VIME_FORMAT}
"""Each recipe's checkpoint format (a reused run's ``meta`` is read with it)."""

BUDGET_KEYS = {"diayn": "collector.total_frames", "maml": "iterations", "vime": "iterations"}
"""Each recipe's total budget, in the unit of its checkpoints' step numbers (``step_<N>.pt``: env frames for DIAYN,
iterations for MAML and VIME): a run whose newest checkpoint reached it has finished its work."""


# ----------------------------------------------------------------------------------------------------------------
# Planning: which pre-training runs and cells a config asks for


def pretrain_key(run: Pretraining, env: str, seed: int) -> str:
    return f"pretrain/{run.kind}/{env}/seed{seed}"


def sgd_schedules(cfg: DictConfig) -> list[str]:
    """``protocol.sgd_schedule`` (validated) as a list: the SGD methods get one cell per schedule."""
    value = cfg.protocol.sgd_schedule
    return [str(value)] if isinstance(value, str) else [str(v) for v in value]


def _hydra_value(value) -> str:
    """A value in Hydra's override grammar (lists as ``[a,b]``, null, strings quoted unless plain)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (list, tuple)):
        return f"[{','.join(_hydra_value(v) for v in value)}]"
    if isinstance(value, str) and not re.fullmatch(r"[\w./:+-]+", value):
        return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"
    return str(value)


def hydra_overrides(values: Mapping, prefix: str = "") -> list[str]:
    """``{"a": {"b": 1}, "c": [1, 2]}`` -> ``["a.b=1", "c=[1,2]"]`` (Hydra overrides for ``umrl.trainers.compose``)."""
    out = []
    for key, value in (to_container(values) if OmegaConf.is_config(values) else dict(values)).items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out += hydra_overrides(value, prefix=f"{name}.")
        else:
            out.append(f"{name}={_hydra_value(value)}")
    return out


@dataclass(frozen=True)
class PretrainRun:
    """One pre-training run of the plan.

    Attributes:
        run: what it trains; ``env``, ``seed``: where and with which seed.
        run_dir: its output directory (``pretrain/<kind>/<env>/seed<s>-<key>``, or the ``reuse`` path).
        overrides: the overrides ``umrl.trainers.train(run.recipe, overrides)`` runs it with (``resume=true`` when a
            checkpoint exists); empty for a reused run.
        key: hash of its resolved config (less :data:`umrl.metatest.cache.UNKEYED`) and the code version; None for
            a reused run.
        budget: its total budget in checkpoint steps (``BUDGET_KEYS``); None for a reused run.
        job_key: the key of the job that trains it (:func:`pretrain_key`, or one DIAYN job for several seeds).
    """

    run: Pretraining
    env: str
    seed: int
    run_dir: Path
    overrides: tuple[str, ...] = ()
    key: str | None = None
    budget: int | None = None
    job_key: str | None = None

    @property
    def reused(self) -> bool:
        return self.key is None

    def done(self) -> bool:
        """A reused run is taken as it is; a suite run is done once finished (:func:`run_finished`)."""
        return self.reused or run_finished(self.run_dir, self.budget)

    def describe(self) -> str:
        return f"{self.run.kind} pre-training on {self.env}, seed {self.seed} -> {self.run_dir}"


def _suite_overrides(cfg: DictConfig, run: Pretraining, env: str, seeds: list[int], group: str,
                     runs: Mapping[tuple[str, str, int], PretrainRun]) -> list[str]:
    """What the suite sets in a recipe's config: env, seed (DIAYN: ``seeds``, all in one program), device, torch
    threads (``launcher.threads``), logging, MAML's proposal and DIAYN run; then the user's
    ``pretrain.<recipe>.overrides`` (which win)."""
    seed = seeds[0]
    values = {"env.name": env, "seed": seed, "device": cfg.device, "num_threads": cfg.launcher.threads,
              "logger.backend": cfg.logger.backend, "logger.group": group, "progress": False}
    if run.recipe == "diayn":
        values["seeds"] = list(seeds)
    if run.recipe == "maml":
        values.update({"proposal": run.proposal, "checkpoint.keep_all": True})
        for needed in run.requires:
            values[cfg.pretrain.maml.diayn_checkpoint_key] = str(runs[needed.kind, env, seed].run_dir)
    return [f"{k}={_hydra_value(v)}" for k, v in values.items()] + hydra_overrides(
        cfg.pretrain[run.recipe].get("overrides") or {})


def _used(cfg: DictConfig, run: Pretraining, env: str, seed: int) -> bool:
    """Whether ``run`` on (``env``, ``seed``) is used: a method starts from it, or a run the suite trains reads it (a
    DIAYN run read only by reused UML-DIAYN runs is not)."""
    starts = {get_method(name).pretraining for name in cfg.methods} - {None}
    return run in starts or any(run in other.requires and reuse_dir(cfg, other, env, seed) is None for other in starts)


def _reused_skill_errors(cfg: DictConfig, run: Pretraining, run_dir: Path) -> list[str]:
    """A reused run is used as it is: a ``pretrain.<recipe>.overrides.num_skills`` that would set its skill count
    (DIAYN's for DIAYN and UML-DIAYN runs, MAML's for the random proposals' discriminators) must be its checkpoint's."""
    if Pretraining("diayn") in (run, *run.requires):
        recipe = "diayn"
    elif run.proposal in ("random", "random_arena"):
        recipe = "maml"
    else:
        return []
    wanted = (cfg.pretrain[recipe].overrides or {}).get("num_skills")
    if wanted is None:
        return []
    trained = RUN_FORMATS[run.recipe].load(run_dir)["meta"]["num_skills"]
    if wanted == trained:
        return []
    return [InvalidValue(f"pretrain.{recipe}.overrides.num_skills", wanted, f"{trained} or no override",
                         note=f"the reused {run.kind} run in {run_dir} (pretrain.{run.recipe}.reuse) has {trained} "
                              "skills and is used as it is").message()]


def plan_pretraining(cfg: DictConfig, group: str, code: str) -> dict[tuple[str, str, int], PretrainRun]:
    """Every pre-training run the config uses, ``(kind, env, seed) -> PretrainRun``, runs before those that read them
    (a DIAYN run only reused UML-DIAYN runs would read is left out).

    A ``reuse`` run is taken as it is; a ``num_skills`` override it was not trained with is refused. Each recipe
    config is composed with ``umrl.trainers.compose`` and checked against its schema here, so a renamed or misspelt
    key or a bad value fails before any work (:class:`~umrl.configs.ConfigError` listing every problem).
    """
    runs: dict[tuple[str, str, int], PretrainRun] = {}
    errors: list[str] = []
    ordered = sorted(needed_pretraining(list(cfg.methods)), key=lambda r: len(r.requires))  # DIAYN before MAML(diayn)
    for env in cfg.envs:
        for run in ordered:
            fresh = []
            for seed in sorted(set(pretrain_seeds(cfg))):
                if not _used(cfg, run, env, seed):
                    continue
                reuse = reuse_dir(cfg, run, env, seed)
                if reuse is not None:
                    errors += _reused_skill_errors(cfg, run, reuse)
                    runs[run.kind, env, seed] = PretrainRun(run, env, seed, reuse)
                else:
                    fresh.append(seed)
            # DIAYN trains all of an env's seeds in one program (stacked networks, one update for all seeds), but
            # one program per seed on a gymnasium env (the seeds would share its vector env's reset noise)
            together = run.recipe == "diayn" and fresh and not env.startswith("gym:")
            for seeds in ([fresh] if together else [[seed] for seed in fresh]):
                errors += _plan_fresh(cfg, run, env, seeds, group, code, runs)
    if errors:
        raise ConfigError("suite pre-training configs", errors)
    return runs


def _plan_fresh(cfg: DictConfig, run: Pretraining, env: str, seeds: list[int], group: str, code: str,
                runs: dict[tuple[str, str, int], PretrainRun]) -> list[str]:
    """Plan one job training ``run`` on ``env`` for ``seeds`` (several only for DIAYN), adding a
    :class:`PretrainRun` per seed to ``runs``; returns the problems of its config."""
    overrides = _suite_overrides(cfg, run, env, seeds, group, runs)
    name = f"pretrain.{run.recipe} ({run.kind}, {env}, seed{'s' * (len(seeds) > 1)} {_seeds_name(seeds)})"
    try:
        composed = umrl.trainers.compose(run.recipe, overrides)
    except Exception as err:  # noqa: BLE001 -- Hydra's override/compose errors, reported with the rest
        return [f"{name}: {type(err).__name__}: {str(err).splitlines()[0]}"]
    values = to_container(composed)
    problems = check_partial(values, RECIPE_SCHEMAS[run.recipe], prefix=f"{name}: ")
    if run.recipe == "maml" and not problems:
        problems = [f"{name}: {error}" for error in hvp_errors(values)]
    budget = OmegaConf.select(OmegaConf.create(values), BUDGET_KEYS[run.recipe])
    if budget is None:
        problems.append(f"{name}: the recipe config has no {BUDGET_KEYS[run.recipe]!r} (its budget); "
                        "update BUDGET_KEYS in umrl/suite/plan.py")
    if problems:
        return problems
    key = config_key(keyed_config(values), code)
    job_dir = Path(cfg.output_dir).absolute() / "pretrain" / run.kind / env / f"seed{_seeds_name(seeds)}-{key}"
    has_checkpoint = Checkpointer(job_dir / "checkpoints").latest() is not None
    overrides += [f"output_dir={_hydra_value(str(job_dir))}", f"resume={_hydra_value(has_checkpoint)}"]
    job_key = pretrain_key(run, env, seeds[0]) if len(seeds) == 1 else f"pretrain/{run.kind}/{env}/seeds{_seeds_name(seeds)}"
    for seed in seeds:  # a DIAYN job's seeds each have their folder in it (umrl.checkpoints.diayn.seed_run_dir)
        run_dir = seed_run_dir(job_dir, seed) if run.recipe == "diayn" else job_dir
        runs[run.kind, env, seed] = PretrainRun(run, env, seed, run_dir, tuple(overrides), key, int(budget), job_key)
    return []


def _seeds_name(seeds: list[int]) -> str:
    return "-".join(str(seed) for seed in seeds)


def _pretrain_job(cfg: DictConfig, runs: Mapping[tuple[str, str, int], PretrainRun], run: PretrainRun) -> Job:
    """The job of ``run`` (and of the other seeds its job trains: every run of ``runs`` with its ``job_key``)."""
    key = job_key(run)
    together = [other for other in runs.values() if not other.reused and job_key(other) == key] or [run]
    name = key.removeprefix("pretrain/").replace("/", "_")
    deps = () if run.reused else tuple(job_key(runs[r.kind, run.env, run.seed]) for r in run.run.requires)

    def finished() -> None:
        for each in together:
            mark_done(each.run_dir)

    return Job(key=key, fn=umrl.trainers.train, args=(run.run.recipe, list(run.overrides)), deps=deps,
               done=lambda: all(each.done() for each in together),
               on_success=(lambda: None) if run.reused else finished,
               what="; ".join(each.describe() for each in together), log=Path(cfg.output_dir).absolute() / "logs" /
               f"pretrain_{name}.log", fresh=True)


def job_key(run: PretrainRun) -> str:
    """The key of the job that trains ``run`` (a reused run's names its own slot)."""
    return run.job_key or pretrain_key(run.run, run.env, run.seed)


def checkpoint_identity(run: PretrainRun, checkpoint: str | os.PathLike) -> str:
    """What a cell's key records of its checkpoint: the path of a suite run (its key is in the path), or for a
    ``reuse`` run the path with the newest checkpoint's name, size and modification time (a replaced run is seen)."""
    if not run.reused:
        return str(checkpoint)
    path = Path(checkpoint)
    file = path if path.is_file() else Checkpointer(path / "checkpoints").latest()
    if file is None:
        return str(path)
    stat = file.stat()
    return f"{path}@{file.name}:{stat.st_size}:{stat.st_mtime_ns}"


def cell_spec(cfg: DictConfig, method: str, env: str, seed: int, checkpoint: str | None, *,
              lr_schedule: str = "constant", num_steps: int | None = None, **extra) -> dict:
    """The settings of one cell (a :class:`CellSpec` mapping without ``output``; ``num_steps`` overrides K)."""
    protocol = {**to_container(cfg.protocol), "sgd_schedule": lr_schedule}
    if num_steps is not None:
        protocol["num_steps"] = num_steps
    return {"method": method, "env": env, "seed": seed, "checkpoint": checkpoint, "protocol": protocol,
            "num_tasks": cfg.num_tasks, "adam_lr": cfg.adam_lr, "sgd_lr": cfg.sgd_lr, "sweep": to_container(cfg.sweep),
            "skill_trajectories": cfg.skill_trajectories, "threads": cfg.launcher.threads, "device": cfg.device,
            "extra": extra}


def keyed_cell(settings: Mapping, checkpoint_id: str | None, code: str, stem: Path) -> CellSpec:
    """The :class:`CellSpec` of ``settings`` writing ``<stem>-<key>.csv``, ``key`` hashing the settings, the
    checkpoint's identity and the code version (the spec is validated here)."""
    key = config_key({**settings, "checkpoint": checkpoint_id}, code)
    return CellSpec.from_mapping({**settings, "output": str(stem.with_name(f"{stem.name}-{key}.csv"))})


def _cell_schedules(cfg: DictConfig, method: str) -> list[str]:
    return sgd_schedules(cfg) if get_method(method).optimizer == "sgd" else ["constant"]


def plan(cfg: DictConfig, group: str, code: str = "", runs: Mapping | None = None) -> list[Job]:
    """Pre-training jobs and one meta-test job per (method, env, seed[, SGD schedule]) cell of a validated config
    (``runs``: :func:`plan_pretraining`'s, computed here if not given)."""
    runs = plan_pretraining(cfg, group, code) if runs is None else runs
    out = Path(cfg.output_dir).absolute()
    jobs: dict[str, Job] = {}
    for env in cfg.envs:
        for seed, pseed in zip(cfg.seeds, pretrain_seeds(cfg)):
            for method in map(get_method, cfg.methods):
                pretraining, deps, checkpoint, checkpoint_id = method.pretraining, (), None, None
                if pretraining is not None:
                    run = runs[pretraining.kind, env, pseed]
                    for needed in (*(() if run.reused else pretraining.requires), pretraining):
                        needed_run = runs[needed.kind, env, pseed]
                        jobs.setdefault(job_key(needed_run), _pretrain_job(cfg, runs, needed_run))
                    deps, checkpoint = (job_key(run),), str(run.run_dir)
                    checkpoint_id = checkpoint_identity(run, checkpoint)
                for schedule in _cell_schedules(cfg, method.name):
                    suffix = "" if schedule == default_lr_schedule(method.name) else f".{schedule}"
                    settings = cell_spec(cfg, method.name, env, seed, checkpoint, lr_schedule=schedule)
                    spec = keyed_cell(settings, checkpoint_id, code, out / "cells" / env / method.name / f"seed{seed}{suffix}")
                    key = f"cell/{env}/{method.name}/seed{seed}{suffix.replace('.', '/')}"
                    jobs[key] = Job(key=key, fn=run_cell, args=(spec,), deps=deps, done=spec.finished,
                                    what=f"meta-test of {method.name} on {env}, seed {seed} -> {spec.output}",
                                    log=out / "logs" / f"cell_{env}_{method.name}_seed{seed}{suffix}.log")
    # Pre-training first, runs others depend on before them (DIAYN before MAML(diayn)), so the critical path starts at once.
    def rank(job: Job) -> tuple[bool, int]:
        needed_by_others = any(job.key in other.deps for other in jobs.values() if other.key.startswith("pretrain/"))
        return not job.key.startswith("pretrain/"), 0 if needed_by_others else (1 if job.deps else 2)

    return sorted(jobs.values(), key=rank)


def _ablation_job(cfg: DictConfig, settings: Mapping, checkpoint_id: str | None, code: str, path: str,
                  what: str) -> Job:
    """The ablation's meta-test job of ``settings``, its files under ``<output_dir>/ablation/<path>``."""
    out = Path(cfg.output_dir).absolute()
    spec = keyed_cell(settings, checkpoint_id, code, out / "ablation" / path)
    return Job(key=f"ablation/{path}", fn=run_cell, args=(spec,), done=spec.finished, what=what,
               log=out / "logs" / f"ablation_{path.replace('/', '_')}.log")


def plan_ablation(cfg: DictConfig, runs: Mapping, code: str = "") -> list[Job]:
    """Meta-test jobs for up to ``ablation.max_checkpoints`` kept MAML checkpoints (evenly spaced, last included),
    and, on an env with any, one per ``ablation.baselines`` method and seed at the same K (its rows carry no
    ``iteration``)."""
    jobs = []
    num_steps = int(cfg.ablation.num_steps)
    pseeds = dict(zip(cfg.seeds, pretrain_seeds(cfg)))

    def run_of(pretraining: Pretraining, env: str, seed: int) -> PretrainRun | None:
        return runs.get((pretraining.kind, env, pseeds.get(seed, seed)))

    for env in cfg.envs:
        checkpoints = []
        for name in cfg.ablation.methods:
            pretraining = get_method(name).pretraining
            if name not in cfg.methods or pretraining is None or pretraining.recipe != "maml":
                continue
            for seed in cfg.ablation.seeds:
                run = run_of(pretraining, env, seed)
                if run is None:
                    continue
                files = Checkpointer(run.run_dir / "checkpoints").all()
                count = min(len(files), int(cfg.ablation.max_checkpoints))
                picks = sorted({round(i * (len(files) - 1) / max(count - 1, 1)) for i in range(count)}) if files else []
                for file in (files[i] for i in picks):
                    iteration = int(file.stem.split("_")[-1])
                    settings = cell_spec(cfg, name, env, seed, str(file), lr_schedule=sgd_schedules(cfg)[0],
                                         num_steps=num_steps, iteration=iteration)
                    checkpoints.append(_ablation_job(cfg, settings, checkpoint_identity(run, file), code,
                                                     f"{env}/{name}/seed{seed}/iter{iteration}",
                                                     f"ablation meta-test of {name} on {env}, seed {seed}, {file.name}"))
        if not checkpoints:
            continue  # a baseline alone would be read against nothing
        for name in cfg.ablation.baselines:
            pretraining = get_method(name).pretraining
            for seed in cfg.ablation.seeds:
                checkpoint = checkpoint_id = None
                if pretraining is not None:
                    run = run_of(pretraining, env, seed)
                    if run is None:
                        continue
                    checkpoint = str(run.run_dir)
                    checkpoint_id = checkpoint_identity(run, checkpoint)
                settings = cell_spec(cfg, name, env, seed, checkpoint, lr_schedule=_cell_schedules(cfg, name)[0],
                                     num_steps=num_steps)
                jobs.append(_ablation_job(cfg, settings, checkpoint_id, code, f"{env}/{name}/seed{seed}",
                                          f"ablation baseline: meta-test of {name} on {env}, seed {seed}"))
        jobs += checkpoints
    return jobs
