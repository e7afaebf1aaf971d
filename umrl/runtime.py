"""What every recipe needs around its training loop: seeding, loggers, checkpoints.

Loggers are TorchRL's (:func:`torchrl.record.loggers.get_logger`): ``wandb`` in offline mode by default (the runs of
one output tree land in one ``wandb/`` folder, :func:`wandb_dir`; publish them later with ``wandb sync``), ``csv`` as a
dependency-free alternative, ``none`` for tests. Checkpoints are :mod:`umrl.checkpoint_file` files (data only, hash-checked)
written atomically, with the resolved config beside them (their formats, saving and checked loading live in
:mod:`umrl.checkpoints`); :func:`rng_state` / :func:`set_rng_state` and :func:`env_state` / :func:`load_env_state` capture what a faithful resume restores.
"""
from __future__ import annotations

import math
import os
import random
import re
import stat
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.data import ReplayBuffer
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.record.loggers import Logger, get_logger

from umrl.checkpoint_file import CheckpointError, file_kind, read_state, write_state
from umrl.validation import InvalidType, check_name

LOGGER_BACKENDS = ("wandb", "csv", "none")

_open_loggers: ContextVar[list[Logger] | None] = ContextVar("umrl_open_loggers", default=None)
"""The loggers :func:`make_logger` made inside the innermost :func:`finishing_loggers` block."""


def seed_everything(seed: int) -> torch.Generator:
    """Seed Python, NumPy and torch; return a torch generator seeded with ``seed`` for explicit sampling."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)


def rng_state(**generators: torch.Generator) -> dict:
    """Every random generator a run draws from: ``{"torch", "cuda" (when available), "numpy", "python",
    "generators": {name: state}}`` for the explicit ``generators`` (restore with :func:`set_rng_state`)."""
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate(),
             "generators": {name: g.get_state() for name, g in generators.items()}}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: Mapping[str, Any], **generators: torch.Generator) -> None:
    """Restore what :func:`rng_state` captured, including the states of the named ``generators``."""
    missing = sorted(set(generators) - set(state["generators"]))
    if missing:
        raise KeyError(f"the saved RNG state has no generator {missing}; it holds {sorted(state['generators'])}.")
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
    for name, generator in generators.items():
        generator.set_state(state["generators"][name])


@contextmanager
def isolated_rng() -> Iterator[None]:
    """Run a block (evaluation, figures) without moving the torch/CUDA global generators the training draws from."""
    with torch.random.fork_rng(devices=range(torch.cuda.device_count()) if torch.cuda.is_available() else []):
        yield


def env_state(env: EnvBase) -> dict:
    """The random state of ``env`` (e.g. MuJoCo reset noise) and of its transforms, for :func:`load_env_state`.

    TorchRL's ``TransformedEnv.state_dict()`` leaves the base env out, so both are taken here."""
    if isinstance(env, TransformedEnv):
        return {"base_env": env_state(env.base_env), "transform": env.transform.state_dict()}
    return {"env": env.state_dict()}


def load_env_state(env: EnvBase, state: Mapping[str, Any]) -> None:
    """Restore what :func:`env_state` took from an env built the same way."""
    if isinstance(env, TransformedEnv):
        load_env_state(env.base_env, state["base_env"])
        env.transform.load_state_dict(state["transform"])
    else:
        env.load_state_dict(state["env"])


def replay_buffer_state(buffer: ReplayBuffer) -> dict:
    """TorchRL's ``buffer.state_dict()`` with the storage cut to its filled rows.

    A ``LazyTensorStorage`` allocates all ``max_size`` rows on its first write and its ``state_dict`` holds them all
    (a 10⁶-row DIAYN buffer was ~250 MB per checkpoint after 1,000 transitions); rows are written from 0 up until
    the buffer wraps, so the first ``len(buffer)`` rows are the whole content."""
    state = buffer.state_dict()
    filled = len(buffer.storage)  # a clone: a slice view would pickle the whole allocation
    state["_storage"] = {"rows": buffer.storage[:filled].clone() if filled else None}
    return state


def load_replay_buffer_state(buffer: ReplayBuffer, state: Mapping[str, Any]) -> None:
    """Restore what :func:`replay_buffer_state` took into a buffer built the same way (same storage size)."""
    rows = state["_storage"]["rows"]
    if rows is not None:
        buffer.storage.set(torch.arange(len(rows), device=rows.device), rows)
    buffer.load_state_dict({**state, "_storage": buffer.storage.state_dict()})


