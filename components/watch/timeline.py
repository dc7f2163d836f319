"""The windows over a stream of frames: which frames each window holds, how it weighs them, and the stream's recent
frames kept to make them.

A window is L consecutive frames ending at frame e, weighted either equally (``--window L``) or as Task II's linear
temporal filter, w ∝ decay^age (``--decay``: :class:`components.domains.absolute.ExponentialFilter`'s weights, cut at
the age where they fall below a tolerance). Window j ends at frame e_j = L − 1 + j·s (s the stride): the first window
once L frames are seen, then one every s frames. The window's *domain* is Task II's weighted mixture of its frames'
posteriors, Σᵢ wᵢ q(θ | xᵢ); its draws are the frames' own draws, weighted wᵢ / n each.

Used by :mod:`components.watch.run` (the drive) and :mod:`components.watch.calibration` (held-out windows of the
sources).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from components.core.seeding import rng
from components.evaluate.summary import HDI_MASS, hdi

__all__ = ["WindowShape", "RecentFrames", "domain_summary"]


@dataclass(frozen=True)
class WindowShape:
    """The frames of a window and their weights.

    Attributes:
        length: L, frames per window (≥ 1).
        stride: s, frames from one window's end to the next's (≥ 1).
        decay: None for equal weights, else the weight factor per frame of age in (0, 1).
    """

    length: int
    stride: int
    decay: float | None = None

    @property
    def weights(self) -> np.ndarray:
        """``(L,)`` normalized weights, oldest frame first: 1/L each, or ∝ decay^age (age L−1 … 0)."""
        if self.decay is None:
            return np.full(self.length, 1.0 / self.length)
        w = float(self.decay) ** np.arange(self.length - 1, -1, -1, dtype=np.float64)
        return w / w.sum()

    def ends(self, start: int, stop: int) -> np.ndarray:
        """The last frames of the windows inside frames ``[start, stop)``: start + L − 1, then every s frames
        (empty when fewer than L frames)."""
        first = start + self.length - 1
        return np.arange(first, stop, self.stride, dtype=np.int64) if first < stop else np.empty(0, dtype=np.int64)

    def is_end(self, frame: int, start: int = 0) -> bool:
        """Whether frame ``frame`` ends a window of a stream starting at ``start``."""
        k = frame - start - (self.length - 1)
        return k >= 0 and k % self.stride == 0


class RecentFrames:
    """The draws of the last L frames of a stream (a ring buffer): memory of one window, whatever the stream's length.

    Arguments:
        shape: the windows' :class:`WindowShape`.
        draws: n, draws per frame.
        dim: d.
    """

    def __init__(self, shape: WindowShape, draws: int, dim: int) -> None:
        self.shape = shape
        self._buffer = np.empty((shape.length, draws, dim))
        self._seen = 0

    def push(self, draws: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
        """Append the next frames' draws ``(b, n, d)``; yields ``(end frame, window draws (L, n, d), oldest first)``
        for each window ending among them (a copy)."""
        length = self.shape.length
        for row in np.asarray(draws):
            self._buffer[self._seen % length] = row
            frame = self._seen
            self._seen += 1
            if self.shape.is_end(frame):
                yield frame, np.roll(self._buffer, -(self._seen % length), axis=0)


def domain_summary(
    draws: np.ndarray, weights: np.ndarray, seed: int, mass: float = HDI_MASS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The median and ``mass`` HDI per parameter of a window's domain Σᵢ wᵢ q(θ | xᵢ) (Task II), from its frames'
    draws.

    With equal weights the pooled draws are draws of the mixture; otherwise as many draws are resampled from them with
    probabilities wᵢ / n (stream ``(seed, "watch", "domain")``), draws of the weighted mixture.

    Arguments:
        draws: ``(L, n, d)`` the window's frames' draws, physical units.
        weights: ``(L,)`` normalized weights.
        seed: the window's seed (used with unequal weights only).
        mass: the HDI's credible mass.

    Returns:
        ``(median, low, high)``, each ``(d,)``.
    """
    a = np.asarray(draws, dtype=np.float64)
    length, n, d = a.shape
    pooled = a.reshape(-1, d)
    w = np.asarray(weights, dtype=np.float64)
    if not np.allclose(w, w[0]):
        p = np.repeat(w / w.sum() / n, n)
        pooled = pooled[rng(seed, "watch", "domain").choice(pooled.shape[0], size=pooled.shape[0], p=p)]
    low, high = hdi(pooled, mass)
    return np.median(pooled, axis=0), low, high
