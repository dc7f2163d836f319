"""Where a target domain differs from the mixture of source domains that Task III fits, parameter by parameter.

Task III's gap δ says *whether* the target's weather is a mixture Σₖ λ̂ₖ p̂_𝒮ₖ of the sources'
(:func:`~components.domains.relative.relate`); a safety engineer also needs to know *where* it is not — more fog than any source, a
night the sources never saw. Per parameter, between the target's marginal and the fitted mixture's:

* the 1-D Wasserstein distance W₁ = ∫ |F_target(t) − F_mixture(t)| dt (``scipy.stats.wasserstein_distance`` with
  weights), in the parameter's physical unit and as a share of the prior's range (so that % and ° compare);
* both medians.

Each domain is given by posterior draws of its images, ``(n, 6)`` in physical units, pooled (every draw of a domain
equally weighted: an equally weighted bag with as many draws per image); the mixture's draws are the sources' pooled
draws, source k's weighted λ̂ₖ / nₖ.

How large a W₁ is large: :class:`InOddDifferences` measures the same W₁ on in-ODD targets made from the sources
themselves — the calibration targets of :func:`~components.domains.relative.calibrate_on_sources`, of the target's
size — and gives per parameter the level they exceed with probability α (the split-conformal rank of the ODD
threshold, :class:`~components.domains.relative.OddDetector`), each parameter on its own. As for the threshold, the
probability is over the draw of the source folders too: a fresh in-ODD target's W₁ holds the source folders' own
sampling error, which no target held out of them shows, so for one draw of small folders a parameter can exceed its
level more often than α (tests/test_difference.py; docs/studies/relate-where.md).

Used by the ``pidc relate`` command.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
from scipy.stats import wasserstein_distance

from components.core.weather import Box
from components.domains.relative import OddDetector

__all__ = ["ParameterDifference", "mixture_draw_weights", "parameter_differences", "InOddDifferences"]


@dataclass(frozen=True)
class ParameterDifference:
    """One parameter's difference between the target and the sources' mixture.

    Attributes:
        name: the parameter (``components.core.weather`` order).
        unit: its physical unit (``%``, ``deg``).
        target_median: the target's marginal median (the unit).
        mixture_median: the fitted mixture's marginal median (the unit).
        wasserstein: W₁ between the two marginals (the unit): 0 when they agree.
        share: ``wasserstein`` / the prior box's range of the parameter (0 … 1).
    """

    name: str
    unit: str
    target_median: float
    mixture_median: float
    wasserstein: float
    share: float

    def to_dict(self) -> dict:
        return asdict(self)


def _draws(a: object, name: str, dim: int) -> np.ndarray:
    x = np.asarray(a, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] == 0 or x.shape[1] != dim or not np.all(np.isfinite(x)):
        raise ValueError(f"{name} must be finite draws of shape (n ≥ 1, {dim}), got shape {x.shape}")
    return x


def mixture_draw_weights(sizes: Sequence[int], weights: object) -> np.ndarray:
    """The weight of each pooled draw of the mixture Σₖ λₖ pₖ: source k's nₖ draws weigh λₖ / nₖ each → ``(Σ nₖ,)``,
    summing to 1. ``weights (K,)`` must be non-negative with a positive sum (they are normalized), ``sizes`` K
    positive counts."""
    lam = np.asarray(weights, dtype=np.float64)
    n = np.asarray(sizes)
    if lam.ndim != 1 or lam.size != n.size or lam.size == 0:
        raise ValueError(f"weights must be one per source ({n.size}), got shape {lam.shape}")
    if not np.all(np.isfinite(lam)) or np.any(lam < 0) or lam.sum() <= 0:
        raise ValueError(f"weights must be non-negative with a positive sum, got {lam.tolist()}")
    if not np.issubdtype(n.dtype, np.integer) or np.any(n < 1):
        raise ValueError(f"sizes must be positive counts of draws, got {n.tolist()}")
    return np.repeat(lam / lam.sum() / n, n)


def parameter_differences(
    target: object, sources: Sequence[object], weights: object, box: Box
) -> list[ParameterDifference]:
    """Per parameter of ``box`` (in its order): the target's marginal against the mixture Σₖ λₖ sourceₖ.

    Arguments:
        target: the target's pooled posterior draws ``(n, d)``, physical units.
        sources: each source's pooled draws ``(nₖ, d)``.
        weights: λ ``(K,)``, one per source (e.g. :attr:`~components.domains.relative.Relation.weights`).
        box: the prior box (names, units, ranges).
    """
    d = len(box.names)
    t = _draws(target, "target", d)
    if len(sources) == 0:
        raise ValueError("at least one source is needed")
    s = [_draws(x, f"source {k}", d) for k, x in enumerate(sources)]
    w = mixture_draw_weights([len(x) for x in s], weights)
    pooled = np.concatenate(s)
    out = []
    for j, name in enumerate(box.names):
        w1 = float(wasserstein_distance(t[:, j], pooled[:, j], v_weights=w))
        out.append(
            ParameterDifference(
                name=name,
                unit=box.units[j],
                target_median=float(np.median(t[:, j])),
                mixture_median=float(np.quantile(pooled[:, j], 0.5, weights=w, method="inverted_cdf")),
                wasserstein=w1,
                share=w1 / float(box.high[j] - box.low[j]),
            )
        )
    return out


class InOddDifferences:
    """Each parameter's W₁ on in-ODD targets: the ``on_target`` of
    :func:`~components.domains.relative.calibrate_on_sources`, called with each calibration target's held-out and kept members of every source and its
    fitted λ̂; the target's draws are its held-out members', the mixture's the kept members'.

    Arguments:
        draws: each source's fixed posterior draws ``(Nₖ, m, d)``, one row per member (the draws the calibration's
            kernel densities use, or any fixed draws of the members).
        box: the prior box.
    """

    def __init__(self, draws: Sequence[object], box: Box) -> None:
        self._draws = [np.asarray(x, dtype=np.float64) for x in draws]
        for k, x in enumerate(self._draws):
            if x.ndim != 3 or x.shape[0] == 0 or x.shape[2] != box.dim:
                raise ValueError(f"draws[{k}] must have shape (members, draws, {box.dim}), got {x.shape}")
        self._box = box
        self.rows: list[np.ndarray] = []  # per calibration target: W₁ per parameter (d,)

    def __call__(self, held: Sequence[np.ndarray], kept: Sequence[np.ndarray], weights: np.ndarray) -> None:
        d = self._box.dim
        target = np.concatenate([x[i].reshape(-1, d) for x, i in zip(self._draws, held, strict=True)])
        reduced = [x[i].reshape(-1, d) for x, i in zip(self._draws, kept, strict=True)]
        differences = parameter_differences(target, reduced, weights, self._box)
        self.rows.append(np.array([q.wasserstein for q in differences]))

    def levels(self, false_alarm_rate: float) -> np.ndarray:
        """Per parameter ``(d,)``: the W₁ that an in-ODD target exceeds with probability ≤ α (the conformal rank of the
        targets measured so far, as :meth:`OddDetector.calibrate`; it needs ⌈(1−α)/α⌉ of them)."""
        if not self.rows:
            raise ValueError("no in-ODD target measured yet: pass this object as calibrate_on_sources(on_target=…)")
        w1 = np.stack(self.rows)
        return np.array([OddDetector.calibrate(w1[:, j], false_alarm_rate).threshold for j in range(w1.shape[1])])
