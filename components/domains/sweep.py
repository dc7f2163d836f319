"""Task III's experiment: targets that mix the source domains and an out-of-ODD bag at noise level η.

Bags b₀, b₁, …, b_K of observations (b₀ out of the ODD, disjoint from the sources' weather). The target of one
experiment is (paper, Task III)

    p_𝒯 = (1 − η) Σₖ λₖ p_{bₖ} + η p_{b₀},

with the images of b₁…b_K equally weighted inside their bag and those of b₀ weighted by u ~ U(0, 1) (drawn per
experiment).

Beyond the paper — *fresh* targets. In the paper's construction the in-ODD part of the target holds the very images
of the sources, so at η = 0 the target's characterization is exactly a mixture of the sources': λ̂ = λ and δ = 0 up
to rounding, and any threshold above rounding noise detects every η > 0. A vehicle never sees the sources' images
again; it sees new images of the same weather. With ``fresh_pools`` (held-out observations of each source's
weather, e.g. other test images in the same sub-box), a fresh target replaces each bₖ by a random subset of its
pool of the same size: at η = 0 it is in the ODD but not an exact mixture, so δ at η = 0 measures the sampling
noise of a bag, the decision threshold is calibrated on realistic in-ODD targets, and the ROC curves say how much
out-of-ODD weather can be told from that noise. A pool must hold none of the bags' observations (the caller
guarantees it: :func:`components.domains.task3.split_bags` builds bags and pools disjoint), else a fresh target
matches a source exactly where it reuses that source's images. Each experiment relates the target to the sources
(:func:`components.domains.relative.relate`, n_W points): λ̂, the gap δ(λ̂), its relative version, δ for a λ drawn at
random on the simplex (the chance baseline) and d_E = ‖λ̂ − λ‖₂. :meth:`NoiseSweep.calibrate` calibrates the
out-of-ODD decision on in-ODD targets (η = 0) of its own seeds, :meth:`NoiseSweep.check_false_alarms` measures its
false-alarm rate on in-ODD targets of new seeds (:class:`FalseAlarmCheck`: the rate's Clopper–Pearson interval and the
range of counts a calibrated decision gives);
:func:`summarize_sweep` gives the per-η medians, detection rates at the calibrated threshold and the ROC AUC of η
against η = 0.

Everything works on the posterior's *context* (the embedding of each image computed once):
``posterior.on_context()`` and ``contexts = posterior.context(x)`` (:class:`components.export.runtime.OnnxPosterior`),
so the sweep's cost is the flow's density evaluations only.

Used by the ``task3`` stage and the scheduled monitoring (``flows/monitor.py``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np
from scipy.stats import binomtest

from components.core.checks import whole_number
from components.core.seeding import derive_seed, rng
from components.domains.absolute import Domain, Posterior
from components.domains.kernel import KernelDomain, sources_bandwidth
from components.domains.relative import (
    Characterization,
    OddDetector,
    SimplexLeastSquares,
    chance_baseline_gap,
    false_alarm_interval,
    relate,
    simplex_distance,
)
from components.evaluate.diagnostics import auc_interval, roc_curve

__all__ = ["SMOOTHINGS", "Experiment", "FalseAlarmCheck", "NoiseSweep", "summarize_sweep", "experiments_by_eta"]

#: confidence level of the false-alarm rate's Clopper–Pearson interval
CONFIDENCE = 0.95
#: how a bag is characterized (:class:`NoiseSweep`): the exact mixture of posteriors, or its kernel smoothing
SMOOTHINGS = ("none", "scott")


@dataclass(frozen=True)
class Experiment:
    """One target related to the sources: noise level, repetition and what came out."""

    eta: float
    repetition: int
    weights: list[float]
    gap: float
    relative_gap: float
    baseline_gap: float
    baseline_relative_gap: float
    d_e: float
    degenerate: bool

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class FalseAlarmCheck:
    """The ODD decision on n in-ODD targets: how many it flagged, the rate with its exact binomial interval, and the
    range of counts a perfectly calibrated decision gives.

    Attributes:
        targets: the target kind (``"paper"`` or ``"fresh"``).
        n: in-ODD targets decided on.
        flagged: those declared out of the ODD.
        rate: flagged / n, the measured false-alarm rate.
        ci_low: the lower end of its Clopper–Pearson interval at :data:`CONFIDENCE` (``scipy.stats.binomtest``):
            where the decision's own rate lies.
        ci_high: the upper end of that interval.
        alpha: the rate α the threshold was calibrated for.
        calibrated_low: the lower end of the central :data:`CONFIDENCE` interval of the count a perfectly calibrated
            decision flags among n targets exchangeable with its calibration targets
            (:func:`~components.domains.relative.false_alarm_interval`): beta-binomial for a threshold at rank r of m
            calibration gaps, which holds the threshold's own spread (the binomial of α alone is too narrow: with
            m = 400 it would call a calibrated decision's count too high in ~7 % of runs, not 2.5 %).
        calibrated_high: the upper end of that interval.
        calibrated_distribution: that count's distribution, e.g. ``"beta-binomial(n=200, m+1−r=20, r=381)"``.
    """

    targets: str
    n: int
    flagged: int
    rate: float
    ci_low: float
    ci_high: float
    alpha: float
    calibrated_low: int
    calibrated_high: int
    calibrated_distribution: str

    @classmethod
    def of(cls, flags: np.ndarray, detector: OddDetector, targets: str) -> FalseAlarmCheck:
        """From the decisions ``flags (n,)`` (True = flagged) of ``detector`` on in-ODD targets of kind ``targets``."""
        f = np.asarray(flags, dtype=bool).ravel()
        if f.size == 0:
            raise ValueError("a false-alarm check needs at least one in-ODD target")
        k, n = int(f.sum()), int(f.size)
        ci = binomtest(k, n).proportion_ci(confidence_level=CONFIDENCE, method="exact")
        alpha = float(detector.false_alarm_rate)
        low, high, name = false_alarm_interval(n, alpha, CONFIDENCE, detector.n_calibration, detector.rank)
        return cls(targets, n, k, k / n, float(ci.low), float(ci.high), alpha, low, high, name)

    @property
    def exceeds_alpha(self) -> bool:
        """True when more targets are flagged than a calibrated decision flags with probability
        1 − (1 − :data:`CONFIDENCE`)/2 (the count above ``calibrated_high``): the decision breaks its promise."""
        return self.flagged > self.calibrated_high

    def to_dict(self) -> dict:
        return asdict(self) | {"exceeds_alpha": self.exceeds_alpha}


class NoiseSweep:
    """The bags of a Task III sweep and the experiments on them.

    Arguments:
        posterior: q(θ | x) taking the bags' observations (e.g. contexts with ``OnnxPosterior.on_context()``).
        out_of_odd: b₀'s observations ``(N₀, ...)``.
        sources: b₁…b_K's observations, K ≥ 1 arrays ``(Nₖ, ...)``.
        weights: the true λ of the sources ``(K,)`` on the simplex.
        n_points: n_W, the points drawn from each target.
        fresh_pools: optional held-out observations of each source's weather (K arrays, each at least as large as
            its source bag): enables fresh targets (``run(..., fresh=True)``).
        smoothing: how a bag is characterized: ``"none"``, the exact mixture of its posteriors
            (:class:`~components.domains.absolute.Domain`, the paper's); ``"scott"``, the kernel density of
            ``draws_per_image`` fixed posterior draws per image with ``bandwidth_scale`` × the sources' Scott
            bandwidth (:class:`~components.domains.kernel.KernelDomain`; drawn once, stream
            ``(seed, "sweep", "kernel")``).
    """

    def __init__(
        self,
        posterior: Posterior,
        out_of_odd: np.ndarray,
        sources: Sequence[np.ndarray],
        weights: Sequence[float],
        n_points: int = 16,
        fresh_pools: Sequence[np.ndarray] | None = None,
        smoothing: str = "none",
        draws_per_image: int = 64,
        bandwidth_scale: float = 1.0,
        seed: int = 0,
    ) -> None:
        if smoothing not in SMOOTHINGS:
            raise ValueError(f"smoothing must be one of {SMOOTHINGS}, got {smoothing!r}")
        bags = [np.asarray(out_of_odd)] + [np.asarray(s) for s in sources]
        for k, bag in enumerate(bags):
            if bag.ndim < 1 or bag.shape[0] == 0:
                raise ValueError(f"bag b{k} is empty: every bag needs at least one observation")
        pools = [] if fresh_pools is None else [np.asarray(p) for p in fresh_pools]
        if fresh_pools is not None:
            if len(pools) != len(sources):
                raise ValueError(f"fresh_pools needs one pool per source ({len(sources)}), got {len(pools)}")
            for k, (pool, bag) in enumerate(zip(pools, bags[1:], strict=False), start=1):
                if pool.ndim < 1 or pool.shape[0] < bag.shape[0]:
                    raise ValueError(
                        f"fresh pool of b{k} has {pool.shape[0] if pool.ndim else 0} observations; a fresh "
                        f"target needs at least the bag's {bag.shape[0]}"
                    )
        lam = np.asarray(weights, dtype=np.float64)
        if lam.shape != (len(sources),) or np.any(lam < 0) or not np.isclose(lam.sum(), 1.0):
            raise ValueError(f"weights must be {len(sources)} values on the simplex, got {lam.tolist()}")
        self.weights = lam
        self.n_points = int(n_points)
        self._sizes = [b.shape[0] for b in bags]
        self._pool_sizes = [p.shape[0] for p in pools]
        self._offsets = np.cumsum([0] + self._sizes + self._pool_sizes)  # b₀, b₁…b_K, then the pools
        self._union = np.concatenate(bags + pools, axis=0)
        self.posterior = posterior
        self.smoothing = smoothing
        self._solver = SimplexLeastSquares()
        if smoothing == "none":
            self.sources: list[Characterization] = [Domain(posterior, b) for b in bags[1:]]
            return
        whole_number("draws_per_image", draws_per_image, low=2)
        if not (isinstance(bandwidth_scale, (int, float)) and 0 < bandwidth_scale < float("inf")):
            raise ValueError(f"bandwidth_scale must be a positive number, got {bandwidth_scale!r}")
        self._draws = np.asarray(
            posterior.sample(self._union, int(draws_per_image), derive_seed(seed, "sweep", "kernel"))
        )
        per_bag = [self._draws[self._offsets[k] : self._offsets[k + 1]] for k in range(1, len(bags))]
        self.bandwidth = float(bandwidth_scale) * sources_bandwidth(per_bag)
        self.sources = [KernelDomain(d, None, self.bandwidth) for d in per_bag]

    @property
    def sizes(self) -> list[int]:
        """|b₀|, |b₁|, …"""
        return list(self._sizes)

    @property
    def has_fresh(self) -> bool:
        """True when fresh targets are available (``fresh_pools`` given)."""
        return bool(self._pool_sizes)

    def target_weights(self, eta: float, seed: int, fresh: bool = False) -> np.ndarray:
        """The target's weights over the union b₀ ∪ b₁ ∪ … ∪ pools ``(Σ Nₖ,)``: η on b₀ (u ~ U(0, 1) per image) and
        (1 − η)λₖ on bₖ (equal inside the bag) — or, ``fresh``, on a random |bₖ|-subset of bₖ's pool."""
        if not 0.0 <= float(eta) <= 1.0:
            raise ValueError(f"noise level η must be in [0, 1], got {eta!r}")
        if fresh and not self.has_fresh:
            raise ValueError("fresh targets need fresh_pools (held-out observations of each source's weather)")
        w = np.zeros(self._offsets[-1])
        u = rng(seed, "sweep", "b0-weights").uniform(0.0, 1.0, self._sizes[0])
        w[: self._sizes[0]] = eta * u / u.sum()
        k_sources = len(self.weights)
        pick = rng(seed, "sweep", "fresh")
        for k, lam in enumerate(self.weights, start=1):
            if fresh:
                start = self._offsets[k_sources + k]
                chosen = start + pick.choice(self._pool_sizes[k - 1], size=self._sizes[k], replace=False)
                w[chosen] = (1.0 - eta) * lam / self._sizes[k]
            else:
                w[self._offsets[k] : self._offsets[k + 1]] = (1.0 - eta) * lam / self._sizes[k]
        return w

    def target(self, eta: float, seed: int, fresh: bool = False) -> Characterization:
        """The target at noise level η, characterized as the sources are (see ``smoothing``)."""
        w = self.target_weights(eta, seed, fresh)
        if self.smoothing == "none":
            return Domain(self.posterior, self._union, w)
        return KernelDomain(self._draws, w, self.bandwidth)

    def run(self, eta: float, repetition: int, seed: int, fresh: bool = False) -> Experiment:
        """One experiment at noise level η (a fresh target when ``fresh``); deterministic in its arguments."""
        s = derive_seed(seed, "sweep", "fresh" if fresh else "paper", f"{float(eta):.6g}", repetition)
        relation = relate(self.target(eta, s, fresh), self.sources, self.n_points, s, solver=self._solver)
        baseline = float(chance_baseline_gap(relation.A, relation.b, s)[0])
        mean_b2 = float(np.mean(relation.b**2))
        return Experiment(
            eta=float(eta),
            repetition=int(repetition),
            weights=relation.weights.tolist(),
            gap=relation.gap,
            relative_gap=relation.relative_gap,
            baseline_gap=baseline,
            baseline_relative_gap=baseline / mean_b2,
            d_e=simplex_distance(relation.weights, self.weights),
            degenerate=relation.degenerate,
        )

    def calibrate(
        self, n_targets: int, false_alarm_rate: float, seed: int, fresh: bool = False
    ) -> tuple[OddDetector, np.ndarray]:
        """The out-of-ODD detector on the relative gap, calibrated on ``n_targets`` in-ODD targets (η = 0, fresh ones
        when ``fresh``) drawn with seeds of their own (independent of :meth:`run`'s); returns it and the gaps."""
        s = derive_seed(seed, "sweep", "calibration")
        gaps = np.array([self.run(0.0, r, s, fresh).relative_gap for r in range(int(n_targets))])
        return OddDetector.calibrate(gaps, false_alarm_rate), gaps

    def check_false_alarms(
        self, detector: OddDetector, n_targets: int, seed: int, fresh: bool = False
    ) -> tuple[FalseAlarmCheck, np.ndarray]:
        """``detector`` on ``n_targets`` in-ODD targets (η = 0; fresh ones when ``fresh``) of new seeds — neither
        :meth:`calibrate`'s nor :meth:`run`'s for the same ``seed`` — drawn exactly as the calibration targets are;
        returns the check and their relative gaps."""
        whole_number("n_targets", n_targets, low=1)
        s = derive_seed(seed, "sweep", "false-alarm-check")
        gaps = np.array([self.run(0.0, r, s, fresh).relative_gap for r in range(int(n_targets))])
        kind = "fresh" if fresh else "paper"
        return FalseAlarmCheck.of(detector.decide_many(gaps), detector, kind), gaps


def summarize_sweep(experiments: Sequence[Experiment], detector: OddDetector) -> dict[str, dict[str, float]]:
    """Per η (keys formatted ``"0.1"``): medians of d_E, δ, the chance baseline δ and the relative gaps; the share
    flagged out of the ODD at the detector's threshold, with its Clopper–Pearson interval; and (η > 0) the AUC of the
    relative gap and of δ against the η = 0 experiments, each with its interval
    (:func:`~components.evaluate.diagnostics.auc_interval`); intervals at :data:`CONFIDENCE`."""
    by_eta: dict[float, list[Experiment]] = {}
    for e in experiments:
        by_eta.setdefault(e.eta, []).append(e)
    if 0.0 not in by_eta:
        raise ValueError("the experiments need η = 0 (in-ODD targets) as the reference")
    ref_rel = np.array([e.relative_gap for e in by_eta[0.0]])
    ref_gap = np.array([e.gap for e in by_eta[0.0]])
    out: dict[str, dict[str, float]] = {}
    for eta in sorted(by_eta):
        es = by_eta[eta]
        rel = np.array([e.relative_gap for e in es])
        gap = np.array([e.gap for e in es])
        row = {
            "d_e_median": float(np.median([e.d_e for e in es])),
            "gap_median": float(np.median(gap)),
            "baseline_gap_median": float(np.median([e.baseline_gap for e in es])),
            "relative_gap_median": float(np.median(rel)),
            "baseline_relative_gap_median": float(np.median([e.baseline_relative_gap for e in es])),
            "repetitions": len(es),
        }
        flagged = int(np.sum(detector.decide_many(rel)))
        ci = binomtest(flagged, len(es)).proportion_ci(confidence_level=CONFIDENCE, method="exact")
        row |= {
            "flagged_rate": flagged / len(es),
            "flagged_rate_ci_low": float(ci.low),
            "flagged_rate_ci_high": float(ci.high),
        }
        if eta > 0:
            for name, ref, scores in (("auc", ref_rel, rel), ("auc_gap", ref_gap, gap)):
                auc = roc_curve(ref, scores)[2]
                low, high = auc_interval(auc, ref.size, scores.size, CONFIDENCE)
                row |= {name: auc, f"{name}_ci_low": low, f"{name}_ci_high": high}
        out[f"{eta:g}"] = row
    return out


def experiments_by_eta(experiments: Sequence[Experiment], field: str) -> Mapping[float, np.ndarray]:
    """η → the values of ``field`` over the repetitions (for box plots and ROC curves)."""
    out: dict[float, list[float]] = {}
    for e in experiments:
        out.setdefault(e.eta, []).append(float(getattr(e, field)))
    return {k: np.array(v) for k, v in sorted(out.items())}
