"""Task I per parameter and true value: one model's error and interval width across each parameter's range.

Input: the profile of :func:`components.evaluate.profile.truth_profile` (``subset → parameter → figure → list over
the bins``, with the bins' ``edges``). Two rows of panels, one column per parameter:

* top: the median |posterior median − truth| in each bin of the true value, by day and at night, with its 95 %
  interval, beside the prior's (grey): where the curve meets the prior's, the image does not tell;
* bottom: the mean width of the central 68 % interval in each bin, beside the prior's (grey, 0.68 of the range): how
  sharp the posterior is, for that weather.

The coverage by bin is in the profile's JSON; calibration does not promise 68 % in each bin of the truth
(:mod:`components.evaluate.profile`).

Used (through :mod:`components.plots`) by the ``evaluate`` stage.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from components.core.weather import PREDICTED
from components.plots.canvas import new_figure
from components.plots.labels import parameter_label

__all__ = ["truth_profile_plot"]

_COLOURS = {"day": "tab:orange", "night": "tab:blue", "all": "tab:green"}


def _series(profile: Mapping, subset: str, name: str, key: str) -> np.ndarray:
    try:
        values = profile[subset][name][key]
    except (KeyError, TypeError):
        raise ValueError(f"profile[{subset!r}][{name!r}] lacks {key!r}") from None
    return np.array([np.nan if v is None else float(v) for v in values])


def truth_profile_plot(
    profile: Mapping[str, Mapping[str, Mapping[str, Sequence]]],
    subsets: Sequence[str] = ("day", "night"),
    title: str = "Task I across the true value",
) -> Figure:
    """The profile's figures for ``subsets`` (default: day and night truths) over the six parameters (module docstring).

    Arguments:
        profile: ``subset → parameter name → {"edges", "images", "median_abs_error", …}``.
        subsets: the subsets drawn, one colour each; the prior's error is drawn from ``all`` (every image) where the
            profile has it, else from the first subset.
    """
    if not isinstance(profile, Mapping) or not profile:
        raise ValueError("profile must be a non-empty mapping of subset → parameter → figures")
    subsets = [s for s in subsets if s in profile]
    if not subsets:
        raise ValueError(f"the profile holds the subsets {sorted(profile)}, none of those asked for")
    fig = new_figure(2.6 * len(PREDICTED), 5.6)
    axes = fig.subplots(2, len(PREDICTED), squeeze=False)
    for k, name in enumerate(PREDICTED):
        edges = _series(profile, subsets[0], name, "edges")
        centres = (edges[:-1] + edges[1:]) / 2
        top, bottom = axes[0, k], axes[1, k]
        prior = _series(profile, "all" if "all" in profile else subsets[0], name, "prior_median_abs_error")
        top.plot(centres, prior, color="0.6", linestyle="--", label="prior")
        for j, subset in enumerate(subsets):
            colour = _COLOURS.get(subset, f"C{j}")
            error = _series(profile, subset, name, "median_abs_error")
            low = _series(profile, subset, name, "median_abs_error_low")
            high = _series(profile, subset, name, "median_abs_error_high")
            top.plot(centres, error, marker="o", markersize=3, color=colour, label=subset)
            top.fill_between(centres, low, high, color=colour, alpha=0.2, linewidth=0)
            width = _series(profile, subset, name, "width68")
            bottom.plot(centres, width, marker="o", markersize=3, color=colour, label=subset)
        bottom.axhline(0.68 * (edges[-1] - edges[0]), color="0.6", linestyle="--", label="prior")
        top.set_title(parameter_label(k), fontsize=9)
        top.set_ylim(bottom=0)
        bottom.set_ylim(bottom=0)
        bottom.set_xlabel("true value")
        for ax in (top, bottom):
            ax.set_xlim(edges[0], edges[-1])
            ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("median |median − truth|")
    axes[1, 0].set_ylabel("68 % interval width")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(
        f"{title}: median |median − truth| (95 % interval shaded) and mean width of the central 68 % interval, by "
        "bin of the true value (grey: the prior's)",
        fontsize=10,
    )
    return fig
