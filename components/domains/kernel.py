"""A domain's weather as a kernel density over its images' posterior draws: the mixture of posteriors, smoothed to
the scale that a bag of N images can resolve.

Task III relates a target to sources through their densities at the target's draws (:mod:`.relative`). With the
exact mixture p̂_𝒟 = Σᵢ wᵢ q(θ | xᵢ) (:class:`components.domains.absolute.Domain`) and a sharp estimator, each
qᵢ holds a tiny share of the prior's volume (the champion's 68 % regions: ~0.2 % of it) while a source sub-box
holds 5–40 % of it and a bag only 20–30 images: the mixture is a set of isolated peaks. A target made of *other*
images of the same weather (a "fresh" target) then puts its draws between the sources' peaks, every p̂_𝒮ₖ is ≈ 0
there, δ(λ) is the same for every λ and says nothing (measured on the default profile: λ̂ = the same source for
every target, median d_E 0.62 at η = 0, ODD AUC 0.34–0.46 < chance, since out-of-ODD night images have *broader*
posteriors, lower densities at their own draws and so smaller gaps).

A density estimate from N sample points needs a kernel as wide as the points are sparse. Here each image gives
m fixed posterior draws θᵢⱼ ~ q(θ | xᵢ), and the domain's density is their weighted Gaussian kernel density

    p̃_𝒟(θ) = Σᵢ wᵢ (1/m) Σⱼ 𝒩(θ; θᵢⱼ, diag h²),

with one bandwidth h for every domain of a sweep: the mean over the sources of Scott's rule (Scott 1992, §6.3)
on each source bag's pooled draws, h_d = σ̂_d · N^(−1/(d+4)) (N the bag's images, d = 6), so that sources and
targets are compared at one resolution. The kernel mixture keeps the two properties Task III relies on: a mixture
of domains is the same mixture of their kernel densities (the paper's targets, made of the sources' own images,
give δ(λ) = 0 at the true λ, exactly as with the exact mixture), and p̃ is a proper density that can be sampled
(choose a draw by weight, add 𝒩(0, diag h²)). It is not confined to the prior box: at the box faces it leaks the
mass of a kernel half-width, the same for target and sources.

Used by the ``task3`` stage and the scheduled monitoring (through :class:`components.domains.sweep.NoiseSweep`), and
by the ``pidc`` CLI's ``relate`` (its folders, and :func:`components.domains.relative.calibrate_on_sources`' held-out
targets).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.special import logsumexp

from components.core.checks import whole_number
from components.core.seeding import rng
from components.domains.absolute import _as_theta, normalized_weights

__all__ = ["KernelDomain", "scott_bandwidth", "sources_bandwidth"]

#: (θ, centre) pairs per block of log_prob: 1 MiB of float64, so that the block's passes (distances, exponentials, sums)
#: stay in the CPU's caches: a Task III experiment in 0.64× the time of 8× larger blocks, the task3 stage's whole sweep
#: in 0.87× (docs/studies/cache-sized-pieces.md). Each θ's row is computed alone, so
#: the block size changes at most the rounding of the distances' matrix product (none on the default profile's sweep
#: with blocks of 2 to 64 rows)
_CENTRES_PER_CALL = 1 << 17


def _check_draws(draws: object, name: str = "draws") -> np.ndarray:
    d = np.asarray(draws, dtype=np.float64)
    if d.ndim != 3 or d.shape[0] == 0 or d.shape[1] == 0 or d.shape[2] == 0:
        raise ValueError(f"{name} must have shape (N images, m draws, d) with N, m, d ≥ 1, got shape {d.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError(f"{name} must be finite (physical units)")
    return d


def scott_bandwidth(draws: object) -> np.ndarray:
    """Scott's rule for the pooled posterior draws of one bag ``draws (N, m, d)`` → ``(d,)``, physical units:
    h_d = σ̂_d · N^(−1/(d+4)), σ̂_d the standard deviation of all N·m draws of parameter d, N the number of images
    (the independent points: the m draws of one image are not)."""
    d = _check_draws(draws)
    n, _, dim = d.shape
    return d.reshape(-1, dim).std(axis=0) * n ** (-1.0 / (dim + 4))


def sources_bandwidth(source_draws: Sequence[object]) -> np.ndarray:
    """The sweep's common bandwidth ``(d,)``: the mean of :func:`scott_bandwidth` over the source bags; an error
    naming the parameter where it is zero (every draw of every source equal)."""
    if len(source_draws) == 0:
        raise ValueError("the bandwidth needs at least one source bag")
    h = np.mean([scott_bandwidth(d) for d in source_draws], axis=0)
    if not np.all(h > 0):
        raise ValueError(
            f"the sources' draws do not vary in parameter(s) {np.flatnonzero(h <= 0).tolist()}: no kernel bandwidth"
        )
    return h


class KernelDomain:
    """p̃_𝒟(θ) = Σᵢ wᵢ (1/m) Σⱼ 𝒩(θ; θᵢⱼ, diag h²) (see the module docstring); satisfies
    :class:`components.domains.relative.Characterization`.

    Arguments:
        draws: ``(N, m, d)`` posterior draws of each image (physical units), fixed: a domain built from a subset or a
            reweighting of the same images must be given the same draws.
        weights: ``(N,)`` non-negative image weights, normalized here; ``None``: equal.
        bandwidth: ``(d,)`` positive kernel standard deviations (physical units).
    """

    def __init__(self, draws: object, weights: object | None, bandwidth: object) -> None:
        d = _check_draws(draws)
        n, m, dim = d.shape
        h = np.asarray(bandwidth, dtype=np.float64)
        if h.shape != (dim,) or not np.all(np.isfinite(h)) or not np.all(h > 0):
            raise ValueError(f"bandwidth must be {dim} positive finite values, got {h.tolist()}")
        w = np.full(n, 1.0 / n) if weights is None else normalized_weights(weights, n)
        active = np.flatnonzero(w > 0)
        self._centres = d[active].reshape(-1, dim) / h  # standardized: the kernel is 𝒩(0, I) there
        self._log_w = np.repeat(np.log(w[active]) - math.log(m), m)
        self._sq_centres = np.einsum("cd,cd->c", self._centres, self._centres)  # ‖c‖², reused by every log_prob
        self._bandwidth = h
        self._log_norm = -0.5 * dim * math.log(2 * math.pi) - float(np.log(h).sum())

    @property
    def bandwidth(self) -> np.ndarray:
        """h ``(d,)``, physical units."""
        return self._bandwidth.copy()

    def __repr__(self) -> str:
        return f"KernelDomain(centres={len(self._log_w)}, bandwidth={np.round(self._bandwidth, 3).tolist()})"

    def log_prob(self, theta: object) -> np.ndarray:
        """log p̃(θ) for ``theta (k, d)`` → ``(k,)`` (physical units; log-sum-exp over the centres)."""
        t = _as_theta(theta)
        if t.shape[1] != len(self._bandwidth):
            raise ValueError(f"theta must be finite of shape (k, {len(self._bandwidth)}), got shape {t.shape}")
        u = t / self._bandwidth
        per_block = max(1, _CENTRES_PER_CALL // len(self._log_w))
        out = np.empty(len(u))
        for a in range(0, len(u), per_block):
            ub = u[a : a + per_block]
            sq = np.einsum("kd,kd->k", ub, ub)[:, None] - 2.0 * ub @ self._centres.T + self._sq_centres[None, :]
            out[a : a + per_block] = logsumexp(self._log_w[None, :] - 0.5 * np.maximum(sq, 0.0), axis=1)
        return out + self._log_norm

    def sample(self, n: int, seed: int) -> np.ndarray:
        """``n`` draws θ ~ p̃ → ``(n, d)``: a centre by weight, plus 𝒩(0, diag h²); stream ``(seed, "kernel")``."""
        whole_number("n", n, low=1)
        r = rng(seed, "kernel", "draws")
        p = np.exp(self._log_w - logsumexp(self._log_w))
        idx = r.choice(len(p), size=int(n), p=p)
        return (self._centres[idx] + r.standard_normal((int(n), self._centres.shape[1]))) * self._bandwidth
