"""Training curves of a posterior model (an MLflow artifact of every training run).

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from components.plots.canvas import new_figure
from components.plots.checks import as_named_arrays

__all__ = ["best_epoch", "loss_curves"]


def best_epoch(history: Mapping[str, Sequence[float]]) -> tuple[str, int]:
    """``(curve, epoch)``: the epoch (1-based) of the lowest loss of the validation curve.

    The validation curve is the first whose name contains ``"val"``; without one, the first curve. Epochs
    with a NaN loss (a diverged epoch) are ignored.
    """
    curves = as_named_arrays(history, "history", allow_nan=True)
    key = next((k for k in curves if "val" in str(k).lower()), next(iter(curves)))
    return str(key), int(np.nanargmin(curves[key])) + 1


def loss_curves(
    history: Mapping[str, Sequence[float]],
    ylabel: str = "loss (negative log-likelihood)",
    title: str = "Training curves",
) -> Figure:
    """Loss per epoch for each curve of ``history`` (e.g. ``{"train": [...], "val": [...]}``), best epoch marked.

    Curves may have different lengths (epoch k is entry k − 1); NaN marks an epoch without a value.
    """
    curves = as_named_arrays(history, "history", allow_nan=True)
    key, best = best_epoch(history)
    fig = new_figure(7.5, 4.6)
    ax = fig.add_subplot()
    for name, values in curves.items():
        epochs = np.arange(1, values.size + 1)
        ax.plot(epochs, values, marker="o" if values.size <= 30 else None, markersize=3, linewidth=1.6, label=str(name))
    best_value = float(curves[next(k for k in curves if str(k) == key)][best - 1])
    ax.axvline(best, color="grey", linestyle=":", linewidth=1)
    ax.plot(
        [best],
        [best_value],
        marker="*",
        markersize=14,
        color="#d62728",
        linestyle="none",
        label=f"best {key}: epoch {best}, {best_value:.4g}",
    )
    ax.set_xlabel("epoch")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.legend(frameon=False)
    ax.grid(alpha=0.25)
    return fig
