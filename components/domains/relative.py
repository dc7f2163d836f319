"""Task III — relative domain characterization: a target domain as a mixture of source domains, and the ODD test.

Under the mixture assumption p_𝒯 = Σₖ λₖ p_𝒮ₖ (λ on the simplex), the weights are estimated by minimizing the mean
squared gap between the target's characterization and the mixture of the sources' (paper, Sec. Task III):

    δ(λ) = ∫ [p̂_𝒯(θ) − Σₖ λₖ p̂_𝒮ₖ(θ)]² p̂_𝒯(θ) dθ  ≃  (1/n_W) Σᵢ [bᵢ − (Aλ)ᵢ]²,   θᵢ ~ p̂_𝒯,

with bᵢ = p̂_𝒯(θᵢ) and Aᵢₖ = p̂_𝒮ₖ(θᵢ) (densities in physical units, so δ has units of density²). λ̂ = argmin δ on
{λ ≥ 0, Σλ = 1} is a convex QP, solved with CVXPY (solver CLARABEL, an interior-point conic solver) as one
*parametrized* problem per (n_W, K), built once and re-solved with new parameter values (DPP: no recompilation).

Scale: 6-D densities in physical units can be tiny or huge. A and b are divided by a common scale s (their largest
entry, taken in log space so nothing overflows) before the solver sees them; λ̂ is unchanged by this and the gap is
reported in original units, δ = s² · δ_scaled.

The Operational Design Domain is the convex hull of the sources; a large δ(λ̂) says the target is outside it.
:class:`OddDetector` turns a gap statistic (δ, or the scale-free :attr:`Relation.relative_gap`) into a decision with
a threshold calibrated on in-ODD gaps for a chosen false-alarm rate; :func:`calibrate_on_sources` builds those gaps
from the sources themselves (targets of random composition held out of the source bags) for the relative gap.

Used by the ``task3`` stage, the scheduled monitoring and the ``pidc`` CLI (``relate``).

References:
    Halin, Piérard et al., "Physically Interpretable Probabilistic Domain Characterization", Task III (the mean
    squared gap, its minimization on the simplex, the baseline by chance); Piérard et al., "Mixture domain
    adaptation to improve semantic segmentation in real-world surveillance", WACV Workshops 2023 (the mixture of
    source domains whose weights λ this estimates); Diamond & Boyd, "CVXPY: A Python-embedded modeling language for
    convex optimization", JMLR 2016, and Agrawal et al., "A rewriting system for convex optimization problems",
    Journal of Control and Decision 2018 (the solver layer).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import cvxpy as cp
import numpy as np
from scipy import stats

from components.core.checks import whole_number
from components.core.seeding import derive_seed, rng

if TYPE_CHECKING:
    from components.domains.absolute import Domain

__all__ = [
    "false_alarm_interval",
    "Characterization",
    "Relation",
    "SimplexLeastSquares",
    "fit_weights",
    "mean_squared_gap",
    "relate",
    "chance_baseline_gap",
    "simplex_distance",
    "OddDetector",
    "calibrate_on_sources",
]

SOLVER = "CLARABEL"
DEGENERACY_RTOL = 1e-7  # σ_min of A on the simplex's tangent space, relative to σ_max(A), below which λ is not unique
RIDGE = 1e-6  # ridge on ‖λ‖² (scaled units) used only for degenerate problems: selects the minimum-norm minimizer


@runtime_checkable
class Characterization(Protocol):
    """What Task III needs of a domain's characterization (e.g. :class:`components.domains.absolute.Domain`)."""

    def log_prob(self, theta: np.ndarray) -> np.ndarray:
        """log p̂(θ) for ``theta (m, d)`` → ``(m,)``, physical units."""
        ...

    def sample(self, n: int, seed: int) -> np.ndarray:
        """``n`` draws θ ~ p̂ → ``(n, d)``, deterministic in ``seed``."""
        ...


@dataclass(frozen=True)
class Relation:
    """The relative characterization of a target w.r.t. K sources.

    Attributes:
        weights: λ̂, shape ``(K,)``, on the simplex.
        gap: δ(λ̂), the mean squared gap in original units (density², physical units).
        points: the θᵢ ~ p̂_𝒯 where the densities were evaluated, shape ``(n_W, d)``.
        A: source densities Aᵢₖ = p̂_𝒮ₖ(θᵢ), shape ``(n_W, K)``.
        b: target densities bᵢ = p̂_𝒯(θᵢ), shape ``(n_W,)``.
        degenerate: True when λ̂ is not unique (e.g. identical sources); λ̂ is then the minimum-norm minimizer.
        scale: the common scale s by which A and b were divided for the solver.
    """

    weights: np.ndarray
    gap: float
    points: np.ndarray
    A: np.ndarray
    b: np.ndarray
    degenerate: bool = False
    scale: float = 1.0

    @property
    def relative_gap(self) -> float:
        """δ(λ̂) / ((1/n_W) Σᵢ bᵢ²): the gap as a fraction of the target's mean squared density (unitless).

        Beyond the paper: δ itself carries the target's density scale (a concentrated target has large densities,
        hence large gaps), so targets of different spread are better compared, and thresholded, on this ratio
        (0 for an exact mixture; ≈ 1 when the sources explain none of the target's mass).
        """
        return float(self.gap / np.mean(self.b**2))


