"""Task II beyond the mixture of posteriors: the bag's weather distribution by maximum likelihood (deconvolution).

The mixture p̂_𝒟(θ) = Σᵢ wᵢ q(θ | xᵢ) (:class:`~components.domains.absolute.Domain`) is not the domain's weather
distribution G but G blurred by the estimator's resolution and pulled toward the training prior π: with images
xᵢ ~ p_G(x) = ∫ p(x | θ) dG(θ) and q(θ | x) = p(x | θ) π(θ) / p_π(x), its expectation is ∫ q(θ | x) p_G(x) dx,
which equals G only when G = π. The bag identifies G through its likelihood (Lindsay 1983; the "population" step of
hierarchical inference from posterior draws),

    ℓ(G) = Σᵢ wᵢ log ∫ p(xᵢ | θ) dG(θ) = Σᵢ wᵢ log ∫ q(θ | xᵢ) / π(θ) dG(θ) + const,

whose EM update is G ← Σᵢ wᵢ q_G(θ | xᵢ), q_G(θ | xᵢ) ∝ q(θ | xᵢ) G(θ) / π(θ) the posterior of image i under the prior
G. Started at G = π the first update *is* the mixture of posteriors: the paper's estimate is one EM step, and further
steps deconvolve. Here G lives on a fixed support, the pooled posterior draws θₖ of the bag's images (m per image),
with weights (self-normalized importance sampling: the support is drawn from the equal-weight mixture M), so an EM
step costs two products with the (N, K) matrix of log q(θₖ | xᵢ) and no new flow evaluation:

    vₖ ← vₖ · Σᵢ wᵢ rᵢₖ / Σⱼ vⱼ rᵢⱼ,      rᵢₖ = q(θₖ | xᵢ) / π(θₖ),      v⁽⁰⁾ₖ ∝ π(θₖ) / M(θₖ).

Unrestricted, the maximum of ℓ is discrete (the NPMLE, Lindsay 1983) and EM creeps toward it; the number of steps
is chosen as the one that maximizes the likelihood of held-out images (``folds``-fold cross-validation over the bag;
each fold's support is its training images' draws), so the data say how far to deconvolve: a bag whose images are
uninformative stops near the mixture, a sharp estimator is deconvolved further. The weighted support is turned into
a proper density by a Gaussian kernel (:class:`~components.domains.kernel.KernelDomain`) whose bandwidth is a scale of
Scott's rule chosen by leave-one-image-out likelihood cross-validation on the weighted support.

π is the training prior, uniform on the prior box: rᵢₖ ∝ q(θₖ | xᵢ) inside it, and every draw of the flow lies inside.

Used by the ``task2`` stage (``task2.estimate: deconvolved``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from components.core.seeding import derive_seed, rng
from components.domains.absolute import Domain, _check_count
from components.domains.kernel import KernelDomain

__all__ = ["EmPath", "Deconvolution", "em_path", "select_steps", "one_standard_error", "deconvolve", "kernel_scale"]

#: kernel bandwidths tried, in units of Scott's rule on the weighted support (log-spaced)
KERNEL_SCALES = tuple(float(s) for s in np.round(np.geomspace(0.05, 1.0, 14), 4))
#: support points (drawn by weight) whose leave-one-image-out density scores a bandwidth
QUERIES = 1000


@dataclass(frozen=True)
class EmPath:
    """EM on a fixed support: ``log_v (steps + 1, K)`` normalized log-weights after 0…steps updates (row 0 the prior,
    row 1 the mixture of posteriors); ``log_likelihood (steps + 1,)`` Σᵢ wᵢ log Σₖ vₖ rᵢₖ of the fitted images (up to
    a constant), non-decreasing along the path (EM)."""

    log_v: np.ndarray
    log_likelihood: np.ndarray


def _log_rows(log_r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``exp(log_r − rowmax)`` and the row maxima: each row's largest ratio is 1 (no overflow, rows never all 0)."""
    top = log_r.max(axis=1)
    if not np.all(np.isfinite(top)):
        bad = int(np.flatnonzero(~np.isfinite(top))[0])
        raise ValueError(f"image {bad} gives no support point a positive density: log q(θₖ | xᵢ) is −inf for every k")
    return np.exp(log_r - top[:, None]), top


