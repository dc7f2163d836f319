"""Task I per parameter: a heat-map of every model's per-parameter error, with its interval coverage, day and night.

Input: the per-parameter figures of :func:`components.evaluate.marginals.parameter_report` for several models
(``model → subset → parameter → figure``; this module reads ``median_abs_error``, ``coverage95`` and ``images``).

Used (through :mod:`components.plots`) by the ``evaluate`` stage.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from components.core.weather import PREDICTED, Box
from components.plots.canvas import new_figure
from components.plots.checks import as_box
from components.plots.labels import short_label, unit_symbol

__all__ = ["parameter_heatmaps"]

#: A flat marginal (the prior) has a median |median − truth| of a quarter of the range: the colour scale's top
_UNINFORMED = 0.25


def _figure(report: Mapping, model: str, subset: str, name: str, key: str) -> float:
    try:
        return float(report[model][subset][name][key])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"report[{model!r}][{subset!r}][{name!r}] lacks a number {key!r}") from None


def parameter_heatmaps(
    report: Mapping[str, Mapping[str, Mapping[str, Mapping[str, float]]]],
    box: Box | None = None,
    subsets: Sequence[str] = ("day", "night"),
    title: str = "Task I per parameter: median |posterior median − truth| and 95 % interval coverage",
) -> Figure:
    """One heat-map per subset (default: day and night truths): rows the models, columns the six parameters.

    A cell's colour is the median over the subset's images of |posterior median − truth| as a share of the
    parameter's prior range (from 0 up to at least ¼, the error of a posterior equal to the uniform prior); its text is
    that error in the parameter's unit and the coverage of the central 95 % interval, marked ↓ when it lies below the
    95 % binomial band of a calibrated model on that many images (overconfident), ↑ above it (too wide).

    Arguments:
        report: ``model → subset → parameter name → {"median_abs_error", "coverage95", "images", …}``.
        box: the prior box (its widths scale the colours; default: the full physical ranges).
        subsets: the subsets shown, one panel each.
    """
    if not isinstance(report, Mapping) or not report:
        raise ValueError("report must be a non-empty mapping of model → subset → parameter → figures")
    b = as_box(box)
    models = [str(m) for m in report]
    subsets = list(subsets)
    if not subsets:
        raise ValueError("subsets must name at least one subset (e.g. 'day', 'night')")
    d = len(PREDICTED)
    errors = np.empty((len(subsets), len(models), d))
    coverage = np.empty_like(errors)
    images = np.empty((len(subsets), len(models)))
    for s, subset in enumerate(subsets):
        for m, model in enumerate(models):
            images[s, m] = _figure(report, model, subset, PREDICTED[0], "images")
            for k, name in enumerate(PREDICTED):
                errors[s, m, k] = _figure(report, model, subset, name, "median_abs_error")
                coverage[s, m, k] = _figure(report, model, subset, name, "coverage95")
    share = errors / b.width
    top = max(_UNINFORMED, float(np.nanmax(share))) if np.isfinite(share).any() else _UNINFORMED
    fig = new_figure(1.25 * d * len(subsets) + 3.2, 0.42 * len(models) + 2.4)
    axes = np.atleast_1d(fig.subplots(1, len(subsets), sharey=True))
    image = None
    for s, (ax, subset) in enumerate(zip(axes, subsets, strict=True)):
        image = ax.imshow(share[s], cmap="magma_r", vmin=0.0, vmax=top, aspect="auto")
        for m in range(len(models)):
            n = images[s, m]
            half = 1.96 * math.sqrt(0.95 * 0.05 / n) if n > 0 else math.nan
            for k, name in enumerate(PREDICTED):
                cov = coverage[s, m, k]
                mark = "↓" if cov < 0.95 - half else "↑" if cov > 0.95 + half else ""
                value = errors[s, m, k]
                text = f"{value:.3g}{unit_symbol(name)}\n{100 * cov:.0f} %{mark}" if np.isfinite(value) else "—"
                dark = np.isfinite(share[s, m, k]) and share[s, m, k] > 0.55 * top
                ax.text(k, m, text, ha="center", va="center", fontsize=7.5, color="white" if dark else "black")
        ax.set_xticks(range(d), [short_label(k) for k in range(d)], rotation=30, ha="right")
        ax.set_yticks(range(len(models)), models)
        ax.set_title(f"{subset} ({int(images[s].max()) if len(models) else 0} images)")
        ax.tick_params(length=0)
    cbar = fig.colorbar(image, ax=list(axes), shrink=0.85, pad=0.02)
    cbar.set_label("median |median − truth| / prior range")
    fig.suptitle(title + "\n(↓ coverage below the 95 % binomial band of a calibrated model: overconfident; ↑ above)")
    return fig
