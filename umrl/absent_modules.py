"""Answer "is this optional package installed?" once per process instead of on every module call.

tensordict (0.14, 0.15) asks ``importlib.util.find_spec("pandas")`` inside ``TensorDict.from_any``, which every
``TensorDictModule`` runs on each output it writes. Where pandas is not installed, each question walks ``sys.path``
again (a few directory look-ups): two per policy call while collecting, about ten per DIAYN update. On the quiet
2-core machine that was 12 % of a point_nav collection's wall time at the MAML reference settings (800 copies) and
6 % at the paper's (2000 copies), more on a loaded machine (README, "Latest performance figures").

:func:`mark_absent_modules` records each absent package as ``None`` in ``sys.modules``, Python's own marker for "not
importable": ``find_spec`` then answers ``None`` at once and ``import pandas`` raises ``ModuleNotFoundError`` as
before. Installed packages are left alone, so nothing changes where pandas is present. It is process-wide, so umrl applies
it only where it owns the process (:func:`umrl.process.tune_process`: the recipes' command lines, the suite's
workers, the benchmarks); a package installed later in the same process is importable only after a restart.
"""
from __future__ import annotations

import importlib.util
import sys

__all__ = ["HOT_PATH_OPTIONAL_MODULES", "mark_absent_modules"]

HOT_PATH_OPTIONAL_MODULES = ("pandas",)
"""Optional packages a dependency looks up on a per-step path (see the module docstring)."""


def mark_absent_modules(names: tuple[str, ...] = HOT_PATH_OPTIONAL_MODULES) -> tuple[str, ...]:
    """Record every top-level package of ``names`` that cannot be imported as absent (``sys.modules[name] = None``);
    idempotent. Returns the names marked by this call."""
    marked = tuple(name for name in names if name not in sys.modules and importlib.util.find_spec(name) is None)
    for name in marked:
        sys.modules[name] = None
    return marked
