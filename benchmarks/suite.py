"""The benchmark suite: does unsupervised meta-learning make RL faster here?

Runs UML-DIAYN, UML-random, oracle, VIME-init, DIAYN-init and scratch on the chosen envs and seeds::

    python benchmarks/suite.py profile=tiny                      # every method at toy budgets (~140 CPU-seconds)
    python benchmarks/suite.py profile=quick                     # point_nav, reduced budgets, minutes on 2 cores
    python benchmarks/suite.py profile=reference envs=[point_nav]  # the reference code's settings
    python benchmarks/suite.py profile=quick launcher.ray_address=auto   # jobs as Ray tasks on a cluster
    python benchmarks/suite.py profile=quick device=auto         # pre-training and meta-test on a GPU if there is one

0. **Validation**: the config is checked against :class:`umrl.configs.suite.SuiteConfig` and every recipe config
   the suite will run is composed (``recipes.compose``) and checked against its schema, so every bad key or value
   is listed before any work starts.
1. **Pre-training** (jobs): DIAYN, VIME and MAML with each proposal (diayn after its DIAYN run), each
   ``recipes.<recipe>.train(cfg)`` in a worker process, its config composed from the recipe's own yaml with the
   suite's settings and ``pretrain.<recipe>.overrides``. Each run lives in
   ``pretrain/<kind>/<env>/seed<s>-<key>/``, ``<key>`` a hash of its resolved config and the code version
   (:mod:`umrl.metatest.cache`): a finished run (marker ``suite_complete``, or a checkpoint at the final step) is
   reused, a killed one resumes from its last checkpoint, a changed config or code gets a new run.
   ``pretrain.<recipe>.reuse`` points at existing runs instead (path templates with ``{env}``, ``{seed}``,
   ``{proposal}``). Meta-test seed ``seeds[i]`` uses the runs of pre-training seed ``pretrain_seeds[i]`` (null: the
   same seed, independent pre-training per seed).
2. **Meta-test cells**: each (method, env, seed) -- and, for the SGD methods, each ``protocol.sgd_schedule`` -- is
   an independent job running :func:`umrl.metatest.run_cell` on a typed :class:`umrl.metatest.CellSpec`; its CSV
   ``cells/<env>/<method>/seed<s>[.<schedule>]-<key>.csv`` (key: the spec, its checkpoint and the code version)
   appears atomically when it finishes and is never recomputed, so a killed suite resumes.
3. **Meta-training ablation**: the kept MAML checkpoints along meta-training are meta-tested the same way.
4. **Reports** (built by :mod:`umrl.metatest.results`) under ``output_dir`` from the cells of *this* config only:
   ``results.csv`` (tidy: method, env, seed, task, step, return, length, lr_schedule), ``summary.md`` (return at
   k = 0, 1, 5, K and AUC: IQM and mean with bootstrap CIs; mean episode length at k = 0 and K where episodes end
   early; pre-training seeds; commit, command, hardware and wall time), ``curves.png``, ``ablation.png`` /
   ``ablation.md``, ``config.yaml`` (the validated config) and wandb runs (offline by default, under
   ``output_dir/wandb``) in one group per suite run.

This file plans and reports only: the jobs run through :mod:`umrl.launch`, what a cell computes and how results are
tabulated live in :mod:`umrl.metatest`. Jobs run as fresh worker processes (``launcher.workers`` at a time; their
output goes to ``logs/<job>.log``), in this process (``launcher.workers=0``) or as Ray tasks when ``launcher.ray_address`` is set
(``local`` starts a Ray instance on this machine). The local workers are plain subprocesses (no multiprocessing
semaphores: a suite killed with SIGKILL leaves nothing in ``/dev/shm``). A failed job is printed with its error and
the tail of its log. Every value is a config override (``benchmarks/config/``).
"""
from __future__ import annotations

import json
import logging
import os
import re
import shlex
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

