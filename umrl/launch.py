"""Jobs and the launchers that run them: in this process, in local worker processes, or as Ray tasks.

A :class:`Job` is ``fn(*args, **kwargs)`` with dependencies; :func:`run_jobs` runs a list of them on a launcher
(:func:`make_launcher`: :class:`InlineLauncher`, :class:`LocalLauncher` or :class:`RayLauncher`), at most
``launcher.slots`` at once, printing each start, finish and failure (with the tail of the job's log). The benchmark
suite (``benchmarks/suite.py``) schedules its pre-training runs and meta-test cells this way.
"""
from __future__ import annotations

import concurrent.futures as cf
import functools
import os
import pickle
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from umrl.process import tuned_call

__all__ = [
    "FORWARDED_ENV",
    "InlineLauncher",
    "Job",
    "JobError",
    "LocalLauncher",
    "RayLauncher",
    "failure_message",
    "forwarded_env",
    "log_tail",
    "make_launcher",
    "run_jobs",
    "with_prelude",
]

LOG_TAIL = 25
"""Lines of a failed job's log printed with its error."""

SOURCE_ROOT = Path(__file__).resolve().parents[1]
"""The tree this ``umrl`` was imported from: first on local workers' ``PYTHONPATH``, so they run
the driver's code even where another copy is installed."""


class JobError(RuntimeError):
    """A job that raised in a worker (``<ExceptionType>: <message>``; the traceback is in its log) or whose worker
    died."""


@dataclass
class Job:
    """One unit of work: ``fn(*args, **kwargs)`` run by a launcher once every job in ``deps`` has succeeded.

    ``fn`` and its arguments must pickle by reference (importable functions, e.g. ``umrl.trainers.train`` or
    ``umrl.metatest.run_cell``): workers are fresh processes or Ray tasks. ``done()`` says whether its result already
    exists (then it is skipped); ``on_success`` runs in the driver; ``what`` is a one-line description for messages;
    ``log`` the file the local launcher sends the worker's output to; ``fresh`` asks it for a worker process of the
    job's own.
    """

    key: str
    fn: Callable
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)
    deps: tuple[str, ...] = ()
    done: Callable[[], bool] = lambda: False
    on_success: Callable[[], None] = lambda: None
    what: str = ""
    log: Path | None = None
    fresh: bool = False


class InlineLauncher:
    """Runs each job in this process when submitted (``launcher.workers=0``: debugging, tests)."""

    slots = 1

    def submit(self, job: Job) -> cf.Future:
        future: cf.Future = cf.Future()
        try:
            future.set_result(job.fn(*job.args, **job.kwargs))
        except Exception as err:  # noqa: BLE001 -- handed to the scheduler exactly like a worker's failure
            future.set_exception(err)
        return future

    def shutdown(self) -> None:
        return None


_WORKER = """
import os, pickle, sys, threading, time, traceback
from umrl.process import tune_process
tune_process(num_threads=int(sys.argv[3]))
tasks, results = os.fdopen(0, "rb"), os.fdopen(int(sys.argv[1]), "wb")
driver = int(sys.argv[2])
def watch_driver():  # a driver killed with SIGKILL cannot stop its workers: they stop themselves
    while os.getppid() == driver:
        time.sleep(%(poll)s)
    os._exit(70)
threading.Thread(target=watch_driver, daemon=True).start()
while True:
    try:
        fn, args, kwargs, log = pickle.load(tasks)
    except EOFError:
        break
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    os.dup2(fd, 1); os.dup2(fd, 2); os.close(fd)
    try:
        result = (True, fn(*args, **kwargs))
    except BaseException as err:
        traceback.print_exc()
        result = (False, f"{type(err).__name__}: {err}")
    sys.stdout.flush(); sys.stderr.flush()
    pickle.dump(result, results); results.flush()
"""
"""A worker process: apply umrl's process tuning (:func:`umrl.process.tune_process`, ``threads`` torch threads),
read ``(fn, args, kwargs, log)`` pickles from stdin, run each with its output appended to
``log``, write ``(ok, result or "Type: message")`` pickles to the result pipe; exit at EOF, or (status 70) within
:data:`DRIVER_POLL_S` of its driver's death (its parent pid changes), even in the middle of a job."""

DRIVER_POLL_S = 1.0
"""How often a local worker checks that the process that started it is alive."""


