"""``LABEL=PATH`` command-line values: a run's label in printed tables and its path (``{seed}`` left in place)."""
from __future__ import annotations

import argparse


def labelled_path(spec: str) -> tuple[str, str]:
    """``"LABEL=PATH"`` → ``(label, path)``, for argparse's ``type=``; anything else is refused with the value."""
    label, sep, path = spec.partition("=")
    if not sep or not label or not path:
        raise argparse.ArgumentTypeError(f"got {spec!r}; expected LABEL=PATH")
    return label, path
