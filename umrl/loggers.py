"""Loggers for runs: TorchRL's (:func:`torchrl.record.loggers.get_logger`), where their files go, and what is logged.

``wandb`` in offline mode by default (the runs of one output tree land in one ``wandb/`` folder, :func:`wandb_dir`;
publish them later with ``wandb sync``), ``csv`` as a dependency-free alternative, ``none`` for tests. Scalars,
images and tables go through :func:`log_metrics`, :func:`log_image` and :func:`log_table`, which do nothing for a
``None`` logger.
"""
from __future__ import annotations

import math
import os
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from torchrl.record.loggers import Logger, get_logger

from umrl.atomic_write import write_text_atomic
from umrl.plain_config import to_container
from umrl.validation import check_choice, check_name, check_writable_dir

LOGGER_BACKENDS = ("wandb", "csv", "none")


def output_tree_root(log_dir: str | os.PathLike) -> Path:
    """The root of the output tree ``log_dir`` lies in: its first folder when it is relative (``outputs`` for every
    recipe's default ``output_dir``; leading ``..`` kept), ``log_dir`` itself when it is absolute.

    >>> [str(output_tree_root(d)) for d in ("outputs/maml/point_nav/oracle/seed0", "../runs/a", "/data/sweep", ".")]
    ['outputs', '../runs', '/data/sweep', '.']
    """
    path = Path(os.path.normpath(log_dir))
    if path.is_absolute() or not path.parts:
        return path
    ups = sum(part == ".." for part in path.parts)  # normpath leaves ".." only in front
    return Path(*path.parts[:ups + 1])


def wandb_dir(log_dir: str | os.PathLike = ".") -> Path:
    """The folder whose ``wandb/`` receives the wandb runs of a job writing to ``log_dir``: ``$WANDB_DIR`` when set,
    else :func:`output_tree_root`. One folder per tree, so ``wandb sync <folder>/wandb`` (or ``wandb sync`` run in
    ``<folder>``) finds every run. A ``$WANDB_DIR`` this process cannot write into (or create) is refused: wandb
    would write to the system's temporary folder instead."""
    if os.environ.get("WANDB_DIR"):
        return Path(check_writable_dir("WANDB_DIR", os.environ["WANDB_DIR"]))
    return output_tree_root(log_dir)


def check_logger_backend(name: str, value: Any) -> str:
    """``value`` if it is one of :data:`LOGGER_BACKENDS`; for ``wandb`` also :func:`wandb_dir`'s check of a
    ``$WANDB_DIR`` that is set (the configs run it, so such a run is refused before it writes anything)."""
    check_choice(name, value, LOGGER_BACKENDS)
    if value == "wandb":
        wandb_dir()
    return value


@contextmanager
def wandb_dir_default(root: str | os.PathLike) -> Iterator[None]:
    """Inside the block, runs of this process and of the processes it starts write to ``root/wandb``: sets the
    ``WANDB_DIR`` environment variable to ``root`` (absolute) and removes it on exit. A ``WANDB_DIR`` the user set
    is left as it is. The suite wraps its jobs and reports in it, so ``wandb sync <suite output_dir>/wandb`` finds
    every run of the suite."""
    if os.environ.get("WANDB_DIR"):
        yield
        return
    os.environ["WANDB_DIR"] = str(Path(root).absolute())
    try:
        yield
    finally:
        os.environ.pop("WANDB_DIR", None)


def make_logger(logger_cfg: Mapping, *, exp_name: str, job_type: str | None = None, config: Any = None,
                log_dir: str | os.PathLike = ".", resume_step: int | None = None) -> Logger | None:
    """Build the TorchRL logger named by ``logger_cfg["backend"]`` and log ``config`` as hyperparameters.

    ``logger_cfg`` keys: ``backend`` (``wandb`` | ``csv`` | ``none``), optional ``project``, ``group``, ``mode``
    (wandb: ``offline`` by default, ``online`` to stream, ``disabled``; the ``WANDB_MODE`` environment variable wins).
    ``job_type`` names what the run is (the recipes pass their name: ``diayn``, ``maml``, ``vime``; the suite's
    report runs ``meta_test`` and ``report``); with ``group`` it is what wandb groups runs by.
    CSV logs go to ``<log_dir>/csv/<exp_name>/``; with ``resume_step`` (a run continuing from its checkpoint at that
    step) the rows a killed run logged past it are dropped first (:func:`drop_csv_rows_after`), so the files hold
    what an uninterrupted run logs. wandb runs to ``<wandb_dir(log_dir)>/wandb`` (:func:`wandb_dir`:
    ``$WANDB_DIR`` if set, else the root of the output tree; recipes pass their ``output_dir``: nothing lands in the
    current directory).

    Every call starts a new wandb run, also while another one is open in this process (Hydra multirun, a Ray
    worker running several jobs); :func:`close_logger` ends it.
    """
    check_name("logger.exp_name", exp_name)  # a folder under <log_dir>/csv, never a path out of it
    backend = logger_cfg.get("backend", "wandb")
    if backend not in LOGGER_BACKENDS:
        raise ValueError(f"unknown logger backend {backend!r}; valid choices: {list(LOGGER_BACKENDS)}.")
    if backend == "none":
        return None
    if backend == "csv":
        if resume_step is not None:
            drop_csv_rows_after(Path(log_dir) / "csv" / exp_name, resume_step)
        logger = get_logger("csv", logger_name=str(Path(log_dir) / "csv"), experiment_name=exp_name)
    else:
        mode = os.environ.get("WANDB_MODE", logger_cfg.get("mode", "offline"))
        Path(log_dir).mkdir(parents=True, exist_ok=True)
        # the mode goes to wandb.init only: TorchRL's own offline=True also sets WANDB_MODE for the whole process
        logger = get_logger(
            "wandb",
            # absolute: wandb's service process, shared by the runs of this process, has its own working directory
            logger_name=str(wandb_dir(log_dir).absolute()),
            experiment_name=exp_name,
            wandb_kwargs={
                "project": logger_cfg.get("project", "umrl"),
                "group": logger_cfg.get("group"),
                "job_type": job_type,
                "mode": mode,
                "reinit": "create_new",  # wandb's default hands back the open run: two jobs would share it
            },
        )
    if config is not None:
        logger.log_hparams(to_container(config))
    return logger