def em_path(log_r: np.ndarray, image_weights: np.ndarray, log_v0: np.ndarray, steps: int) -> EmPath:
    """``steps`` EM updates of the support weights from ``log_v0 (K,)`` for the images' log ratios ``log_r (N, K)``
    = log q(θₖ | xᵢ) − log π(θₖ) and their weights ``image_weights (N,)`` (summing to 1)."""
    r, top = _log_rows(np.asarray(log_r, dtype=np.float64))
    r_t = np.ascontiguousarray(r.T)
    w = np.asarray(image_weights, dtype=np.float64)
    v = np.exp(log_v0 - logsumexp(log_v0))
    log_v = np.empty((steps + 1, v.size))
    ll = np.empty(steps + 1)
    for s in range(steps + 1):
        fit = r @ v  # (N,) Σₖ vₖ rᵢₖ (scaled by the row maxima)
        ll[s] = float(w @ (np.log(fit) + top))
        with np.errstate(divide="ignore"):
            log_v[s] = np.log(v)
        if s < steps:
            v = v * (r_t @ (w / fit))
            v /= v.sum()
    return EmPath(log_v, ll)


def _proposal_log_v0(log_r: np.ndarray) -> np.ndarray:
    """log v⁽⁰⁾ₖ = −log M(θₖ) (+ const), M the equal-weight mixture of the images whose draws form the support."""
    return -(logsumexp(log_r, axis=0) - math.log(log_r.shape[0]))


def select_steps(
    log_r: np.ndarray, image_weights: np.ndarray, owner: np.ndarray, max_steps: int, folds: int, seed: int
) -> tuple[int, np.ndarray]:
    """The number of EM steps chosen by held-out likelihood, and the held-out log likelihood per image and step
    ``(max_steps + 1,)`` (Σᵢ wᵢ log Σₖ vₖ rᵢₖ with Σ wᵢ = 1, up to a constant, each image scored by the fold that held
    it out).

    ``owner (K,)`` is the image whose posterior drew support point k; fold f fits its training images on their own
    draws only (rows and columns of ``log_r``) and scores the held-out images' rows on those columns. The folds are a
    seeded permutation of the images (stream ``(seed, "deconvolution", "folds")``). The choice is the one-standard-
    error rule (Breiman et al. 1984): the fewest steps whose held-out likelihood is within one standard error (over
    the images) of the best — where the likelihood is flat the estimate is deconvolved no further than the data ask.
    """
    n = log_r.shape[0]
    if not 2 <= folds <= n:
        raise ValueError(f"folds must be between 2 and the number of images ({n}), got {folds}")
    fold_of = rng(seed, "deconvolution", "folds").permutation(n) % folds
    per_image = np.zeros((max_steps + 1, n))  # wᵢ-free held-out log likelihood of image i after s steps
    for f in range(folds):
        train, test = np.flatnonzero(fold_of != f), np.flatnonzero(fold_of == f)
        cols = np.flatnonzero(np.isin(owner, train))
        fit = log_r[np.ix_(train, cols)]
        path = em_path(fit, image_weights[train] / image_weights[train].sum(), _proposal_log_v0(fit), max_steps)
        r, top = _log_rows(log_r[np.ix_(test, cols)])
        with np.errstate(divide="ignore"):
            per_image[:, test] = np.log(np.exp(path.log_v) @ r.T) + top[None, :]
    w = image_weights / image_weights.sum()
    return one_standard_error(per_image, w), per_image @ w


def one_standard_error(per_image: np.ndarray, weights: np.ndarray) -> int:
    """The one-standard-error rule (Breiman et al. 1984) on held-out scores ``per_image (S, N)`` of S candidates (e.g.
    EM steps, simplest first) and N images weighted by ``weights (N,)`` (Σ = 1): the first candidate whose weighted
    mean score is within one standard error of the best's, the error that of the mean of the images' paired
    differences to the best (weighted second moment over N)."""
    n = per_image.shape[1]
    best = int(np.argmax(per_image @ weights))
    diff = per_image - per_image[best][None, :]  # (S, N) per-image differences to the best candidate
    mean = diff @ weights
    se = np.sqrt(np.maximum((diff * diff) @ weights - mean * mean, 0.0) / n)
    return int(np.flatnonzero(mean >= -se)[0])


