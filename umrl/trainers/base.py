"""The trainers' shared skeleton: :class:`Trainer`, one ``train()`` loop with named hook points.

A trainer is built from its config without side effects beyond claiming its ``output_dir`` (modules, envs, the
state of a resumed run). :meth:`Trainer.setup` does the I/O, once: the initial evaluation and checkpoint where
the trainer has them, the logger (``cfg.logger``), then the ``"setup"`` hooks. :meth:`~Trainer.train` and the
first :meth:`~Trainer.step`, :meth:`~Trainer.evaluate` or :meth:`~Trainer.log` call it.

:meth:`~Trainer.train` steps until the budget is spent (``done``): after each :meth:`~Trainer.step` it
evaluates when the trainer's schedule says so, logs the metrics, and saves every ``cfg.checkpoint.every`` and
at the end; then it runs the final :meth:`~Trainer.evaluate` and returns the last metrics with the
``"checkpoint"`` path. A SIGTERM or SIGINT (:mod:`umrl.signals`) finishes the step in progress, saves it and
raises :class:`~umrl.signals.TrainingStopped`; :meth:`~Trainer.request_stop` (from a hook) does the same,
without the exception.

Hook points (:meth:`Trainer.register_op`, after TorchRL's ``Trainer.register_op``): each op is called with the
trainer first, in the order registered; its return value is ignored.

================= ========================== ==============================================================
point             called as                  when
================= ========================== ==============================================================
``setup``         ``op(trainer)``            once, at the end of :meth:`~Trainer.setup` (the logger is open)
``pre_step``      ``op(trainer)``            before each step
``post_step``     ``op(trainer, metrics)``   after each step, with its metrics (``{}`` for a step with none
                                             to log, e.g. DIAYN's between ``log_every`` frames)
``pre_phase``     ``op(trainer, name)``      before a named part of a step (the trainer's ``PHASES``)
``post_phase``    ``op(trainer, name)``      after it, also when it raised
``post_log``      ``op(trainer, metrics)``   after ``metrics`` went to the logger at ``trainer.progress``
``post_evaluate`` ``op(trainer, metrics)``   after each evaluation, with its metrics
``post_save``     ``op(trainer, path)``      after each checkpoint, with its path
``shutdown``      ``op(trainer)``            in :meth:`~Trainer.close`, before the envs and the logger close
================= ========================== ==============================================================

``docs/design.md`` ("Hooks") shows logging to another backend, an early stop and the time of each part of a
step.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, ClassVar

import tqdm
from omegaconf import DictConfig

from umrl.loggers import close_logger, log_metrics, make_logger
from umrl.signals import stop_requests

__all__ = ["HOOK_POINTS", "Trainer"]

HOOK_POINTS = ("setup", "pre_step", "post_step", "pre_phase", "post_phase", "post_log", "post_evaluate",
               "post_save", "shutdown")
"""The names :meth:`Trainer.register_op` accepts (the module docstring says when each runs)."""


class Trainer:
    """The skeleton of :class:`~umrl.trainers.DIAYNTrainer`, :class:`~umrl.trainers.MAMLTrainer` and
    :class:`~umrl.trainers.VIMETrainer`: the loop, the hook points, setup, logging, saving and closing.

    A subclass calls ``super().__init__()`` first, then sets ``cfg`` (validated), ``output_dir``,
    ``checkpointer`` and ``folder_lock``, and defines :attr:`progress`, :attr:`budget`, ``state_dict`` /
    ``load_state_dict``, ``_step`` (one step's work and metrics), ``_save`` (writes a checkpoint, returns its
    path) and ``_envs`` (what :meth:`close` closes); optionally ``_setup`` (the I/O before the logger opens;
    returns metrics to log once), ``_evaluate`` / ``_evaluation_due``, ``_checkpoint_due``, ``_result``,
    ``_postfix`` and ``_description``.

    Class attributes: ``name`` (the logger's job type: ``diayn``, ``maml``, ``vime``), ``PHASES`` (the parts
    of a step that run the ``pre_phase`` / ``post_phase`` hooks), ``stop_message`` (where a stopped run
    stopped, formatted with ``progress`` and ``budget``), ``progress_unit`` (the progress bar's).
    """

    name: ClassVar[str]
    PHASES: ClassVar[tuple[str, ...]] = ()
    stop_message: ClassVar[str] = "after {progress} of {budget}"
    progress_unit: ClassVar[str] = "it"

    cfg: DictConfig
    output_dir: Path

    def __init__(self) -> None:
        self._ops: dict[str, list[Callable[..., Any]]] = {point: [] for point in HOOK_POINTS}
        self.is_set_up = False
        self.logger = None
        self.start_time: float | None = None
        self.stop_reason: str | None = None

    # --- what a subclass defines -------------------------------------------------------------------------
    @property
    def progress(self) -> int:
        """How far the run is, in its budget's unit (env frames per seed for DIAYN, iterations for MAML and
        VIME): the step the metrics are logged at and the number a checkpoint is named after."""
        raise NotImplementedError

    @property
    def budget(self) -> int:
        """Where :attr:`progress` ends the run."""
        raise NotImplementedError

    def _step(self) -> dict[str, float]:
        raise NotImplementedError

    def _save(self) -> Path:
        raise NotImplementedError

    def _envs(self) -> list:
        raise NotImplementedError

    def _setup(self) -> dict[str, float]:
        return {}

    def restore(self, path: Path, state: dict) -> None:
        """``load_state_dict(state)`` of the checkpoint read from ``path``; a state that does not fit this run is
        refused with a ``ValueError`` naming the file."""
        try:
            self.load_state_dict(state)
        except (ValueError, KeyError, RuntimeError) as e:
            raise ValueError(f"cannot resume from {path}: {e}") from e

    def _evaluate(self, final: bool) -> dict[str, float]:
        return {}

    def _evaluation_due(self) -> bool:
        return False

    def _checkpoint_due(self, before: int) -> bool:
        """Whether the step that moved :attr:`progress` from ``before`` crossed a multiple of
        ``cfg.checkpoint.every``."""
        every = self.cfg.checkpoint.every
        return before // every < self.progress // every

    def _result(self) -> dict:
        """What :meth:`train` returns beside the metrics and the checkpoint path."""
        return {}

    def _postfix(self, metrics: dict[str, float]) -> dict[str, str]:
        """The progress bar's summary of a step's ``metrics``."""
        return {}

    # --- hooks -------------------------------------------------------------------------------------------
    def register_op(self, dest: str, op: Callable[..., Any]) -> None:
        """Call ``op`` at hook point ``dest`` (one of :data:`HOOK_POINTS`; the module docstring gives each
        one's arguments)."""
        if dest not in self._ops:
            raise ValueError(f"register_op: unknown hook point {dest!r}; accepted: {list(HOOK_POINTS)}")
        if not callable(op):
            raise TypeError(f"register_op({dest!r}, ...): got {op!r}; expected a callable")
        self._ops[dest].append(op)

    def _run_ops(self, point: str, *args: Any) -> None:
        for op in self._ops[point]:
            op(self, *args)

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        """The block of a step's part ``name``: the ``pre_phase`` ops before it, the ``post_phase`` ops after
        it (also when it raised, so that what a ``pre_phase`` op entered is left)."""
        self._run_ops("pre_phase", name)
        try:
            yield
        finally:
            self._run_ops("post_phase", name)

    def request_stop(self, reason: str) -> None:
        """End :meth:`train` after the step in progress (from a hook: an early stop): it saves that step, runs
        the final evaluation and returns with ``"stopped": reason``."""
        self.stop_reason = reason

    # --- the loop ----------------------------------------------------------------------------------------
    @property
    def done(self) -> bool:
        """Whether the budget is spent."""
        return self.progress >= self.budget

    def setup(self) -> None:
        """The run's I/O, once: the trainer's own (``_setup``: DIAYN's random-policy evaluation, MAML's
        checkpoint 0), the logger, the metrics ``_setup`` returned, then the ``setup`` hooks."""
        if self.is_set_up:
            return
        initial = self._setup()
        cfg = self.cfg
        self.logger = make_logger(cfg.logger, exp_name=cfg.logger.exp_name, job_type=self.name, config=cfg,
                                  log_dir=self.output_dir, resume_step=self.progress)
        self.is_set_up = True
        if initial:
            self.log(initial)
        self.start_time = time.perf_counter()
        self._run_ops("setup")

    def step(self) -> dict[str, float]:
        """One step (set up first if needed), between the ``pre_step`` and ``post_step`` hooks; its
        metrics."""
        self.setup()
        self._run_ops("pre_step")
        metrics = self._step()
        self._run_ops("post_step", metrics)
        return metrics

    def evaluate(self, final: bool = False) -> dict[str, float]:
        """The trainer's evaluation of its current state (``final``: the one at the end of :meth:`train`),
        then the ``post_evaluate`` hooks; its metrics (``{}`` for a trainer without metrics to evaluate)."""
        self.setup()
        metrics = self._evaluate(final)
        self._run_ops("post_evaluate", metrics)
        return metrics

    def log(self, metrics: dict[str, float]) -> None:
        """Send ``metrics`` to the configured logger at :attr:`progress`, then to the ``post_log`` hooks."""
        self.setup()
        log_metrics(self.logger, metrics, self.progress)
        self._run_ops("post_log", metrics)

    def save(self) -> Path:
        """Write the checkpoint of the current :attr:`progress`, then run the ``post_save`` hooks; its
        path."""
        path = self._save()
        self._run_ops("post_save", path)
        return path

    def train(self) -> dict:
        """Step to the budget (module docstring); returns the last value of every metric logged, the final
        evaluation's, the trainer's own entries, the last ``checkpoint`` path and, after :meth:`request_stop`,
        ``stopped`` (its reason)."""
        self.stop_reason = None
        self.setup()
        bar = tqdm.tqdm(total=self.budget, initial=self.progress, disable=not self.cfg.progress,
                        unit=self.progress_unit, desc=self._description())
        last, path, saved = {}, self.checkpointer.latest(), self.progress
        with stop_requests() as stop:
            while not self.done and not stop and self.stop_reason is None:
                before = self.progress
                metrics = self.step()
                bar.update(self.progress - before)
                if self._evaluation_due():
                    metrics = {**metrics, **self.evaluate()}
                if metrics:
                    self.log(metrics)
                    last.update(metrics)
                    if postfix := self._postfix(metrics):
                        bar.set_postfix(postfix)
                if self._checkpoint_due(before) or self.done:  # on schedule, and the last step
                    path, saved = self.save(), self.progress
            bar.close()
            if not self.done and (stop or self.stop_reason is not None):
                path = path if path is not None and saved == self.progress else self.save()
                if stop:
                    where = self.stop_message.format(progress=self.progress, budget=self.budget)
                    raise stop.stopped(where, path)
        final = self.evaluate(final=True)
        if final:
            self.log(final)
        stopped = {} if self.stop_reason is None else {"stopped": self.stop_reason}
        return {**last, **final, **self._result(), "checkpoint": str(path), **stopped}

    def _description(self) -> str:
        """The progress bar's label."""
        return f"{self.name.upper()} {self.cfg.env.name}"

    def close(self) -> None:
        """Run the ``shutdown`` hooks, close the envs and the logger, release ``output_dir``."""
        try:
            self._run_ops("shutdown")
        finally:
            for env in self._envs():
                env.close()
            close_logger(self.logger)
            self.folder_lock.release()