def mean_squared_gap(A: np.ndarray, b: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """δ(λ) = (1/n_W) ‖Aλ − b‖² for ``A (n_W, K)``, ``b (n_W,)`` and ``weights`` λ of shape ``(K,)`` or ``(r, K)``.

    Returns a scalar array for one λ, ``(r,)`` for r of them.
    """
    lam = np.asarray(weights, dtype=np.float64)
    residual = lam @ np.asarray(A, dtype=np.float64).T - np.asarray(b, dtype=np.float64)
    return np.mean(residual**2, axis=-1)


def _check_matrices(A: object, b: object) -> tuple[np.ndarray, np.ndarray]:
    A = np.asarray(A, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if A.ndim != 2 or A.shape[0] == 0 or A.shape[1] == 0:
        raise ValueError(f"A must have shape (n_W, K) with n_W ≥ 1 and K ≥ 1, got shape {A.shape}")
    if b.shape != (A.shape[0],):
        raise ValueError(f"b must have shape ({A.shape[0]},) to match A {A.shape}, got shape {b.shape}")
    for name, v in (("A", A), ("b", b)):
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{name} (densities) must be finite, got {v[~np.isfinite(v)].ravel()[0]}")
        if np.any(v < 0):
            raise ValueError(f"{name} (densities) must be non-negative, got {v[v < 0].ravel()[0]}")
    if A.shape[0] < A.shape[1]:
        raise ValueError(f"n_W = {A.shape[0]} points cannot determine K = {A.shape[1]} weights: need n_W ≥ K")
    return A, b


_Entry = tuple[cp.Problem, cp.Variable, cp.Parameter, cp.Parameter, cp.Parameter]  # problem, λ, A, b, ridge


class SimplexLeastSquares:
    """min_λ (1/n_W) ‖Aλ − b‖² + ρ‖λ‖² s.t. λ ≥ 0, Σλ = 1, as DPP-compliant CVXPY problems cached per (n_W, K).

    A, b and ρ are ``cvxpy.Parameter``s: a solve only assigns their values and re-solves the same ``Problem``, so
    CVXPY reuses the compiled problem. ρ is 0 unless the problem is degenerate (λ not unique), then :data:`RIDGE`.

    Arguments:
        solver: a CVXPY solver name (default ``"CLARABEL"``; ``"OSQP"`` also works).
        degeneracy_rtol: see :data:`DEGENERACY_RTOL`.
    """

    def __init__(self, solver: str = SOLVER, degeneracy_rtol: float = DEGENERACY_RTOL) -> None:
        if solver not in cp.installed_solvers():
            raise ValueError(f"solver {solver!r} is not installed; installed: {cp.installed_solvers()}")
        self.solver = solver
        self.degeneracy_rtol = float(degeneracy_rtol)
        self._problems: dict[tuple[int, int], _Entry] = {}

    def problem(self, n_points: int, n_sources: int) -> cp.Problem:
        """The cached parametrized problem for A of shape ``(n_points, n_sources)`` (built on first use)."""
        return self._entry(n_points, n_sources)[0]

    def _entry(self, n: int, k: int) -> _Entry:
        key = (n, k)
        if key not in self._problems:
            lam = cp.Variable(k, name="lambda")
            A = cp.Parameter((n, k), name="A")
            b = cp.Parameter(n, name="b")
            ridge = cp.Parameter(nonneg=True, name="ridge")
            objective = cp.sum_squares(A @ lam - b) / n + ridge * cp.sum_squares(lam)
            problem = cp.Problem(cp.Minimize(objective), [lam >= 0, cp.sum(lam) == 1])
            if not problem.is_dpp():  # pragma: no cover - guards the formulation above
                raise RuntimeError("the simplex least-squares problem is not DPP")
            self._problems[key] = (problem, lam, A, b, ridge)
        return self._problems[key]

    def is_degenerate(self, A_scaled: np.ndarray) -> bool:
        """Whether δ has more than one minimizer direction: A is not injective on {v : Σv = 0} (numerically)."""
        k = A_scaled.shape[1]
        if k == 1:
            return False
        top = np.linalg.norm(A_scaled, 2)
        if top == 0.0:
            return True
        basis = np.linalg.svd(np.ones((1, k)))[2][1:].T  # (K, K−1), orthonormal, columns sum to 0
        return bool(np.linalg.svd(A_scaled @ basis, compute_uv=False).min() <= self.degeneracy_rtol * top)

    def solve(self, A: np.ndarray, b: np.ndarray, scale: float | None = None) -> tuple[np.ndarray, float, bool, float]:
        """λ̂, δ(λ̂) in original units, degenerate flag, and scale s, for ``A (n_W, K)`` and ``b (n_W,)``.

        ``scale``: divide A and b by it for the solver (default: their largest entry).
        """
        A, b = _check_matrices(A, b)
        n, k = A.shape
        s = float(max(A.max(), b.max())) if scale is None else float(scale)
        if s == 0.0:  # all densities zero: every λ is optimal, the minimum-norm one is uniform
            return np.full(k, 1.0 / k), 0.0, k > 1, 1.0
        if not (math.isfinite(s) and s > 0):
            raise ValueError(f"scale must be positive and finite, got {scale!r}")
        return self._solve_scaled(A / s, b / s, s)

    def _solve_scaled(self, As: np.ndarray, bs: np.ndarray, s: float) -> tuple[np.ndarray, float, bool, float]:
        n, k = As.shape
        if k == 1:
            lam = np.ones(1)
            return lam, float(mean_squared_gap(As, bs, lam)) * s * s, False, s
        degenerate = self.is_degenerate(As)
        problem, lam_var, A_par, b_par, ridge_par = self._entry(n, k)
        A_par.value, b_par.value, ridge_par.value = As, bs, (RIDGE if degenerate else 0.0)
        try:
            problem.solve(solver=self.solver)
        except cp.error.SolverError as err:
            raise RuntimeError(f"CVXPY solver {self.solver} failed on the simplex least squares: {err}") from err
        if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or lam_var.value is None:
            raise RuntimeError(f"CVXPY solver {self.solver} returned status {problem.status!r}")
        lam = np.clip(np.asarray(lam_var.value, dtype=np.float64), 0.0, None)
        lam /= lam.sum()
        return lam, float(mean_squared_gap(As, bs, lam)) * s * s, degenerate, s


_DEFAULT = SimplexLeastSquares()


def fit_weights(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """λ̂ = argmin δ(λ) on the simplex, with the module's shared :class:`SimplexLeastSquares` (CLARABEL, problems
    reused across calls).

    Arguments:
        A: source densities Aᵢₖ = p̂_𝒮ₖ(θᵢ), ``(n_W, K)``, physical units, non-negative.
        b: target densities bᵢ = p̂_𝒯(θᵢ), ``(n_W,)``, in the same units.

    Returns:
        λ̂ ``(K,)`` on the simplex and δ(λ̂), the mean squared gap in the units of A and b squared.

    Raises:
        ValueError: non-finite or negative densities, mismatched shapes, or n_W < K.
    """
    lam, gap, _, _ = _DEFAULT.solve(A, b)
    return lam, gap


def relate(
    target: Characterization,
    sources: Sequence[Characterization],
    n_points: int = 16,
    seed: int = 0,
    *,
    solver: SimplexLeastSquares | None = None,
) -> Relation:
    """Relative characterization of ``target`` w.r.t. ``sources`` (K ≥ 1): λ̂, δ(λ̂) and the data behind them.

    n_W = ``n_points`` draws θᵢ ~ p̂_𝒯 (seed ``derive_seed(seed, "relative", "points")``), then bᵢ = p̂_𝒯(θᵢ) and
    Aᵢₖ = p̂_𝒮ₖ(θᵢ), then :class:`SimplexLeastSquares`. With one source, λ̂ = [1] trivially and δ is still the gap
    between the target and that source (no solve). A source may have zero density at some θᵢ (disjoint support); the
    target may not at its own draws.

    Arguments:
        target: the target domain's characterization p̂_𝒯 (a :class:`Characterization`, e.g. a
            :class:`components.domains.absolute.Domain`), over θ ``(d,)`` in physical units.
        sources: the K source domains' characterizations p̂_𝒮ₖ, over the same θ.
        n_points: n_W, the number of draws of the target where the densities are compared (≥ 1, ≥ K to solve).
        seed: root of the stream of those draws.
        solver: the :class:`SimplexLeastSquares` to use (default the module's shared one).

    Returns:
        The :class:`Relation`: λ̂ ``(K,)``, the gap δ(λ̂) (density², physical units), its scale-free
        :attr:`Relation.relative_gap` (0 for an exact mixture, ≈ 1 when the sources explain none of the target) and
        the points and densities behind them. An ODD decision thresholds the gap: :class:`OddDetector`.

    Examples:
        Two 1-D sources N(−2, 1) and N(2, 1); a target that is their 0.3/0.7 mixture, and one far from both:

        >>> import numpy as np
        >>> from scipy import stats
        >>> class Mix:  # a Gaussian mixture of unit variances, as a Characterization
        ...     def __init__(self, weights, means):
        ...         self.w, self.m = np.asarray(weights, float), np.asarray(means, float)
        ...     def log_prob(self, theta):
        ...         return np.log(stats.norm.pdf(theta[:, :1], self.m) @ self.w)
        ...     def sample(self, n, seed):
        ...         r = np.random.default_rng(seed)
        ...         return r.normal(self.m[r.choice(len(self.w), n, p=self.w)], 1.0)[:, None]
        >>> sources = [Mix([1], [-2.0]), Mix([1], [2.0])]
        >>> inside = relate(Mix([0.3, 0.7], [-2.0, 2.0]), sources, n_points=256, seed=0)
        >>> inside.weights.round(3).tolist(), inside.relative_gap < 1e-9
        ([0.3, 0.7], True)
        >>> outside = relate(Mix([1], [8.0]), sources, n_points=256, seed=0)
        >>> round(outside.relative_gap, 3)  # the sources explain none of this target
        1.0
    """
    if isinstance(sources, Characterization) or not isinstance(sources, Sequence):
        raise TypeError("sources must be a sequence of characterizations (objects with log_prob and sample)")
    sources = list(sources)
    if not sources:
        raise ValueError("relate needs at least one source domain")
    for name, obj in [("target", target)] + [(f"sources[{k}]", s) for k, s in enumerate(sources)]:
        if not isinstance(obj, Characterization):
            raise TypeError(f"{name} must have log_prob(theta) and sample(n, seed), got {type(obj).__name__}")
    k = len(sources)
    whole_number("n_points", n_points, low=1)
    if n_points < k:
        raise ValueError(f"n_points = {n_points} cannot determine {k} mixture weights: need n_points ≥ {k}")
    points = np.asarray(target.sample(int(n_points), derive_seed(seed, "relative", "points")), dtype=np.float64)
    if points.ndim != 2 or points.shape[0] != n_points or not np.all(np.isfinite(points)):
        raise ValueError(f"target.sample must return finite draws of shape ({n_points}, d), got shape {points.shape}")
    log_b = _log_densities(target.log_prob(points), n_points, "target")
    if np.any(np.isneginf(log_b)):
        raise ValueError("the target density is zero at one of its own draws: target.log_prob and sample disagree")
    log_A = np.stack([_log_densities(s.log_prob(points), n_points, f"sources[{j}]") for j, s in enumerate(sources)], 1)
    log_s = float(max(log_A.max(), log_b.max()))  # finite: log_b is
    solver = _DEFAULT if solver is None else solver
    lam, gap, degenerate, s = solver._solve_scaled(np.exp(log_A - log_s), np.exp(log_b - log_s), math.exp(log_s))
    return Relation(lam, gap, points, np.exp(log_A), np.exp(log_b), degenerate, s)


def _log_densities(values: object, n: int, name: str) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)
    if v.shape != (n,):
        raise ValueError(f"{name}.log_prob returned shape {v.shape}, expected ({n},)")
    if np.any(np.isnan(v)) or np.any(v == np.inf):
        raise ValueError(f"{name}.log_prob returned NaN or +inf: densities must be finite")
    return v


def chance_baseline_gap(A: np.ndarray, b: np.ndarray, seed: int, n_draws: int = 1) -> np.ndarray:
    """The paper's "baseline by chance": δ(λ) for λ drawn uniformly on the simplex (Dirichlet(1, …, 1)).

    ``A (n_W, K)``, ``b (n_W,)`` in original units → ``(n_draws,)`` gaps; stream ``(seed, "relative", "chance")``.
    """
    A, b = _check_matrices(A, b)
    whole_number("n_draws", n_draws, low=1)
    lam = rng(seed, "relative", "chance").dirichlet(np.ones(A.shape[1]), size=int(n_draws))
    return np.atleast_1d(mean_squared_gap(A, b, lam))


def simplex_distance(estimate: np.ndarray, truth: np.ndarray, atol: float = 1e-6) -> float:
    """d_E = ‖λ̂ − λ‖₂ between two points of the simplex, both shape ``(K,)`` (checked to sum to 1 within ``atol``)."""
    out = []
    for name, v in (("estimate", estimate), ("truth", truth)):
        a = np.asarray(v, dtype=np.float64)
        if a.ndim != 1 or a.size == 0 or not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be a finite vector of shape (K,), got shape {a.shape}")
        if np.any(a < -atol) or abs(a.sum() - 1.0) > atol:
            raise ValueError(f"{name} must lie on the simplex (λ ≥ 0, Σλ = 1), got {a.tolist()}")
        out.append(a)
    if out[0].shape != out[1].shape:
        raise ValueError(f"estimate {out[0].shape} and truth {out[1].shape} have different numbers of sources")
    return float(np.linalg.norm(out[0] - out[1]))


@dataclass(frozen=True)
class OddDetector:
    """Out-of-ODD decision on the mean squared gap: outside when δ > threshold.

    Build it with :meth:`calibrate` on gaps of targets known to be in the ODD. With n exchangeable calibration
    gaps, the threshold is the r-th smallest with r = ⌈(n+1)(1−α)⌉ (a split-conformal rank), so a fresh in-ODD gap
    is flagged with probability ≤ α (and ≥ α − 1/(n+1) for continuous gaps).

    Attributes:
        threshold: δ above which a target is declared outside the ODD (density², physical units).
        false_alarm_rate: α, the rate the threshold was calibrated for.
        n_calibration: n, the number of calibration gaps.

    References:
        Vovk, Gammerman & Shafer, "Algorithmic Learning in a Random World", Springer 2005, and Lei et al.,
        "Distribution-Free Predictive Inference for Regression", JASA 2018 (the split-conformal rank).

    Examples:
        19 in-ODD gaps calibrate α = 0.05 (the fewest that can: r = ⌈20 · 0.95⌉ = 19, the largest gap):

        >>> import numpy as np
        >>> detector = OddDetector.calibrate(np.linspace(0.01, 0.19, 19), false_alarm_rate=0.05)
        >>> detector.rank, detector.threshold
        (19, 0.19)
        >>> detector.decide(0.5), detector.decide(0.1)  # True: outside the ODD
        (True, False)
    """

    threshold: float
    false_alarm_rate: float
    n_calibration: int

    @classmethod
    def calibrate(cls, in_odd_gaps: np.ndarray | Sequence[float], false_alarm_rate: float = 0.05) -> OddDetector:
        """Calibrate on in-ODD gaps ``(n,)`` for false-alarm rate α ∈ (0, 1); needs n ≥ ⌈(n+1)(1−α)⌉."""
        gaps = np.asarray(in_odd_gaps, dtype=np.float64)
        alpha = float(false_alarm_rate)
        if not (0.0 < alpha < 1.0):
            raise ValueError(f"false_alarm_rate must be in (0, 1), got {false_alarm_rate!r}")
        if gaps.ndim != 1 or gaps.size == 0:
            raise ValueError(f"in_odd_gaps must be a non-empty vector (n,), got shape {gaps.shape}")
        if not np.all(np.isfinite(gaps)) or np.any(gaps < 0):
            raise ValueError("in_odd_gaps must be finite and non-negative (mean squared gaps)")
        n = gaps.size
        rank = math.ceil((n + 1) * (1.0 - alpha) - 1e-9)
        if rank > n:
            need = math.ceil((1.0 - alpha) / alpha - 1e-9)
            raise ValueError(
                f"{n} calibration gaps are too few for false_alarm_rate {alpha}: need at least {need} "
                f"(the rank ⌈(n+1)(1−α)⌉ must not exceed n)"
            )
        return cls(float(np.sort(gaps)[rank - 1]), alpha, n)

    @property
    def rank(self) -> int:
        """r = ⌈(n+1)(1−α)⌉: the threshold is the r-th smallest of the n calibration gaps."""
        return math.ceil((self.n_calibration + 1) * (1.0 - self.false_alarm_rate) - 1e-9)

    def decide(self, gap: float) -> bool:
        """True when the target with mean squared gap ``gap`` is outside the ODD (gap > threshold)."""
        g = float(gap)
        if not math.isfinite(g) or g < 0:
            raise ValueError(f"gap must be a finite non-negative mean squared gap, got {gap!r}")
        return g > self.threshold

    def decide_many(self, gaps: np.ndarray | Sequence[float]) -> np.ndarray:
        """Vectorized :meth:`decide`: ``(m,)`` gaps → ``(m,)`` booleans (True = outside the ODD)."""
        g = np.asarray(gaps, dtype=np.float64)
        if not np.all(np.isfinite(g)) or np.any(g < 0):
            raise ValueError("gaps must be finite and non-negative (mean squared gaps)")
        return g > self.threshold


def false_alarm_interval(
    n: int, alpha: float, level: float, calibration_targets: int | None = None, rank: int | None = None
) -> tuple[int, int, str]:
    """The central interval ``[low, high]`` of the number of false alarms among ``n`` in-ODD targets that holds at least
    ``level`` of its distribution (each tail ≤ (1 − level)/2), and the distribution's name: BB(n, m + 1 − r, r) for a
    threshold at rank ``rank`` = r of ``calibration_targets`` = m calibration gaps, else the binomial B(n, α)."""
    whole_number("n", n, low=1, floats=True, hint=" (a number of targets)")
    if not 0.0 < float(alpha) < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha!r}")
    if not 0.0 < float(level) < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    if (calibration_targets is None) != (rank is None):
        raise ValueError("give both calibration_targets and rank, or neither")
    if calibration_targets is None:
        dist, name = stats.binom(int(n), float(alpha)), f"binomial(n={int(n)}, α={float(alpha):g})"
    else:
        m, r = int(calibration_targets), int(rank)
        if not 1 <= r <= m:
            raise ValueError(f"rank must lie in 1…{m} (calibration_targets), got {rank!r}")
        dist, name = stats.betabinom(int(n), m + 1 - r, r), f"beta-binomial(n={int(n)}, m+1−r={m + 1 - r}, r={r})"
    tail = (1.0 - float(level)) / 2.0
    # ppf(q): the smallest k with P(K ≤ k) ≥ q; so P(K < low) < tail and P(K > high) ≤ tail
    low, high = int(dist.ppf(tail)), int(dist.ppf(1.0 - tail))
    return low, high, name


def _held_out_counts(lam: np.ndarray, capacity: np.ndarray, size: int, r: np.random.Generator) -> np.ndarray:
    """Members taken from each source for a target of ``size``: multinomial by λ, capped by ``capacity`` (K,),
    the overflow re-drawn among sources with room left; the total is min(size, Σ capacity)."""
    counts = np.zeros(lam.size, dtype=np.int64)
    left = int(min(size, capacity.sum()))
    while left > 0:
        room = capacity - counts
        p = np.where(room > 0, lam, 0.0)
        p = p / p.sum() if p.sum() > 0 else (room > 0) / np.count_nonzero(room > 0)
        counts = np.minimum(counts + r.multinomial(left, p), capacity)
        left = int(min(size, capacity.sum())) - int(counts.sum())
    return counts


def calibrate_on_sources(
    sources: Sequence[Domain],
    n_targets: int = 100,
    n_points: int = 16,
    false_alarm_rate: float = 0.05,
    seed: int = 0,
    *,
    target_size: int | None = None,
    solver: SimplexLeastSquares | None = None,
    progress: bool = False,
    draws: Sequence[np.ndarray] | None = None,
    bandwidth: np.ndarray | None = None,
    on_target: Callable[[list[np.ndarray], list[np.ndarray], np.ndarray], None] | None = None,
) -> OddDetector:
    """An :class:`OddDetector` on :attr:`Relation.relative_gap`, calibrated on in-ODD targets made from the sources.

    The statistic is the scale-free relative gap δ/mean(b²), not δ: targets of different spread have densities, hence
    gaps, of different scales. Use the detector as
    ``detector.decide(relate(target, sources, n_points, s).relative_gap)`` with the same ``sources`` and ``n_points``.

    An exact mixture Σₖ λₖ p̂_𝒮ₖ of the sources' characterizations has δ = 0, so it cannot calibrate anything: a real
    in-ODD target is a *new, finite* bag of observations from the mixture of the source domains, none of which is in
    a source bag. Each calibration target t is made so (the sources must be :class:`components.domains.absolute.Domain` bags
    sharing one posterior), by holding observations out of the sources:

    1. λ ~ Dirichlet(1, …, 1); counts mₖ ~ Multinomial(``target_size``, λ), each at most half of source k's members of
       positive weight (overflow re-drawn among the other sources; the bag is smaller when the sources cannot hold
       out ``target_size`` members in all);
    2. the target is the bag of mₖ members drawn from each source k without replacement (by weight), equally weighted:
       the composition of :func:`components.domains.absolute.mixture_of` (sources, λ) with fresh members;
    3. its relative gap from ``relate(target, sources without their held-out members, n_points)``.

    The threshold is the split-conformal rank of these ``n_targets`` gaps (:meth:`OddDetector.calibrate`). Holding
    out, rather than resampling the sources' own members into the target, matters: a target that shares members with
    the sources matches them exactly where their posteriors are sharp, its gaps are far too small, and fresh in-ODD
    targets are then flagged far above α (measured 15–50 % for α = 5 % with sharp posteriors). Held out, the rate is
    close to α; it is lower (conservative) when the target is large next to the sources, as the reduced sources and
    the capped targets make the calibration gaps larger. Measured on bags of known densities (Gaussian posteriors of
    σ = 0.1 and 0.5 over three uniform boxes of side 2, sources of 25 and 80 observations, targets of 10 and 30,
    α = 0.05; tests/test_relative.py): 0.02–0.07, and 0.002–0.045 for targets of 30 from sources of 25.

    Arguments:
        sources: K ≥ 1 source domains (with one source, the detector tests whether the target is like that source);
            at least one needs two members of positive weight.
        n_targets: number of calibration targets; at least ⌈(1−α)/α⌉ (19 for α = 0.05).
        n_points: n_W of :func:`relate`, the same as for the target to decide on.
        false_alarm_rate: α ∈ (0, 1).
        seed: root of the streams ``(seed, "relative", "calibration", t, …)`` of target t.
        target_size: observations in each calibration target: the size of the target to decide on (the in-ODD gap
            shrinks as the bag grows); default half the mean size of the sources.
        solver: the :class:`SimplexLeastSquares` to use (default the module's shared one).
        progress: show a tqdm bar over the calibration targets.
        draws: with ``bandwidth``, every bag (the held-out target and the reduced sources) is the
            :class:`components.domains.kernel.KernelDomain` of its members' fixed posterior draws — ``draws[k]``
            ``(Nₖ, m, d)``, one row per member of source k — the ``task3`` stage's smoothing, for a target related to
            kernel densities of the sources. Without them, the exact mixtures of posteriors.
        bandwidth: the kernel bandwidth ``(d,)`` of ``draws``, physical units; given with ``draws`` or not at all.
        on_target: called after each calibration target is related, with ``(held, kept, weights)``: per source the
            indices of its members held out into the target and of those kept, and the target's fitted λ̂ ``(K,)``
            (e.g. to measure, on the same in-ODD targets, another statistic of the target against the sources).

    Returns:
        The :class:`OddDetector` whose threshold is on the relative gap (unitless), for false-alarm rate α.
    """
    sources = _bags_to_hold_out_from(sources)
    kernel = _kernel_inputs(sources, draws, bandwidth)
    alpha, n_targets = _calibration_rate(false_alarm_rate, n_targets)
    plan = _HoldOut.of(sources, target_size, kernel)
    gaps = np.empty(n_targets)
    for t in _calibration_steps(n_targets, progress):
        target, reduced, outs, keeps = plan.draw(rng(seed, "relative", "calibration", t))
        rel = relate(
            target, reduced, n_points, derive_seed(seed, "relative", "calibration", t, "relate"), solver=solver
        )
        gaps[t] = rel.relative_gap
        if on_target is not None:
            on_target(outs, keeps, rel.weights)
    return OddDetector.calibrate(gaps, alpha)


def _calibration_rate(false_alarm_rate: float, n_targets: int) -> tuple[float, int]:
    """``(α, n_targets)`` checked: α ∈ (0, 1), and enough calibration targets for a split-conformal rank at α."""
    alpha = float(false_alarm_rate)
    if not (0.0 < alpha < 1.0):
        raise ValueError(f"false_alarm_rate must be in (0, 1), got {false_alarm_rate!r}")
    need = math.ceil((1.0 - alpha) / alpha - 1e-9)
    return alpha, whole_number("n_targets", n_targets, low=need, hint=f" for false_alarm_rate {alpha}")


def _bags_to_hold_out_from(sources: Sequence[Domain]) -> list[Domain]:
    """``sources`` as a list, checked to be bags of one posterior and one observation shape (the calibration targets
    mix members of all of them under one estimator)."""
    from components.domains.absolute import Domain

    sources = list(sources)
    if not sources:
        raise ValueError("calibrate_on_sources needs at least one source domain")
    for k, s in enumerate(sources):
        if not isinstance(s, Domain):
            raise TypeError(
                f"sources[{k}] must be a components.domains.absolute.Domain (a bag to hold out from), "
                f"got {type(s).__name__}"
            )
    for k, s in enumerate(sources[1:], start=1):
        if s.posterior is not sources[0].posterior or s.bag.shape[1:] != sources[0].bag.shape[1:]:
            raise ValueError(
                f"sources[{k}] uses another posterior or observation shape than sources[0]: the "
                "calibration targets mix members of all sources under one estimator"
            )
    return sources


def _calibration_steps(n_targets: int, progress: bool) -> Iterable[int]:
    """The indices of the calibration targets, with a tqdm bar when ``progress``."""
    steps = range(n_targets)
    if not progress:
        return steps
    from tqdm.auto import tqdm

    return tqdm(steps, desc="calibrating the ODD threshold", unit="target")


@dataclass(frozen=True)
class _HoldOut:
    """How :func:`calibrate_on_sources` holds calibration targets out of the sources.

    ``positive[k]``: the members of source k of positive weight; ``capacity[k]``: at most half of them go into one
    target; ``size``: the target's members (``target_size``); ``kernel``: ``(draws per source, bandwidth)`` for
    kernel-density bags, or None for the exact mixtures of posteriors.
    """

    sources: list[Domain]
    positive: list[np.ndarray]
    capacity: np.ndarray
    size: int
    kernel: tuple[list[np.ndarray], np.ndarray] | None

    @classmethod
    def of(
        cls, sources: list[Domain], target_size: int | None, kernel: tuple[list[np.ndarray], np.ndarray] | None
    ) -> _HoldOut:
        """The plan for ``sources``; ``target_size`` None: half the mean size of the sources."""
        if target_size is None:
            target_size = max(1, round(float(np.mean([len(s) for s in sources])) / 2))
        size = whole_number("target_size", target_size, low=1)
        positive = [np.flatnonzero(s.weights > 0) for s in sources]
        capacity = np.array([p.size // 2 for p in positive], dtype=np.int64)
        if capacity.sum() == 0:
            raise ValueError(
                "the sources are too small to hold out a calibration target: at least one needs two "
                "members of positive weight"
            )
        return cls(sources, positive, capacity, size, kernel)

    def draw(
        self, r: np.random.Generator
    ) -> tuple[Characterization, list[Characterization], list[np.ndarray], list[np.ndarray]]:
        """One calibration target from the stream ``r``: ``(target, reduced sources, held, kept)``, with per source
        the indices of its members held out into the target and of those kept (steps 1 and 2 of
        :func:`calibrate_on_sources`)."""
        from components.domains.absolute import Domain
        from components.domains.kernel import KernelDomain

        counts = _held_out_counts(r.dirichlet(np.ones(len(self.sources))), self.capacity, self.size, r)
        held, reduced, outs, keeps = [], [], [], []
        for j, (s, members, m) in enumerate(zip(self.sources, self.positive, counts, strict=False)):
            w = s.weights[members]
            out = r.choice(members, size=int(m), replace=False, p=w / w.sum()) if m else members[:0]
            keep = np.setdiff1d(np.arange(len(s)), out)
            outs.append(out)
            keeps.append(keep)
            if self.kernel is None:
                held.append(s.bag[out])
                reduced.append(Domain(s.posterior, s.bag[keep], s.weights[keep]))
            else:
                held.append(self.kernel[0][j][out])
                reduced.append(KernelDomain(self.kernel[0][j][keep], s.weights[keep], self.kernel[1]))
        if self.kernel is None:
            target: Characterization = Domain(self.sources[0].posterior, np.concatenate(held))
        else:
            target = KernelDomain(np.concatenate(held), None, self.kernel[1])
        return target, reduced, outs, keeps


def _kernel_inputs(
    sources: Sequence[Domain], draws: Sequence[np.ndarray] | None, bandwidth: np.ndarray | None
) -> tuple[list[np.ndarray], np.ndarray] | None:
    """``(draws per source, bandwidth)`` checked against the sources, or None for the exact mixtures."""
    if draws is None and bandwidth is None:
        return None
    if draws is None or bandwidth is None:
        raise ValueError("kernel densities need both draws (one array per source) and a bandwidth")
    if len(draws) != len(sources):
        raise ValueError(f"draws must hold one array per source ({len(sources)}), got {len(draws)}")
    per = [np.asarray(d, dtype=np.float64) for d in draws]
    for k, (d, s) in enumerate(zip(per, sources, strict=False)):
        if d.ndim != 3 or d.shape[0] != len(s) or d.shape[1] < 1:
            raise ValueError(
                f"draws[{k}] must have shape ({len(s)} members, m draws, d), one row per member of sources[{k}], "
                f"got shape {d.shape}"
            )
    h = np.asarray(bandwidth, dtype=np.float64)
    if h.shape != (per[0].shape[2],):
        raise ValueError(f"bandwidth must have shape ({per[0].shape[2]},), got shape {h.shape}")
    return per, h
