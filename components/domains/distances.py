"""Distances between two samples of weather, for scoring a characterization p̂_𝒟 against the truth P_𝒟 (Task II).

* :func:`energy_distance_sq` — the squared energy distance (Székely & Rizzo)

      D²(P, Q) = 2 E‖X − Y‖ − E‖X − X′‖ − E‖Y − Y′‖,      X, X′ ~ P,  Y, Y′ ~ Q independent,

  by its *U-statistic* (the within-sample means over distinct pairs i ≠ j). It is unbiased: for two samples of one
  distribution it is 0 up to sampling noise (and may be slightly negative), whereas the V-statistic (all pairs, the
  zero diagonal included) has a positive floor ≈ E‖X − X′‖ (1/n + 1/m) — 0.02–0.06 in prior-width units for a few
  thousand 6-D draws — that hides how close a sharp estimate is.
* :func:`wasserstein_1d` — per parameter, the 1-D Wasserstein-1 distance W₁ = ∫ |F_P(t) − F_Q(t)| dt of the
  marginals (``scipy.stats.wasserstein_distance``), in the parameter's physical unit (% or °).
* :func:`resampled_wasserstein_1d` — the same W₁ for many resamplings of a bag's images (a bootstrap), each one a
  cumulative sum over one sorted order instead of a sort of its own.
* :func:`marginal_hdr` — per parameter, the estimate's highest-density region at a credible level (from a histogram
  of its draws on the prior's range), its total width and the share of another sample inside it.

Everything is numpy/scipy on ``(n, d)`` samples in physical units.

Used by the ``task2`` stage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.distance import cdist
from scipy.stats import wasserstein_distance

from components.core.checks import whole_number

__all__ = ["energy_distance_sq", "wasserstein_1d", "resampled_wasserstein_1d", "MarginalHdr", "marginal_hdr"]

_CHUNK = 2048  # rows of a pairwise-distance block


def _samples(a: object, name: str) -> np.ndarray:
    x = np.asarray(a, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2 or not np.all(np.isfinite(x)):
        raise ValueError(f"{name} must be finite samples of shape (n, d) with n ≥ 2, got shape {x.shape}")
    return x


def _sum_distances(x: np.ndarray, y: np.ndarray) -> float:
    """Σᵢⱼ ‖xᵢ − yⱼ‖ over every pair, in blocks of :data:`_CHUNK` rows."""
    return float(sum(cdist(x[i : i + _CHUNK], y).sum() for i in range(0, x.shape[0], _CHUNK)))


def energy_distance_sq(a: object, b: object, scale: object | None = None) -> float:
    """The U-statistic of D²(P, Q) for samples ``a (n, d)`` ~ P and ``b (m, d)`` ~ Q (n, m ≥ 2).

    ``2 · mean‖aᵢ − bⱼ‖ − Σ_{i≠i′}‖aᵢ − aᵢ′‖ / (n(n−1)) − Σ_{j≠j′}‖bⱼ − bⱼ′‖ / (m(m−1))``: unbiased for D², so its
    expectation is 0 when P = Q (sampling noise of order E‖X − X′‖/n either side). ``scale (d,)`` divides each
    coordinate first (e.g. the prior's widths, so that %, degrees… weigh alike); D², a difference of mean distances,
    then has the unit of a distance in the scaled space (prior widths). O(n·m) time, O(chunk·m) memory.
    """
    x, y = _samples(a, "a"), _samples(b, "b")
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"a and b must have the same dimension, got {x.shape[1]} and {y.shape[1]}")
    if scale is not None:
        s = np.asarray(scale, dtype=np.float64)
        if s.shape != (x.shape[1],) or not np.all(s > 0):
            raise ValueError(f"scale must be positive of shape ({x.shape[1]},), got {s.shape}")
        x, y = x / s, y / s
    n, m = x.shape[0], y.shape[0]
    xy = _sum_distances(x, y) / (n * m)
    xx = _sum_distances(x, x) / (n * (n - 1))  # the diagonal is zero: the sum is over i ≠ i′
    yy = _sum_distances(y, y) / (m * (m - 1))
    return float(2.0 * xy - xx - yy)


def wasserstein_1d(a: object, b: object) -> np.ndarray:
    """W₁ between the marginals of ``a (n, d)`` and ``b (m, d)``, per parameter → ``(d,)`` (the samples' unit)."""
    x, y = _samples(a, "a"), _samples(b, "b")
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"a and b must have the same dimension, got {x.shape[1]} and {y.shape[1]}")
    return np.array([wasserstein_distance(x[:, k], y[:, k]) for k in range(x.shape[1])])


def resampled_wasserstein_1d(points: object, reference: object, counts: object) -> np.ndarray:
    """W₁ between pooled points resampled by image and a ``reference`` sample, for each of many resamplings.

    ``points (N, n)``: image i's n points of one parameter; ``reference (m,)``; ``counts (R, N)``: how often each image
    is taken in each of R resamplings (non-negative integers, the same positive total in every row, e.g. the
    ``bincount`` of a bootstrap's indices). Row r is the W₁ between the points of the images taken, each as often as
    ``counts[r]`` says, and the reference: ``wasserstein_distance(points[idx].ravel(), reference)`` for the indices idx
    behind that row, up to float rounding (~1e-15). The points and the reference are sorted once; each row is then a
    cumulative sum, O(Nn + m), where a row by itself sorts its Nn + m values.

    Returns ``(R,)`` in the points' unit.
    """
    x = np.asarray(points, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    c = np.asarray(counts)
    if x.ndim != 2 or x.size == 0 or not np.all(np.isfinite(x)):
        raise ValueError(f"points must be finite of shape (N, n), got shape {x.shape}")
    if ref.ndim != 1 or ref.size == 0 or not np.all(np.isfinite(ref)):
        raise ValueError(f"reference must be a finite sample of shape (m,), got shape {ref.shape}")
    if c.ndim != 2 or c.shape[1] != x.shape[0] or not np.issubdtype(c.dtype, np.integer) or np.any(c < 0):
        raise ValueError(f"counts must be non-negative integers of shape (R, {x.shape[0]}), got {c.dtype} {c.shape}")
    totals = c.sum(axis=1)
    if np.any(totals <= 0):
        raise ValueError("every resampling (row of counts) must take at least one image")
    values = np.concatenate([x.ravel(), ref])
    order = np.argsort(values, kind="stable")
    deltas = np.diff(values[order])
    is_ref = order >= x.size
    owner = np.where(is_ref, 0, np.minimum(order, x.size - 1) // x.shape[1])  # the image of each sorted point
    ref_cdf = np.cumsum(is_ref)[:-1] / ref.size
    out = np.empty(c.shape[0])
    for r in range(c.shape[0]):
        weight = np.where(is_ref, 0, c[r][owner])
        cdf = np.cumsum(weight)[:-1] / (totals[r] * x.shape[1])
        out[r] = np.sum(np.abs(cdf - ref_cdf) * deltas)
    return out


@dataclass(frozen=True)
class MarginalHdr:
    """The estimate's highest-density region of one parameter, from a histogram of its draws.

    Attributes:
        level: the credible level (e.g. 0.95).
        width: the HDR's total length (a union of histogram bins), the parameter's unit: small = sharp.
        width_share: ``width`` / the prior's range (1 for an estimate as broad as the uniform prior, about ``level``).
        mass_inside: the share of the other sample (the truth) inside the HDR; ``level`` when it follows the estimate.
    """

    level: float
    width: float
    width_share: float
    mass_inside: float


def marginal_hdr(estimate: object, truth: object, low: float, high: float, level: float, bins: int) -> MarginalHdr:
    """The ``level`` HDR of the 1-D sample ``estimate (S,)`` on ``[low, high]`` and the share of ``truth (n,)`` in it.

    The density is the histogram of ``estimate`` on ``bins`` equal bins of ``[low, high]``; the HDR is the smallest
    set of bins, densest first, that holds at least ``level`` of the draws (ties broken by bin order). A truth value
    on a bin edge belongs to the bin above it (the last edge to the last bin), as in ``numpy.histogram``.
    """
    est = np.asarray(estimate, dtype=np.float64).ravel()
    tru = np.asarray(truth, dtype=np.float64).ravel()
    if est.size == 0 or tru.size == 0 or not (np.all(np.isfinite(est)) and np.all(np.isfinite(tru))):
        raise ValueError("estimate and truth must be non-empty and finite")
    if not 0.0 < float(level) < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    if not (np.isfinite(low) and np.isfinite(high) and low < high):
        raise ValueError(f"need finite low < high, got [{low}, {high}]")
    whole_number("bins", bins, low=2)
    edges = np.linspace(low, high, int(bins) + 1)
    counts = np.histogram(np.clip(est, low, high), bins=edges)[0]
    order = np.argsort(-counts, kind="stable")
    need = int(np.searchsorted(np.cumsum(counts[order]), level * counts.sum() - 1e-9)) + 1
    inside = np.zeros(int(bins), dtype=bool)
    inside[order[:need]] = True
    where = np.clip(np.searchsorted(edges, np.clip(tru, low, high), side="right") - 1, 0, int(bins) - 1)
    width = float(inside.sum() * (high - low) / bins)
    return MarginalHdr(float(level), width, width / float(high - low), float(np.mean(inside[where])))