class _Worker:
    """One worker process of :class:`LocalLauncher` and its two pipes."""

    def __init__(self, cwd: Path, env: Mapping[str, str], threads: int):
        read, write = os.pipe()
        self.process = subprocess.Popen([sys.executable, "-c", _WORKER % {"poll": DRIVER_POLL_S}, str(write),
                                         str(os.getpid()), str(threads)], cwd=cwd, env=dict(env),
                                        stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                        pass_fds=(write,))
        os.close(write)
        self.results = os.fdopen(read, "rb")

    def run(self, fn: Callable, job: Job, log: Path):
        try:
            pickle.dump((fn, job.args, job.kwargs, str(log)), self.process.stdin)
            self.process.stdin.flush()
            ok, value = pickle.load(self.results)
        except (EOFError, BrokenPipeError, pickle.UnpicklingError) as err:
            raise JobError(f"the worker process died (exit code {self.process.wait()}) before finishing the job: "
                           f"{type(err).__name__}") from None
        if not ok:
            raise JobError(value)
        return value

    def close(self, timeout: float = 10) -> None:
        self.process.stdin.close()
        try:
            self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.results.close()


class LocalLauncher:
    """Up to ``workers`` jobs at once in worker processes: ``python`` subprocesses with ``threads`` torch/OpenMP
    threads and working directory ``cwd``, each job's output appended to ``job.log``; ``prelude()`` runs in the
    worker before each job (:func:`with_prelude`).

    A worker runs one job after another (imports paid once); a job with ``fresh=True`` (pre-training) gets a worker
    of its own, started for it and ended after it, as a separate run would. Jobs pickle by reference, so this is
    spawn-safe. No ``multiprocessing`` objects are involved: nothing is left in ``/dev/shm`` whatever kills the
    suite, and a worker that dies fails its job only. ``shutdown`` terminates running workers.
    """

    def __init__(self, workers: int, *, threads: int = 1, cwd: str | os.PathLike = ".",
                 prelude: Callable[[], object] | None = None):
        self.slots, self.cwd, self.threads, self.prelude = workers, Path(cwd), threads, prelude
        self.env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
                    "PYTHONPATH": os.pathsep.join(filter(None, [str(SOURCE_ROOT), os.environ.get("PYTHONPATH")]))}
        self.pool = cf.ThreadPoolExecutor(max_workers=workers)
        self.idle: list[_Worker] = []
        self.busy: set[_Worker] = set()
        self.lock = threading.Lock()

    def submit(self, job: Job) -> cf.Future:
        return self.pool.submit(self._run, job)

    def _run(self, job: Job):
        with self.lock:
            worker = None if job.fresh or not self.idle else self.idle.pop()
        worker = worker or _Worker(self.cwd, self.env, self.threads)
        with self.lock:
            self.busy.add(worker)
        log = job.log or self.cwd / "logs" / "jobs.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        with log.open("a") as out:
            out.write(f"==== {time.strftime('%Y-%m-%dT%H:%M:%S')} {job.key}: {job.what}\n")
        try:
            return worker.run(with_prelude(self.prelude, job.fn), job, log)
        finally:
            with self.lock:
                self.busy.discard(worker)
                keep = not job.fresh and worker.process.poll() is None
                if keep:
                    self.idle.append(worker)
            if not keep:
                worker.close()

    def shutdown(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)
        with self.lock:
            running, idle = list(self.busy), list(self.idle)
            self.idle.clear()
        for worker in running:
            worker.process.terminate()
        for worker in idle + running:
            worker.close()
        self.pool.shutdown(wait=True)


FORWARDED_ENV = ("WANDB_DIR",)
"""Environment variables a Ray task gets from the driver as it is when the job is submitted (a local worker
inherits the driver's whole environment): the suite's one wandb folder (:func:`umrl.loggers.wandb_dir_default`)."""


