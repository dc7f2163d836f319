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
  credible than w* (the paper's Fig. "superiority"); π ≈ 1 − α, uniform on [0, 1] for the exact posterior;
* calibration band: the calibration error a perfectly calibrated model shows on n images by chance alone (its
  q-quantile, simulated): an observed calibration error inside the band is calibrated within noise.

Used by the ``evaluate``, ``task2`` and ``task3`` stages, and through :mod:`components.plots` by the ``train`` stage
and the ``pidc`` CLI.
"""

from __future__ import annotations

import numpy as np

from components.core.checks import whole_number

__all__ = [
    "hpd_credibility",
    "superiority",
    "expected_coverage",
    "calibration_error",
    "calibration_band",
    "coverage_error",
    "hdr_mass",
    "roc_curve",
    "auc_interval",
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


def calibration_band(
    images: int,
    samples: int,
    levels: object | None,
    rng: np.random.Generator,
    quantile: float = 0.95,
    replicates: int = 2000,
) -> float:
    """The ``quantile`` of :func:`calibration_error` for a perfectly calibrated model on ``images`` images.

    For the exact posterior, the ground truth is exchangeable with the ``samples`` draws of its image, so the number
    of draws at least as dense as the truth is uniform on {0, 1, …, samples} and α(i) = K/samples (what
    :func:`hpd_credibility` returns, ties aside): a discrete uniform, iid over images. The band simulates
    ``replicates`` such sets of ``images`` credibilities with ``rng`` and returns the ``quantile`` of their
    calibration error at ``levels`` (None: the supremum over every level) — the metric's own sampling distribution,
    exact up to Monte Carlo error (±√(q(1−q)/replicates) in quantile level). For large n it approaches the
    Kolmogorov–Smirnov quantile (1.36/√n at 95 % for ``levels=None``); the maximum over a grid of levels is a little
    smaller.

    Arguments:
        images: n ≥ 1, images per evaluation.
        samples: S ≥ 1, posterior draws per image.
        levels: the credible levels of the calibration error (as given to :func:`calibration_error`), or None.
        rng: the random stream (seeded by the caller).
        quantile: q in (0, 1), e.g. 0.95.
        replicates: simulated evaluations (≥ 100).

    Returns:
        the band, in [0, 1]: 95 % of perfectly calibrated models have a calibration error ≤ it (for q = 0.95).
    """
    images = whole_number("images", images, low=1, floats=True)
    samples = whole_number("samples", samples, low=1, floats=True)
    if not 0.0 < float(quantile) < 1.0:
        raise ValueError(f"quantile must be in (0, 1), got {quantile!r}")
    replicates = whole_number("replicates", replicates, low=100, floats=True)
    lv = None if levels is None else _levels(levels)
    errors = np.empty(int(replicates))
    for r in range(int(replicates)):
        alpha = rng.integers(0, int(samples) + 1, size=int(images)) / int(samples)
        errors[r] = calibration_error(alpha, lv)
    return float(np.quantile(errors, float(quantile)))


def coverage_error(credibility: object, levels: object | None = None) -> float:
    """The deviation c(l) − l of largest magnitude, with its sign: < 0 overconfident, > 0 underconfident.

    ``abs(coverage_error(...)) == calibration_error(...)``; ``levels`` as in :func:`calibration_error`.
    """
    _, dev = _deviation(credibility, levels)
    return float(dev[np.argmax(np.abs(dev))])


def hdr_mass(log_prob_estimate: object, log_prob_points: object, level: float) -> float:
    """The share of ``points`` inside the estimate's highest-density region at credible ``level``.

    The HDR {θ : p̂(θ) ≥ t} holds ``level`` of p̂'s mass; t is estimated as the (1 − level)-quantile of p̂'s
    log-density at draws from p̂ (``log_prob_estimate (S,)``). ``log_prob_points (n,)``: p̂'s log-density at draws of
    another distribution P (Task II: the true weather distribution); the result estimates P(p̂(W) ≥ t).
    Equals ``level`` in expectation when P = p̂.
    """
    est, pts = (np.asarray(v, dtype=np.float64).ravel() for v in (log_prob_estimate, log_prob_points))
    if not 0.0 < float(level) < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    if est.size == 0 or pts.size == 0 or np.any(np.isnan(est)) or np.any(np.isnan(pts)):
        raise ValueError("log-densities must be non-empty and free of NaN")
    threshold = np.quantile(est, 1.0 - float(level))
    return float(np.mean(pts >= threshold))


def _scores(values: object, name: str) -> np.ndarray:
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"scores[{name!r}] must be an array of numbers, got {type(values).__name__}") from None
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"scores[{name!r}] must be a non-empty 1-D array, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"scores[{name!r}] contains non-finite values")
    return a


def roc_curve(negatives: object, positives: object) -> tuple[np.ndarray, np.ndarray, float]:
    """ROC of the decision "positive when score ≥ s" swept over every threshold s.

    Arguments:
        negatives: ``(m,)`` scores of negative cases (Task III: δ for targets in the ODD, η = 0).
        positives: ``(p,)`` scores of positive cases (δ for targets out of the ODD, η > 0).

    Returns:
        ``(fpr, tpr, auc)``: false- and true-positive rates from (0, 0) to (1, 1) (one point per distinct score,
        ties moving both rates at once), and the area under the curve (trapezoids), which equals the
        Mann–Whitney probability P(score⁺ > score⁻) + ½ P(score⁺ = score⁻).
    """
    neg, pos = _scores(negatives, "negatives"), _scores(positives, "positives")
    scores = np.concatenate([pos, neg])
    is_pos = np.concatenate([np.ones(pos.size), np.zeros(neg.size)])
    order = np.argsort(-scores, kind="mergesort")
    scores, is_pos = scores[order], is_pos[order]
    last_of_tie = np.r_[np.nonzero(np.diff(scores))[0], scores.size - 1]
    tp = np.cumsum(is_pos)[last_of_tie]
    fp = np.cumsum(1 - is_pos)[last_of_tie]
    tpr = np.r_[0.0, tp / pos.size]
    fpr = np.r_[0.0, fp / neg.size]
    auc = float(np.sum(np.diff(fpr) * (tpr[1:] + tpr[:-1]) / 2))
    return fpr, tpr, auc


def auc_interval(auc: float, negatives: int, positives: int, confidence: float = 0.95) -> tuple[float, float]:
    """Confidence interval of an AUC (the Mann–Whitney probability θ = P(score⁺ > score⁻)) from ``negatives`` and
    ``positives`` cases: Newcombe's hybrid score interval (Newcombe 2006, *Statistics in Medicine* 25:559, method 5).

    The limits are the two solutions θ of (θ̂ − θ)² = z² V(θ), with Hanley and McNeil's variance written as a function
    of θ and both sample sizes replaced by N* = (m + n)/2 − 1:

        V(θ) = θ(1 − θ) / (m n) · [1 + (N* − 1) ((1 − θ)/(2 − θ) + θ/(1 + θ))]

    Unlike the Wald or DeLong intervals it does not collapse to a point at θ̂ = 1 (30 against 30 cases, every one
    separated: [0.935, 1]). Checked by simulation on binormal scores (``tests/test_diagnostics.py``): coverage
    0.94–0.98 at 95 % for θ from 0.6 to 0.99 and 15–200 cases per class.

    Returns ``(low, high)`` within [0, 1]; ``ValueError`` for an AUC outside [0, 1], fewer than one case of a class or
    a confidence outside (0, 1).
    """
    from scipy import optimize, stats

    if not 0.0 <= float(auc) <= 1.0:
        raise ValueError(f"auc must lie in [0, 1], got {auc!r}")
    for name, count in (("negatives", negatives), ("positives", positives)):
        whole_number(name, count, low=1, hint=" (a number of cases)")
    if not 0.0 < float(confidence) < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence!r}")
    a, m, n = float(auc), int(negatives), int(positives)
    z2 = float(stats.norm.ppf(0.5 + float(confidence) / 2)) ** 2
    k = (m + n) / 2.0 - 2.0  # N* − 1

    def excess(t: float) -> float:  # (θ̂ − θ)² − z² V(θ): positive outside the interval
        return (a - t) ** 2 - z2 * t * (1.0 - t) / (m * n) * (1.0 + k * ((1.0 - t) / (2.0 - t) + t / (1.0 + t)))

    eps = 1e-12  # the roots at θ̂ = 0 or 1 themselves (V = 0 there) are not limits
    low = optimize.brentq(excess, 0.0, a - eps) if a > eps and excess(0.0) > 0 else 0.0
    high = optimize.brentq(excess, a + eps, 1.0) if a < 1.0 - eps and excess(1.0) > 0 else 1.0
    return float(low), float(high)
