"""The benchmark suite: does unsupervised meta-learning make RL faster here?

Runs UML-DIAYN, UML-random, oracle, VIME-init, DIAYN-init and scratch on the chosen envs and seeds::

    python benchmarks/suite.py profile=quick                     # point_nav, reduced budgets, minutes on 2 cores
    python benchmarks/suite.py profile=paper envs=[point_nav]    # PROTOCOL.md settings
    python benchmarks/suite.py profile=quick launcher.ray_address=auto   # cells as Ray tasks on a cluster

1. **Pre-training** (jobs): DIAYN, VIME and MAML with each proposal (diayn after its DIAYN run), by invoking the
   recipes as subprocesses with Hydra overrides (``pretrain.<recipe>.overrides``). A run that finished (marker file
   ``suite_complete``) is reused; a killed one resumes from its last checkpoint; ``pretrain.<recipe>.reuse`` points
   at existing runs (path templates with ``{env}``, ``{seed}``, ``{proposal}``).
2. **Meta-test cells**: each (method, env, seed) is an independent job running :func:`umrl.evaluation.run_cell`; its
   CSV appears atomically when it finishes, and an existing CSV is never recomputed, so a killed suite resumes.
3. **Meta-training ablation**: the kept MAML checkpoints along meta-training are meta-tested the same way.
4. **Reports** under ``output_dir``: ``results.csv`` (tidy: method, env, seed, task, step, return), ``summary.md``
   (return at k = 0, 1, 5, K and AUC: IQM and mean with bootstrap CIs), ``curves.png``, ``ablation.png`` /
   ``ablation.md``, and wandb runs (offline by default) in one group per suite run.

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

from umrl.evaluation import (
    METHODS,
    curves_from_rows,
    read_rows,
    run_cell,
    run_matrix,
    summary_table,
    write_rows,
)
from umrl.plots import Curve, plot_ablation, plot_adaptation_curves
from umrl.runtime import Checkpointer, log_image, log_metrics, make_logger, to_container
from umrl.stats import auc, bootstrap_ci

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


def pretrain_key(kind: str, env: str, seed: int) -> str:
    return f"pretrain/{kind}/{env}/seed{seed}"


def cell_path(cfg: DictConfig, env: str, method: str, seed: int) -> Path:
    return Path(cfg.output_dir).absolute() / "cells" / env / method / f"seed{seed}.csv"


def pretrain_dir(cfg: DictConfig, kind: str, env: str, seed: int) -> Path:
    """Where pre-training ``kind`` (diayn, vime, maml_<proposal>) of (env, seed) lives (``reuse`` wins)."""
    recipe, _, proposal = kind.partition("_")
    template = cfg.pretrain[recipe].get("reuse")
    if isinstance(template, Mapping) or OmegaConf.is_dict(template):
        template = template.get(proposal)
    if template:
        return Path(str(template).format(env=env, seed=seed, proposal=proposal)).absolute()
    return Path(cfg.output_dir).absolute() / "pretrain" / kind / env / f"seed{seed}"


def _has_checkpoint(run_dir: Path) -> bool:
    return Checkpointer(run_dir / "checkpoints").latest() is not None


def pretrain_done(cfg: DictConfig, kind: str, env: str, seed: int) -> bool:
    run_dir = pretrain_dir(cfg, kind, env, seed)
    reused = cfg.pretrain[kind.partition("_")[0]].get("reuse")
    if reused and _has_checkpoint(run_dir):
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


def pretrain_command(cfg: DictConfig, kind: str, env: str, seed: int, group: str) -> list[str]:
    """The recipe invocation (Hydra overrides) for one pre-training run; resumes if a checkpoint exists."""
    recipe, _, proposal = kind.partition("_")
    spec = cfg.pretrain[recipe]
    run_dir = pretrain_dir(cfg, kind, env, seed)
    cmd = [sys.executable, str(REPO / spec.recipe), f"env.name={env}", f"seed={seed}", f"output_dir={run_dir}",
           f"logger.backend={cfg.logger.backend}", f"logger.group={group}", "progress=false"]
    if recipe == "maml":
        cmd += [f"proposal={proposal}", "checkpoint.keep_all=true"]
        if proposal == "diayn":
            cmd.append(f"{spec.diayn_checkpoint_key}={pretrain_dir(cfg, 'diayn', env, seed)}")
    cmd += hydra_overrides(spec.get("overrides") or {})
    if _has_checkpoint(run_dir):
        cmd.append("resume=true")
    return cmd


def _pretrain_job(cfg: DictConfig, kind: str, env: str, seed: int, group: str) -> Job:
    run_dir = pretrain_dir(cfg, kind, env, seed)
    log_file = Path(cfg.output_dir).absolute() / "logs" / f"{kind}_{env}_seed{seed}.log"
    log_file.parent.mkdir(parents=True, exist_ok=True)
    deps = (pretrain_key("diayn", env, seed),) if kind == "maml_diayn" else ()
    threads = str(cfg.launcher.threads)
    environ = {**os.environ, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads, "PYTHONPATH": str(REPO)}

    shell = f"{shlex.join(pretrain_command(cfg, kind, env, seed, group))} > {shlex.quote(str(log_file))} 2>&1"
    return Job(key=pretrain_key(kind, env, seed), fn=subprocess.run, args=(["bash", "-c", shell],), deps=deps,
               kwargs={"check": True, "cwd": str(REPO), "env": environ},
               done=lambda: pretrain_done(cfg, kind, env, seed),
               on_success=lambda: (run_dir / DONE_MARKER).write_text(time.strftime("%Y-%m-%dT%H:%M:%S")))


def _cell_spec(cfg: DictConfig, method: str, env: str, seed: int, output: Path, checkpoint: str | None,
               **extra) -> dict:
    protocol = to_container(cfg.protocol)
    if "num_steps" in extra.get("protocol_overrides", {}):
        protocol["num_steps"] = extra.pop("protocol_overrides")["num_steps"]
    return {"method": method, "env": env, "seed": seed, "checkpoint": checkpoint, "output": str(output),
            "protocol": protocol, "num_tasks": cfg.num_tasks, "adam_lr": cfg.adam_lr, "sgd_lr": cfg.sgd_lr,
            "sweep": to_container(cfg.sweep), "skill_trajectories": cfg.skill_trajectories,
            "threads": cfg.launcher.threads, "extra": extra}


def plan(cfg: DictConfig, group: str) -> list[Job]:
    """Pre-training jobs and one meta-test job per (method, env, seed) cell."""
    unknown = [m for m in cfg.methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown methods {unknown}; valid choices: {list(METHODS)}.")
    jobs: dict[str, Job] = {}
    for env in cfg.envs:
        for seed in cfg.seeds:
            pseed = seed if cfg.pretrain_seed is None else int(cfg.pretrain_seed)
            for method in cfg.methods:
                kind = METHODS[method][0]
                deps: tuple[str, ...] = ()
                checkpoint = None
                if kind is not None:
                    needed = [kind] + (["diayn"] if kind == "maml_diayn" else [])
                    for k in needed:
                        key = pretrain_key(k, env, pseed)
                        if key not in jobs:
                            jobs[key] = _pretrain_job(cfg, k, env, pseed, group)
                    deps = (pretrain_key(kind, env, pseed),)
                    checkpoint = str(pretrain_dir(cfg, kind, env, pseed))
                output = cell_path(cfg, env, method, seed)
                spec = _cell_spec(cfg, method, env, seed, output, checkpoint)
                key = f"cell/{env}/{method}/seed{seed}"
                jobs[key] = Job(key=key, fn=run_cell, args=(spec,), deps=deps, done=output.exists)
    # Pre-training first (DIAYN before the rest: MAML(diayn) waits for it), so the critical path starts at once.
    rank = {"diayn": 0, "maml_diayn": 1}
    return sorted(jobs.values(), key=lambda j: (not j.key.startswith("pretrain/"), rank.get(j.key.split("/")[1], 2)))


def plan_ablation(cfg: DictConfig) -> list[Job]:
    """Meta-test jobs for up to ``ablation.max_checkpoints`` kept MAML checkpoints (evenly spaced, last included)."""
    jobs = []
    for env in cfg.envs:
        for method in cfg.ablation.methods:
            if method not in cfg.methods or not METHODS[method][0].startswith("maml"):
                continue
            for seed in cfg.ablation.seeds:
                pseed = seed if cfg.pretrain_seed is None else int(cfg.pretrain_seed)
                files = Checkpointer(pretrain_dir(cfg, METHODS[method][0], env, pseed) / "checkpoints").all()
                if not files:
                    continue
                count = min(len(files), int(cfg.ablation.max_checkpoints))
                picks = sorted({round(i * (len(files) - 1) / max(count - 1, 1)) for i in range(count)})
                for file in (files[i] for i in picks):
                    iteration = int(file.stem.split("_")[-1])
                    output = Path(cfg.output_dir).absolute() / "ablation" / env / method / f"seed{seed}" / f"iter{iteration}.csv"
                    spec = _cell_spec(cfg, method, env, seed, output, str(file), iteration=iteration,
                                      protocol_overrides={"num_steps": int(cfg.ablation.num_steps)})
                    key = f"ablation/{env}/{method}/seed{seed}/iter{iteration}"
                    jobs.append(Job(key=key, fn=run_cell, args=(spec,), done=output.exists))
    return jobs


# ----------------------------------------------------------------------------------------------------------------
# Reports


def ablation_curves(rows: Sequence[Mapping], *, metric: str) -> dict[str, dict[str, Curve]]:
    """``{env: {method: Curve over meta-training iterations}}`` of the per-run ``metric`` (``auc`` or ``final``)."""
    curves: dict[str, dict[str, Curve]] = {}
    for env, method in sorted({(r["env"], r["method"]) for r in rows}):
        iterations = sorted({int(r["iteration"]) for r in rows if r["env"] == env and r["method"] == method})
        stats = []
        for it in iterations:
            subset = [r for r in rows if r["env"] == env and r["method"] == method and int(r["iteration"]) == it]
            matrix = run_matrix(subset, env=env, method=method)
            values = auc(matrix) if metric == "auc" else matrix[:, -1]
            stats.append((values.mean(), *bootstrap_ci(values)))
        mean, low, high = (list(x) for x in zip(*stats))
        curves.setdefault(env, {})[method] = Curve(iterations, mean, low, high)
    return curves


def report(cfg: DictConfig, group: str, timings: Mapping[str, float]) -> str:
    """Write results.csv, summary.md, curves.png (+ ablation) and log them to wandb; returns the markdown."""
    out = Path(cfg.output_dir)
    cells = [cell_path(cfg, env, m, s) for env in cfg.envs for m in cfg.methods for s in cfg.seeds]
    rows = read_rows([p for p in cells if p.exists()])
    if not rows:
        raise RuntimeError(f"no finished cells under {out / 'cells'}: nothing to report (see {out / 'logs'}).")
    write_rows(rows, out / "results.csv")
    table, records = summary_table(rows, steps=list(cfg.report.steps), methods=list(cfg.methods))
    plot_adaptation_curves(curves_from_rows(rows, methods=list(cfg.methods)), out / "curves.png")
    settings = OmegaConf.to_yaml(OmegaConf.create({k: to_container(cfg)[k] for k in (
        "envs", "methods", "seeds", "pretrain_seed", "num_tasks", "protocol", "adam_lr", "sgd_lr", "sweep")}))
    lrs = {}
    for p in cells:
        if p.with_suffix(".json").exists():
            info = json.loads(p.with_suffix(".json").read_text())
            lrs.setdefault((info["env"], info["method"]), set()).add(round(info["lr"], 6))
    lr_lines = [f"- {env} / {method}: lr {sorted(v)}" for (env, method), v in sorted(lrs.items())]
    time_lines = [f"- {k}: {v:.0f} s" for k, v in timings.items()] + [
        "", "(Jobs run with launcher.workers in parallel; per-job times of every invocation are in timings.json.)"]
    markdown = (f"# Benchmark suite `{cfg.profile_name}`\n\nMeta-test return (IQM over tasks x seeds, 95% bootstrap "
                f"CI); AUC = trapezoidal area under the return curve over k = 0..K.\n\n{table}\n"
                f"## Meta-test learning rates\n\n" + "\n".join(lr_lines) + "\n\n## Wall time\n\n"
                + "\n".join(time_lines) + f"\n\n## Settings\n\n```yaml\n{settings}```\n")
    ablation_files = sorted((out / "ablation").rglob("iter*.csv")) if (out / "ablation").exists() else []
    ablation_rows = [r for r in read_rows(ablation_files) if r["env"] in cfg.envs and r["method"] in cfg.methods]
    if ablation_rows:
        curves = ablation_curves(ablation_rows, metric="auc")
        plot_ablation(curves, out / "ablation.png", metric=f"meta-test AUC (k = 0..{cfg.ablation.num_steps})")
        lines = ["| env | method | iteration | AUC mean [95% CI] |", "|---|---|---|---|"]
        for env, methods in curves.items():
            for method, c in methods.items():
                lines += [f"| {env} | {method} | {it} | {m:.1f} [{lo:.1f}, {hi:.1f}] |"
                          for it, m, lo, hi in zip(c.x, c.mean, c.low, c.high)]
        ablation_md = "# Meta-training ablation\n\n" + "\n".join(lines) + "\n"
        (out / "ablation.md").write_text(ablation_md)
        markdown += "\n" + ablation_md.replace("# Meta", "## Meta")
    (out / "summary.md").write_text(markdown)
    _log_to_wandb(cfg, group, rows, records, out)
    return markdown


def _log_to_wandb(cfg: DictConfig, group: str, rows, records, out: Path) -> None:
    """One run per (env, method) with the mean curve and summary metrics, plus a report run with the figures."""
    logger_cfg = {**to_container(cfg.logger), "group": group}
    curves = curves_from_rows(rows)
    for env, methods in curves.items():
        for method, curve in methods.items():
            logger = make_logger(logger_cfg, exp_name=f"{method}_{env}", config={"method": method, "env": env})
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
    markdown = report(cfg, group, summarize_timings(history))
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
