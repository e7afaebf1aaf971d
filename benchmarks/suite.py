"""The benchmark suite: does unsupervised meta-learning make RL faster here?

Runs UML-DIAYN, UML-random, oracle, VIME-init, DIAYN-init and scratch on the chosen envs and seeds::

    python benchmarks/suite.py profile=quick                     # point_nav, reduced budgets, minutes on 2 cores
    python benchmarks/suite.py profile=paper envs=[point_nav]    # PROTOCOL.md settings
    python benchmarks/suite.py profile=quick launcher.ray_address=auto   # cells as Ray tasks on a cluster

1. **Pre-training** (jobs): DIAYN, VIME and MAML with each proposal (diayn after its DIAYN run), by invoking the
   recipes as subprocesses with Hydra overrides (``pretrain.<recipe>.overrides``). A run that finished (marker file
   ``suite_complete``) is reused; a killed one resumes from its last checkpoint; ``pretrain.<recipe>.reuse`` points
   at existing runs (path templates with ``{env}``, ``{seed}``, ``{proposal}``). Meta-test seed ``seeds[i]`` uses
   the runs of pre-training seed ``pretrain_seeds[i]`` (null: the same seed, independent pre-training per seed).
2. **Meta-test cells**: each (method, env, seed) -- and, for the SGD methods, each ``protocol.sgd_schedule`` -- is
   an independent job running :func:`umrl.metatest.run_cell` on a typed :class:`umrl.metatest.CellSpec`; its CSV
   appears atomically when it finishes, and an existing CSV is never recomputed, so a killed suite resumes.
3. **Meta-training ablation**: the kept MAML checkpoints along meta-training are meta-tested the same way.
4. **Reports** (built by :mod:`umrl.metatest.results`) under ``output_dir``: ``results.csv`` (tidy: method, env,
   seed, task, step, return, lr_schedule), ``summary.md`` (return at k = 0, 1, 5, K and AUC: IQM and mean with
   bootstrap CIs; pre-training seeds; commit, command, hardware and wall time), ``curves.png``, ``ablation.png`` /
   ``ablation.md``, and wandb runs (offline by default) in one group per suite run.

This file schedules and launches only; what a cell computes and how results are tabulated live in
:mod:`umrl.metatest`.

Jobs run in a local process pool (``launcher.workers``) or as Ray tasks when ``launcher.ray_address`` is set
(``local`` starts a Ray instance on this machine). Every value is a config override (``benchmarks/config/``).
"""
from __future__ import annotations

import concurrent.futures as cf
import json
import multiprocessing
import os
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from umrl.metatest import (
    SGD_SCHEDULES,
    CellSpec,
    Pretraining,
    ablation_curves,
    ablation_table,
    arm_label,
    arm_styles,
    curves_from_rows,
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
from umrl.runtime import Checkpointer, log_image, log_metrics, make_logger, to_container

REPO = Path(__file__).resolve().parents[1]
DONE_MARKER = "suite_complete"


# ----------------------------------------------------------------------------------------------------------------
# Jobs and launchers


@dataclass
class Job:
    """One unit of work: ``fn(*args, **kwargs)`` run by a launcher once every job in ``deps`` has succeeded.

    ``done()`` says whether its result already exists (then it is skipped); ``on_success`` runs in the driver.
    """

    key: str
    fn: Callable
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)
    deps: tuple[str, ...] = ()
    done: Callable[[], bool] = lambda: False
    on_success: Callable[[], None] = lambda: None


class InlineLauncher:
    """Runs each job in this process when submitted (``launcher.workers=0``: debugging, tests)."""

    slots = 1

    def submit(self, fn: Callable, *args, **kwargs) -> cf.Future:
        future: cf.Future = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as err:  # noqa: BLE001 -- handed to the scheduler exactly like a worker's failure
            future.set_exception(err)
        return future

    def shutdown(self) -> None:
        return None