def to_container(config: Any) -> dict:
    """A plain, resolved ``dict`` from a Hydra/OmegaConf config (or a mapping)."""
    if isinstance(config, DictConfig):
        return OmegaConf.to_container(config, resolve=True)
    return dict(config)


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
    ``<folder>``) finds every run."""
    return Path(os.environ["WANDB_DIR"]) if os.environ.get("WANDB_DIR") else output_tree_root(log_dir)


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
                log_dir: str | os.PathLike = ".") -> Logger | None:
    """Build the TorchRL logger named by ``logger_cfg["backend"]`` and log ``config`` as hyperparameters.

    ``logger_cfg`` keys: ``backend`` (``wandb`` | ``csv`` | ``none``), optional ``project``, ``group``, ``mode``
    (wandb: ``offline`` by default, ``online`` to stream, ``disabled``; the ``WANDB_MODE`` environment variable wins).
    ``job_type`` names what the run is (the recipes pass their name: ``diayn``, ``maml``, ``vime``; the suite's
    report runs ``meta_test`` and ``report``); with ``group`` it is what wandb groups runs by.
    CSV logs go to ``<log_dir>/csv/<exp_name>/``; wandb runs to ``<wandb_dir(log_dir)>/wandb`` (:func:`wandb_dir`:
    ``$WANDB_DIR`` if set, else the root of the output tree; recipes pass their ``output_dir``: nothing lands in the
    current directory).

    Every call starts a new wandb run, also while another one is open in this process (Hydra multirun, a Ray
    worker running several jobs); :func:`close_logger` ends it, and inside a :func:`finishing_loggers` block that
    happens when the block exits.
    """
    check_name("logger.exp_name", exp_name)  # a folder under <log_dir>/csv, never a path out of it
    backend = logger_cfg.get("backend", "wandb")
    if backend not in LOGGER_BACKENDS:
        raise ValueError(f"unknown logger backend {backend!r}; valid choices: {list(LOGGER_BACKENDS)}.")
    if backend == "none":
        return None
    if backend == "csv":
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
    opened = _open_loggers.get()
    if opened is not None:
        opened.append(logger)
    if config is not None:
        logger.log_hparams(to_container(config))
    return logger


def close_logger(logger: Logger | None) -> None:
    """End ``logger``'s wandb run; nothing to do for CSV or ``None``.

    wandb-core finishes writing the run's files shortly after this returns, and at the latest when the process
    exits; read an offline run's ``.wandb`` file only once it holds its exit record."""
    experiment = getattr(logger, "experiment", None)
    if experiment is not None and hasattr(experiment, "finish"):
        experiment.finish()


@contextmanager
def finishing_loggers() -> Iterator[None]:
    """Close every logger :func:`make_logger` makes inside the block when it exits, by an error too: one wandb run
    per job however jobs are launched. Also a decorator: the recipes' ``train`` functions are wrapped in it."""
    opened: list[Logger] = []
    token = _open_loggers.set(opened)
    try:
        yield
    finally:
        _open_loggers.reset(token)
        for logger in opened:
            close_logger(logger)


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
    """Log a PNG file to wandb (other backends keep the file on disk only)."""
    run = _wandb_run(logger)
    if run is None:
        return
    import wandb

    run.log({name: wandb.Image(str(path)), "step": step})


