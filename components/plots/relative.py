"""Task III figures: box plots of d_E and of the mean square gap δ against the noise level η, and ROC curves
of the out-of-ODD decision "δ above a threshold".

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from components.plots.canvas import new_figure
from components.plots.checks import as_named_arrays

__all__ = ["boxplots_by_level", "roc_curves"]


def _level_label(level: object) -> str:
    return f"{level:g}" if isinstance(level, (int, float, np.floating, np.integer)) else str(level)


def boxplots_by_level(
    values: Mapping[float, object],
    baseline: Mapping[float, object] | None = None,
    xlabel: str = "noise level η",
    ylabel: str = "value",
    title: str | None = None,
    labels: tuple[str, str] = ("measured", "chance baseline"),
) -> Figure:
    """Box-and-whisker plots of a statistic for each level (e.g. d_E or δ for each η), in the given order.

    Arguments:
        values: level → ``(r,)`` values of the statistic over the repetitions at that level.
        baseline: optional level → ``(r',)`` values of the same statistic achieved by chance (e.g. δ for
            random weights); drawn as grey boxes beside the measured ones. Its levels must be among ``values``'.
    """
    vals = as_named_arrays(values, "values")
    base = None if baseline is None else as_named_arrays(baseline, "baseline")
    if base is not None:
        missing = [k for k in base if k not in vals]
        if missing:
            raise ValueError(f"baseline has level(s) {missing} that values does not have")
    keys = list(vals)
    n_boxes = len(keys) * (2 if base is not None else 1)
    fig = new_figure(min(13.0, max(6.5, 0.45 * n_boxes + 2.5)), 4.8)
    ax = fig.add_subplot()
    pos = np.arange(1, len(keys) + 1, dtype=float)
    shift = 0.2 if base is not None else 0.0
    width = 0.35 if base is not None else 0.6
    common = {"patch_artist": True, "widths": width, "medianprops": {"color": "black"}, "flierprops": {"markersize": 3}}
    main = ax.boxplot([vals[k] for k in keys], positions=pos - shift, **common)
    for patch in main["boxes"]:
        patch.set_facecolor("#6a8fc7")
    handles = [Patch(facecolor="#6a8fc7", edgecolor="black", label=labels[0])]
    if base is not None:
        bkeys = [k for k in keys if k in base]
        bpos = np.array([pos[keys.index(k)] for k in bkeys]) + shift
        chance = ax.boxplot([base[k] for k in bkeys], positions=bpos, **common)
        for patch in chance["boxes"]:
            patch.set_facecolor("#cfcfcf")
        handles.append(Patch(facecolor="#cfcfcf", edgecolor="black", label=labels[1]))
        ax.legend(handles=handles, frameon=False)
    ax.set_xticks(pos, [_level_label(k) for k in keys])
    ax.set_xlim(0.4, len(keys) + 0.6)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(axis="y", alpha=0.25)
    return fig


def roc_curves(
    curves: Mapping[float, tuple[object, object, float]],
    score_name: str = "δ",
    title: str = "Out-of-ODD detection",
    intervals: Mapping[float, tuple[float, float]] | None = None,
    operating_points: Mapping[float, tuple[float, float]] | None = None,
    alpha: float | None = None,
) -> Figure:
    """ROC curves of "out of the ODD when the score ≥ s", one per level, AUC in the legend.

    Arguments:
        curves: level → ``(fpr, tpr, auc)`` of the out-of-ODD targets at that level against the in-ODD ones
            (:func:`components.evaluate.diagnostics.roc_curve`; Task III: δ at each η > 0 against δ at η = 0).
        score_name: the score's symbol in the title.
        intervals: optional level → ``(low, high)``, each AUC's confidence interval
            (:func:`components.evaluate.diagnostics.auc_interval`), shown in the legend; its levels must be the curves'.
        operating_points: optional level → ``(fpr, tpr)``, where the deployed decision's threshold puts each curve
            (the share of in-ODD and of out-of-ODD targets it flags), drawn as a marker on it; the curves' levels.
        alpha: optional false-alarm rate the threshold was calibrated for, a vertical line at fpr = α.
    """
    if intervals is not None and set(intervals) != set(curves):
        raise ValueError(f"intervals must have the curves' levels {sorted(curves)}, got {sorted(intervals)}")
    if operating_points is not None and set(operating_points) != set(curves):
        raise ValueError(
            f"operating_points must have the curves' levels {sorted(curves)}, got {sorted(operating_points)}"
        )
    if alpha is not None and not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be a false-alarm rate in (0, 1), got {alpha!r}")
    if not isinstance(curves, Mapping) or not curves:
        raise ValueError("curves must be a non-empty mapping level → (fpr, tpr, auc)")
    checked = {}
    for level, curve in curves.items():
        if len(curve) != 3:
            raise ValueError(f"curves[{level!r}] must be (fpr, tpr, auc), got {len(curve)} items")
        fpr, tpr, auc = np.asarray(curve[0], float), np.asarray(curve[1], float), float(curve[2])
        if fpr.shape != tpr.shape or fpr.ndim != 1 or not (np.isfinite(fpr).all() and np.isfinite(tpr).all()):
            raise ValueError(f"curves[{level!r}]: fpr and tpr must be finite 1-D arrays of one length")
        checked[level] = (fpr, tpr, auc)
    fig = new_figure(6.6, 6.0)
    ax = fig.add_subplot()
    ax.plot([0, 1], [0, 1], color="grey", linestyle=":", linewidth=1, label="chance (AUC 0.5)")
    cmap_n = max(1, len(checked) - 1)
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    for k, (level, (fpr, tpr, auc)) in enumerate(checked.items()):
        ax.plot(
            fpr,
            tpr,
            drawstyle="default",
            color=cmap(0.9 * k / cmap_n),
            linewidth=1.6,
            label=f"η = {_level_label(level)}  (AUC {auc:.3f}"
            + ("" if intervals is None else " [{:.2f}, {:.2f}]".format(*intervals[level]))
            + ")",
        )
        if operating_points is not None:
            ax.plot(*operating_points[level], marker="o", markersize=6, color=cmap(0.9 * k / cmap_n), zorder=3)
    if operating_points is not None:
        ax.plot([], [], marker="o", linestyle="none", color="black", label="the ODD alarm's threshold on each curve")
    if alpha is not None:
        ax.axvline(
            alpha, color="tab:red", linestyle="--", linewidth=1, label=f"α = {alpha:g}: its calibrated false-alarm rate"
        )
    ax.set_xlim(-0.01, 1.01)
    ax.set_ylim(-0.01, 1.01)
    ax.set_aspect("equal")
    ax.set_xlabel("false-positive rate (in-ODD targets flagged)")
    ax.set_ylabel("true-positive rate (out-of-ODD targets flagged)")
    ax.set_title(f"{title}: {score_name} ≥ threshold")
    ax.legend(loc="lower right", fontsize=8, frameon=False)
    ax.grid(alpha=0.25)
    return fig
