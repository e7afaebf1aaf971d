"""Writing figures: matplotlib :class:`~matplotlib.figure.Figure` objects made without pyplot, so no backend is
selected and a notebook user's backend is left as it is."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any


def save_figure(fig: Any, path: str | os.PathLike, *, dpi: int = 120) -> Path:
    """Lay out ``fig``, a :class:`matplotlib.figure.Figure` made without pyplot (nothing to close, no backend
    selected), and write it to ``path`` (PNG; parent folders created)."""
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path