import recipes
from umrl.configs import ConfigError, validate
from umrl.configs.maml import hvp_errors
from umrl.configs.suite import RECIPE_SCHEMAS, SuiteConfig, needed_pretraining, pretrain_seeds, reuse_dir
from umrl.configs.validate import check_partial, fill_env_defaults
from umrl.launch import Job, directory_lock, make_launcher, run_jobs
from umrl.metatest import (
    CellSpec,
    Pretraining,
    ablation_curves,
    ablation_table,
    arm_label,
    arm_styles,
    cell_finished,
    curves_from_rows,
    default_lr_schedule,
    get_method,
    plot_ablation,
    plot_adaptation_curves,
    pretraining_note,
    provenance,
    read_rows,
    run_cell,
    suite_summary,
    summary_table,
    write_rows,
)
from umrl.metatest.cache import (
    config_key,
    keyed_config,
    mark_done,
    remove_stale_tmp,
    run_finished,
    source_version,
    write_json_atomic,
)
from umrl.runtime import (
    Checkpointer,
    close_logger,
    log_image,
    log_metrics,
    make_logger,
    to_container,
    write_text_atomic,
)

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
    """``{"a": {"b": 1}, "c": [1, 2]}`` -> ``["a.b=1", "c=[1,2]"]`` (Hydra overrides for ``recipes.compose``)."""
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
        overrides: the overrides ``recipes.train(run.recipe, overrides)`` runs it with (``resume=true`` when a
            checkpoint exists); empty for a reused run.
        key: hash of its resolved config (less :data:`umrl.metatest.cache.UNKEYED`) and the code version; None for
            a reused run.
        budget: its total budget in checkpoint steps (``BUDGET_KEYS``); None for a reused run.
    """

    run: Pretraining
    env: str
    seed: int
    run_dir: Path
    overrides: tuple[str, ...] = ()
    key: str | None = None
    budget: int | None = None

    @property
    def reused(self) -> bool:
        return self.key is None

    def done(self) -> bool:
        """A reused run is taken as it is; a suite run is done once finished (:func:`run_finished`)."""
        return self.reused or run_finished(self.run_dir, self.budget)

    def describe(self) -> str:
        return f"{self.run.kind} pre-training on {self.env}, seed {self.seed} -> {self.run_dir}"


def _suite_overrides(cfg: DictConfig, run: Pretraining, env: str, seed: int, group: str,
                     runs: Mapping[tuple[str, str, int], PretrainRun]) -> list[str]:
    """What the suite sets in a recipe's config: env, seed, device, torch threads (``launcher.threads``), logging,
    MAML's proposal and DIAYN run; then the user's ``pretrain.<recipe>.overrides`` (which win)."""
    values = {"env.name": env, "seed": seed, "device": cfg.device, "num_threads": cfg.launcher.threads,
              "logger.backend": cfg.logger.backend, "logger.group": group, "progress": False}
    if run.recipe == "maml":
        values.update({"proposal": run.proposal, "checkpoint.keep_all": True})
        for needed in run.requires:
            values[cfg.pretrain.maml.diayn_checkpoint_key] = str(runs[needed.kind, env, seed].run_dir)
    return [f"{k}={_hydra_value(v)}" for k, v in values.items()] + hydra_overrides(
        cfg.pretrain[run.recipe].get("overrides") or {})


def plan_pretraining(cfg: DictConfig, group: str, code: str) -> dict[tuple[str, str, int], PretrainRun]:
    """Every pre-training run the config needs, ``(kind, env, seed) -> PretrainRun``, runs before those that read them.

    Each recipe config is composed with ``recipes.compose`` and checked against its schema here, so a renamed or
    misspelt key or a bad value fails before any work (:class:`~umrl.configs.ConfigError` listing every problem).
    """
    runs: dict[tuple[str, str, int], PretrainRun] = {}
    errors: list[str] = []
    ordered = sorted(needed_pretraining(list(cfg.methods)), key=lambda r: len(r.requires))  # DIAYN before MAML(diayn)
    for env in cfg.envs:
        for seed in sorted(set(pretrain_seeds(cfg))):
            for run in ordered:
                reuse = reuse_dir(cfg, run, env, seed)
                if reuse is not None:
                    runs[run.kind, env, seed] = PretrainRun(run, env, seed, reuse)
                    continue
                overrides = _suite_overrides(cfg, run, env, seed, group, runs)
                name = f"pretrain.{run.recipe} ({run.kind}, {env}, seed {seed})"
                try:
                    composed = recipes.compose(run.recipe, overrides)
                except Exception as err:  # noqa: BLE001 -- Hydra's override/compose errors, reported with the rest
                    errors.append(f"{name}: {type(err).__name__}: {str(err).splitlines()[0]}")
                    continue
                values = to_container(composed)
                problems = check_partial(values, RECIPE_SCHEMAS[run.recipe], prefix=f"{name}: ")
                if run.recipe == "maml" and not problems:
                    problems = [f"{name}: {error}" for error in hvp_errors(values)]
                if not problems:  # env-dependent defaults (budgets, DIAYN's episode length) enter the run's key
                    fill_env_defaults(values, RECIPE_SCHEMAS[run.recipe])
                budget = OmegaConf.select(OmegaConf.create(values), BUDGET_KEYS[run.recipe])
                if budget is None:
                    problems.append(f"{name}: the recipe config has no {BUDGET_KEYS[run.recipe]!r} (its budget); "
                                    "update BUDGET_KEYS in benchmarks/suite.py")
                if problems:
                    errors += problems
                    continue
                key = config_key(keyed_config(values), code)
                run_dir = Path(cfg.output_dir).absolute() / "pretrain" / run.kind / env / f"seed{seed}-{key}"
                has_checkpoint = Checkpointer(run_dir / "checkpoints").latest() is not None
                overrides += [f"output_dir={_hydra_value(str(run_dir))}", f"resume={_hydra_value(has_checkpoint)}"]
                runs[run.kind, env, seed] = PretrainRun(run, env, seed, run_dir, tuple(overrides), key, int(budget))
    if errors:
        raise ConfigError("suite pre-training configs", errors)
    return runs


def _pretrain_job(cfg: DictConfig, run: PretrainRun) -> Job:
    log = Path(cfg.output_dir).absolute() / "logs" / f"pretrain_{run.run.kind}_{run.env}_seed{run.seed}.log"
    return Job(key=pretrain_key(run.run, run.env, run.seed), fn=recipes.train, args=(run.run.recipe, list(run.overrides)),
               deps=tuple(pretrain_key(r, run.env, run.seed) for r in run.run.requires), done=run.done,
               on_success=(lambda: None) if run.reused else (lambda: mark_done(run.run_dir)),
               what=run.describe(), log=log, fresh=True)


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
                    for needed in (*pretraining.requires, pretraining):
                        run = runs[needed.kind, env, pseed]
                        jobs.setdefault(pretrain_key(needed, env, pseed), _pretrain_job(cfg, run))
                    run = runs[pretraining.kind, env, pseed]
                    deps, checkpoint = (pretrain_key(pretraining, env, pseed),), str(run.run_dir)
                    checkpoint_id = checkpoint_identity(run, checkpoint)
                for schedule in _cell_schedules(cfg, method.name):
                    suffix = "" if schedule == default_lr_schedule(method.name) else f".{schedule}"
                    settings = cell_spec(cfg, method.name, env, seed, checkpoint, lr_schedule=schedule)
                    spec = keyed_cell(settings, checkpoint_id, code, out / "cells" / env / method.name / f"seed{seed}{suffix}")
                    key = f"cell/{env}/{method.name}/seed{seed}{suffix.replace('.', '/')}"
                    jobs[key] = Job(key=key, fn=run_cell, args=(spec,), deps=deps, done=partial(cell_finished, spec.output),
                                    what=f"meta-test of {method.name} on {env}, seed {seed} -> {spec.output}",
                                    log=out / "logs" / f"cell_{env}_{method.name}_seed{seed}{suffix}.log")
    # Pre-training first, runs others depend on before them (DIAYN before MAML(diayn)), so the critical path starts at once.
    def rank(job: Job) -> tuple[bool, int]:
        needed_by_others = any(job.key in other.deps for other in jobs.values() if other.key.startswith("pretrain/"))
        return not job.key.startswith("pretrain/"), 0 if needed_by_others else (1 if job.deps else 2)

    return sorted(jobs.values(), key=rank)


def plan_ablation(cfg: DictConfig, runs: Mapping, code: str = "") -> list[Job]:
    """Meta-test jobs for up to ``ablation.max_checkpoints`` kept MAML checkpoints (evenly spaced, last included)."""
    jobs = []
    out = Path(cfg.output_dir).absolute()
    for env in cfg.envs:
        for name in cfg.ablation.methods:
            pretraining = get_method(name).pretraining
            if name not in cfg.methods or pretraining is None or pretraining.recipe != "maml":
                continue
            for seed in cfg.ablation.seeds:
                pseed = pretrain_seeds(cfg)[list(cfg.seeds).index(seed)] if seed in cfg.seeds else seed
                if (pretraining.kind, env, pseed) not in runs:
                    continue
                run = runs[pretraining.kind, env, pseed]
                files = Checkpointer(run.run_dir / "checkpoints").all()
                count = min(len(files), int(cfg.ablation.max_checkpoints))
                picks = sorted({round(i * (len(files) - 1) / max(count - 1, 1)) for i in range(count)}) if files else []
                for file in (files[i] for i in picks):
                    iteration = int(file.stem.split("_")[-1])
                    settings = cell_spec(cfg, name, env, seed, str(file), lr_schedule=sgd_schedules(cfg)[0],
                                         num_steps=int(cfg.ablation.num_steps), iteration=iteration)
                    spec = keyed_cell(settings, checkpoint_identity(run, file), code,
                                      out / "ablation" / env / name / f"seed{seed}" / f"iter{iteration}")
                    key = f"ablation/{env}/{name}/seed{seed}/iter{iteration}"
                    jobs.append(Job(key=key, fn=run_cell, args=(spec,), done=partial(cell_finished, spec.output),
                                    what=f"ablation meta-test of {name} on {env}, seed {seed}, {file.name}",
                                    log=out / "logs" / f"ablation_{env}_{name}_seed{seed}_iter{iteration}.log"))
    return jobs


# ----------------------------------------------------------------------------------------------------------------
# Reports


def report(cfg: DictConfig, group: str, timings: Mapping[str, float], cells: Sequence[Path],
           ablation: Sequence[Path] = (), *, wall_seconds: float) -> str:
    """Write results.csv, summary.md, curves.png (+ ablation) from this config's ``cells`` and ``ablation`` CSVs
    (missing ones are left out: failed jobs) and log them to wandb; returns the markdown."""
    out = Path(cfg.output_dir)
    cells = [Path(p) for p in cells if Path(p).exists()]
    rows = read_rows(cells)
    if not rows:
        raise RuntimeError(f"no finished cells under {out / 'cells'}: nothing to report (see {out / 'logs'}).")
    write_rows(rows, out / "results.csv")
    table, records = summary_table(rows, steps=list(cfg.report.steps), methods=list(cfg.methods))
    curves = curves_from_rows(rows, methods=list(cfg.methods))
    plot_adaptation_curves(curves, out / "curves.png", styles=arm_styles(rows))
    settings = OmegaConf.to_yaml(OmegaConf.create({k: to_container(cfg)[k] for k in (
        "envs", "methods", "seeds", "pretrain_seeds", "num_tasks", "protocol", "adam_lr", "sgd_lr", "sweep",
        "device")}))
    lrs = {}
    for p in cells:
        if p.with_suffix(".json").exists():
            info = json.loads(p.with_suffix(".json").read_text())
            label = arm_label(info["method"], info.get("lr_schedule", "constant"))
            lrs.setdefault((info["env"], label), set()).add(round(info["lr"], 6))
    lr_lines = [f"- {env} / {method}: lr {sorted(v)}" for (env, method), v in sorted(lrs.items())]
    time_lines = [f"- {k}: {v:.0f} s" for k, v in timings.items()] + [
        "", "(Jobs run with launcher.workers in parallel; per-job times of every invocation are in timings.json.)"]
    ablation_rows = read_rows([Path(p) for p in ablation if Path(p).exists()])
    ablation_md = None
    if ablation_rows:
        along_training = ablation_curves(ablation_rows, metric="auc")
        plot_ablation(along_training, out / "ablation.png",
                      metric=f"meta-test AUC (k = 0..{cfg.ablation.num_steps})", styles=arm_styles(ablation_rows))
        ablation_md = ablation_table(along_training)
        write_text_atomic(out / "ablation.md", ablation_md)
    record = provenance(command=shlex.join([Path(sys.executable).name, *sys.argv]), wall_seconds=wall_seconds,
                        job_threads=int(cfg.launcher.threads))
    markdown = suite_summary(table, profile=cfg.profile_name, pretraining=pretraining_note(
        list(cfg.seeds), pretrain_seeds(cfg)), lr_lines=lr_lines, time_lines=time_lines, settings_yaml=settings,
        provenance=record, ablation=ablation_md)
    write_text_atomic(out / "summary.md", markdown)
    _log_to_wandb(cfg, group, curves, records, out)
    return markdown


def _log_to_wandb(cfg: DictConfig, group: str, curves, records, out: Path) -> None:
    """One run per (env, arm) of ``curves`` (the report's) with the mean curve and summary metrics, plus a report
    run with the figures; wandb runs land in ``out/wandb`` (or ``$WANDB_DIR/wandb``)."""
    logger_cfg = {**to_container(cfg.logger), "group": group}
    for env, methods in curves.items():
        for method, curve in methods.items():
            logger = make_logger(logger_cfg, exp_name=f"{method}_{env}".replace(" ", "_"),
                                 config={"method": method, "env": env}, log_dir=out)
            for k, (m, lo, hi) in enumerate(zip(curve.mean, curve.low, curve.high)):
                log_metrics(logger, {"meta_test/return": m, "meta_test/return_low": lo,
                                     "meta_test/return_high": hi}, step=k)
            summary = {f"summary/{r['metric']}_iqm": r["iqm"] for r in records
                       if r["env"] == env and r["method"] == method}
            log_metrics(logger, summary, step=len(curve.mean) - 1)
            close_logger(logger)
    logger = make_logger(logger_cfg, exp_name="report", config=to_container(cfg), log_dir=out)
    for name in ("curves", "ablation"):
        if (out / f"{name}.png").exists():
            log_image(logger, f"report/{name}", out / f"{name}.png", step=0)
    close_logger(logger)


# ----------------------------------------------------------------------------------------------------------------
# Entry point


def suite_group(cfg: DictConfig) -> str:
    """The wandb group: ``logger.group`` or ``suite-<profile>-<first start>``, stable across resumes (kept in
    ``suite_state.json``, written atomically)."""
    if cfg.logger.get("group"):
        return str(cfg.logger.group)
    state = Path(cfg.output_dir) / "suite_state.json"
    if state.exists():
        return json.loads(state.read_text())["group"]
    group = f"suite-{cfg.profile_name}-{time.strftime('%Y%m%d-%H%M%S')}"
    write_json_atomic(state, {"group": group})
    return group


def summarize_timings(history: Sequence[Mapping]) -> dict[str, float]:
    """Wall times for the report: each invocation, each pre-training job and the mean cell (latest successful runs)."""
    jobs: dict[str, float] = {}
    for invocation in history:
        jobs.update(invocation["jobs"])
    timings = {f"suite invocation {i + 1} (wall)": inv["wall"] for i, inv in enumerate(history)}
    timings.update({k: v for k, v in jobs.items() if k.startswith("pretrain/")})
    for prefix in ("cell/", "ablation/"):
        cells = [v for k, v in jobs.items() if k.startswith(prefix)]
        if cells:
            timings[f"{prefix}* ({len(cells)} jobs, mean per job)"] = sum(cells) / len(cells)
    return timings


def code_version() -> str:
    """The hash of the sources every result depends on (``umrl/`` and ``recipes/``, configs included)."""
    import umrl

    return source_version([Path(umrl.__file__).parent, Path(recipes.__file__).parent])


def _raise_on_sigterm(signum, frame):  # a `kill` stops the suite like Ctrl-C: running workers are terminated
    raise KeyboardInterrupt(f"signal {signum}")


def run_suite(cfg: DictConfig, *, log: Callable[[str], None] = print) -> str:
    """Validate, plan, run (resuming), ablate and report; raises if any job failed (after reporting what finished).

    Every bad input (suite keys, recipe overrides, missing ``reuse`` runs) raises
    :class:`~umrl.configs.ConfigError` before any job starts.
    """
    cfg = validate(cfg, SuiteConfig)
    with directory_lock(cfg.output_dir):  # a second suite in the same output_dir refuses, naming this one's pid
        return _run_suite(cfg, log)


def _run_suite(cfg: DictConfig, log: Callable[[str], None]) -> str:
    out = Path(cfg.output_dir).absolute()
    code = code_version()
    group = suite_group(cfg)
    runs = plan_pretraining(cfg, group, code)
    jobs = plan(cfg, group, code, runs)
    for stale in remove_stale_tmp(out):
        log(f"[clean] removed {stale} (left by a killed write)")
    write_text_atomic(out / "config.yaml", OmegaConf.to_yaml(cfg))
    start = time.perf_counter()
    job_times: dict[str, float] = {}
    ablation: list[Job] = []
    launcher = make_launcher(cfg.launcher, out)
    previous = signal.signal(signal.SIGTERM, _raise_on_sigterm) if threading.current_thread() is threading.main_thread() else None
    try:
        _, failed = run_jobs(jobs, launcher, log=log, timings=job_times)
        if cfg.ablation.enabled:
            ablation = plan_ablation(cfg, runs, code)
            failed.update(run_jobs(ablation, launcher, log=log, timings=job_times)[1])
    finally:
        launcher.shutdown()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    timings_file = out / "timings.json"
    history = json.loads(timings_file.read_text()) if timings_file.exists() else []
    history.append({"wall": time.perf_counter() - start, "jobs": job_times})
    write_json_atomic(timings_file, history)
    cells = [Path(job.args[0].output) for job in jobs if job.key.startswith("cell/")]
    markdown = report(cfg, group, summarize_timings(history), cells, [Path(j.args[0].output) for j in ablation],
                      wall_seconds=sum(inv["wall"] for inv in history))
    log(markdown)
    log(f"reports in {out} (wandb group {group})")
    if failed:
        raise RuntimeError(f"{len(failed)} job(s) failed or were blocked (errors printed above; logs in {out / 'logs'}):\n"
                           + "\n".join(f"  {k}: {v}" for k, v in failed.items()))
    return markdown


@hydra.main(version_base="1.3", config_path="config", config_name="suite")
def main(cfg: DictConfig) -> None:
    run_suite(cfg, log=logging.getLogger(__name__).info)  # also into hydra/suite.log


if __name__ == "__main__":
    recipes.register_help_text(Path(__file__).resolve().parent / "config")
    main()
