"""Highest-density regions (HDR) from samples (Hyndman, 1996), in 6-D and on 2-D grids.

The HDR of a density q at credible level α is R_α = {θ : q(θ) ≥ t_α} with P_q(R_α) = α. From samples
θ_j ~ q with their log-densities log q(θ_j), t_α is the (1 − α) quantile of the log q(θ_j): a fraction α
of the samples has log q ≥ t_α. For a 2-D marginal, whose density is unknown, the density is estimated on a
grid (histogram, lightly smoothed) and the cells are ordered by decreasing density; the threshold is the
density of the cell at which the accumulated mass reaches α ("mass-ordered thresholds").

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter

from components.core.checks import whole_number
from components.plots.checks import as_levels

__all__ = ["hdr_log_threshold", "in_hdr", "grid_density", "grid_hdr_thresholds"]


def hdr_log_threshold(log_prob_samples: object, level: float) -> float:
    """t_α: the log-density threshold of the HDR at ``level`` α, from samples' own log-densities.

    Arguments:
        log_prob_samples: ``(n,)``, log q(θ_j) of samples θ_j ~ q (any units, as long as they are consistent).
        level: the credible level α, strictly inside (0, 1).

    Returns:
        t_α, the (1 − α) quantile (linear interpolation) of the log-densities: θ is in the HDR iff log q(θ) ≥ t_α.

    Raises:
        ValueError: a level outside (0, 1); not a 1-D array of finite values; fewer than ⌈1/(1 − α)⌉ samples
            (with fewer, not even one sample is expected outside the HDR and the quantile is meaningless).
    """
    (alpha,) = as_levels(level, name="level")
    lp = np.asarray(log_prob_samples, dtype=np.float64)
    if lp.ndim != 1:
        raise ValueError(f"log_prob_samples must have shape (n,), got {lp.shape}")
    if not np.isfinite(lp).all():
        raise ValueError("log_prob_samples contains non-finite log-densities (NaN or ±inf)")
    needed = math.ceil(1.0 / (1.0 - alpha) - 1e-9)
    if lp.size < needed:
        raise ValueError(f"the HDR at level {alpha:g} needs at least {needed} samples (⌈1/(1 − level)⌉), got {lp.size}")
    return float(np.quantile(lp, 1.0 - alpha))


def in_hdr(log_prob_samples: object, level: float) -> np.ndarray:
    """Boolean mask ``(n,)``: which samples lie in the HDR at ``level`` (log q(θ_j) ≥ t_α)."""
    t = hdr_log_threshold(log_prob_samples, level)
    return np.asarray(log_prob_samples, dtype=np.float64) >= t


def grid_density(
    x: np.ndarray,
    y: np.ndarray,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    bins: int = 40,
    smooth: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 2-D marginal on a grid: the probability mass of each cell, from samples.

    Arguments:
        x: ``(n,)`` first coordinates of the samples (physical units).
        y: ``(n,)`` second coordinates of the samples (physical units).
        x_range: the grid's extent along x; samples outside it count in the total but in no cell.
        y_range: the grid's extent along y.
        bins: cells per axis.
        smooth: standard deviation, in cells, of the Gaussian smoothing of the histogram (0: none). The
            smoothing keeps the mass that falls inside the grid.

    Returns:
        ``(x_edges (bins+1,), y_edges (bins+1,), mass (bins, bins))`` with ``mass[i, j]`` the estimated
        probability of cell (x_i, y_j); ``mass.sum()`` is the fraction of samples inside the grid.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.ndim != 1 or x.shape != y.shape or x.size == 0:
        raise ValueError(f"x and y must be non-empty 1-D arrays of one shape, got {x.shape} and {y.shape}")
    whole_number("bins", bins, low=2)
    if not smooth >= 0:
        raise ValueError(f"smooth must be >= 0 cells, got {smooth!r}")
    for name, (lo, hi) in (("x_range", x_range), ("y_range", y_range)):
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ValueError(f"{name} must be finite with low < high, got ({lo}, {hi})")
    counts, xe, ye = np.histogram2d(x, y, bins=bins, range=[x_range, y_range])
    mass = counts / x.size
    if smooth > 0 and mass.sum() > 0:
        inside = mass.sum()
        mass = _gaussian_smooth(mass, smooth)
        mass *= inside / mass.sum()
    return xe, ye, mass


def _gaussian_smooth(a: np.ndarray, sigma: float) -> np.ndarray:
    """Separable Gaussian smoothing (zero padding) of a 2-D array; sigma in cells, kernel cut at ⌈3σ⌉ cells (≥ 1)."""
    return gaussian_filter(a, sigma, mode="constant", cval=0.0, radius=max(1, math.ceil(3 * sigma)))


def grid_hdr_thresholds(mass: np.ndarray, levels: object) -> np.ndarray:
    """Mass-ordered HDR thresholds of a gridded density.

    Arguments:
        mass: cell probabilities (any shape, non-negative; their sum is the mass on the grid, ≤ 1).
        levels: credible levels α, strictly inside (0, 1).

    Returns:
        ``(L,)`` thresholds in the order of the sorted levels (decreasing thresholds): the region
        {cells : mass ≥ t_α} is the smallest set of cells holding at least α of the total probability
        (α of 1, not of the grid's share, so a grid that clips some mass gives a wider region).
    """
    lv = as_levels(levels)
    m = np.asarray(mass, dtype=np.float64).ravel()
    if m.size == 0 or not np.isfinite(m).all() or (m < 0).any():
        raise ValueError("mass must be a non-empty array of non-negative finite cell probabilities")
    order = np.sort(m)[::-1]
    cumulative = np.cumsum(order)
    idx = np.searchsorted(cumulative, lv, side="left")
    idx = np.minimum(idx, m.size - 1)
    return order[idx]
