"""Paper, Task I, 1st analysis: the 6 marginal histograms of a predicted weather distribution, HDR highlighted.

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from components.core.checks import whole_number
from components.core.weather import PREDICTED, Box
from components.plots.canvas import new_figure
from components.plots.checks import N_THETA, as_box, as_log_prob, as_samples, as_truth
from components.plots.hdr import in_hdr
from components.plots.labels import parameter_label, unit_symbol

__all__ = ["marginal_hdr_histograms", "marginal_histograms"]

HDR_COLOUR = "#1f5fa8"
OUTSIDE_COLOUR = "#b9cde5"
TRUTH_COLOUR = "#d62728"


def marginal_hdr_histograms(
    samples: object, log_prob: object, level: float = 0.6827, box: Box | None = None, bins: int = 40
) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """The numbers behind :func:`marginal_histograms`.

    Arguments:
        samples: ``(n, 6)`` θ_j ~ P̂(W | I = i), physical units.
        log_prob: ``(n,)`` log p̂(θ_j | i).
        level: credible level α of the highlighted HDR.
        box: the histogram ranges (default: physical ranges).
        bins: histogram bins per parameter.

    Returns:
        ``(edges, inside, outside)``: ``edges[k]`` is the ``(bins+1,)`` bin edges of θ_k; ``inside`` and
        ``outside`` have shape ``(6, bins)``: the probability mass (fraction of all n samples) of each bin
        coming from samples inside / outside the HDR at level α (so ``inside.sum(1) ≈ α``).
    """
    theta = as_samples(samples)
    lp = as_log_prob(log_prob, theta.shape[0])
    b = as_box(box)
    whole_number("bins", bins, low=2)
    mask = in_hdr(lp, level)
    n = theta.shape[0]
    edges, inside, outside = [], np.zeros((N_THETA, bins)), np.zeros((N_THETA, bins))
    for k in range(N_THETA):
        e = np.linspace(b.low[k], b.high[k], bins + 1)
        inside[k] = np.histogram(theta[mask, k], bins=e)[0] / n
        outside[k] = np.histogram(theta[~mask, k], bins=e)[0] / n
        edges.append(e)
    return edges, inside, outside


def marginal_histograms(
    samples: object,
    log_prob: object,
    truth: object | None = None,
    level: float = 0.6827,
    box: Box | None = None,
    bins: int = 40,
) -> Figure:
    """2×3 histograms of the 6 marginals of P̂(W | I = i), the HDR at ``level`` highlighted.

    Each bar is stacked: the density coming from samples inside the HDR {θ : p̂(θ | i) ≥ t_α} in a strong
    colour, the rest in a light one. The HDR is the joint, 6-D one (the paper's: the weathers whose density is
    above t_α), so a bin of one marginal can hold draws inside and outside it; a marginal's own highest-density
    interval (``pidc characterize``'s table) is another set (bars are probability densities per unit of the parameter, so the total
    area of a panel is the share of samples inside the box, ≈ 1). The ground truth θ* (``(6,)``) is a
    vertical line. Shapes as in :func:`marginal_hdr_histograms`.
    """
    b = as_box(box)
    edges, inside, outside = marginal_hdr_histograms(samples, log_prob, level, b, bins)
    t = as_truth(truth)
    fig = new_figure(11.0, 6.4)
    axes = fig.subplots(2, 3)
    for k, ax in enumerate(axes.ravel()):
        e = edges[k]
        width = np.diff(e)
        ax.bar(e[:-1], inside[k] / width, width=width, align="edge", color=HDR_COLOUR, linewidth=0)
        ax.bar(
            e[:-1],
            outside[k] / width,
            width=width,
            bottom=inside[k] / width,
            align="edge",
            color=OUTSIDE_COLOUR,
            linewidth=0,
        )
        if t is not None:
            ax.axvline(t[k], color=TRUTH_COLOUR, linewidth=2)
        ax.set_xlim(b.low[k], b.high[k])
        ax.set_xlabel(parameter_label(k))
        ax.set_ylabel(f"density [1/{unit_symbol(PREDICTED[k])}]")
        ax.ticklabel_format(axis="y", style="sci", scilimits=(-2, 3))
    handles = [
        Patch(color=HDR_COLOUR, label=f"draws in the joint {100 * level:.2f} % HDR"),
        Patch(color=OUTSIDE_COLOUR, label="draws outside it"),
    ]
    if t is not None:
        handles.append(Patch(color=TRUTH_COLOUR, label="ground truth"))
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), frameon=False)
    fig.suptitle(
        "Marginals of the predicted weather distribution\nin dark, the draws inside its joint "
        f"{100 * level:.2f} % highest-density region (all six parameters at once)"
    )
    return fig