class LocalLauncher:
    """A process pool (spawn) of ``workers`` processes; ``submit`` returns a ``concurrent.futures.Future``."""

    def __init__(self, workers: int):
        self.slots = workers
        self.pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"))

    def submit(self, fn: Callable, *args, **kwargs) -> cf.Future:
        return self.pool.submit(fn, *args, **kwargs)

    def shutdown(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


class RayLauncher:
    """Ray tasks of ``cpus_per_job`` CPUs; connects to ``address`` (``local``: start one here) unless Ray is up."""

    def __init__(self, address: str, cpus_per_job: float = 1.0):
        import ray

        if not ray.is_initialized():
            ray.init(address=None if address == "local" else address, include_dashboard=False)
        self.ray, self.cpus = ray, cpus_per_job
        self.slots = max(1, int(ray.cluster_resources().get("CPU", 1) // cpus_per_job))

    def submit(self, fn: Callable, *args, **kwargs) -> cf.Future:
        return self.ray.remote(num_cpus=self.cpus)(fn).remote(*args, **kwargs).future()

    def shutdown(self) -> None:  # the Ray instance belongs to whoever started it
        return None


def make_launcher(launcher_cfg: Mapping):
    """``RayLauncher`` when ``ray_address`` is set, else ``LocalLauncher`` (``InlineLauncher`` for 0 workers)."""
    if launcher_cfg.get("ray_address"):
        return RayLauncher(str(launcher_cfg["ray_address"]), float(launcher_cfg.get("threads", 1)))
    workers = int(launcher_cfg.get("workers", 2))
    return LocalLauncher(workers) if workers > 0 else InlineLauncher()


def run_jobs(jobs: Sequence[Job], launcher, *, log: Callable[[str], None] = print,
             timings: dict[str, float] | None = None) -> tuple[set[str], dict[str, str]]:
    """Run ``jobs`` respecting dependencies; returns (succeeded keys, {failed or blocked key: reason}).

    Jobs whose ``done()`` is true are not run. At most ``launcher.slots`` jobs run at once, so the wall time of each
    successful job (written into ``timings``) excludes queueing. A failure does not stop independent jobs; its dependants are
    blocked.
    """
    keys = {job.key for job in jobs}
    if len(keys) != len(jobs):
        raise ValueError("job keys must be unique.")
    succeeded = {job.key for job in jobs if job.done()}
    pending = {job.key: job for job in jobs if job.key not in succeeded}
    failed: dict[str, str] = {}
    running: dict[cf.Future, Job] = {}
    started: dict[str, float] = {}
    timings = {} if timings is None else timings
    for key in sorted(succeeded):
        log(f"[skip] {key}: already done")
    while pending or running:
        for key, job in list(pending.items()):
            missing = [d for d in job.deps if d not in keys]
            blocked = [d for d in job.deps if d in failed]
            if missing or blocked:
                failed[key] = f"blocked by {missing or blocked}"
                del pending[key]
            elif all(d in succeeded for d in job.deps) and len(running) < launcher.slots:
                log(f"[start] {key}")
                started[key] = time.perf_counter()
                running[launcher.submit(job.fn, *job.args, **job.kwargs)] = job
                del pending[key]
        if not running:
            break
        finished, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
        for future in finished:
            job = running.pop(future)
            seconds = time.perf_counter() - started[job.key]
            try:
                future.result()
                job.on_success()
            except Exception as err:  # noqa: BLE001 -- recorded; run_suite raises once independent jobs ran
                failed[job.key] = f"{type(err).__name__}: {err}"
                log(f"[fail] {job.key}: {failed[job.key]}")
            else:
                succeeded.add(job.key)
                timings[job.key] = seconds
                log(f"[done] {job.key} ({seconds:.0f} s)")
    return succeeded, failed


# ----------------------------------------------------------------------------------------------------------------
# Planning: which pre-training runs and cells a config asks for


def pretrain_key(run: Pretraining, env: str, seed: int) -> str:
    return f"pretrain/{run.kind}/{env}/seed{seed}"


def _plain(value):
    """A config node as plain Python (lists and dicts), anything else as it is (for error messages)."""
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def sgd_schedules(cfg: DictConfig) -> list[str]:
    """``protocol.sgd_schedule`` as a list: one schedule, or several (the SGD methods get one cell per schedule)."""
    value = cfg.protocol.sgd_schedule
    schedules = [str(value)] if isinstance(value, str) else [str(v) for v in value]
    bad = [s for s in schedules if s not in SGD_SCHEDULES]
    if not schedules or bad:
        raise ValueError(f"protocol.sgd_schedule: got {_plain(value)!r}; accepted: one of {list(SGD_SCHEDULES)} "
                         "or a non-empty list of them.")
    return schedules


def pretrain_seeds(cfg: DictConfig) -> list[int]:
    """The pre-training seed of each meta-test seed: ``pretrain_seeds`` null (= the meta-test seeds: independent
    pre-training), an int (one run shared by every seed) or a list as long as ``seeds``."""
    value, seeds = cfg.pretrain_seeds, [int(s) for s in cfg.seeds]
    if value is None:
        return seeds
    if isinstance(value, int) and not isinstance(value, bool):
        return [value] * len(seeds)
    values = [int(v) for v in value] if OmegaConf.is_list(value) or isinstance(value, (list, tuple)) else None
    if values is None or len(values) != len(seeds):
        raise ValueError(f"pretrain_seeds: got {_plain(value)!r}; "
                         f"accepted: null, an int, or a list of {len(seeds)} ints (one per seed in {seeds}).")
    return values


def cell_path(cfg: DictConfig, env: str, method: str, seed: int, lr_schedule: str = "constant") -> Path:
    """A cell's CSV: ``cells/<env>/<method>/seed<s>.csv`` (``seed<s>.<schedule>.csv`` for a non-constant schedule)."""
    suffix = "" if lr_schedule == "constant" else f".{lr_schedule}"
    return Path(cfg.output_dir).absolute() / "cells" / env / method / f"seed{seed}{suffix}.csv"


def pretrain_dir(cfg: DictConfig, run: Pretraining, env: str, seed: int) -> Path:
    """Where pre-training ``run`` of (env, seed) lives (``pretrain.<recipe>.reuse`` wins)."""
    template = cfg.pretrain[run.recipe].get("reuse")
    if isinstance(template, Mapping) or OmegaConf.is_dict(template):
        template = template.get(run.proposal)
    if template:
        return Path(str(template).format(env=env, seed=seed, proposal=run.proposal)).absolute()
    return Path(cfg.output_dir).absolute() / "pretrain" / run.kind / env / f"seed{seed}"


def _has_checkpoint(run_dir: Path) -> bool:
    return Checkpointer(run_dir / "checkpoints").latest() is not None


def pretrain_done(cfg: DictConfig, run: Pretraining, env: str, seed: int) -> bool:
    run_dir = pretrain_dir(cfg, run, env, seed)
    if cfg.pretrain[run.recipe].get("reuse") and _has_checkpoint(run_dir):
        return True  # an external run given by the user: taken as it is
    return (run_dir / DONE_MARKER).exists()


def hydra_overrides(values: Mapping, prefix: str = "") -> list[str]:
    """``{"a": {"b": 1}, "c": [1, 2]}`` -> ``["a.b=1", "c=[1,2]"]`` (Hydra command-line overrides)."""
    out = []
    for key, value in (to_container(values) if OmegaConf.is_config(values) else dict(values)).items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out += hydra_overrides(value, prefix=f"{name}.")
        elif isinstance(value, (list, tuple)):
            out.append(f"{name}=[{','.join(str(v) for v in value)}]")
        else:
            out.append(f"{name}={'null' if value is None else value}")
    return out


def pretrain_command(cfg: DictConfig, run: Pretraining, env: str, seed: int, group: str) -> list[str]:
    """The recipe invocation (Hydra overrides) for one pre-training run; resumes if a checkpoint exists."""
    spec = cfg.pretrain[run.recipe]
    run_dir = pretrain_dir(cfg, run, env, seed)
    cmd = [sys.executable, str(REPO / spec.recipe), f"env.name={env}", f"seed={seed}", f"output_dir={run_dir}",
           f"logger.backend={cfg.logger.backend}", f"logger.group={group}", "progress=false"]
    if run.recipe == "maml":
        cmd += [f"proposal={run.proposal}", "checkpoint.keep_all=true"]
        for needed in run.requires:
            cmd.append(f"{spec.diayn_checkpoint_key}={pretrain_dir(cfg, needed, env, seed)}")
    cmd += hydra_overrides(spec.get("overrides") or {})
    if _has_checkpoint(run_dir):
        cmd.append("resume=true")
    return cmd


def _pretrain_job(cfg: DictConfig, run: Pretraining, env: str, seed: int, group: str) -> Job:
    run_dir = pretrain_dir(cfg, run, env, seed)
    log_file = Path(cfg.output_dir).absolute() / "logs" / f"{run.kind}_{env}_seed{seed}.log"
    log_file.parent.mkdir(parents=True, exist_ok=True)
    threads = str(cfg.launcher.threads)
    environ = {**os.environ, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads, "PYTHONPATH": str(REPO)}

    shell = f"{shlex.join(pretrain_command(cfg, run, env, seed, group))} > {shlex.quote(str(log_file))} 2>&1"
    return Job(key=pretrain_key(run, env, seed), fn=subprocess.run, args=(["bash", "-c", shell],),
               deps=tuple(pretrain_key(r, env, seed) for r in run.requires),
               kwargs={"check": True, "cwd": str(REPO), "env": environ},
               done=lambda: pretrain_done(cfg, run, env, seed),
               on_success=lambda: (run_dir / DONE_MARKER).write_text(time.strftime("%Y-%m-%dT%H:%M:%S")))


def cell_spec(cfg: DictConfig, method: str, env: str, seed: int, output: Path, checkpoint: str | None, *,
              lr_schedule: str = "constant", num_steps: int | None = None, **extra) -> CellSpec:
    """The typed :class:`CellSpec` of one cell from the suite config (``num_steps`` overrides ``protocol``'s K)."""
    protocol = {**to_container(cfg.protocol), "sgd_schedule": lr_schedule}
    if num_steps is not None:
        protocol["num_steps"] = num_steps
    return CellSpec.from_mapping({
        "method": method, "env": env, "seed": seed, "output": str(output), "checkpoint": checkpoint,
        "protocol": protocol, "num_tasks": cfg.num_tasks, "adam_lr": cfg.adam_lr, "sgd_lr": cfg.sgd_lr,
        "sweep": to_container(cfg.sweep), "skill_trajectories": cfg.skill_trajectories,
        "threads": cfg.launcher.threads, "extra": extra})


def _cell_schedules(cfg: DictConfig, method: str) -> list[str]:
    return sgd_schedules(cfg) if get_method(method).optimizer == "sgd" else ["constant"]


def plan(cfg: DictConfig, group: str) -> list[Job]:
    """Pre-training jobs and one meta-test job per (method, env, seed[, SGD schedule]) cell."""
    methods = [get_method(m) for m in cfg.methods]
    jobs: dict[str, Job] = {}
    for env in cfg.envs:
        for seed, pseed in zip(cfg.seeds, pretrain_seeds(cfg)):
            for method in methods:
                run, deps, checkpoint = method.pretraining, (), None
                if run is not None:
                    for needed in (*run.requires, run):
                        jobs.setdefault(pretrain_key(needed, env, pseed), _pretrain_job(cfg, needed, env, pseed, group))
                    deps = (pretrain_key(run, env, pseed),)
                    checkpoint = str(pretrain_dir(cfg, run, env, pseed))
                for schedule in _cell_schedules(cfg, method.name):
                    output = cell_path(cfg, env, method.name, seed, schedule)
                    spec = cell_spec(cfg, method.name, env, seed, output, checkpoint, lr_schedule=schedule)
                    suffix = "" if schedule == "constant" else f"/{schedule}"
                    key = f"cell/{env}/{method.name}/seed{seed}{suffix}"
                    jobs[key] = Job(key=key, fn=run_cell, args=(spec,), deps=deps, done=output.exists)
    # Pre-training first, runs others depend on before them (DIAYN before MAML(diayn)), so the critical path starts at once.
    def rank(job: Job) -> tuple[bool, int]:
        needed_by_others = any(job.key in other.deps for other in jobs.values() if other.key.startswith("pretrain/"))
        return not job.key.startswith("pretrain/"), 0 if needed_by_others else (1 if job.deps else 2)

    return sorted(jobs.values(), key=rank)


def plan_ablation(cfg: DictConfig) -> list[Job]:
    """Meta-test jobs for up to ``ablation.max_checkpoints`` kept MAML checkpoints (evenly spaced, last included)."""
    jobs = []
    for env in cfg.envs:
        for name in cfg.ablation.methods:
            run = get_method(name).pretraining
            if name not in cfg.methods or run is None or run.recipe != "maml":
                continue
            for seed in cfg.ablation.seeds:
                pseed = pretrain_seeds(cfg)[list(cfg.seeds).index(seed)] if seed in cfg.seeds else seed
                files = Checkpointer(pretrain_dir(cfg, run, env, pseed) / "checkpoints").all()
                if not files:
                    continue
                count = min(len(files), int(cfg.ablation.max_checkpoints))
                picks = sorted({round(i * (len(files) - 1) / max(count - 1, 1)) for i in range(count)})
                for file in (files[i] for i in picks):
                    iteration = int(file.stem.split("_")[-1])
                    output = Path(cfg.output_dir).absolute() / "ablation" / env / name / f"seed{seed}" / f"iter{iteration}.csv"
                    spec = cell_spec(cfg, name, env, seed, output, str(file), lr_schedule=sgd_schedules(cfg)[0],
                                     num_steps=int(cfg.ablation.num_steps), iteration=iteration)
                    key = f"ablation/{env}/{name}/seed{seed}/iter{iteration}"
                    jobs.append(Job(key=key, fn=run_cell, args=(spec,), done=output.exists))
    return jobs


# ----------------------------------------------------------------------------------------------------------------
# Reports


def report(cfg: DictConfig, group: str, timings: Mapping[str, float], *, wall_seconds: float) -> str:
    """Write results.csv, summary.md, curves.png (+ ablation) and log them to wandb; returns the markdown."""
    out = Path(cfg.output_dir)
    cells = [cell_path(cfg, env, m, s, schedule) for env in cfg.envs for m in cfg.methods
             for schedule in _cell_schedules(cfg, m) for s in cfg.seeds]
    rows = read_rows([p for p in cells if p.exists()])
    if not rows:
        raise RuntimeError(f"no finished cells under {out / 'cells'}: nothing to report (see {out / 'logs'}).")
    write_rows(rows, out / "results.csv")
    table, records = summary_table(rows, steps=list(cfg.report.steps), methods=list(cfg.methods))
    plot_adaptation_curves(curves_from_rows(rows, methods=list(cfg.methods)), out / "curves.png",
                           styles=arm_styles(rows))
    settings = OmegaConf.to_yaml(OmegaConf.create({k: to_container(cfg)[k] for k in (
        "envs", "methods", "seeds", "pretrain_seeds", "num_tasks", "protocol", "adam_lr", "sgd_lr", "sweep")}))
    lrs = {}
    for p in cells:
        if p.with_suffix(".json").exists():
            info = json.loads(p.with_suffix(".json").read_text())
            label = arm_label(info["method"], info.get("lr_schedule", "constant"))
            lrs.setdefault((info["env"], label), set()).add(round(info["lr"], 6))
    lr_lines = [f"- {env} / {method}: lr {sorted(v)}" for (env, method), v in sorted(lrs.items())]
    time_lines = [f"- {k}: {v:.0f} s" for k, v in timings.items()] + [
        "", "(Jobs run with launcher.workers in parallel; per-job times of every invocation are in timings.json.)"]
    ablation_files = sorted((out / "ablation").rglob("iter*.csv")) if (out / "ablation").exists() else []
    ablation_rows = [r for r in read_rows(ablation_files) if r["env"] in cfg.envs and r["method"] in cfg.methods]
    ablation_md = None
    if ablation_rows:
        curves = ablation_curves(ablation_rows, metric="auc")
        plot_ablation(curves, out / "ablation.png", metric=f"meta-test AUC (k = 0..{cfg.ablation.num_steps})",
                      styles=arm_styles(ablation_rows))
        ablation_md = ablation_table(curves)
        (out / "ablation.md").write_text(ablation_md)
    record = provenance(command=shlex.join([Path(sys.executable).name, *sys.argv]), wall_seconds=wall_seconds,
                        job_threads=int(cfg.launcher.threads))
    markdown = suite_summary(table, profile=cfg.profile_name, pretraining=pretraining_note(
        list(cfg.seeds), pretrain_seeds(cfg)), lr_lines=lr_lines, time_lines=time_lines, settings_yaml=settings,
        provenance=record, ablation=ablation_md)
    (out / "summary.md").write_text(markdown)
    _log_to_wandb(cfg, group, rows, records, out)
    return markdown


def _log_to_wandb(cfg: DictConfig, group: str, rows, records, out: Path) -> None:
    """One run per (env, arm) with the mean curve and summary metrics, plus a report run with the figures."""
    logger_cfg = {**to_container(cfg.logger), "group": group}
    curves = curves_from_rows(rows)
    for env, methods in curves.items():
        for method, curve in methods.items():
            logger = make_logger(logger_cfg, exp_name=f"{method}_{env}".replace(" ", "_"),
                                 config={"method": method, "env": env})
            for k, (m, lo, hi) in enumerate(zip(curve.mean, curve.low, curve.high)):
                log_metrics(logger, {"meta_test/return": m, "meta_test/return_low": lo,
                                     "meta_test/return_high": hi}, step=k)
            summary = {f"summary/{r['metric']}_iqm": r["iqm"] for r in records
                       if r["env"] == env and r["method"] == method}
            log_metrics(logger, summary, step=len(curve.mean) - 1)
            _finish(logger)
    logger = make_logger(logger_cfg, exp_name="report", config=to_container(cfg))
    for name in ("curves", "ablation"):
        if (out / f"{name}.png").exists():
            log_image(logger, f"report/{name}", out / f"{name}.png", step=0)
    _finish(logger)


def _finish(logger) -> None:
    experiment = getattr(logger, "experiment", None)
    if experiment is not None and hasattr(experiment, "finish"):
        experiment.finish()


# ----------------------------------------------------------------------------------------------------------------
# Entry point


def suite_group(cfg: DictConfig) -> str:
    """The wandb group: ``logger.group`` or ``suite-<profile>-<first start>``, stable across resumes."""
    if cfg.logger.get("group"):
        return str(cfg.logger.group)
    state = Path(cfg.output_dir) / "suite_state.json"
    if state.exists():
        return json.loads(state.read_text())["group"]
    group = f"suite-{cfg.profile_name}-{time.strftime('%Y%m%d-%H%M%S')}"
    state.parent.mkdir(parents=True, exist_ok=True)
    state.write_text(json.dumps({"group": group}))
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


def run_suite(cfg: DictConfig, *, log: Callable[[str], None] = print) -> str:
    """Plan, run (resuming), ablate and report; raises if any job failed (after reporting what finished)."""
    group = suite_group(cfg)
    start = time.perf_counter()
    job_times: dict[str, float] = {}
    launcher = make_launcher(cfg.launcher)
    try:
        _, failed = run_jobs(plan(cfg, group), launcher, log=log, timings=job_times)
        if cfg.ablation.enabled:
            failed.update(run_jobs(plan_ablation(cfg), launcher, log=log, timings=job_times)[1])
    finally:
        launcher.shutdown()
    timings_file = Path(cfg.output_dir) / "timings.json"
    history = json.loads(timings_file.read_text()) if timings_file.exists() else []
    history.append({"wall": time.perf_counter() - start, "jobs": job_times})
    timings_file.write_text(json.dumps(history, indent=1))
    markdown = report(cfg, group, summarize_timings(history), wall_seconds=sum(inv["wall"] for inv in history))
    log(markdown)
    log(f"reports in {Path(cfg.output_dir).resolve()} (wandb group {group})")
    if failed:
        raise RuntimeError("some jobs failed (logs in " f"{Path(cfg.output_dir) / 'logs'}):\n"
                           + "\n".join(f"  {k}: {v}" for k, v in failed.items()))
    return markdown


@hydra.main(version_base="1.3", config_path="config", config_name="suite")
def main(cfg: DictConfig) -> None:
    run_suite(cfg)


if __name__ == "__main__":
    main()