def kernel_scale(
    support: np.ndarray,
    weights: np.ndarray,
    owner: np.ndarray,
    scott: np.ndarray,
    scales: tuple[float, ...],
    seed: int,
    queries: int = QUERIES,
) -> tuple[float, np.ndarray]:
    """The bandwidth scale (units of ``scott (d,)``) maximizing the leave-one-image-out log likelihood of the weighted
    support ``support (K, d)``, ``weights (K,)`` under its own Gaussian kernel density,
    E_{k ~ v} log [Σ_{j: owner j ≠ owner k} vⱼ 𝒩(θₖ; θⱼ, diag (s·scott)²) / (1 − V_owner k)], estimated on ``queries``
    points drawn by weight (stream ``(seed, "deconvolution", "queries")``). Returns the scale and the score per scale."""
    d = support.shape[1]
    q = rng(seed, "deconvolution", "queries").choice(len(weights), size=min(queries, len(weights)), p=weights)
    u, uq = support / scott, support[q] / scott
    sq = np.einsum("kd,kd->k", u, u)
    dist2 = np.maximum(np.einsum("qd,qd->q", uq, uq)[:, None] + sq[None, :] - 2.0 * uq @ u.T, 0.0)  # (Q, K)
    other = owner[q][:, None] != owner[None, :]
    own = np.bincount(owner, weights=weights, minlength=int(owner.max()) + 1)[owner[q]]
    with np.errstate(divide="ignore"):
        log_v = np.where(other, np.log(weights)[None, :], -np.inf)
    scores = np.empty(len(scales))
    for a, s in enumerate(scales):
        dens = (
            logsumexp(log_v - 0.5 * dist2 / (s * s), axis=1) - d * math.log(s) - np.log(np.maximum(1.0 - own, 1e-300))
        )
        scores[a] = float(dens.mean()) - 0.5 * d * math.log(2 * math.pi) - float(np.log(scott).sum())
    return scales[int(np.argmax(scores))], scores


@dataclass(frozen=True)
class Deconvolution:
    """The deconvolved estimate of a bag's weather distribution.

    ``density`` is the kernel density of the weighted support (sample and log_prob like a domain); ``support (K, d)``
    and ``weights (K,)`` the EM solution after ``steps`` updates (0: the prior, 1: the mixture of posteriors);
    ``held_out (max_steps + 1,)`` the cross-validated log likelihood per image and step, ``kernel_scale`` the
    bandwidth in units of Scott's rule (``scott (d,)``, physical units)."""

    density: KernelDomain
    support: np.ndarray
    weights: np.ndarray
    steps: int
    held_out: np.ndarray
    kernel_scale: float
    scott: np.ndarray


def deconvolve(
    domain: Domain, draws_per_image: int, max_steps: int, folds: int, seed: int, log_prior: float = 0.0
) -> Deconvolution:
    """Deconvolve the bag of ``domain`` (its posterior and image weights): support = ``draws_per_image`` posterior
    draws per image (seed ``derive_seed(seed, "deconvolution", "support")``), EM for the cross-validated number of
    steps ≤ ``max_steps``, kernel at the cross-validated bandwidth. ``log_prior`` is log π(θ), constant on the box."""
    m = _check_count(draws_per_image, "draws_per_image")
    max_steps = _check_count(max_steps, "max_steps")
    active = np.flatnonzero(domain.weights > 0)
    bag, w = domain.bag[active], domain.weights[active]
    draws = np.asarray(domain.posterior.sample(bag, m, derive_seed(seed, "deconvolution", "support")))
    n, _, d = draws.shape
    support = draws.reshape(n * m, d).astype(np.float64)
    owner = np.repeat(np.arange(n), m)
    log_r = domain.member_log_prob(support) - log_prior  # (N, K)
    steps, held_out = select_steps(log_r, w, owner, max_steps, folds, seed)
    path = em_path(log_r, w, _proposal_log_v0(log_r), steps)
    v = np.exp(path.log_v[-1])
    n_eff = 1.0 / float(np.sum(v * v))
    mean = v @ support
    scott = np.sqrt(np.maximum(v @ (support - mean) ** 2, 1e-12)) * n_eff ** (-1.0 / (d + 4))
    scale, _ = kernel_scale(support, v, owner, scott, KERNEL_SCALES, seed)
    density = KernelDomain(support[:, None, :], v, scott * scale)
    return Deconvolution(density, support, v, steps, held_out, scale, scott)