def drop_csv_rows_after(csv_dir: str | os.PathLike, step: int) -> int:
    """Remove the rows logged past ``step`` from the scalar CSV files under ``csv_dir`` (TorchRL's ``CSVLogger``:
    ``scalars/<name>.csv``, one ``step,value`` line per row); returns how many were removed. A last line without
    its newline (a write cut by the kill) goes too. A file is rewritten atomically, and only when it loses a row.

    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> (folder / "scalars").mkdir()
    >>> _ = (folder / "scalars" / "loss.csv").write_text("1,0.5\\n2,0.4\\n3,0.3\\n")
    >>> drop_csv_rows_after(folder, 2), (folder / "scalars" / "loss.csv").read_text()
    (1, '1,0.5\\n2,0.4\\n')
    """
    removed = 0
    for file in sorted((Path(csv_dir) / "scalars").rglob("*.csv")):
        lines = file.read_text().splitlines(keepends=True)
        kept = [line for line in lines if line.endswith("\n") and int(float(line.split(",", 1)[0])) <= step]
        if len(kept) < len(lines):
            write_text_atomic(file, "".join(kept))
            removed += len(lines) - len(kept)
    return removed


def close_logger(logger: Logger | None) -> None:
    """End ``logger``'s wandb run; nothing to do for CSV or ``None``.

    wandb-core finishes writing the run's files shortly after this returns, and at the latest when the process
    exits; read an offline run's ``.wandb`` file only once it holds its exit record."""
    experiment = getattr(logger, "experiment", None)
    if experiment is not None and hasattr(experiment, "finish"):
        experiment.finish()


def log_location(logger_cfg: Mapping, log_dir: str | os.PathLike = ".") -> str:
    """Where :func:`make_logger` with these arguments writes, in words (for the end-of-run summary)."""
    backend = logger_cfg.get("backend", "wandb")
    if backend == "none":
        return "not logged (logger.backend=none)"
    if backend == "csv":
        return f"{Path(log_dir) / 'csv'} (CSV)"
    mode = os.environ.get("WANDB_MODE", logger_cfg.get("mode", "offline"))
    return f"{wandb_dir(log_dir) / 'wandb'} (wandb, {mode})"


def run_summary(title: str, result: Mapping[str, Any], keys: Sequence[str], logs: str) -> str:
    """A few lines for the end of a run: ``title``, the ``keys`` of ``result`` it has (4 significant digits), its
    ``"checkpoint"`` and where every metric was logged (``logs``, e.g. :func:`log_location`'s).

    >>> print(run_summary("maml finished", {"iteration": 5, "train/kl": 0.00612, "checkpoint": "out/step_5.pt"},
    ...                   ["iteration", "train/kl", "train/absent"], "out/wandb (wandb, offline)"))
    maml finished: iteration 5 | train/kl 0.00612
    checkpoint: out/step_5.pt
    every metric: out/wandb (wandb, offline)
    """
    values = [f"{k} {result[k]:.4g}" if isinstance(result[k], float) else f"{k} {result[k]}" for k in keys if k in result]
    lines = [f"{title}: {' | '.join(values)}"]
    if result.get("checkpoint"):
        lines.append(f"checkpoint: {result['checkpoint']}")
    return "\n".join([*lines, f"every metric: {logs}"])


def log_metrics(logger: Logger | None, metrics: Mapping[str, float], step: int) -> None:
    """Log scalar ``metrics`` at ``step``; non-finite values are logged too (they are what needs seeing)."""
    if logger is None:
        return
    for name, value in metrics.items():
        value = float(value)
        logger.log_scalar(name, value if math.isfinite(value) else float("nan"), step=step)


def _wandb_run(logger: Logger | None) -> Any:
    """``logger``'s wandb run, or ``None`` for other backends."""
    experiment = getattr(logger, "experiment", None)
    return experiment if experiment is not None and hasattr(experiment, "log") else None


def log_image(logger: Logger | None, name: str, path: str | os.PathLike, step: int) -> None:
    """Log a PNG file to wandb (other backends keep the file on disk only). The run gets its own copy of the pixels
    (wandb would otherwise link to ``path`` when media symlinks are allowed): ``path`` may be a temporary file."""
    run = _wandb_run(logger)
    if run is None:
        return
    import wandb
    from PIL import Image

    with Image.open(path) as image:
        run.log({name: wandb.Image(image.copy()), "step": step})


def log_table(logger: Logger | None, name: str, columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """Log a table to wandb: ``columns`` names, ``rows`` one list of values each (other backends: nothing; the
    callers keep the same numbers in files)."""
    run = _wandb_run(logger)
    if run is None:
        return
    import wandb

    run.log({name: wandb.Table(columns=list(columns), data=[list(row) for row in rows])})
