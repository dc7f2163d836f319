"""Posterior draws of each frame, seeded by the frame's number, and each frame's median and 68.27 % HDI (Task I).

Frame k of a stream gets the base noise ε ``(n, d)`` and the ensemble members of its n draws from the stream
``rng(seed, "watch", stream, k)``, pushed through the flow with
:meth:`components.export.runtime.OnnxPosterior.sample_from_noise`: one graph call per batch of frames, and draws that do
not depend on how the frames are batched (nor on the other frames of the batch). The first m of a frame's n draws are
its *fixed draws*, the support of the windows' kernel densities (:mod:`components.watch.relation`).

Used by :mod:`components.watch.run`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from components.core.seeding import rng
from components.evaluate.summary import HDI_MASS, hdi

__all__ = ["frame_noise", "frame_draws", "frame_summaries"]


def frame_noise(seed: int, stream: str, index: int, n: int, dim: int, ensemble: int) -> tuple[np.ndarray, np.ndarray]:
    """The base noise ``(n, dim)`` float32 and the ensemble members ``(n,)`` int64 of frame ``index``'s n draws, from
    the stream ``(seed, "watch", stream, index)``."""
    r = rng(seed, "watch", stream, int(index))
    eps = r.standard_normal((n, dim)).astype(np.float32)
    members = r.integers(ensemble, size=n) if ensemble > 1 else np.zeros(n, dtype=np.int64)
    return eps, members


def frame_draws(posterior: Any, x: np.ndarray, index: np.ndarray, n: int, seed: int, stream: str) -> np.ndarray:
    """n posterior draws θ ~ q(θ | x_k) of each frame, seeded per frame (:func:`frame_noise`).

    Arguments:
        posterior: an :class:`~components.export.runtime.OnnxPosterior` (``sample_from_noise``, ``dim``,
            ``ensemble``).
        x: ``(b, …)`` the frames' posterior inputs.
        index: ``(b,)`` the frames' numbers in their stream.
        n: draws per frame.
        seed: the root seed.
        stream: the stream's name (``"drive"``, or a source's).

    Returns:
        θ ``(b, n, d)`` float64, physical units.
    """
    noise = [frame_noise(seed, stream, int(k), n, posterior.dim, posterior.ensemble) for k in index]
    eps = np.stack([e for e, _ in noise])
    members = np.stack([m for _, m in noise])
    theta, _ = posterior.sample_from_noise(x, eps, members if posterior.ensemble > 1 else None)
    return theta


def frame_summaries(draws: np.ndarray, mass: float = HDI_MASS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each frame's median and ``mass`` highest-density interval per parameter (:func:`components.evaluate.summary.hdi`).

    Arguments:
        draws: ``(b, n, d)`` draws of b frames.
        mass: the HDI's credible mass (68.27 %).

    Returns:
        ``(median, low, high)``, each ``(b, d)``, physical units.
    """
    a = np.asarray(draws, dtype=np.float64)
    median = np.median(a, axis=1)
    bounds = [hdi(a[i], mass) for i in range(a.shape[0])]
    return median, np.stack([lo for lo, _ in bounds]), np.stack([hi for _, hi in bounds])
