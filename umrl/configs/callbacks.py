"""Hydra callbacks of the command lines (``hydra.callbacks`` in the recipes' and the suite's yaml): checks that must
run before Hydra itself writes.

Hydra creates ``hydra.run.dir`` (``${output_dir}/hydra``) before it calls the script's ``main``, where the schemas
check ``output_dir``; an ``output_dir`` that is a file or not writable would fail there with a bare ``OSError``.
"""
from __future__ import annotations

from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from umrl.configs.validate import ConfigError
from umrl.validation import InvalidValue, check_writable_dir


class OutputDirCheck(Callback):
    """Refuse an ``output_dir`` (then a ``hydra.run.dir``) that is not a writable directory
    (:func:`umrl.validation.check_writable_dir`) before a single run starts (``-m`` runs are checked by their schemas,
    once Hydra made their own directories).

    The refusal ends the process (``SystemExit`` with the :class:`~umrl.configs.ConfigError` message, status 1):
    Hydra turns any ``Exception`` a callback raises into a warning and carries on."""

    def on_run_start(self, config: DictConfig, config_name: str | None = None, **kwargs: Any) -> None:
        for key in ("output_dir", "hydra.run.dir"):
            try:
                check_writable_dir(key, OmegaConf.select(config, key))
            except InvalidValue as e:
                raise SystemExit(str(ConfigError(config_name or "command line", [e.message()]))) from None
