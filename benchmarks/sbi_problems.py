"""Four standard simulation-based-inference problems with exact reference posteriors, and the C2ST metric.

The problems follow sbibm (Lueckmann et al., "Benchmarking simulation-based inference", AISTATS 2021), each with a
box-uniform prior (pidc's estimator needs a bounded box) and a reference posterior that this module samples EXACTLY
(no MCMC, no download):

* ``gaussian_linear_uniform`` — θ ~ U(−1, 1)¹⁰, x ~ N(θ, 0.1·I) (variance 0.1 per dimension, as sbibm's precision
  matrix 10·I). The posterior is N(x, 0.1·I) truncated to the box: it factorizes, so each dimension is drawn from a
  one-dimensional truncated normal (inverse CDF, exact in the far tails; sbibm uses rejection, same distribution).
* ``two_moons`` — θ ~ U(−1, 1)², a ~ U(−π/2, π/2), r ~ N(0.1, 0.01²), p = (r cos a + 0.25, r sin a),
  x = p + (−|z₀|, z₁) with z = R(−π/4)·θ. Given x, the map θ ↦ x − (−|z₀(θ)|, z₁(θ)) is two-to-one with unit
  Jacobian (a rotation and a reflection), so the posterior is sampled by drawing the nuisance p, setting
  |z₀| = p₀ − x₀ and z₁ = x₁ − p₁, picking the sign of z₀ by a fair coin and rotating back — rejecting the draw when
  θ leaves the prior box OR when p₀ < x₀ (no θ has |z₀| < 0; sbibm's sampler omits this second check, which matters
  only for observations with |z₀| ≲ 0.13, and :func:`TwoMoons.reference_posterior` counts them).
* ``gaussian_mixture`` — θ ~ U(−10, 10)², x ~ ½ N(θ, I) + ½ N(θ, 0.01·I) (one component per simulation). The
  posterior is the same mixture centred on x, truncated to the box: component k keeps weight ∝ ½·P_k(box) and is a
  product of one-dimensional truncated normals.
* ``slcp`` — θ ~ U(−3, 3)⁵, x = four i.i.d. draws from N(m, Σ) with m = (θ₁, θ₂), s₁ = θ₃², s₂ = θ₄², ρ = tanh θ₅,
  Σ = [[s₁², ρs₁s₂], [ρs₁s₂, s₂²]] (x ∈ ℝ⁸). sbibm's reference is 10 000 MCMC draws at ten fixed observations;
  here the posterior is sampled exactly by rejection in (m, Σ): the proposal Σ ~ IW(S, 5/2), m | Σ ~ N(x̄, Σ/4)
  (x̄ and S = Σᵢ(xᵢ − x̄)(xᵢ − x̄)ᵀ of the four draws) leaves the target/proposal ratio (1 − ρ²)^¼ · 1[θ ∈ box] ≤ 1
  once the prior's Jacobian |∂(m, Σ)/∂θ| = 16 |θ₃θ₄|⁵ (1 − ρ²) is counted (:meth:`SLCP.reference_posterior`);
  the signs of θ₃ and θ₄, which x cannot see, are fair coins.

Observations: ``n`` per problem, θₒ drawn from the prior and xₒ simulated, from a fixed seed per problem
(:func:`observations`). The metric is sbibm's classifier two-sample test (:func:`c2st`): accuracy of an MLP telling
reference draws from the estimator's draws, 5-fold cross-validated; 0.5 = indistinguishable, 1.0 = disjoint.

Only numpy, scipy and scikit-learn are imported, so that both pidc's ``.venv`` and the sbi environment
``.venv-sbi`` (``benchmarks/bench_sbi_problems.py --estimator sbi``) use the very same problems.
"""

from __future__ import annotations

import math
import zlib
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from scipy import special

__all__ = [
    "Problem",
    "GaussianLinearUniform",
    "TwoMoons",
    "GaussianMixture",
    "SLCP",
    "PROBLEMS",
    "get_problem",
    "observations",
    "c2st",
    "truncated_normal",
]


