"""Creating figures without pyplot and writing them atomically.

Figures are built with :class:`matplotlib.figure.Figure` and an explicit Agg canvas, never through
``pyplot``: no global figure registry, no backend switch, so an interactive backend a caller may have
selected keeps working, and nothing leaks between calls (no ``matplotlib.use`` here at all).

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from components.core.files import atomic_path

__all__ = ["new_figure", "save_figure"]


def new_figure(width: float, height: float, *, layout: str | None = "constrained") -> Figure:
    """A figure of ``width`` × ``height`` inches attached to an Agg canvas (no pyplot)."""
    if not (width > 0 and height > 0):
        raise ValueError(f"figure size must be positive inches, got {width} × {height}")
    fig = Figure(figsize=(width, height), layout=layout)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str | os.PathLike[str], dpi: int = 120) -> Path:
    """Write ``fig`` to ``path`` atomically and close it; returns the path.

    The image format follows the suffix of ``path`` (``.png``, ``.pdf``, ``.svg``, …). The figure is first
    written to a temporary file in the destination folder (created if needed) and then moved into place with
    ``os.replace`` (:func:`components.core.files.atomic_path`), so a reader never sees a half-written file. The
    figure is closed afterwards: removed from pyplot's registry when pyplot made it; a figure made without pyplot
    holds no global reference and is freed with the caller's last reference.
    """
    if not isinstance(fig, Figure):
        raise TypeError(f"save_figure expects a matplotlib Figure, got {type(fig).__name__}")
    if not (isinstance(dpi, (int, float)) and dpi > 0):
        raise ValueError(f"dpi must be a positive number, got {dpi!r}")
    target = Path(path)
    fmt = target.suffix.lstrip(".").lower()
    supported = FigureCanvasAgg.get_supported_filetypes()
    if fmt not in supported:
        raise ValueError(
            f"cannot infer an image format from {str(target)!r}; use one of the suffixes {sorted(supported)}"
        )
    try:
        with atomic_path(target, fsync=False) as tmp:
            with open(tmp, "wb") as handle:
                fig.savefig(handle, format=fmt, dpi=dpi)
            os.chmod(tmp, 0o644)  # a report is meant to be read, whatever the umask
    finally:
        _close(fig)
    return target


def _close(fig: Figure) -> None:
    """Close a figure made by pyplot (drop it from pyplot's registry, its only global reference).

    A figure made here (no pyplot) is referenced by nobody else and is freed with its last reference;
    clearing its axes one by one would only cost time (~1 s for a 72-panel corner comparison).
    """
    pyplot = sys.modules.get("matplotlib.pyplot")
    if pyplot is not None and getattr(fig.canvas, "manager", None) is not None:
        pyplot.close(fig)