class RayLauncher:
    """Ray tasks of ``cpus_per_job`` CPUs; connects to ``address`` (``local``: start one here) unless Ray is up.
    Each task's ``runtime_env`` carries the driver's :data:`FORWARDED_ENV` (Ray merges them into the job's
    ``env_vars``), whatever environment the Ray workers were started with; ``prelude()`` runs before each job
    (:func:`with_prelude`)."""

    def __init__(self, address: str, cpus_per_job: float = 1.0, prelude: Callable[[], object] | None = None):
        import ray

        if not ray.is_initialized():
            ray.init(address=None if address == "local" else address, include_dashboard=False)
        self.ray, self.cpus, self.prelude = ray, cpus_per_job, prelude
        self.slots = max(1, int(ray.cluster_resources().get("CPU", 1) // cpus_per_job))

    def submit(self, job: Job) -> cf.Future:
        threads = max(1, int(self.cpus))  # each task tunes its worker process as the local launcher's workers do
        task = self.ray.remote(num_cpus=self.cpus, runtime_env={"env_vars": forwarded_env()})(tuned_call)
        return task.remote(with_prelude(self.prelude, job.fn), threads, *job.args, **job.kwargs).future()

    def shutdown(self) -> None:  # the Ray instance belongs to whoever started it
        return None


def _after_prelude(prelude: Callable[[], object], fn: Callable, /, *args, **kwargs):
    prelude()
    return fn(*args, **kwargs)


def with_prelude(prelude: Callable[[], object] | None, fn: Callable) -> Callable:
    """``fn``, or with a ``prelude`` a function that calls ``prelude()`` and then ``fn`` with its arguments (a job
    in a fresh process first does what the driver did before it planned the job, e.g. import the module that
    registers a user's envs). Pickles by reference when both do."""
    return fn if prelude is None else functools.partial(_after_prelude, prelude, fn)


def forwarded_env() -> dict[str, str]:
    """The :data:`FORWARDED_ENV` variables set in this process, with their values."""
    return {name: os.environ[name] for name in FORWARDED_ENV if os.environ.get(name)}


def make_launcher(launcher_cfg: Mapping, output_dir: str | os.PathLike = ".",
                  prelude: Callable[[], object] | None = None):
    """``RayLauncher`` when ``ray_address`` is set, else ``LocalLauncher`` (``InlineLauncher`` for 0 workers) whose
    workers run in ``output_dir`` (so nothing a job writes by accident lands in the caller's directory). Their jobs
    run after ``prelude()`` (:func:`with_prelude`; inline jobs run in the caller, where it already ran)."""
    if launcher_cfg.get("ray_address"):
        return RayLauncher(str(launcher_cfg["ray_address"]), float(launcher_cfg.get("threads", 1)), prelude)
    workers = int(launcher_cfg.get("workers", 2))
    if workers == 0:
        return InlineLauncher()
    Path(output_dir).mkdir(parents=True, exist_ok=True)
    return LocalLauncher(workers, threads=int(launcher_cfg.get("threads", 1)), cwd=output_dir, prelude=prelude)


def log_tail(path: Path | None, lines: int = LOG_TAIL) -> str:
    """The last ``lines`` lines of ``path`` ("" if there is no such file)."""
    if path is None or not path.is_file():
        return ""
    with path.open("rb") as f:
        f.seek(max(0, f.seek(0, os.SEEK_END) - 64 * 1024))
        text = f.read().decode(errors="replace")
    return "\n".join(text.splitlines()[-lines:])


def failure_message(job: Job, err: BaseException) -> str:
    """What a failed job prints: its description, the error and the tail of its log."""
    lines = [f"[fail] {job.key}" + (f" ({job.what})" if job.what else ""), f"  error: {type(err).__name__}: {err}"]
    tail = log_tail(job.log)
    if tail:
        lines += [f"  last lines of {job.log}:", *(f"    | {line}" for line in tail.splitlines())]
    return "\n".join(lines)


def run_jobs(jobs: Sequence[Job], launcher, *, log: Callable[[str], None] = print,
             timings: dict[str, float] | None = None) -> tuple[set[str], dict[str, str]]:
    """Run ``jobs`` respecting dependencies; returns (succeeded keys, {failed or blocked key: reason}).

    Jobs whose ``done()`` is true are not run. At most ``launcher.slots`` jobs run at once, so the wall time of each
    successful job (written into ``timings``) excludes queueing. A failure is printed through ``log`` with the job's
    error and log tail; it does not stop independent jobs; its dependants are blocked.
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
                log(f"[blocked] {key}: {failed[key]}")
                del pending[key]
            elif all(d in succeeded for d in job.deps) and len(running) < launcher.slots:
                log(f"[start] {key}")
                started[key] = time.perf_counter()
                running[launcher.submit(job)] = job
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
            except Exception as err:  # noqa: BLE001 -- printed; run_suite raises once independent jobs ran
                failed[job.key] = f"{type(err).__name__}: {err}".splitlines()[0][:300]
                log(failure_message(job, err))
            else:
                succeeded.add(job.key)
                timings[job.key] = seconds
                log(f"[done] {job.key} ({seconds:.0f} s)")
    return succeeded, failed
