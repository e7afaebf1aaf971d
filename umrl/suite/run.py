"""Running a suite: validate, plan (:mod:`umrl.suite.plan`), run the jobs through :mod:`umrl.launch` (resuming what a
killed suite left), ablate and report (:mod:`umrl.suite.report`).
"""
from __future__ import annotations

import functools
import json
import signal
import threading
import time
import warnings
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from umrl.atomic_write import write_text_atomic
from umrl.configs import validate
from umrl.configs.suite import SuiteConfig
from umrl.envs.user_envs import env_module_source, import_env_module
from umrl.folder_lock import lock_folder
from umrl.launch import Job, make_launcher, run_jobs
from umrl.loggers import wandb_dir_default
from umrl.metatest.cache import remove_stale_tmp, source_version, write_json_atomic
from umrl.suite.plan import plan, plan_ablation, plan_pretraining
from umrl.suite.report import report, summarize_timings

__all__ = ["code_version", "read_suite_file", "run_suite", "suite_group"]


def read_suite_file(path: Path, kind: type):
    """The JSON ``kind`` (dict or list) the suite keeps in ``path`` (its group, its timings), or None when there is
    none; a file that is not one (empty, cut, garbage) is named in a ``UserWarning`` and read as none, so a suite
    neither stops before its work nor loses its report after it."""
    if not path.exists():
        return None
    try:
        value = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        value = e
    if isinstance(value, kind):
        return value
    warnings.warn(f"{path} is not the {kind.__name__} the suite wrote ({value!r:.80}): starting it afresh",
                  stacklevel=2)
    return None


def suite_group(cfg: DictConfig) -> str:
    """The wandb group: ``logger.group`` or ``suite-<profile>-<first start>``, stable across resumes (kept in
    ``suite_state.json``, written atomically)."""
    if cfg.logger.get("group"):
        return str(cfg.logger.group)
    state = Path(cfg.output_dir) / "suite_state.json"
    saved = read_suite_file(state, dict)
    if saved is not None:
        if isinstance(saved.get("group"), str):
            return saved["group"]
        warnings.warn(f"{state} is not the dict the suite wrote (no group name in {saved!r:.80}): starting it afresh",
                      stacklevel=2)
    group = f"suite-{cfg.profile_name}-{time.strftime('%Y%m%d-%H%M%S')}"
    write_json_atomic(state, {"group": group})
    return group


def code_version(env_module: str | None = None) -> str:
    """The hash of the sources every result depends on: ``umrl/`` (the trainers' configs included) and, when the
    config names an ``env_module``, that module's source (:func:`~umrl.envs.user_envs.env_module_source`): an edit
    to a user's env recomputes what ran on it."""
    import umrl

    return source_version([Path(umrl.__file__).parent, *([env_module_source(env_module)] if env_module else [])])


def _env_module_import(cfg: DictConfig) -> Callable[[], object] | None:
    """What every job runs first when the config names an ``env_module`` (validation imported it in this process):
    its import, a ``.py`` file by its absolute path (local workers run in ``output_dir``)."""
    module = cfg.get("env_module")
    if not module:
        return None
    return functools.partial(import_env_module, "env_module", str(Path(module).resolve()) if module.endswith(".py")
                             else module)


def _raise_on_sigterm(signum, frame):  # a `kill` stops the suite like Ctrl-C: running workers are terminated
    raise KeyboardInterrupt(f"signal {signum}")


def run_suite(cfg: DictConfig, *, log: Callable[[str], None] = print) -> str:
    """Validate, plan, run (resuming), ablate and report; raises if any job failed (after reporting what finished).

    Every bad input (suite keys, recipe overrides, missing ``reuse`` runs) raises
    :class:`~umrl.configs.ConfigError` before any job starts.
    """
    cfg = validate(cfg, SuiteConfig)
    with (lock_folder(cfg.output_dir),  # a second suite (or a trainer) in this output_dir is refused, naming this one
          wandb_dir_default(cfg.output_dir)):  # every job's wandb run in <output_dir>/wandb unless WANDB_DIR is set
        return _run_suite(cfg, log)


def _run_suite(cfg: DictConfig, log: Callable[[str], None]) -> str:
    out = Path(cfg.output_dir).absolute()
    code = code_version(cfg.get("env_module"))
    group = suite_group(cfg)
    runs = plan_pretraining(cfg, group, code)
    jobs = plan(cfg, group, code, runs)
    for stale in remove_stale_tmp(out):
        log(f"[clean] removed {stale} (left by a killed write)")
    write_text_atomic(out / "config.yaml", OmegaConf.to_yaml(cfg))
    start = time.perf_counter()
    job_times: dict[str, float] = {}
    ablation: list[Job] = []
    launcher = make_launcher(cfg.launcher, out, prelude=_env_module_import(cfg))
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
    history = read_suite_file(timings_file, list) or []
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
