"""Task I per parameter and true value: where a posterior is sharp, and where it is honest instead.

The figures of :mod:`components.evaluate.marginals` are averages over the test images, but the images do not show
every weather equally well: the sun's altitude near the horizon far better than near the zenith, where the exposure
evens out the brightness; puddles on a dry or a flooded road better than half-covered ones; nothing of the clouds at
night. This module splits the same per-image scores (:class:`~components.evaluate.marginals.MarginalScores`) by the
parameter's true value θₖ*. For the images whose θₖ* lies in each of B equal-width bins of the prior range
[lowₖ, highₖ], and for all, day and night truths (:func:`~components.evaluate.marginals.subset_masks`):

* the median |median − truth| (physical units), with its distribution-free 95 % interval;
* the mean width of the central 68 % interval (physical units);
* the 68 % interval's coverage with its Clopper–Pearson 95 % interval;
* beside them what the prior alone would give on the same images: its median, the centre of the range, misses θₖ* by
  |centre − θₖ*|, and its central 68 % interval is 0.68 of the range wide. A posterior far below these is sharp; one
  that stays near them is saying that the image does not tell.

Calibration promises 68 % coverage on average over the prior, not in each bin of the truth. Where the posterior is sharp
and the truth away from the faces of the box, the coverage in a bin should be near 68 %. Where the image tells little,
an honest posterior's interval stays near the middle of the range: it covers more of the truths there and fewer near
the faces. The prior's own central interval, [16, 84] % of the range, covers every truth in the middle bins and none
in the outer ones.

A bin with no image gives ``None`` in every list (valid JSON). Used by the ``evaluate`` stage (``profiles.json``,
``plots/<model>/profile.png``).
"""

from __future__ import annotations

import numpy as np

from components.core.checks import whole_number
from components.core.weather import Box
from components.evaluate.marginals import MarginalScores, parameter_figures, subset_masks

__all__ = ["MASS", "FIGURES", "truth_bins", "truth_profile"]

#: The mass of the central interval whose width and coverage are profiled.
MASS = 0.68
#: The per-bin figures of :func:`truth_profile`, each a list over the bins.
FIGURES: tuple[str, ...] = (
    "images",
    "median_abs_error",
    "median_abs_error_low",
    "median_abs_error_high",
    "width68",
    "coverage68",
    "coverage68_low",
    "coverage68_high",
    "prior_median_abs_error",
)


def truth_bins(box: Box, bins: int) -> np.ndarray:
    """The edges ``(d, bins + 1)`` of ``bins`` equal-width bins of each parameter's prior range (physical units)."""
    whole_number("the profile's number of bins", bins, low=1)
    return np.stack([np.linspace(lo, hi, int(bins) + 1) for lo, hi in zip(box.low, box.high, strict=True)])


def _bin_of(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The bin ``(N,)`` of each value of one parameter: bins are closed on the left, the last one on both sides."""
    return np.clip(np.searchsorted(edges, values, side="right") - 1, 0, len(edges) - 2)


def _figures(scores: MarginalScores, j: int, mask: np.ndarray, centre: float, truth: np.ndarray, width: float) -> dict:
    """The :data:`FIGURES` of parameter ``j`` over the images of ``mask (N,)``, one bin's worth: its
    :func:`~components.evaluate.marginals.parameter_figures` (the width in physical units) and the prior's error; None
    for what no image, or too few for an interval, can give."""
    fig = parameter_figures(scores, mask, j)
    fig["width68"] = float(fig["width68"] * width)
    fig["prior_median_abs_error"] = float(np.median(np.abs(centre - truth[mask, j]))) if fig["images"] else np.nan
    return {
        name: (int(fig[name]) if name == "images" else None if np.isnan(fig[name]) else fig[name]) for name in FIGURES
    }


def truth_profile(scores: MarginalScores, truth: object, box: Box, bins: int) -> dict[str, dict[str, dict[str, list]]]:
    """``subset → parameter → figure → list over the bins`` of the truths ``(N, d)`` (physical units) and their
    per-image ``scores`` (:func:`~components.evaluate.marginals.marginal_scores` of the same images), with the bins'
    ``edges`` (``bins + 1`` values) beside the :data:`FIGURES`."""
    t = np.asarray(truth, dtype=np.float64)
    if t.ndim != 2 or t.shape != scores.abs_error.shape:
        raise ValueError(f"truth must have the scores' shape {scores.abs_error.shape}, got {t.shape}")
    if MASS not in scores.masses:
        raise ValueError(f"the scores hold the central intervals {scores.masses}, not the profile's {MASS}")
    edges = truth_bins(box, bins)
    centre = (np.asarray(box.low, dtype=np.float64) + np.asarray(box.high, dtype=np.float64)) / 2
    which = np.stack([_bin_of(t[:, j], edges[j]) for j in range(t.shape[1])], axis=1)
    out: dict[str, dict[str, dict[str, list]]] = {}
    for subset, mask in subset_masks(t, box).items():
        out[subset] = {}
        for j, name in enumerate(box.names):
            per_bin = [
                _figures(scores, j, mask & (which[:, j] == b), centre[j], t, box.width[j])
                for b in range(edges.shape[1] - 1)
            ]
            out[subset][name] = {"edges": edges[j].tolist()} | {f: [fig[f] for fig in per_bin] for f in FIGURES}
    return out
