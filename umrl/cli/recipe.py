"""What each recipe command (``umrl diayn|maml|vime``) does with its composed config."""
from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Sequence

from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from umrl.configs.env_groups import ENV_GROUPS
from umrl.folder_lock import reserve_folder
from umrl.loggers import log_location, run_summary
from umrl.process import tune_process
from umrl.run_folders import named_keys, place_default_run

__all__ = ["sweep_job_folder", "train_and_summarize"]


def _multirun() -> bool:
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def sweep_job_folder(cfg: DictConfig, argv: Sequence[str]) -> DictConfig:
    """In a Hydra multirun (``-m``), each job's own ``output_dir``: ``<output_dir>/<key=value,...>`` for the keys the
    command line ``argv`` sweeps whose value ``output_dir`` does not already name (``-m maml.inner_lr=0.1,0.5
    output_dir=outputs/sweep`` runs in ``outputs/sweep/maml.inner_lr=0.1`` and ``.../maml.inner_lr=0.5``; ``-m
    seed=0,1`` keeps ``.../seed0`` and ``.../seed1``). A single run's config is returned unchanged."""
    if not _multirun():
        return cfg
    overrides = OverridesParser.create().parse_overrides([a for a in argv if "=" in a and not a.startswith("-")])
    swept = [o.get_key_element() for o in overrides if o.is_sweep_override()]
    named = str(OmegaConf.to_container(cfg, resolve=False)["output_dir"])
    job = dict(line.split("=", 1) for line in HydraConfig.get().overrides.task)
    env_group = {group: "env.name" for group in ENV_GROUPS.values()}  # -m env.name=a,b sweeps the env's group
    parts = [f"{env_group.get(key, key)}={job[key]}" for key in swept
             if key in job and "${" + env_group.get(key, key.lstrip("+~")) + "}" not in named]
    if parts:
        cfg.output_dir = f"{cfg.output_dir}/{','.join(parts).replace('/', '_')}"
    return cfg


def train_and_summarize(name: str, cfg: DictConfig, train: Callable[[DictConfig], dict], keys: Sequence[str],
                        log: logging.Logger) -> dict:
    """Apply umrl's process tuning (the command owns its process: :func:`umrl.process.tune_process` with the
    config's ``num_threads``), run ``train(cfg)`` and log the summary of ``keys`` (``<name> <env> finished: ...``,
    the checkpoint, where every metric went); returns ``train``'s result. A multirun job runs in its own folder
    (:func:`sweep_job_folder`), a new one per rerun when the command line leaves ``output_dir`` at its default
    (:mod:`umrl.run_folders`, as the callback does for a single run)."""
    tune_process(num_threads=cfg.num_threads)
    cfg = sweep_job_folder(cfg, sys.argv[1:])
    lock = None
    if _multirun():  # a single run's folder is placed before Hydra writes there (umrl.configs.callbacks)
        lock, notes = place_default_run(cfg, named_keys(HydraConfig.get().overrides.task))
        if lock is not None:
            reserve_folder(lock)  # the trainer takes it over
        for note in notes:
            log.info(note)
    try:
        result = train(cfg)
    finally:
        if lock is not None:  # the trainer took it over and released it, unless it failed before
            lock.release()
    log.info(run_summary(f"{name} {cfg.env.name} finished", result, keys, log_location(cfg.logger, cfg.output_dir)))
    return result