def truncated_normal(
    loc: np.ndarray, scale: float | np.ndarray, low: np.ndarray, high: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Exact draws from N(loc, scale²) truncated to [low, high], elementwise (all arrays broadcast to one shape).

    Inverse CDF on the side of the mean away from the nearer tail (``ndtr`` of the upper tail via symmetry), so
    that a truncation many standard deviations from the mean keeps full precision.

    Returns an array of the broadcast shape, inside [low, high].
    """
    loc, scale, low, high = np.broadcast_arrays(
        np.asarray(loc, float), np.asarray(scale, float), np.asarray(low, float), np.asarray(high, float)
    )
    a, b = (low - loc) / scale, (high - loc) / scale
    # work on the side where the interval's CDF values are small: flip when the interval lies above the mean
    flip = a > 0
    a_, b_ = np.where(flip, -b, a), np.where(flip, -a, b)
    pa, pb = special.ndtr(a_), special.ndtr(b_)
    u = rng.uniform(size=loc.shape)
    z = special.ndtri(pa + u * (pb - pa))
    z = np.clip(z, a_, b_)
    z = np.where(flip, -z, z)
    return np.clip(loc + scale * z, low, high)


@dataclass(frozen=True)
class Problem(ABC):
    """A problem: a box-uniform prior over θ ∈ ℝᵈ, a simulator x | θ and the exact posterior θ | x.

    Attributes:
        name: sbibm's task name.
        low, high: the prior box ``(d,)``.
        x_dim: the dimension of x.
    """

    name: str
    low: np.ndarray
    high: np.ndarray
    x_dim: int

    @property
    def dim(self) -> int:
        """d, the number of parameters."""
        return int(self.low.size)

    def prior(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n draws from the uniform prior: ``(n, d)``."""
        return rng.uniform(self.low, self.high, size=(n, self.dim))

    def in_box(self, theta: np.ndarray) -> np.ndarray:
        """Mask ``(...)`` of θ ``(..., d)`` inside the closed box."""
        return np.all((theta >= self.low) & (theta <= self.high), axis=-1)

    @abstractmethod
    def simulate(self, theta: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """x for each θ: ``(n, d) → (n, x_dim)``."""

    @abstractmethod
    def log_likelihood(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        """log p(x | θ) for θ ``(..., d)`` and x ``(..., x_dim)`` broadcast together: ``(...)`` (−inf where impossible)."""

    @abstractmethod
    def reference_posterior(self, x: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
        """n exact draws from p(θ | x) for one x ``(x_dim,)``: ``(n, d)``, inside the box."""


class GaussianLinearUniform(Problem):
    """sbibm ``gaussian_linear_uniform``: θ ~ U(−1, 1)¹⁰, x ~ N(θ, 0.1·I)."""

    variance: float = 0.1

    def __init__(self, dim: int = 10, bound: float = 1.0) -> None:
        super().__init__("gaussian_linear_uniform", np.full(dim, -bound), np.full(dim, bound), dim)

    def simulate(self, theta: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return theta + math.sqrt(self.variance) * rng.standard_normal(theta.shape)

    def log_likelihood(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        r2 = np.sum((x - theta) ** 2, axis=-1)
        return -0.5 * r2 / self.variance - 0.5 * self.dim * math.log(2 * math.pi * self.variance)

    def reference_posterior(self, x: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
        loc = np.broadcast_to(np.asarray(x, float), (n, self.dim))
        return truncated_normal(loc, math.sqrt(self.variance), self.low, self.high, rng)


class TwoMoons(Problem):
    """sbibm ``two_moons``: θ ~ U(−1, 1)², x = p(a, r) + (−|z₀|, z₁), z = R(−π/4)·θ (see the module docstring)."""

    r_loc: float = 0.1
    r_scale: float = 0.01
    offset: float = 0.25

    def __init__(self) -> None:
        super().__init__("two_moons", np.full(2, -1.0), np.full(2, 1.0), 2)

    @staticmethod
    def _rotate(theta: np.ndarray) -> np.ndarray:
        """z = R(−π/4)·θ: ``(..., 2) → (..., 2)``."""
        c = s = math.sqrt(0.5)  # cos(π/4) = sin(π/4)
        return np.stack([c * theta[..., 0] + s * theta[..., 1], -s * theta[..., 0] + c * theta[..., 1]], axis=-1)

    @staticmethod
    def _unrotate(z: np.ndarray) -> np.ndarray:
        """θ = R(π/4)·z, the inverse of :meth:`_rotate`."""
        c = s = math.sqrt(0.5)
        return np.stack([c * z[..., 0] - s * z[..., 1], s * z[..., 0] + c * z[..., 1]], axis=-1)

    def nuisance(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """p = (r cos a + 0.25, r sin a): ``(n, 2)``."""
        a = rng.uniform(-math.pi / 2, math.pi / 2, size=n)
        r = self.r_loc + self.r_scale * rng.standard_normal(n)
        return np.stack([r * np.cos(a) + self.offset, r * np.sin(a)], axis=-1)

    def simulate(self, theta: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        z = self._rotate(theta)
        return self.nuisance(len(theta), rng) + np.stack([-np.abs(z[:, 0]), z[:, 1]], axis=-1)

    def log_likelihood(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The density of p at u = x − (−|z₀|, z₁) in Cartesian coordinates: N(r; 0.1, 0.01²)/(π r), u₀ − 0.25 ≥ 0."""
        z = self._rotate(theta)
        u0 = x[..., 0] + np.abs(z[..., 0]) - self.offset
        u1 = x[..., 1] - z[..., 1]
        r = np.hypot(u0, u1)
        with np.errstate(divide="ignore"):
            log_r = (
                -0.5 * ((r - self.r_loc) / self.r_scale) ** 2
                - math.log(math.sqrt(2 * math.pi) * self.r_scale)
                - math.log(math.pi)
                - np.log(r)
            )
        return np.where(u0 >= 0, log_r, -np.inf)

    def reference_posterior(self, x: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
        return self.reference_posterior_with_rates(x, n, rng)[0]

    def reference_posterior_with_rates(
        self, x: np.ndarray, n: int, rng: np.random.Generator
    ) -> tuple[np.ndarray, float, float]:
        """Draws ``(n, 2)``, the acceptance rate, and the share of proposals rejected for p₀ < x₀ only.

        The second share is what sbibm's sampler (which checks the box only) would have kept wrongly.
        """
        out: list[np.ndarray] = []
        proposed = kept = wrong_branch = 0
        while kept < n:
            m = max(2 * (n - kept), 1024)
            p = self.nuisance(m, rng)
            abs_z0 = p[:, 0] - x[0]
            sign = np.where(rng.uniform(size=m) < 0.5, -1.0, 1.0)
            theta = self._unrotate(np.stack([sign * abs_z0, x[1] - p[:, 1]], axis=-1))
            inside = self.in_box(theta)
            ok = inside & (abs_z0 >= 0)
            wrong_branch += int(np.sum(inside & (abs_z0 < 0)))
            proposed += m
            out.append(theta[ok])
            kept += int(ok.sum())
        return np.concatenate(out)[:n], kept / proposed, wrong_branch / proposed


class GaussianMixture(Problem):
    """sbibm ``gaussian_mixture``: θ ~ U(−10, 10)², x ~ ½ N(θ, I) + ½ N(θ, 0.01·I)."""

    scales: tuple[float, float] = (1.0, 0.1)
    weights: tuple[float, float] = (0.5, 0.5)

    def __init__(self, dim: int = 2, bound: float = 10.0) -> None:
        super().__init__("gaussian_mixture", np.full(dim, -bound), np.full(dim, bound), dim)

    def simulate(self, theta: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        k = rng.choice(len(self.weights), size=len(theta), p=self.weights)
        scale = np.asarray(self.scales)[k][:, None]
        return theta + scale * rng.standard_normal(theta.shape)

    def log_likelihood(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        r2 = np.sum((x - theta) ** 2, axis=-1)
        parts = [
            math.log(w) - 0.5 * r2 / s**2 - self.dim * math.log(math.sqrt(2 * math.pi) * s)
            for w, s in zip(self.weights, self.scales, strict=True)
        ]
        return np.logaddexp(*parts)

    def component_weights(self, x: np.ndarray) -> np.ndarray:
        """The truncated posterior's component weights ``(K,)``: ∝ w_k · P(N(x, s_k² I) ∈ box)."""
        mass = [np.prod(special.ndtr((self.high - x) / s) - special.ndtr((self.low - x) / s)) for s in self.scales]
        w = np.asarray(self.weights) * np.asarray(mass)
        return w / w.sum()

    def reference_posterior(self, x: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
        k = rng.choice(len(self.scales), size=n, p=self.component_weights(x))
        scale = np.asarray(self.scales)[k][:, None]
        loc = np.broadcast_to(np.asarray(x, float), (n, self.dim))
        return truncated_normal(loc, scale, self.low, self.high, rng)


class SLCP(Problem):
    """sbibm ``slcp`` ("simple likelihood, complex posterior"): θ ~ U(−3, 3)⁵, x = four draws of N(m, Σ(θ)).

    m = (θ₁, θ₂), s₁ = θ₃², s₂ = θ₄², ρ = tanh θ₅ and Σ = [[s₁², ρs₁s₂], [ρs₁s₂, s₂²]]; x = (x₁, y₁, …, x₄, y₄).
    The posterior has four modes (the signs of θ₃ and θ₄) and is sampled exactly (the module's docstring).
    """

    draws: int = 4
    #: ν of the inverse-Wishart proposal: the smallest that bounds the target/proposal ratio (module docstring).
    proposal_df: float = 2.5

    def __init__(self) -> None:
        super().__init__("slcp", np.full(5, -3.0), np.full(5, 3.0), 2 * self.draws)

    @staticmethod
    def spread(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s₁, s₂, ρ) of θ ``(..., 5)``, each ``(..., 1)``: the standard deviations and correlation of x's draws."""
        return theta[..., 2:3] ** 2, theta[..., 3:4] ** 2, np.tanh(theta[..., 4:5])

    def simulate(self, theta: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        s1, s2, rho = self.spread(theta)
        z = rng.standard_normal((len(theta), self.draws, 2))
        x = theta[:, None, 0] + s1 * z[..., 0]
        y = theta[:, None, 1] + s2 * (rho * z[..., 0] + np.sqrt(1 - rho**2) * z[..., 1])
        return np.stack([x, y], axis=-1).reshape(len(theta), self.x_dim)

    def log_likelihood(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Σ over the four draws of log N(xᵢ; m, Σ), by the standardized pair (a, b) of each draw."""
        pts = np.asarray(x).reshape(*np.shape(x)[:-1], self.draws, 2)
        s1, s2, rho = self.spread(theta)
        with np.errstate(divide="ignore", invalid="ignore"):
            a = (pts[..., 0] - theta[..., 0:1]) / s1
            b = ((pts[..., 1] - theta[..., 1:2]) / s2 - rho * a) / np.sqrt(1 - rho**2)
            log_p = -0.5 * (a**2 + b**2) - math.log(2 * math.pi) - np.log(s1 * s2) - 0.5 * np.log1p(-(rho**2))
        return np.sum(log_p, axis=-1)

    def reference_posterior(self, x: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
        return self.reference_posterior_with_rate(x, n, rng)[0]

    def reference_posterior_with_rate(
        self, x: np.ndarray, n: int, rng: np.random.Generator
    ) -> tuple[np.ndarray, float]:
        """Draws ``(n, 5)`` by rejection from (Σ ~ IW(S, 5/2), m | Σ ~ N(x̄, Σ/4)), and the acceptance rate."""
        from scipy.stats import invwishart

        pts = np.asarray(x, float).reshape(self.draws, 2)
        mean = pts.mean(axis=0)
        scatter = (pts - mean).T @ (pts - mean)
        out: list[np.ndarray] = []
        proposed = kept = 0
        while kept < n:
            size = max(4 * (n - kept), 4096)
            cov = invwishart(df=self.proposal_df, scale=scatter).rvs(size=size, random_state=rng).reshape(size, 2, 2)
            m = mean + np.einsum("nij,nj->ni", np.linalg.cholesky(cov / self.draws), rng.standard_normal((size, 2)))
            s1, s2 = np.sqrt(cov[:, 0, 0]), np.sqrt(cov[:, 1, 1])
            rho = cov[:, 0, 1] / (s1 * s2)
            with np.errstate(divide="ignore"):
                theta5 = np.arctanh(rho)
            signs = np.where(rng.uniform(size=(size, 2)) < 0.5, -1.0, 1.0)
            theta = np.column_stack([m, signs[:, 0] * np.sqrt(s1), signs[:, 1] * np.sqrt(s2), theta5])
            ok = self.in_box(theta) & (rng.uniform(size=size) < (1 - rho**2) ** 0.25)
            proposed += size
            kept += int(ok.sum())
            out.append(theta[ok])
        return np.concatenate(out)[:n], kept / proposed


#: sbibm's names → the problems, in the order of the tables.
PROBLEMS: dict[str, type[Problem]] = {
    "gaussian_linear_uniform": GaussianLinearUniform,
    "two_moons": TwoMoons,
    "gaussian_mixture": GaussianMixture,
    "slcp": SLCP,
}


def get_problem(name: str) -> Problem:
    """The problem named ``name`` (a key of :data:`PROBLEMS`)."""
    if name not in PROBLEMS:
        raise KeyError(f"unknown problem {name!r}; choose from {', '.join(PROBLEMS)}")
    return PROBLEMS[name]()


def problem_rng(problem: Problem, seed: int, *keys: int | str) -> np.random.Generator:
    """A numpy generator for the stream ``(seed, problem, *keys)``, stable across processes and numpy versions."""
    words = [seed, zlib.crc32(problem.name.encode())]
    words += [k if isinstance(k, int) else zlib.crc32(k.encode()) for k in keys]
    return np.random.default_rng(np.random.SeedSequence(words))


def observations(problem: Problem, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n observations of a problem from a fixed seed: true θₒ ``(n, d)`` drawn from the prior and xₒ ``(n, x_dim)``."""
    rng = problem_rng(problem, seed, "observations")
    theta = problem.prior(n, rng)
    return theta, problem.simulate(theta, rng)


def c2st(
    reference: np.ndarray, estimate: np.ndarray, *, seed: int = 1, folds: int = 5, early_stopping: bool = False
) -> float:
    """sbibm's classifier two-sample test accuracy between two sample sets ``(n, d)`` and ``(m, d)``.

    Both sets are z-scored with the reference's mean and std; an MLP (two hidden ReLU layers of 10·d units, Adam,
    ``max_iter=10000``, sklearn's defaults otherwise) is cross-validated with ``folds`` shuffled folds. Returns the
    mean held-out accuracy: 0.5 = the classifier cannot tell them apart, 1.0 = it always can.

    ``early_stopping=True`` (not sbibm's) stops each fold's training when the accuracy on 10 % of its training part
    has not improved for 10 epochs, instead of training until the training loss stalls: far cheaper in 10-D.
    """
    from sklearn.model_selection import KFold, cross_val_score
    from sklearn.neural_network import MLPClassifier

    mean, std = reference.mean(axis=0), reference.std(axis=0)
    std = np.where(std > 0, std, 1.0)
    data = np.concatenate([(reference - mean) / std, (estimate - mean) / std])
    target = np.concatenate([np.zeros(len(reference)), np.ones(len(estimate))])
    d = reference.shape[1]
    clf = MLPClassifier(
        activation="relu",
        hidden_layer_sizes=(10 * d, 10 * d),
        max_iter=10_000,
        solver="adam",
        random_state=seed,
        early_stopping=early_stopping,
    )
    cv = KFold(n_splits=folds, shuffle=True, random_state=seed)
    return float(np.mean(cross_val_score(clf, data, target, cv=cv, scoring="accuracy")))