def log_table(logger: Logger | None, name: str, columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """Log a table to wandb: ``columns`` names, ``rows`` one list of values each (other backends: nothing; the
    callers keep the same numbers in files)."""
    run = _wandb_run(logger)
    if run is None:
        return
    import wandb

    run.log({name: wandb.Table(columns=list(columns), data=[list(row) for row in rows])})


def log_band(logger: Logger | None, name: str, x: Sequence[float], lines: Mapping[str, Sequence[float]], *,
             xname: str, title: str) -> None:
    """Log a curve with its interval to wandb as one table ``name`` (column ``xname`` then one column per entry of
    ``lines``, e.g. ``iqm``, ``iqm_low``, ``iqm_high``) and a line plot ``<name>_plot`` of those lines
    (``wandb.plot.line_series``, which works offline); other backends: nothing."""
    run = _wandb_run(logger)
    if run is None:
        return
    import wandb

    columns = [xname, *lines]
    rows = [[x_value, *(float(line[i]) for line in lines.values())] for i, x_value in enumerate(x)]
    plot = wandb.plot.line_series(xs=list(x), ys=[[float(v) for v in line] for line in lines.values()],
                                  keys=list(lines), title=title, xname=xname)
    run.log({name: wandb.Table(columns=columns, data=rows), f"{name}_plot": plot})


def save_figure(fig: Any, path: str | os.PathLike, *, dpi: int = 120) -> Path:
    """Lay out ``fig``, a :class:`matplotlib.figure.Figure` made without pyplot (nothing to close, no backend
    selected), and write it to ``path`` (PNG; parent folders created)."""
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path


def check_finite(losses: Mapping[str, torch.Tensor], where: str) -> None:
    """Fail fast with the names of the non-finite entries of ``losses``."""
    bad = [k for k, v in losses.items() if torch.is_tensor(v) and not torch.isfinite(v).all()]
    if bad:
        raise FloatingPointError(
            f"non-finite {bad} in {where}: lower the learning rate or check the inputs; the last checkpoint is intact."
        )


def read_checkpoint(path: str | os.PathLike) -> Any:
    """The state saved at ``path`` (:mod:`umrl.checkpoint_file`: tensors as data, hash checked; nothing is
    unpickled), tensors on the CPU; a truncated, corrupted, empty, foreign, special or malformed file raises
    :class:`CheckpointError` naming it, a torch.save pickle of older umrl versions its subclass
    :class:`~umrl.checkpoint_file.LegacyCheckpointError` (``python -m umrl.checkpoints.convert`` a trusted one)."""
    return read_state(path)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and ``os.replace`` (a kill never leaves half a file)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


class Checkpointer:
    """Saves ``state`` dicts as ``<directory>/step_<N>.pt`` with the resolved config in ``<directory>/config.yaml``.

    Every file is written atomically (a ``.tmp`` then ``os.replace``). The temporary files a killed save left behind
    (``step_<N>.pt.tmp``, ``config.yaml.tmp`` and safetensors' own hidden ``.tmp<6 letters or digits>``) are removed
    by the writer: by :meth:`remove_stale_tmp`, which the trainers call once they hold their folder's lock
    (:mod:`umrl.folder_lock`), else at its first :meth:`save` or :meth:`load_latest_valid` (a resume). Read-only
    lookups (:meth:`latest`, :func:`resolve_checkpoint`, loaders) never touch them: another run may be writing there.

    A checkpoint is exactly what :meth:`save` writes: an entry whose whole name is ``step_<N>.pt`` and which is a
    regular file, not a symlink (checked with ``os.lstat``, without opening it). Anything else in the folder
    (``best_step_3.pt``, a FIFO, a folder or a symlink named ``step_3.pt``) is never listed, read or deleted.

    Args:
        directory: where checkpoints go (created on first save).
        keep_all: keep every checkpoint (meta-training ablations evaluate them all); otherwise only the newest.
    """

    _pattern = re.compile(r"step_([0-9]+)\.pt")
    _tmp_pattern = re.compile(r"step_[0-9]+\.pt\.tmp|config\.yaml\.tmp|\.tmp[A-Za-z0-9]{6}")
    """What a killed :meth:`save` leaves: its own ``.tmp`` files, and the hidden file safetensors writes first (the
    ``tempfile`` crate's ``.tmp`` + 6 random letters or digits, renamed to the ``.pt.tmp`` once complete)."""

    def __init__(self, directory: str | os.PathLike, keep_all: bool = False):
        self.directory = Path(directory)
        self.keep_all = keep_all
        self._stale_removed = False

    def remove_stale_tmp(self) -> None:
        """Once per writer: delete the temporary files a killed save left in :attr:`directory` (regular files named
        as :meth:`save` and safetensors name them, :attr:`_tmp_pattern`; other ``*.tmp`` entries are not umrl's and
        stay)."""
        if not self._stale_removed and self.directory.is_dir():
            for stale in self.directory.iterdir():
                if self._tmp_pattern.fullmatch(stale.name) and _is_regular_file(stale):
                    stale.unlink()
        self._stale_removed = True

    def all(self) -> list[Path]:
        """Every checkpoint on disk, oldest step first: regular files (not symlinks) named exactly ``step_<N>.pt``."""
        if not self.directory.is_dir():
            return []
        found = [(int(m.group(1)), p) for p in self.directory.iterdir()
                 if (m := self._pattern.fullmatch(p.name)) and _is_regular_file(p)]
        return [p for _, p in sorted(found)]

    def latest(self) -> Path | None:
        """The checkpoint with the largest step, or ``None``."""
        found = self.all()
        return found[-1] if found else None

    def save(self, state: Mapping[str, Any], step: int, config: Any = None) -> Path:
        """Write ``state`` for ``step`` atomically (a killed save never leaves a broken newest file)."""
        self.remove_stale_tmp()
        self.directory.mkdir(parents=True, exist_ok=True)
        path = self.directory / f"step_{step}.pt"
        tmp = path.with_suffix(".pt.tmp")
        write_state(state, tmp)
        os.replace(tmp, path)
        if config is not None:
            write_text_atomic(self.directory / "config.yaml", OmegaConf.to_yaml(OmegaConf.create(to_container(config))))
        if not self.keep_all:
            for old in self.all():
                if old != path:
                    old.unlink()
        return path

    def load(self, path: str | os.PathLike | None = None) -> dict:
        """Load ``path`` (default: the latest checkpoint); an unreadable file raises :class:`CheckpointError`."""
        target = Path(path) if path is not None else self.latest()
        if target is None or not target.is_file():
            where = target if target is not None else self.directory
            raise FileNotFoundError(
                f"no checkpoint at {where}: run the recipe once without resume=true, or point to an existing .pt file."
            )
        return read_checkpoint(target)

    def load_latest_valid(self, check: Callable[[Any, Path], Any] | None = None) -> tuple[Path, Any]:
        """``(path, state)`` of the newest readable checkpoint, for ``resume=true``: an unreadable newer file is
        skipped with a warning naming it and, once a readable one is found, renamed ``<name>.unreadable`` (else it
        would stay the latest, the one loaders and the suite read); ``FileNotFoundError`` if there is none,
        :class:`CheckpointError` if none can be read (nothing is renamed then). ``check(state, path)`` (a format's
        :meth:`~umrl.checkpoints.CheckpointFormat.check`) returns the state or raises :class:`CheckpointError` for
        content that cannot be the run's (non-finite weights, sizes the tensors do not have): that file is skipped
        too."""
        self.remove_stale_tmp()
        found = self.all()
        if not found:
            return self.load()  # raises FileNotFoundError saying where it looked
        errors = []
        for path in reversed(found):
            try:
                state = read_checkpoint(path)
                if check is not None:
                    state = check(state, path)
            except CheckpointError as e:
                errors.append(str(e))
                warnings.warn(f"skipping unreadable checkpoint {path}; trying the previous one. ({e})", stacklevel=2)
                continue
            for skipped in found[found.index(path) + 1:]:
                skipped.rename(skipped.with_name(skipped.name + ".unreadable"))
                warnings.warn(f"moved the unreadable checkpoint {skipped} aside to {skipped.name}.unreadable; "
                              f"resuming from {path}.", stacklevel=2)
            return path, state
        raise CheckpointError("no readable checkpoint in " f"{self.directory}:\n" + "\n".join(errors))


def _is_regular_file(path: Path) -> bool:
    """Whether ``path`` itself is a regular file (a symlink is not), judged by ``os.lstat``: nothing is opened."""
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:  # gone meanwhile, or unreadable metadata
        return False


def checkpoint_path(path: Any) -> Path:
    """``path`` as a :class:`~pathlib.Path`; :class:`~umrl.validation.InvalidType` naming it when it is no path."""
    if not isinstance(path, (str, os.PathLike)):
        raise InvalidType("path", path, "a checkpoint file or run directory (a str or os.PathLike)")
    return Path(path)


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """``path`` if it is a checkpoint file, else the latest ``step_*.pt`` inside the directory ``path`` (or its
    ``checkpoints/`` subfolder). Raises ``FileNotFoundError`` saying what was looked for, and
    :class:`CheckpointError`, before opening anything, for a ``path`` that is neither a regular file (a symlink to
    one is followed) nor a folder, or is a folder named like a checkpoint.

    >>> resolve_checkpoint("/dev/null")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    umrl.checkpoint_file.CheckpointError: /dev/null is not a regular checkpoint file (a character device); ...
    """
    path = checkpoint_path(path)
    try:
        mode = os.stat(path).st_mode  # follows a symlink the user named, opens nothing
    except FileNotFoundError:
        mode = None
    except (OSError, ValueError) as e:  # a name too long, a loop of symlinks, a NUL byte: no file can be there
        raise CheckpointError(f"cannot read checkpoint {str(path)!r} (not opened): "
                              f"{e.strerror if isinstance(e, OSError) else e}.") from e
    if mode is not None and stat.S_ISREG(mode):
        return path
    if mode is not None and (not stat.S_ISDIR(mode) or Checkpointer._pattern.fullmatch(path.name)):
        raise CheckpointError(f"{path} is not a regular checkpoint file ({file_kind(mode)}); "
                              "give a step_<N>.pt file or a run folder.")
    for directory in (path, path / "checkpoints"):
        latest = Checkpointer(directory).latest()
        if latest is not None:
            return latest
    raise FileNotFoundError(f"no checkpoint file at {path} (looked for step_*.pt in it and in {path / 'checkpoints'}).")
