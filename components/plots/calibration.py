"""Paper, Task I, 4th and 5th analyses: coverage plot and box plots of the superiority of the ground truth π.

Both compare several models (the paper's 9: 3 backbones × 3 training sizes). Models named
``"<backbone>-<size>"`` (e.g. ``"resnet-50k"``) get one colour per backbone and one line style per size.

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from components.plots.canvas import new_figure
from components.plots.checks import as_named_arrays

__all__ = ["model_styles", "coverage_plot", "superiority_boxplot"]

_SIZE = re.compile(r"^(\d+(?:\.\d+)?)([kKmM]?)$")
_LINESTYLES = ("-", "--", ":", "-.", (0, (5, 1, 1, 1, 1, 1)))
_MARKERS = ("o", "s", "^", "D", "v", "P")


#: colours of the models beside a grid (variants), distinct from the backbones' C0…C9
_EXTRA_COLOURS = ("black", "dimgray", "darkred", "darkgoldenrod", "indigo", "teal")


def _size_value(size: str) -> float | None:
    m = _SIZE.match(size)
    if not m:
        return None
    return float(m.group(1)) * {"": 1, "k": 1e3, "m": 1e6}[m.group(2).lower()]


def model_styles(names: Sequence[str]) -> dict[str, dict[str, object]]:
    """Matplotlib line styles (``color``, ``linestyle``, ``marker``) for each model name.

    Names ``"<backbone>-<size>"`` with a numeric size (``500``, ``50k``, ``1M``): a colour per backbone (in
    order of appearance), a line style per size (smallest first); up to six other names beside such a grid
    (e.g. calibrated variants) get heavy solid lines in colours of their own. Otherwise: distinct colours
    (tab20) with cycled line styles. A marker is added for every style so that curves stay distinguishable in grey.
    """
    names = list(names)
    grid = [n for n in names if len(p := n.rsplit("-", 1)) == 2 and _size_value(p[1]) is not None]
    parts = [n.rsplit("-", 1) for n in grid]
    backbones = list(dict.fromkeys(p[0] for p in parts))
    sizes = sorted({p[1] for p in parts}, key=_size_value)
    others = [n for n in names if n not in grid]
    styles: dict[str, dict[str, object]] = {}
    if grid and len(backbones) <= 10 and len(sizes) <= len(_LINESTYLES) and len(others) <= len(_EXTRA_COLOURS):
        for name, (backbone, size) in zip(grid, parts, strict=False):
            b, s = backbones.index(backbone), sizes.index(size)
            styles[name] = {"color": f"C{b}", "linestyle": _LINESTYLES[s], "marker": _MARKERS[s % len(_MARKERS)]}
        # models beside the grid (e.g. calibrated variants "<backbone>-<size>-<name>"): heavy lines of their own
        for k, name in enumerate(others):
            styles[name] = {
                "color": _EXTRA_COLOURS[k],
                "linestyle": "-",
                "marker": _MARKERS[k % len(_MARKERS)],
                "linewidth": 2.6,
            }
        return styles
    from matplotlib import colormaps

    palette = colormaps["tab20"]
    for k, name in enumerate(names):
        styles[name] = {
            "color": palette(k % 20),
            "linestyle": _LINESTYLES[(k // 20) % len(_LINESTYLES)],
            "marker": _MARKERS[k % len(_MARKERS)],
        }
    return styles


def coverage_plot(
    curves: Mapping[str, tuple[object, object]],
    title: str = "Expected coverage of the highest-density regions",
    band: float | None = None,
    band_label: str = "band of a perfectly calibrated model",
) -> Figure:
    """Expected coverage c(l) against the credible level l for every model, in one plot.

    Arguments:
        curves: model name → ``(levels (L,), coverage (L,))``, both in [0, 1] (e.g. from
            :func:`components.evaluate.diagnostics.expected_coverage`); L may differ between models.
        band: the half-width b of the strip l ± b around the diagonal that a perfectly calibrated model stays in on
            the same number of images (e.g. :func:`components.evaluate.diagnostics.calibration_band`, a bound on the
            largest deviation: a curve inside the strip everywhere has a calibration error ≤ b); None: no strip.
        band_label: the strip's legend entry.

    The diagonal c = l is calibration; above it a model is conservative (underconfident, its regions too
    wide), below it overconfident (too narrow). Both halves are shaded and labelled.
    """
    if not isinstance(curves, Mapping) or len(curves) == 0:
        raise ValueError("curves must be a non-empty mapping of model name → (levels, coverage)")
    checked: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, pair in curves.items():
        if not isinstance(pair, (tuple, list)) or len(pair) != 2:
            raise ValueError(f"curves[{name!r}] must be a pair (levels, coverage)")
        lv, cov = (np.asarray(v, dtype=np.float64) for v in pair)
        if lv.ndim != 1 or lv.size < 2 or cov.shape != lv.shape:
            raise ValueError(
                f"curves[{name!r}]: levels and coverage must be 1-D of one length >= 2, got {lv.shape} and {cov.shape}"
            )
        for what, v in (("levels", lv), ("coverage", cov)):
            if not np.isfinite(v).all() or (v < 0).any() or (v > 1).any():
                raise ValueError(f"curves[{name!r}]: {what} must lie in [0, 1]")
        checked[str(name)] = (lv, cov)
    if band is not None and not (np.isfinite(band) and 0 <= band <= 1):
        raise ValueError(f"band must be a half-width in [0, 1], got {band!r}")
    styles = model_styles(list(checked))
    fig = new_figure(8.6, 6.2)
    ax = fig.add_subplot()
    ax.fill_between([0, 1], [0, 1], [1, 1], color="#2ca02c", alpha=0.07, linewidth=0)
    ax.fill_between([0, 1], [0, 0], [0, 1], color="#d62728", alpha=0.07, linewidth=0)
    ax.text(0.04, 0.93, "conservative\n(underconfident)", color="#1e6b1e", fontsize=11, va="top", ha="left")
    ax.text(0.96, 0.05, "overconfident", color="#9b1c1c", fontsize=11, va="bottom", ha="right")
    if band is not None:
        grid = np.linspace(0.0, 1.0, 201)
        ax.fill_between(
            grid,
            np.clip(grid - band, 0, 1),
            np.clip(grid + band, 0, 1),
            color="grey",
            alpha=0.28,
            linewidth=0,
            label=f"{band_label}\n(±{band:.3f})",
        )
    ax.plot([0, 1], [0, 1], color="black", linewidth=1, linestyle=(0, (4, 3)), label="calibrated")
    for name, (lv, cov) in checked.items():
        st = styles[name]
        order = np.argsort(lv)
        ax.plot(
            lv[order],
            cov[order],
            color=st["color"],
            linestyle=st["linestyle"],
            marker=st["marker"],
            markevery=max(1, lv.size // 8),
            markersize=4.5,
            linewidth=st.get("linewidth", 1.6),
            label=name,
        )
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_aspect("equal")
    ax.set_xlabel("credible level l")
    ax.set_ylabel("expected coverage c(l)")
    ax.set_title(title)
    ax.legend(loc="center left", bbox_to_anchor=(1.02, 0.5), frameon=False, fontsize=9)
    ax.grid(alpha=0.25)
    return fig


def superiority_boxplot(
    pi: Mapping[str, object],
    title: str = "Superiority of the ground truth π",
) -> Figure:
    """Box-and-whisker plots of π (one value in [0, 1] per test image) for each model, in the given order.

    π(i) is the share of weathers drawn from P̂(W | I = i) whose density is ≤ the ground truth's (higher is
    better); for the exact posterior π is uniform on [0, 1], median 0.5 (dotted reference line). Each box's
    median is written above it.
    """
    values = as_named_arrays(pi, "pi")
    for name, v in values.items():
        if (v < 0).any() or (v > 1).any():
            raise ValueError(f"pi[{name!r}] must lie in [0, 1]")
    names = [str(k) for k in values]
    styles = model_styles(names)
    fig = new_figure(max(6.0, 0.75 * len(names) + 2.5), 5.4)
    ax = fig.add_subplot()
    box = ax.boxplot(
        list(values.values()),
        tick_labels=names,
        patch_artist=True,
        widths=0.6,
        medianprops={"color": "black", "linewidth": 1.6},
        flierprops={"markersize": 3, "alpha": 0.5},
    )
    for patch, name in zip(box["boxes"], names, strict=False):
        patch.set_facecolor(styles[name]["color"])
        patch.set_alpha(0.55)
    for k, v in enumerate(values.values(), start=1):
        med = float(np.median(v))
        ax.text(k, 1.015, f"{med:.2f}", ha="center", va="bottom", fontsize=9, transform=ax.get_xaxis_transform())
    ax.axhline(0.5, color="grey", linestyle=":", linewidth=1, label="median for the exact posterior")
    ax.set_ylim(-0.02, 1.02)
    ax.set_ylabel("π (share of draws no denser than the truth)")
    ax.set_xlabel("model")
    ax.set_title(title + "  (medians above the boxes)", pad=22)
    ax.legend(loc="lower right", frameon=False, fontsize=9)
    if len(names) > 5 or max(len(n) for n in names) > 10:
        ax.tick_params(axis="x", labelrotation=35)
        for lab in ax.get_xticklabels():
            lab.set_ha("right")
    ax.grid(axis="y", alpha=0.25)
    return fig
