"""Known weather distributions for the Task II and Task III experiments.

* :class:`GaussianMixtureWeather` — Task II's domain: every predicted parameter fixed except two (fog density and
  precipitation by default), which follow a mixture of Gaussians truncated to the prior box.
* :func:`in_sub_box` — Task III's bags: the images whose weather lies in a sub-box of the prior (so that, the test
  split being uniform on the prior, a bag's weather is uniform on its sub-box).

θ in physical units, in :data:`components.core.weather.PREDICTED` order.

Used by the ``task2`` and ``task3`` stages.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from components.core import weather

__all__ = ["GaussianMixtureWeather", "in_sub_box"]


@dataclass(frozen=True)
class GaussianMixtureWeather:
    """θ with ``fixed`` parameters held at their values and ``free`` = (p, q) ~ Σⱼ wⱼ N(μⱼ, diag σⱼ²) truncated to
    ``box`` (rejection: a draw outside the box is redrawn from the same component's mixture).

    Attributes:
        fixed: the fixed predicted parameters ``{name: value}`` (physical units; every name but ``free``).
        weights: ``(k,)`` mixture weights (normalized here).
        means: ``(k, 2)`` component means of ``free``, physical units.
        stds: ``(k, 2)`` component standard deviations, physical units.
        box: the prior box (truncation).
        free: the two mixture parameters.
    """

    fixed: Mapping[str, float]
    weights: np.ndarray
    means: np.ndarray
    stds: np.ndarray
    box: weather.Box
    free: tuple[str, str] = ("fog_density", "precipitation")

    def __post_init__(self) -> None:
        w, mu, sd = (np.asarray(a, dtype=np.float64) for a in (self.weights, self.means, self.stds))
        if w.ndim != 1 or w.size == 0 or mu.shape != (w.size, 2) or sd.shape != (w.size, 2):
            raise ValueError(f"need weights (k,), means (k, 2), stds (k, 2); got {w.shape}, {mu.shape}, {sd.shape}")
        if not (np.all(np.isfinite(w)) and np.all(w > 0) and np.all(np.isfinite(mu)) and np.all(sd > 0)):
            raise ValueError("mixture weights and standard deviations must be positive, means finite")
        expected = set(self.box.names) - set(self.free)
        if set(self.fixed) != expected:
            raise ValueError(f"fixed must give exactly {sorted(expected)}, got {sorted(self.fixed)}")
        for name, value in self.fixed.items():
            i = self.box.names.index(name)
            if not self.box.low[i] <= value <= self.box.high[i]:
                raise ValueError(
                    f"fixed {name} = {value} is outside the prior [{self.box.low[i]:g}, {self.box.high[i]:g}]"
                )
        object.__setattr__(self, "weights", w / w.sum())
        object.__setattr__(self, "means", mu)
        object.__setattr__(self, "stds", sd)

    @property
    def _free_index(self) -> list[int]:
        return [self.box.names.index(n) for n in self.free]

    def _base(self, n: int) -> np.ndarray:
        theta = np.empty((n, self.box.dim))
        for name, value in self.fixed.items():
            theta[:, self.box.names.index(name)] = value
        return theta

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` draws θ ``(n, d)``; the components' truncated normals by rejection (deterministic in ``rng``)."""
        idx = self._free_index
        low, high = self.box.low[idx], self.box.high[idx]
        comp = rng.choice(self.weights.size, size=n, p=self.weights)
        free = rng.normal(self.means[comp], self.stds[comp])
        bad = np.flatnonzero(np.any((free < low) | (free > high), axis=1))
        for _ in range(10_000):
            if bad.size == 0:
                break
            free[bad] = rng.normal(self.means[comp[bad]], self.stds[comp[bad]])
            bad = bad[np.any((free[bad] < low) | (free[bad] > high), axis=1)]
        else:
            raise ValueError("a mixture component has (almost) no mass inside the prior box")
        theta = self._base(n)
        theta[:, idx] = free
        return theta

    def modes(self) -> np.ndarray:
        """θ at each component's mean ``(k, d)`` (the fixed parameters at their values)."""
        theta = self._base(self.weights.size)
        theta[:, self._free_index] = self.means
        return theta


def in_sub_box(theta: np.ndarray, ranges: Mapping[str, Sequence[float]]) -> np.ndarray:
    """Boolean mask ``(n,)``: θ ``(n, 6)`` inside the sub-box ``{name: (low, high)}`` (omitted names: unrestricted)."""
    return weather.Box.from_mapping(ranges).contains(np.asarray(theta, dtype=np.float64))
