"""A window of frames related to the source domains (Task III): λ̂ on the simplex, the relative gap, and per parameter
the W₁ between the window's marginal and the fitted mixture's.

Each domain is a kernel density of fixed posterior draws, as ``pidc relate`` characterizes folders
(:class:`components.domains.kernel.KernelDomain`, one bandwidth h = ``scale`` × the mean over the sources of Scott's
rule, :func:`components.domains.kernel.sources_bandwidth`):

- a source 𝒮ₖ: the kernel density of C draws picked at random (seeded) among the pooled fixed draws of its density
  frames — a subsample keeps a window's Task III at a few milliseconds whatever the sources' lengths, and every
  window is compared to the same densities;
- a window: the kernel density of its L frames' fixed draws ``(L, m, d)``, weighted as the window weighs its frames.

Then :func:`components.domains.relative.relate` (n_W points drawn from the window, the CVXPY problem reused across
windows) gives λ̂ and δ(λ̂)/mean(b²). Where the window differs: per parameter W₁ between the window's marginal (its
frames' draws, frame i's weighing wᵢ/m each) and the mixture Σₖ λ̂ₖ 𝒮ₖ's (the sources' C draws each, weighing λ̂ₖ/C),
as :func:`components.domains.difference.parameter_differences` measures it for equally weighted targets.

Used by :mod:`components.watch.run` and :mod:`components.watch.calibration`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import wasserstein_distance

from components.core.seeding import rng
from components.domains.difference import mixture_draw_weights
from components.domains.kernel import KernelDomain, sources_bandwidth
from components.domains.relative import SimplexLeastSquares, relate

__all__ = ["SourceDensities", "WindowRelation", "relate_window", "marginal_distances"]


@dataclass(frozen=True)
class SourceDensities:
    """The sources as Task III sees them.

    Attributes:
        names: the K sources' names.
        draws: per source the C (or fewer) draws kept, ``(C_k, d)``, physical units: the kernel centres and the
            mixture's marginals.
        bandwidth: h ``(d,)``, physical units.
        kernels: per source its :class:`~components.domains.kernel.KernelDomain`.
    """

    names: list[str]
    draws: list[np.ndarray]
    bandwidth: np.ndarray
    kernels: list[KernelDomain]

    @classmethod
    def build(
        cls, names: Sequence[str], draws: Sequence[np.ndarray], scale: float, centres: int, seed: int
    ) -> SourceDensities:
        """From each source's density frames' fixed draws ``(N_k, m, d)``: the bandwidth ``scale`` × Scott's rule
        (mean over the sources), and ``centres`` pooled draws kept per source (all when it has fewer), picked without
        replacement from the stream ``(seed, "watch", "centres", k)``."""
        bandwidth = float(scale) * sources_bandwidth(list(draws))
        kept: list[np.ndarray] = []
        for k, d in enumerate(draws):
            pooled = np.asarray(d, dtype=np.float64).reshape(-1, d.shape[-1])
            if pooled.shape[0] > centres:
                pick = np.sort(rng(seed, "watch", "centres", k).choice(pooled.shape[0], size=centres, replace=False))
                pooled = pooled[pick]
            kept.append(pooled)
        kernels = [KernelDomain(p[:, None, :], None, bandwidth) for p in kept]
        return cls(list(names), kept, bandwidth, kernels)


@dataclass(frozen=True)
class WindowRelation:
    """A window against the sources.

    Attributes:
        weights: λ̂ ``(K,)`` on the simplex.
        gap: δ(λ̂), density², physical units.
        relative_gap: δ(λ̂)/mean(b²), unitless (0: a mixture of the sources; ≈ 1: the sources explain none of it).
        degenerate: whether λ̂ is not unique.
        wasserstein: ``(d,)`` W₁ per parameter between the window's marginal and the fitted mixture's, physical units.
    """

    weights: np.ndarray
    gap: float
    relative_gap: float
    degenerate: bool
    wasserstein: np.ndarray


def marginal_distances(
    target: np.ndarray, target_weights: np.ndarray | None, sources: Sequence[np.ndarray], weights: np.ndarray
) -> np.ndarray:
    """Per parameter, W₁ between the target's weighted draws and the mixture Σₖ λₖ sourceₖ's draws.

    Arguments:
        target: ``(n, d)`` draws; ``target_weights`` ``(n,)`` their weights (None: equal).
        sources: per source ``(n_k, d)`` draws, each weighing λₖ / n_k.
        weights: λ ``(K,)``.

    Returns:
        ``(d,)`` W₁, the parameters' units (with equal target weights, the ``wasserstein`` of
        :func:`components.domains.difference.parameter_differences`).
    """
    w = mixture_draw_weights([len(s) for s in sources], weights)
    pooled = np.concatenate(sources)
    return np.array(
        [
            wasserstein_distance(target[:, j], pooled[:, j], u_weights=target_weights, v_weights=w)
            for j in range(target.shape[1])
        ]
    )


def relate_window(
    draws: np.ndarray,
    weights: np.ndarray,
    sources: SourceDensities,
    n_points: int,
    seed: int,
    solver: SimplexLeastSquares | None = None,
) -> WindowRelation:
    """A window's :class:`WindowRelation` to ``sources``.

    Arguments:
        draws: ``(L, m, d)`` the window's frames' fixed draws, physical units.
        weights: ``(L,)`` the frames' normalized weights.
        sources: the :class:`SourceDensities`.
        n_points: n_W, points drawn from the window's kernel density.
        seed: the root of those points' stream (:func:`components.domains.relative.relate`).
        solver: the :class:`~components.domains.relative.SimplexLeastSquares` (default: relate's shared one).
    """
    a = np.asarray(draws, dtype=np.float64)
    length, m, d = a.shape
    target = KernelDomain(a, weights, sources.bandwidth)
    rel = relate(target, sources.kernels, n_points, seed, solver=solver)
    w = np.asarray(weights, dtype=np.float64)
    equal = bool(np.allclose(w, w[0]))
    per_draw = None if equal else np.repeat(w / w.sum() / m, m)
    w1 = marginal_distances(a.reshape(-1, d), per_draw, sources.draws, rel.weights)
    return WindowRelation(rel.weights, float(rel.gap), rel.relative_gap, bool(rel.degenerate), w1)
