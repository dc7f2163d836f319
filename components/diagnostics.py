"""Calibration diagnostics of predicted weather distributions: HPD credibility, expected coverage, superiority π.

Notation of the paper: an image i with ground-truth weather w* (the θ of the simulator), the predicted
distribution P̂(W | I = i) with density p̂(w | i), and a credible level l ∈ [0, 1]. The highest-density (HPD)
credible region at level l is the set of weathers {w : p̂(w | i) ≥ t_l(i)} whose predicted probability is l.

Everything is estimated from posterior samples w₁…w_S ~ P̂(W | I = i) and their log-densities, so it works
for any model exposing ``sample_and_log_prob`` and ``log_prob`` (torch or ONNX runtime). Arrays may be numpy
arrays or CPU tensors; results are numpy float64.

* credibility α(i) = P̂(p̂(W | i) ≥ p̂(w* | i)): the smallest level l whose HPD region contains w*;
* expected coverage c(l) = E_i[1(α(i) ≤ l)] (Hermans et al., 2022): the probability that w* lies in the HPD
  region at level l. Calibrated: c(l) = l (α is uniform on [0, 1]); overconfident (too narrow): c(l) < l;
  underconfident (conservative, too wide): c(l) > l;
* superiority of the ground truth π(i) = P̂(p̂(W | i) ≤ p̂(w* | i)): the share of drawn weathers no more
  credible than w* (the paper's Fig. "superiority"); π ≈ 1 − α, uniform on [0, 1] for the exact posterior.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "hpd_credibility",
    "superiority",
    "expected_coverage",
    "calibration_error",
    "coverage_error",
    "DEFAULT_LEVELS",
]

#: The credible levels of coverage plots: 0, 0.01, …, 1.
DEFAULT_LEVELS: np.ndarray = np.linspace(0.0, 1.0, 101)


def _pair(log_prob_samples: object, log_prob_truth: object) -> tuple[np.ndarray, np.ndarray]:
    s = np.asarray(log_prob_samples, dtype=np.float64)
    t = np.asarray(log_prob_truth, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] == 0:
        raise ValueError(f"log_prob_samples must have shape (n_obs, n_samples) with n_samples >= 1, got {s.shape}")
    if t.shape != (s.shape[0],):
        raise ValueError(f"log_prob_truth must have shape (n_obs,) = ({s.shape[0]},), got {t.shape}")
    if np.isnan(s).any() or np.isnan(t).any():
        raise ValueError("log-densities contain NaN")
    return s, t


def hpd_credibility(log_prob_samples: object, log_prob_truth: object) -> np.ndarray:
    """α(i): the share of posterior samples at least as dense as the ground truth.

    Arguments:
        log_prob_samples: ``(n_obs, n_samples)``, log p̂(w_s | i) of samples w_s ~ P̂(W | I = i).
        log_prob_truth: ``(n_obs,)``, log p̂(w* | i) of the ground truth of each image.

    Returns:
        ``(n_obs,)`` in [0, 1]: the smallest credible level whose HPD region contains w* (0: w* is denser than
        every sample; 1: every sample is at least as dense).
    """
    s, t = _pair(log_prob_samples, log_prob_truth)
    return (s >= t[:, None]).mean(axis=1)


def superiority(log_prob_samples: object, log_prob_truth: object) -> np.ndarray:
    """π(i): the share of posterior samples whose density is ≤ the ground truth's (higher is better).

    Arguments and shapes as :func:`hpd_credibility`; returns ``(n_obs,)`` in [0, 1].
    """
    s, t = _pair(log_prob_samples, log_prob_truth)
    return (s <= t[:, None]).mean(axis=1)


def _credibility(credibility: object) -> np.ndarray:
    a = np.asarray(credibility, dtype=np.float64)
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"credibility must be a non-empty 1-D array (one α per image), got shape {a.shape}")
    if np.isnan(a).any() or (a < 0).any() or (a > 1).any():
        raise ValueError("credibility values must lie in [0, 1]")
    return a


def _levels(levels: object) -> np.ndarray:
    lv = np.asarray(levels, dtype=np.float64)
    if lv.ndim != 1 or lv.size == 0 or np.isnan(lv).any() or (lv < 0).any() or (lv > 1).any():
        raise ValueError(f"credible levels must be a non-empty 1-D array in [0, 1], got {lv!r}")
    return lv


def expected_coverage(credibility: object, levels: object = DEFAULT_LEVELS) -> np.ndarray:
    """c(l) = (1/n) Σᵢ 1(α(i) ≤ l), the empirical expected coverage of the HPD regions.

    Arguments:
        credibility: ``(n_obs,)`` α(i) of :func:`hpd_credibility`.
        levels: credible levels l, shape ``(L,)`` in [0, 1].

    Returns:
        ``(L,)`` coverages in [0, 1].
    """
    a = np.sort(_credibility(credibility))
    lv = _levels(levels)
    return np.searchsorted(a, lv, side="right") / a.size


def _deviation(credibility: object, levels: object | None) -> tuple[np.ndarray, np.ndarray]:
    """Signed deviations c(l) − l at the levels, or at every jump of c (both one-sided limits) when ``levels`` is None."""
    a = np.sort(_credibility(credibility))
    if levels is not None:
        lv = _levels(levels)
        return lv, np.searchsorted(a, lv, side="right") / a.size - lv
    n = a.size
    above = np.arange(1, n + 1) / n - a  # c just at/after each jump
    below = np.arange(0, n) / n - a  # c just before each jump
    return np.concatenate([a, a]), np.concatenate([above, below])


def calibration_error(credibility: object, levels: object | None = None) -> float:
    """max_l |c(l) − l|: 0 for a perfectly calibrated model, at most 1.

    With ``levels=None`` the supremum over all l ∈ [0, 1] is exact (the Kolmogorov–Smirnov distance between the
    α(i) and the uniform distribution); with levels, the maximum over those levels.
    """
    _, dev = _deviation(credibility, levels)
    return float(np.abs(dev).max())


def coverage_error(credibility: object, levels: object | None = None) -> float:
    """The deviation c(l) − l of largest magnitude, with its sign: < 0 overconfident, > 0 underconfident.

    ``abs(coverage_error(...)) == calibration_error(...)``; ``levels`` as in :func:`calibration_error`.
    """
    _, dev = _deviation(credibility, levels)
    return float(dev[np.argmax(np.abs(dev))])
