"""Paper, Task I, 2nd analysis (and Task II): corner plots of a 6-D weather distribution.

Diagonal: the 1-D marginal histograms. Lower triangle: for each pair (θ_j, θ_i), the 2-D marginal as an
image (histogram on a grid, lightly smoothed) and its HDR contours at the given credible levels.

Contours are computed **from each 2-D marginal itself**, not from the 6-D density: the grid's cells are
ordered by decreasing estimated mass and the contour at level α is drawn at the mass of the cell where the
accumulated mass reaches α (:func:`components.plots.hdr.grid_hdr_thresholds`), so each contour encloses α
of the 2-D marginal's probability (up to the grid's resolution). The 6-D HDR projected onto a plane would
enclose more than α of the 2-D marginal, which is why it is not used here.

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure, SubFigure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

from components.core.weather import Box
from components.plots.canvas import new_figure
from components.plots.checks import N_THETA, as_box, as_levels, as_log_prob, as_samples, as_truth
from components.plots.hdr import grid_density, grid_hdr_thresholds, in_hdr
from components.plots.labels import short_label

__all__ = ["corner_ranges", "corner_plot", "corner_compare"]

PAPER_LEVELS = (0.6827, 0.9545, 0.9973)
ZOOM_LEVEL = 0.9973
ZOOM_PAD = 0.05  # fraction of the span added on each side of a zoomed axis
MAIN = {"line": "#1f3f7a", "cmap": "Blues", "fill": "#6a8fc7"}
OTHER = {"line": "#e07b00"}
TRUTH_COLOUR = "#d62728"
LINESTYLES = ("-", "--", ":", "-.")


def corner_ranges(
    samples: object,
    log_prob: object | None = None,
    truth: object | None = None,
    zoom: bool = False,
    box: Box | None = None,
    reference_samples: object | None = None,
) -> np.ndarray:
    """The ``(6, 2)`` axis ranges (low, high) of a corner plot, physical units.

    ``zoom=False``: the box (default: the physical ranges). ``zoom=True``: the bounding box of the samples in
    the 99.73 % HDR (log_prob given) or, without log-densities, of each parameter's central 99.73 % interval;
    widened to include the ground truth and the reference samples' central 99.73 % intervals, padded by 5 % of
    the span on each side, and clipped to the box.
    """
    theta = as_samples(samples)
    b = as_box(box)
    if not zoom:
        return np.stack([b.low, b.high], axis=1)
    if log_prob is not None:
        lp = as_log_prob(log_prob, theta.shape[0])
        core = theta[in_hdr(lp, ZOOM_LEVEL)]
        lo, hi = core.min(axis=0), core.max(axis=0)
    else:
        lo, hi = _central(theta)
    if reference_samples is not None:
        rlo, rhi = _central(as_samples(reference_samples, "reference_samples"))
        lo, hi = np.minimum(lo, rlo), np.maximum(hi, rhi)
    t = as_truth(truth)
    if t is not None:
        lo, hi = np.minimum(lo, t), np.maximum(hi, t)
    span = np.maximum(hi - lo, 0.01 * b.width)
    lo, hi = np.maximum(lo - ZOOM_PAD * span, b.low), np.minimum(hi + ZOOM_PAD * span, b.high)
    return np.stack([lo, hi], axis=1)


def _central(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    tail = (1.0 - ZOOM_LEVEL) / 2
    return np.quantile(theta, tail, axis=0), np.quantile(theta, 1.0 - tail, axis=0)


def corner_plot(
    samples: object,
    log_prob: object | None = None,
    truth: object | None = None,
    levels: Sequence[float] = PAPER_LEVELS,
    zoom: bool = False,
    box: Box | None = None,
    reference_samples: object | None = None,
    labels: tuple[str, str] = ("prediction", "reference"),
    bins: int = 40,
    smooth: float = 1.0,
    title: str | None = None,
) -> Figure:
    """A 6×6 corner plot of θ samples (``(n, 6)``, physical units) with 2-D HDR contours at ``levels``.

    Arguments:
        samples: ``(n, 6)`` θ_j drawn from the distribution to show.
        log_prob: ``(n,)`` their log-densities (needed only for ``zoom=True``; without it the zoom uses central
            intervals).
        truth: ``(6,)`` ground-truth θ*, pinned by lines and a star in every panel.
        levels: credible levels of the contours (paper: 68.27, 95.45, 99.73 %).
        zoom: axes over the physical box (False) or over the 99.73 % region, padded (True); see
            :func:`corner_ranges`.
        reference_samples: ``(m, 6)`` optional second distribution overlaid as contours and step histograms in
            another colour (Task II: the true weather distribution of a domain).
        labels: legend names of the samples and of the reference.
        bins: grid cells per axis of the 2-D histograms.
        smooth: Gaussian smoothing of the 2-D histograms, in cells.
    """
    theta = as_samples(samples)
    if log_prob is not None:
        as_log_prob(log_prob, theta.shape[0])
    ref = None if reference_samples is None else as_samples(reference_samples, "reference_samples")
    lv = as_levels(levels)
    ranges = corner_ranges(theta, log_prob, truth, zoom, box, ref)
    fig = new_figure(11.0, 11.0, layout=None)
    _draw_corner(fig, theta, ranges, lv, as_truth(truth), ref, labels, bins, smooth)
    if title is None:
        title = "Corner plot of the predicted weather distribution" + (" (zoomed)" if zoom else "")
    fig.suptitle(title, y=0.985, fontsize=14)
    return fig


def corner_compare(
    a: object,
    b: object,
    labels: tuple[str, str] = ("ground truth", "estimate"),
    truth: object | None = None,
    levels: Sequence[float] = PAPER_LEVELS,
    zoom: bool = False,
    box: Box | None = None,
    overlay: bool = False,
    bins: int = 40,
    smooth: float = 1.0,
) -> Figure:
    """Two weather distributions (``(n, 6)`` and ``(m, 6)`` samples) side by side on identical axes, or overlaid.

    Task II: ``a`` drawn from the true weather distribution P_D(W) of a domain, ``b`` from its estimate P̂_D(W).
    ``overlay=True`` draws ``b`` as the main plot and ``a`` as contours on top (one 6×6 grid).
    """
    ta, tb = as_samples(a, "a"), as_samples(b, "b")
    if len(labels) != 2:
        raise ValueError(f"labels must name the two distributions, got {labels!r}")
    if overlay:
        return corner_plot(
            tb,
            None,
            truth,
            levels,
            zoom,
            box,
            ta,
            (labels[1], labels[0]),
            bins,
            smooth,
            title=f"{labels[1]} (filled) and {labels[0]} (contours)",
        )
    lv = as_levels(levels)
    t = as_truth(truth)
    ranges = corner_ranges(ta, None, t, zoom, box, tb)
    fig = new_figure(20.0, 10.6, layout=None)
    for sub, theta, name in zip(fig.subfigures(1, 2, wspace=0.02), (ta, tb), labels, strict=False):
        _draw_corner(sub, theta, ranges, lv, t, None, (name, ""), bins, smooth)
        sub.suptitle(name, y=0.985, fontsize=15)
    return fig


def _draw_corner(
    container: Figure | SubFigure,
    theta: np.ndarray,
    ranges: np.ndarray,
    levels: np.ndarray,
    truth: np.ndarray | None,
    ref: np.ndarray | None,
    labels: tuple[str, str],
    bins: int,
    smooth: float,
) -> None:
    axes = container.subplots(
        N_THETA,
        N_THETA,
        gridspec_kw={"left": 0.085, "right": 0.985, "bottom": 0.075, "top": 0.955, "wspace": 0.07, "hspace": 0.07},
    )
    for i in range(N_THETA):
        for j in range(N_THETA):
            ax = axes[i, j]
            if j > i:
                ax.set_axis_off()
                continue
            if i == j:
                _diagonal(ax, theta[:, i], ranges[i], bins, ref[:, i] if ref is not None else None)
                if truth is not None:
                    ax.axvline(truth[i], color=TRUTH_COLOUR, linewidth=1.5)
            else:
                _pair(
                    ax, theta[:, j], theta[:, i], ranges[j], ranges[i], levels, bins, smooth, MAIN["line"], image=True
                )
                if ref is not None:
                    _pair(
                        ax, ref[:, j], ref[:, i], ranges[j], ranges[i], levels, bins, smooth, OTHER["line"], image=False
                    )
                if truth is not None:
                    ax.axvline(truth[j], color=TRUTH_COLOUR, linewidth=0.9)
                    ax.axhline(truth[i], color=TRUTH_COLOUR, linewidth=0.9)
                    ax.plot(
                        truth[j],
                        truth[i],
                        marker="*",
                        markersize=11,
                        color=TRUTH_COLOUR,
                        markeredgecolor="white",
                        markeredgewidth=0.6,
                    )
                ax.set_ylim(*ranges[i])
            ax.set_xlim(*ranges[j])
            ax.xaxis.set_major_locator(MaxNLocator(4, prune="both"))
            ax.yaxis.set_major_locator(MaxNLocator(4, prune="both"))
            ax.tick_params(labelsize=8)
            if i == N_THETA - 1:
                ax.set_xlabel(short_label(j), fontsize=11)
                ax.tick_params(axis="x", labelrotation=45)
            else:
                ax.tick_params(axis="x", labelbottom=False)
            if j == 0 and i > 0:
                ax.set_ylabel(short_label(i), fontsize=11)
            else:
                ax.tick_params(axis="y", labelleft=False)
            if i == j:
                ax.tick_params(axis="y", left=False)
    level_colour = MAIN["line"] if ref is None else "dimgray"  # with a reference, the styles apply to both colours
    handles = [
        Line2D([], [], color=level_colour, linestyle=LINESTYLES[k % len(LINESTYLES)], label=f"{100 * lev:.2f} % HDR")
        for k, lev in enumerate(levels)
    ]
    if ref is not None:
        handles = [
            Line2D([], [], color=MAIN["line"], linewidth=3, label=labels[0]),
            Line2D([], [], color=OTHER["line"], linewidth=3, label=labels[1]),
        ] + handles
    if truth is not None:
        handles.append(Line2D([], [], color=TRUTH_COLOUR, marker="*", markersize=11, label="ground truth"))
    axes[0, N_THETA - 1].legend(handles=handles, loc="upper right", fontsize=11, frameon=False, title="2-D marginals")


def _diagonal(ax, x: np.ndarray, rng: np.ndarray, bins: int, ref: np.ndarray | None) -> None:
    edges = np.linspace(rng[0], rng[1], bins + 1)
    width = edges[1] - edges[0]
    h = np.histogram(x, bins=edges)[0] / (x.size * width)
    ax.stairs(h, edges, fill=True, color=MAIN["fill"], alpha=0.85)
    top = h.max()
    if ref is not None:
        hr = np.histogram(ref, bins=edges)[0] / (ref.size * width)
        ax.stairs(hr, edges, color=OTHER["line"], linewidth=1.6)
        top = max(top, hr.max())
    ax.set_ylim(0, 1.08 * top if top > 0 else 1.0)


def _pair(ax, x, y, xr, yr, levels: np.ndarray, bins: int, smooth: float, colour: str, image: bool) -> None:
    xe, ye, mass = grid_density(x, y, tuple(xr), tuple(yr), bins, smooth)
    if image:
        ax.pcolormesh(xe, ye, mass.T, cmap=MAIN["cmap"], shading="flat", rasterized=True)
    thresholds = grid_hdr_thresholds(mass, levels)  # decreasing as levels increase
    styles = {}
    for k, t in enumerate(thresholds):
        if t > 0 and t not in styles:
            styles[t] = LINESTYLES[k % len(LINESTYLES)]
    if not styles:
        return
    ordered = sorted(styles)
    xc, yc = 0.5 * (xe[:-1] + xe[1:]), 0.5 * (ye[:-1] + ye[1:])
    ax.contour(xc, yc, mass.T, levels=ordered, colors=colour, linestyles=[styles[t] for t in ordered], linewidths=1.2)
