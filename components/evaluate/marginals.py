"""Task I per parameter: how well each marginal of a posterior locates its parameter, from posterior draws.

For test image xᵢ with true weather θᵢ* and draws θᵢⱼ ~ q(θ | xᵢ) (j = 1…n, physical units), per parameter k:

* central interval of mass m (68 % and 95 %): the (1 − m)/2 and (1 + m)/2 quantiles of the draws θᵢⱼₖ; its width as
  a share of the prior range [lowₖ, highₖ] (sharpness) and whether it holds θᵢₖ* (coverage: m for the exact
  posterior, less when overconfident);
* |median − truth|: the draws' median against θᵢₖ*, in the parameter's unit (% or °);
* marginal information gain: log qₖ(θᵢₖ* | xᵢ) − log pₖ(θᵢₖ*), the log-ratio of the marginal posterior density to the
  uniform prior's 1/(highₖ − lowₖ), in nats (its mean is a proper log score; 0 for a posterior equal to the prior).

The marginal density qₖ is not available in closed form (the flow's density is joint), so it is estimated from the
draws by a Gaussian kernel density estimate reflected at the box faces (Silverman 1986, §2.10; Jones 1993):

    q̂ₖ(t) = 1/(n h) Σⱼ [φ((t − θⱼ)/h) + φ((t − (2 low − θⱼ))/h) + φ((t − (2 high − θⱼ))/h)],   t ∈ [low, high],

with Silverman's rule h = 0.9 · min(σ̂, IQR/1.349) · n^(−1/5) per image and parameter (floored at 1e-4 of the range).

n draws cannot resolve a density below about 1/n of the prior's: a truth beyond every draw gets from the Gaussian
kernel's tail a log-density that says more about h than about the posterior (−3 600 nats for one test image of
cues-50000, whose precipitation draws all lie below 2 % against a truth of 10 %: that one image moved the mean over
2 000 images by 1.8 nats). The information gain is therefore that of the defensive mixture (Hesterberg 1995)

    q̃ₖ = (1 − 1/n) q̂ₖ + (1/n) pₖ,   log q̃ₖ(t) − log pₖ(t) = log((1 − 1/n) q̂ₖ(t)/pₖ(t) + 1/n)  ≥ −log n,

so a truth the draws miss entirely costs log n nats (6.2 at n = 500), the most n draws can attest. Where the draws
do resolve the truth the change is about (pₖ/q̂ₖ − 1)/n nats (q̂ₖ/pₖ ≫ 1/n); a flat marginal keeps exactly 0.
The reflections put back the kernel mass that would leak out of the box, so a flat marginal (a parameter the image
does not inform) is estimated without the halving at the faces a plain KDE suffers: its information gain is ≈ 0 up
to the truth's position. For a Gaussian marginal of sd σ, the smoothing by h ≈ 0.23 σ (n = 1000) biases the
expected log-density at the truth by ≈ −6·10⁻⁴ nats (second order in h/σ); at a face where the density's slope is not
zero the reflection leaves an O(h) bias.

Every figure is reported for all images and split by the truth into day (sun_altitude_angle > 0°) and night; each
coverage with its exact binomial (Clopper–Pearson) interval and each median error with its distribution-free interval
from order statistics, both at 95 % (``…_low``, ``…_high``): a reader sees whether 62 % against a target of 63 % is a
miss or noise.

Used by the ``evaluate`` stage.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import scipy.stats

from components.core.weather import Box

__all__ = [
    "MASSES",
    "SUBSETS",
    "FIGURES",
    "SUN",
    "CONFIDENCE",
    "MarginalScores",
    "silverman_bandwidth",
    "reflected_kde_log_density",
    "marginal_scores",
    "subset_masks",
    "coverage_interval",
    "median_interval",
    "parameter_figures",
    "summarize_scores",
    "summarize_subsets",
    "parameter_report",
    "flat_errors",
]

#: The credible masses of the central intervals.
MASSES: tuple[float, ...] = (0.68, 0.95)
#: The image subsets: every image, daytime truths (sun above the horizon) and night-time ones.
SUBSETS: tuple[str, ...] = ("all", "day", "night")
#: The per-parameter figures of :func:`summarize_scores`, in order.
FIGURES: tuple[str, ...] = (
    "images",
    "width68",
    "width95",
    "coverage68",
    "coverage68_low",
    "coverage68_high",
    "coverage95",
    "coverage95_low",
    "coverage95_high",
    "median_abs_error",
    "median_abs_error_low",
    "median_abs_error_high",
    "info_gain_nats",
)
#: The confidence of the intervals reported beside a coverage and a median error (``…_low``, ``…_high``).
CONFIDENCE = 0.95
#: The parameter whose truth splits day (> 0°) from night.
SUN = "sun_altitude_angle"
#: The smallest kernel bandwidth, as a share of the prior range (draws that coincide).
_MIN_BANDWIDTH = 1e-4
#: Images per block: every score is computed block by block on sorted draws (cache-sized working memory).
_BLOCK = 32


@dataclass(frozen=True)
class MarginalScores:
    """Per image and parameter scores of posterior draws against the truth (:func:`marginal_scores`).

    Attributes:
        masses: the central intervals' masses ``(M,)``.
        width: ``(M, N, d)`` the intervals' widths as shares of the prior ranges.
        covered: ``(M, N, d)`` bool, the interval holds the truth.
        abs_error: ``(N, d)`` |median − truth| in physical units.
        log_ratio: ``(N, d)`` log q̃ₖ(θₖ* | x) − log pₖ(θₖ*) in nats, q̃ₖ the KDE mixed with the prior at weight 1/n
            (at least −log n; module docstring).
    """

    masses: tuple[float, ...]
    width: np.ndarray
    covered: np.ndarray
    abs_error: np.ndarray
    log_ratio: np.ndarray


def _check_samples(samples: object, box: Box) -> np.ndarray:
    s = np.asarray(samples, dtype=np.float64)
    if s.ndim != 3 or s.shape[1] < 2 or s.shape[2] != box.dim:
        raise ValueError(f"samples must have shape (N, n, {box.dim}) with n >= 2, got {s.shape}")
    if not (np.isfinite(s).all() and box.contains(s).all()):
        raise ValueError("samples must be finite and lie inside the box")
    return s


def _check(samples: object, truth: object, box: Box) -> tuple[np.ndarray, np.ndarray]:
    s = _check_samples(samples, box)
    t = np.asarray(truth, dtype=np.float64)
    if t.shape != (s.shape[0], box.dim):
        raise ValueError(f"truth must have shape ({s.shape[0]}, {box.dim}), one θ per image, got {t.shape}")
    if not (np.isfinite(t).all() and box.contains(t).all()):
        raise ValueError("truth must be finite and lie inside the box")
    return s, t


def _sorted_blocks(s: np.ndarray):
    """``(start, draws)`` per block of images: the draws ``(b, d, n)`` sorted along the last axis."""
    for a in range(0, s.shape[0], _BLOCK):
        yield a, np.sort(s[a : a + _BLOCK].transpose(0, 2, 1), axis=-1)


def _quantile(sorted_draws: np.ndarray, q: float) -> np.ndarray:
    """The q-quantile along the last axis of sorted draws (numpy's default, linear interpolation)."""
    n = sorted_draws.shape[-1]
    pos = q * (n - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, n - 1)
    return sorted_draws[..., lo] + (pos - lo) * (sorted_draws[..., hi] - sorted_draws[..., lo])


def _bandwidth(sorted_draws: np.ndarray, width: np.ndarray) -> np.ndarray:
    n = sorted_draws.shape[-1]
    sd = sorted_draws.std(axis=-1, ddof=1)
    iqr = (_quantile(sorted_draws, 0.75) - _quantile(sorted_draws, 0.25)) / 1.349
    spread = np.where(iqr > 0, np.minimum(sd, iqr), sd)
    return np.maximum(0.9 * spread * n ** (-0.2), _MIN_BANDWIDTH * width)


def _kde_log_density(draws: np.ndarray, points: np.ndarray, h: np.ndarray, box: Box) -> np.ndarray:
    """Reflected Gaussian KDE of ``draws (b, d, n)`` with bandwidths ``h (b, d)`` at ``points (b, d)`` → ``(b, d)``."""
    n = draws.shape[-1]
    low, high = box.low[None, :, None], box.high[None, :, None]
    t, inv = points[:, :, None], 1.0 / h[:, :, None]
    # standardized distances to the kernel centres: the draws and their mirror images in the two faces
    terms = [(t - draws) * inv, (t + draws - 2 * low) * inv, (2 * high - draws - t) * inv]
    for u in terms:
        np.square(u, out=u)
    nearest = np.minimum(np.minimum(terms[0].min(-1), terms[1].min(-1)), terms[2].min(-1))
    total = np.zeros(points.shape)
    for u in terms:  # log-sum-exp: Σ exp(−u²/2) = exp(−m/2) Σ exp(−(u² − m)/2), m the smallest u²
        u -= nearest[:, :, None]
        u *= -0.5
        total += np.exp(u, out=u).sum(-1)
    return -0.5 * nearest + np.log(total) - np.log(n * h * np.sqrt(2 * np.pi))


def silverman_bandwidth(samples: object, box: Box) -> np.ndarray:
    """Silverman's rule of thumb per image and parameter of ``samples (N, n, d)`` → ``(N, d)``, physical units:
    h = 0.9 · min(σ̂, IQR/1.349) · n^(−1/5) (σ̂ alone when the IQR is 0), at least 1e-4 of the prior range."""
    s = _check_samples(samples, box)
    return np.concatenate([_bandwidth(a, box.width) for _, a in _sorted_blocks(s)])


def reflected_kde_log_density(samples: object, points: object, box: Box, bandwidth: object | None = None) -> np.ndarray:
    """log q̂ₖ(pointᵢₖ): each image's marginal densities estimated from its draws, at one point per image.

    Arguments:
        samples: ``(N, n, d)`` draws per image, inside ``box`` (physical units).
        points: ``(N, d)`` where to evaluate (e.g. the truths), inside ``box``.
        box: the prior box whose faces reflect the kernels.
        bandwidth: ``(N, d)`` kernel standard deviations (physical units); default :func:`silverman_bandwidth`.

    Returns:
        ``(N, d)`` log-densities per unit of each parameter (nats; finite for any finite distance: log-sum-exp).
    """
    s, t = _check(samples, points, box)
    h = None if bandwidth is None else np.asarray(bandwidth, dtype=np.float64)
    if h is not None and (h.shape != t.shape or not (h > 0).all()):
        raise ValueError(f"bandwidth must be positive of shape {t.shape}, got {h.shape}")
    out = np.empty(t.shape)
    for a, draws in _sorted_blocks(s):
        hb = _bandwidth(draws, box.width) if h is None else h[a : a + draws.shape[0]]
        out[a : a + draws.shape[0]] = _kde_log_density(draws, t[a : a + draws.shape[0]], hb, box)
    return out


def marginal_scores(samples: object, truth: object, box: Box, masses: tuple[float, ...] = MASSES) -> MarginalScores:
    """Central intervals, coverage, median error and marginal information gain of ``samples (N, n, d)`` against
    ``truth (N, d)`` (physical units, inside ``box``); see :class:`MarginalScores`. Time and memory: O(N·n·d), in
    blocks of images (≈ 1 s for 2000 images × 1000 draws × 6 on one core)."""
    s, t = _check(samples, truth, box)
    m = tuple(float(v) for v in masses)
    if not all(0.0 < v < 1.0 for v in m):
        raise ValueError(f"masses must lie in (0, 1), got {masses!r}")
    big_n, d = t.shape
    width = np.empty((len(m), big_n, d))
    covered = np.empty((len(m), big_n, d), dtype=bool)
    abs_error = np.empty((big_n, d))
    log_ratio = np.empty((big_n, d))
    log_prior = -np.log(box.width)
    for a, draws in _sorted_blocks(s):
        rows = slice(a, a + draws.shape[0])
        tb = t[rows]
        for i, mass in enumerate(m):
            low, high = _quantile(draws, (1 - mass) / 2), _quantile(draws, (1 + mass) / 2)
            width[i, rows] = (high - low) / box.width
            covered[i, rows] = (low <= tb) & (tb <= high)
        abs_error[rows] = np.abs(_quantile(draws, 0.5) - tb)
        log_ratio[rows] = _kde_log_density(draws, tb, _bandwidth(draws, box.width), box) - log_prior
    # the defensive mixture with the prior (module docstring): log((1 − 1/n) q̂/p + 1/n), at least −log n
    n = s.shape[1]
    log_ratio = np.logaddexp(np.log1p(-1.0 / n) + log_ratio, -np.log(n))
    return MarginalScores(m, width, covered, abs_error, log_ratio)


def subset_masks(truth: object, box: Box) -> dict[str, np.ndarray]:
    """Boolean masks ``(N,)`` of :data:`SUBSETS` from the truths ``(N, d)``: all, day (true sun altitude > 0°) and night
    (≤ 0°); only ``all`` when the box has no sun altitude."""
    t = np.asarray(truth, dtype=np.float64)
    masks = {"all": np.ones(t.shape[0], dtype=bool)}
    if SUN in box.names:
        day = t[:, box.names.index(SUN)] > 0.0
        masks |= {"day": day, "night": ~day}
    return masks


def coverage_interval(hits: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The Clopper–Pearson (exact binomial) interval of a coverage: ``hits`` truths inside their intervals out of ``n``
    images; it holds the true coverage with probability ≥ ``confidence``. NaNs for n = 0."""
    if n == 0:
        return float("nan"), float("nan")
    ci = scipy.stats.binomtest(int(hits), int(n)).proportion_ci(confidence_level=confidence, method="exact")
    return float(ci.low), float(ci.high)


def median_interval(values: np.ndarray, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The distribution-free interval of a median from order statistics: [v₍ₗ₎, v₍ₙ₋ₗ₊₁₎] with l the largest rank such
    that P(B ≤ l − 1) ≤ (1 − confidence)/2 for B ~ Binomial(n, ½) (the count of values below the true median); it holds
    the median with probability ≥ ``confidence`` whatever the distribution. NaNs where n is too small for one."""
    v = np.sort(np.asarray(values, dtype=np.float64))
    n = v.size
    tail = (1.0 - confidence) / 2
    low_rank = int(scipy.stats.binom.ppf(tail, n, 0.5)) if n else 0  # smallest k with P(B ≤ k) ≥ tail
    if n and scipy.stats.binom.cdf(low_rank, n, 0.5) <= tail:
        low_rank += 1
    if low_rank < 1:
        return float("nan"), float("nan")
    return float(v[low_rank - 1]), float(v[n - low_rank])


def parameter_figures(scores: MarginalScores, mask: np.ndarray, j: int) -> dict[str, float]:
    """The :data:`FIGURES` of parameter ``j`` over the images of ``mask (N,)``: their number, the mean interval widths
    (shares of the prior range), the coverages with their Clopper–Pearson intervals (:func:`coverage_interval`), the
    median |median − truth| (physical units) with its distribution-free interval (:func:`median_interval`) and the mean
    marginal information gain (nats). NaN where no image is in ``mask``."""
    k = int(np.count_nonzero(mask))
    nan = float("nan")
    fig: dict[str, float] = {"images": k}
    for i, mass in enumerate(scores.masses):
        tag = f"{round(100 * mass)}"
        hits = int(np.count_nonzero(scores.covered[i, mask, j]))
        fig[f"width{tag}"] = float(scores.width[i, mask, j].mean()) if k else nan
        fig[f"coverage{tag}"] = hits / k if k else nan
        fig[f"coverage{tag}_low"], fig[f"coverage{tag}_high"] = coverage_interval(hits, k)
    errors = scores.abs_error[mask, j]
    fig["median_abs_error"] = float(np.median(errors)) if k else nan
    fig["median_abs_error_low"], fig["median_abs_error_high"] = median_interval(errors)
    fig["info_gain_nats"] = float(scores.log_ratio[mask, j].mean()) if k else nan
    return {key: fig[key] for key in FIGURES}


def summarize_scores(scores: MarginalScores, mask: np.ndarray, names: tuple[str, ...]) -> dict[str, dict[str, float]]:
    """Per parameter name, its :func:`parameter_figures` over the images of ``mask (N,)``."""
    return {name: parameter_figures(scores, mask, j) for j, name in enumerate(names)}


def summarize_subsets(scores: MarginalScores, truth: object, box: Box) -> dict[str, dict[str, dict[str, float]]]:
    """``subset → parameter → figure``: :func:`summarize_scores` of ``scores`` for every subset of
    :func:`subset_masks` of their truths ``(N, d)`` (physical units)."""
    return {name: summarize_scores(scores, mask, box.names) for name, mask in subset_masks(truth, box).items()}


def parameter_report(samples: object, truth: object, box: Box) -> dict[str, dict[str, dict[str, float]]]:
    """``subset → parameter → figure``: :func:`summarize_subsets` of :func:`marginal_scores` (``samples (N, n, d)``,
    ``truth (N, d)``, physical units)."""
    return summarize_subsets(marginal_scores(samples, truth, box), truth, box)


def flat_errors(report: Mapping[str, Mapping[str, Mapping[str, float]]], short: Mapping[str, str]) -> dict[str, float]:
    """``err_<subset>_<short name>`` → median |median − truth| for the day and night subsets of a
    :func:`parameter_report` (``short``: parameter name → short name, e.g. ``cloudiness → cloud``)."""
    return {
        f"err_{subset}_{short[name]}": figures["median_abs_error"]
        for subset in ("day", "night")
        if subset in report
        for name, figures in report[subset].items()
    }
