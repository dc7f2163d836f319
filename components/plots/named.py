"""Named weathers × parameters: a model's 68.27 % HDI coverage beside an exact posterior's on a toy of the same faces."""

from __future__ import annotations

import numpy as np
from matplotlib.colors import TwoSlopeNorm
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from components.core.weather import SHORT_NAMES
from components.plots.canvas import new_figure

__all__ = ["named_heatmap"]

#: the nominal mass of the intervals counted (the colour map's centre)
NOMINAL = 0.6827


def named_heatmap(rows: list[dict], level: float, title: str) -> Figure:
    """Two heatmaps weathers × parameters: the model's 68 % coverage (a cell below or above the 95 % range of a
    correct model's coverage on as many images marked − or +; a cell whose marginal L-C2ST rejects the weather's
    images as a set at ``level`` outlined) and the exact toy's.

    Arguments:
        rows: :func:`components.evaluate.named.weather_row` results, each with ``lc2st`` (per parameter ``p_value``).
        level: the L-C2ST's α.
        title: the figure's title (the model).
    """
    names = [r["weather"] for r in rows]
    parameters = list(rows[0]["parameters"])
    fig = new_figure(13, 0.36 * len(rows) + 1.8)
    axes = fig.subplots(1, 2, sharey=True)
    titles = ("model (− / + outside a correct model's range; box: L-C2ST rejects)", "exact posterior, same faces")
    im = None
    for ax, key, sub in zip(axes, ("coverage68", "toy68"), titles, strict=True):
        c = np.array([[r["parameters"][p][key] for p in parameters] for r in rows])
        im = ax.imshow(c, cmap="RdBu", norm=TwoSlopeNorm(NOMINAL, 0.0, 1.0), aspect="auto")
        for i, r in enumerate(rows):
            for j, p in enumerate(parameters):
                cell, mark = r["parameters"][p], ""
                if key == "coverage68":
                    mark = "−" if cell["below"] else "+" if cell["above"] else ""
                    if r["lc2st"][p]["p_value"] <= level:
                        ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, lw=1.6, ec="black"))
                ax.text(j, i, f"{c[i, j]:.2f}{mark}", ha="center", va="center", fontsize=7)
        ax.set_xticks(range(len(parameters)), SHORT_NAMES[: len(parameters)])
        ax.set_title(f"68.27 % HDI coverage — {sub}", fontsize=9)
    axes[0].set_yticks(range(len(names)), names, fontsize=8)
    fig.colorbar(im, ax=axes, shrink=0.6, label="coverage (nominal 0.683)")
    fig.suptitle(title, fontsize=10)
    return fig
