"""Task II: the six 1-D marginals of the true weather distribution, its estimate and the prior, overlaid.

Each panel shows one parameter on the prior's range: the estimate P̂_D(W) and the prior as step histograms
(probability density per unit of the parameter), the truth P_D(W) likewise — or, for a parameter the truth holds
fixed (a point mass: every draw equal), as a vertical line at its value; optionally a reference estimate (e.g. the
mixture of posteriors beside its deconvolution) dotted. A note per panel (e.g. the Wasserstein distances) goes into
its title.

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from components.core.weather import PREDICTED, Box
from components.plots.canvas import new_figure
from components.plots.checks import N_THETA, as_box, as_samples
from components.plots.labels import parameter_label, unit_symbol

__all__ = ["marginals_overlay"]

_COLOURS = ("#d62728", "#1f5fa8", "#7f7f7f", "#2ca02c")  # truth, estimate, prior, reference
_STYLES = ("-", "-", "--", ":")


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
    """2×3 panels, one per parameter: the marginals of ``truth``, ``estimate`` and ``prior`` (``(n, 6)`` samples each,
    physical units) overlaid on the box's range (default: the physical ranges), and of ``reference`` (``(n, 6)``,
    dotted, labelled ``reference_label``) if given. ``notes``: six strings, one per parameter, appended to the panel
    titles."""
    if len(labels) != 3:
        raise ValueError(f"labels must name truth, estimate and prior, got {labels!r}")
    named = [(truth, "truth"), (estimate, "estimate"), (prior, "prior")]
    if reference is not None:
        named.append((reference, "reference"))
        labels = (*labels, reference_label)
    samples = [as_samples(s, name) for s, name in named]
    b = as_box(box)
    if notes is not None and len(notes) != N_THETA:
        raise ValueError(f"notes must hold one string per parameter ({N_THETA}), got {len(notes)}")
    if not (isinstance(bins, (int, np.integer)) and bins >= 2):
        raise ValueError(f"bins must be an integer >= 2, got {bins!r}")
    fig = new_figure(12.0, 7.5)
    axes = fig.subplots(2, 3)
    for k, ax in enumerate(axes.ravel()):
        edges = np.linspace(b.low[k], b.high[k], bins + 1)
        for s, colour, style in zip(samples, _COLOURS, _STYLES, strict=False):
            col = s[:, k]
            if s is samples[0] and np.ptp(col) == 0.0:  # the truth holds this parameter fixed: a point mass
                ax.axvline(col[0], color=colour, linewidth=2)
                continue
            density = np.histogram(np.clip(col, b.low[k], b.high[k]), bins=edges, density=True)[0]
            ax.stairs(density, edges, color=colour, linestyle=style, linewidth=1.6)
        ax.set_xlim(b.low[k], b.high[k])
        ax.set_xlabel(parameter_label(k))
        ax.set_ylabel(f"density [1/{unit_symbol(PREDICTED[k])}]")
        ax.ticklabel_format(axis="y", style="plain")  # no offset text: it would collide with a multi-line title
        if notes is not None:
            ax.set_title(notes[k], fontsize=9)
        ax.grid(alpha=0.25)
    handles = [
        Line2D([], [], color=c, linestyle=s, linewidth=1.6, label=lab)
        for c, s, lab in zip(_COLOURS, _STYLES, labels, strict=False)
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=len(labels), frameon=False)
    fig.suptitle(title or "Marginals: truth (a line where it is fixed), estimate and prior")
    return fig
