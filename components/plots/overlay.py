"""Task II: the six 1-D marginals of the true weather distribution, its estimate and the prior, overlaid.

Each panel shows one parameter on the prior's range: the estimate P̂_D(W) and the prior as step histograms
(probability density per unit of the parameter), the truth P_D(W) likewise — or, for a parameter the truth holds
fixed (a point mass: every draw equal), as a vertical line at its value; optionally a reference estimate (e.g. the
mixture of posteriors beside its deconvolution) dotted. A note per panel (e.g. the Wasserstein distances) goes into
its title. :func:`overlay_marginals` draws any list of weighted samples so (``pidc relate``'s figure too).

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from components.core.checks import whole_number
from components.core.weather import PREDICTED, Box
from components.plots.canvas import new_figure
from components.plots.checks import N_THETA, as_box, as_samples
from components.plots.labels import parameter_label, unit_symbol

__all__ = ["Marginals", "overlay_marginals", "marginals_overlay"]

_COLOURS = ("#d62728", "#1f5fa8", "#7f7f7f", "#2ca02c")  # truth, estimate, prior, reference
_STYLES = ("-", "-", "--", ":")


@dataclass(frozen=True)
class Marginals:
    """One sample's six marginals in an overlay.

    Attributes:
        samples: ``(n, 6)`` draws, physical units.
        weights: ``(n,)`` non-negative per draw, or None (equal).
        label: its legend entry.
        colour: its line's colour.
        style: its line's style.
        width: its line's width.
        point_mass: a parameter whose draws are all equal is drawn as a vertical line at that value (e.g. a truth that
            holds the parameter fixed) instead of a histogram.
    """

    samples: object
    label: str
    colour: str
    style: str = "-"
    width: float = 1.6
    weights: object | None = None
    point_mass: bool = False


def overlay_marginals(
    series: Sequence[Marginals],
    box: Box | None = None,
    notes: Sequence[str] | None = None,
    title: str = "",
    bins: int = 50,
    legend_columns: int | None = None,
) -> Figure:
    """2×3 panels, one per parameter, each with the step histograms (probability density per unit) of every
    :class:`Marginals` of ``series`` on the box's range (default: the physical ranges), drawn in order; ``notes``:
    six strings, one per parameter, as the panel titles; one legend below (``legend_columns`` columns, default one
    per series)."""
    drawn = [(as_samples(m.samples, m.label), m) for m in series]
    weights = []
    for samples, m in drawn:
        w = None if m.weights is None else np.asarray(m.weights, dtype=np.float64)
        if w is not None and (w.shape != samples.shape[:1] or not np.all(np.isfinite(w)) or np.any(w < 0)):
            raise ValueError(f"weights of {m.label!r} must be {samples.shape[0]} non-negative numbers, got {w.shape}")
        weights.append(w)
    b = as_box(box)
    if notes is not None and len(notes) != N_THETA:
        raise ValueError(f"notes must hold one string per parameter ({N_THETA}), got {len(notes)}")
    whole_number("bins", bins, low=2)
    fig = new_figure(12.0, 7.5)
    axes = fig.subplots(2, 3)
    for k, ax in enumerate(axes.ravel()):
        edges = np.linspace(b.low[k], b.high[k], bins + 1)
        for (s, m), w in zip(drawn, weights, strict=True):
            col = s[:, k]
            if m.point_mass and np.ptp(col) == 0.0:  # e.g. the truth holds this parameter fixed
                ax.axvline(col[0], color=m.colour, linewidth=2)
                continue
            density = np.histogram(np.clip(col, b.low[k], b.high[k]), bins=edges, weights=w, density=True)[0]
            ax.stairs(density, edges, color=m.colour, linestyle=m.style, linewidth=m.width)
        ax.set_xlim(b.low[k], b.high[k])
        ax.set_xlabel(parameter_label(k))
        ax.set_ylabel(f"density [1/{unit_symbol(PREDICTED[k])}]")
        ax.ticklabel_format(axis="y", style="plain")  # no offset text: it would collide with a multi-line title
        if notes is not None:
            ax.set_title(notes[k], fontsize=9)
        ax.grid(alpha=0.25)
    handles = [Line2D([], [], color=m.colour, linestyle=m.style, linewidth=m.width, label=m.label) for m in series]
    fig.legend(handles=handles, loc="outside lower center", ncol=legend_columns or len(series), frameon=False)
    fig.suptitle(title)
    return fig


def marginals_overlay(
    truth: object,
    estimate: object,
    prior: object,
    box: Box | None = None,
    labels: tuple[str, str, str] = ("truth P_D(W)", "estimate P̂_D(W)", "prior"),
    notes: Sequence[str] | None = None,
    title: str | None = None,
    bins: int = 50,
    reference: object | None = None,
    reference_label: str = "mixture of posteriors",
) -> Figure:
    """Task II's overlay (:func:`overlay_marginals`): the marginals of ``truth`` (a line where it is fixed),
    ``estimate`` and ``prior`` (``(n, 6)`` samples each, physical units) on the box's range (default: the physical
    ranges), and of ``reference`` (``(n, 6)``, dotted, labelled ``reference_label``) if given. ``notes``: six strings,
    one per parameter, appended to the panel titles."""
    if len(labels) != 3:
        raise ValueError(f"labels must name truth, estimate and prior, got {labels!r}")
    given = [(truth, "truth"), (estimate, "estimate"), (prior, "prior")]
    if reference is not None:
        given.append((reference, "reference"))
        labels = (*labels, reference_label)
    named = [as_samples(x, name) for x, name in given]
    series = [
        Marginals(samples, label, colour, style, point_mass=i == 0)
        for i, (samples, label, colour, style) in enumerate(zip(named, labels, _COLOURS, _STYLES, strict=False))
    ]
    return overlay_marginals(
        series, box, notes, title or "Marginals: truth (a line where it is fixed), estimate and prior", bins
    )
