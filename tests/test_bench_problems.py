"""The SBI benchmark problems (``benchmarks/sbi_problems.py``): simulators, likelihoods, exact reference posteriors.

Each reference sampler is checked against the posterior's mean and variance computed independently, by quadrature
of prior × likelihood on a grid; each likelihood is checked against its simulator (it integrates to one over x and
has the simulated mean). Fast: numpy only, a few seconds in all.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_sbi_problems as bench  # noqa: E402
import sbi_problems as sp  # noqa: E402

N = 20_000  # reference draws per check


def grid_moments(problem: sp.Problem, x: np.ndarray, lo: np.ndarray, hi: np.ndarray, step: float):
    """Posterior mean ``(2,)`` and variance ``(2,)`` of a 2-D problem by the midpoint rule on [lo, hi] ∩ box."""
    lo, hi = np.maximum(lo, problem.low), np.minimum(hi, problem.high)
    axes = [np.arange(a + step / 2, b, step) for a, b in zip(lo, hi, strict=True)]
    t = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 2)
    log_w = problem.log_likelihood(t, x)
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    mean = w @ t
    return mean, w @ (t - mean) ** 2


def assert_moments(draws: np.ndarray, mean: np.ndarray, var: np.ndarray) -> None:
    """Sample mean within 5 standard errors, sample variance within 5 % + 5 standard errors of a normal's."""
    se_mean = np.sqrt(var / len(draws))
    np.testing.assert_array_less(np.abs(draws.mean(axis=0) - mean), 5 * se_mean + 1e-12)
    np.testing.assert_allclose(draws.var(axis=0), var, rtol=0.05 + 5 * math.sqrt(2 / len(draws)))


def test_truncated_normal_far_tail() -> None:
    """An interval 8 standard deviations above the mean: draws inside it, with the exponential tail's mean."""
    rng = np.random.default_rng(0)
    z = sp.truncated_normal(np.zeros(N), 1.0, np.full(N, 8.0), np.full(N, 9.0), rng)
    assert z.min() >= 8.0 and z.max() <= 9.0
    assert abs(z.mean() - (8.0 + 1 / 8.0 - 2 / 8.0**3)) < 0.01  # Mills ratio: E[z | z > a] ≈ a + 1/a − 2/a³


@pytest.mark.parametrize("name", list(sp.PROBLEMS))
def test_likelihood_matches_simulator(name: str) -> None:
    """For one θ, exp(log p(x | θ)) integrates to 1 over x and has the mean of simulated x (2-D problems on a grid;
    the 10-D Gaussian is a product of 1-D normals, compared with its closed form)."""
    problem = sp.get_problem(name)
    rng = np.random.default_rng(1)
    theta = problem.low + 0.3 * (problem.high - problem.low)
    xs = problem.simulate(np.repeat(theta[None], N, axis=0), rng)
    if name == "slcp":
        from scipy.stats import multivariate_normal

        s1, s2, rho = theta[2] ** 2, theta[3] ** 2, math.tanh(theta[4])
        cov = np.array([[s1**2, rho * s1 * s2], [rho * s1 * s2, s2**2]])
        mvn = multivariate_normal(theta[:2], cov)
        expected = mvn.logpdf(xs[:5].reshape(5, 4, 2)).sum(axis=1)
        np.testing.assert_allclose(problem.log_likelihood(theta[None], xs[:5]), expected, rtol=1e-10)
        np.testing.assert_allclose(np.cov(xs.reshape(-1, 2).T), cov, rtol=0.03, atol=1e-3)
        np.testing.assert_allclose(xs.reshape(-1, 2).mean(axis=0), theta[:2], atol=0.02)
        return
    if problem.dim > 2:
        from scipy.stats import multivariate_normal

        mvn = multivariate_normal(theta, 0.1 * np.eye(problem.dim))
        np.testing.assert_allclose(problem.log_likelihood(theta[None], xs[0]), mvn.logpdf(xs[0]), rtol=1e-10)
        np.testing.assert_allclose(np.cov(xs.T), 0.1 * np.eye(problem.dim), atol=0.01)
        return
    step = 0.002 if name == "two_moons" else 0.01
    lo, hi = xs.min(axis=0) - 0.5, xs.max(axis=0) + 0.5
    axes = [np.arange(a + step / 2, b, step) for a, b in zip(lo, hi, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 2)
    dens = np.exp(problem.log_likelihood(theta[None], grid))
    assert abs(dens.sum() * step**2 - 1) < 0.01
    np.testing.assert_allclose(dens @ grid * step**2, xs.mean(axis=0), atol=0.03)


def test_gaussian_linear_uniform_reference() -> None:
    """Truncated posterior, with x beyond the box in some dimensions: moments per dimension by 1-D quadrature (the
    likelihood factorizes, checked above against the 10-D normal)."""
    problem = sp.get_problem("gaussian_linear_uniform")
    x = np.array([1.3, -1.2, 0.95, 0.0, -0.5, 0.7, -1.6, 0.2, 1.0, -0.99])
    draws = problem.reference_posterior(x, N, np.random.default_rng(2))
    assert draws.shape == (N, 10) and problem.in_box(draws).all()
    t = np.linspace(-1, 1, 20_001)
    w = np.exp(-0.5 * (t[None, :] - x[:, None]) ** 2 / 0.1)
    w /= w.sum(axis=1, keepdims=True)
    mean = w @ t
    var = (w * (t[None, :] - mean[:, None]) ** 2).sum(axis=1)
    assert_moments(draws, mean, var)


@pytest.mark.parametrize("obs", [0, 4])
def test_two_moons_reference(obs: int) -> None:
    """Observation 0 (two crescents cut by the box) and 4 (|z₀| ≈ 0: half the nuisance draws have p₀ < x₀ and must
    be rejected; sbibm's sampler would keep them) against quadrature on a fine grid over the box."""
    problem = sp.TwoMoons()
    x = sp.observations(problem, 10)[1][obs]
    draws, _, wrong = problem.reference_posterior_with_rates(x, N, np.random.default_rng(3))
    assert problem.in_box(draws).all()
    assert (wrong > 0.3) == (obs == 4)
    mean, var = grid_moments(problem, x, problem.low, problem.high, 0.001)
    assert_moments(draws, mean, var)


def test_gaussian_mixture_reference() -> None:
    """x near a corner: the wide component is cut by two faces, so the truncated weights matter."""
    problem = sp.GaussianMixture()
    x = np.array([9.6, -9.3])
    draws = problem.reference_posterior(x, N, np.random.default_rng(4))
    assert problem.in_box(draws).all()
    w = problem.component_weights(x)
    assert w[1] > 0.55  # the narrow component keeps all its mass, the wide one loses some
    mean, var = grid_moments(problem, x, x - 7, x + 7, 0.005)
    assert_moments(draws, mean, var)


def test_slcp_reference() -> None:
    """The rejection sampler in (m, Σ) against self-normalized importance sampling of prior × likelihood in θ, which
    shares none of its algebra (the proposal, the Jacobian). Moments of (θ₁, θ₂, |θ₃|, |θ₄|, θ₅) within 5 standard
    errors (both estimates' noise; the weights' effective sample size ~2·10⁴). The sampler with a proposal of ν = 2
    or 3 instead of 5/2 (its acceptance ratio then wrong) fails it by 12–19 standard errors."""
    problem = sp.SLCP()
    x = sp.observations(problem, 10)[1][2]
    draws, rate = problem.reference_posterior_with_rate(x, N, np.random.default_rng(6))
    assert draws.shape == (N, 5) and problem.in_box(draws).all() and 0 < rate <= 1

    def summary(theta: np.ndarray) -> np.ndarray:
        return np.column_stack([theta[:, :2], np.abs(theta[:, 2:4]), theta[:, 4]])

    prior = problem.prior(2_000_000, np.random.default_rng(7))
    log_w = problem.log_likelihood(prior, x)
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    ess = 1 / np.sum(w**2)
    assert ess > 10_000
    mean = w @ summary(prior)
    var = w @ (summary(prior) - mean) ** 2
    np.testing.assert_array_less(np.abs(summary(draws).mean(axis=0) - mean), 5 * np.sqrt(var / N + var / ess))
    np.testing.assert_allclose(summary(draws).var(axis=0), var, rtol=0.05)
    assert abs(np.mean(draws[:, 2] > 0) - 0.5) < 0.02 and abs(np.mean(draws[:, 3] > 0) - 0.5) < 0.02


def test_observations_are_fixed_and_in_the_prior() -> None:
    for name in sp.PROBLEMS:
        problem = sp.get_problem(name)
        a, b = sp.observations(problem, 10), sp.observations(problem, 10)
        np.testing.assert_array_equal(a[1], b[1])
        assert a[0].shape == (10, problem.dim) and a[1].shape == (10, problem.x_dim)
        assert problem.in_box(a[0]).all()


def test_c2st_extremes() -> None:
    """Same distribution → ≈ 0.5; disjoint → ≈ 1.0."""
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(400, 2)), rng.normal(size=(400, 2))
    assert abs(sp.c2st(a, b, early_stopping=True) - 0.5) < 0.08
    assert sp.c2st(a, b + 6.0, early_stopping=True) > 0.97


def test_rules_leave_the_10k_budget_unchanged() -> None:
    """The candidate rules that scale with the data leave the 10k budget's training (9 000 simulations) as it is."""
    from components.posterior import FlowConfig, TrainingConfig

    base = (FlowConfig(hidden_features=(128, 128)), TrainingConfig(epochs=60, patience=10, batch_size=256))
    assert bench.pidc_configs("default", 900, base) == base
    for name in ("steps", "batch", "batch-small", "steps-small", "wd"):
        assert bench.pidc_configs(name, bench.N_REF, base) == base, name
    flow, training = bench.pidc_configs("steps", 900, base)
    assert (training.epochs, training.patience) == (600, 100)
    assert bench.pidc_configs("batch", 900, base)[1].batch_size == 32
    assert bench.pidc_configs("batch-small", 900, base)[0].hidden_features == (48, 48)
    flow, training = bench.pidc_configs("steps-small", 900, base)
    assert flow.hidden_features == (48, 48) and (training.epochs, training.patience) == (600, 100)


def test_a_result_of_other_settings_is_not_reused():
    """``run_cell`` reuses a pidc result file only when its flow and training settings are today's: the 10-D
    Gaussian's 1k record trained before ``train.few_features_recipe`` (the same params with it null) is stale, one
    of today's settings is current, another setting's is not; sbi's files carry no settings of ours."""
    import argparse
    import json
    from dataclasses import asdict

    from components.core.config import PROJECT_ROOT, load_params

    params = load_params(PROJECT_ROOT / "params.yaml")
    before_params = params.model_copy(update={"train": params.train.model_copy(update={"few_features_recipe": None})})
    problem = sp.get_problem("gaussian_linear_uniform")
    sims = bench.simulate(problem, 1000, 0)
    n_train = len(sims.split(0.1)[0].theta)

    def record(p, setting):
        args = argparse.Namespace(pidc_params=p, seed=0, val_fraction=0.1)
        flow, training = bench.pidc_setting_configs(problem, n_train, args, setting)
        return json.loads(json.dumps({"flow": asdict(flow), "training": asdict(training), "c2st": [0.7]}))

    args = argparse.Namespace(pidc_params=params, seed=0, val_fraction=0.1)
    before, now = record(before_params, "default"), record(params, "default")
    assert before["training"]["schedule"] == "cosine" and now["training"]["schedule"] == "constant"
    assert not bench.same_settings(before, problem, sims, "pidc", "default", args)
    assert bench.same_settings(now, problem, sims, "pidc", "default", args)
    assert not bench.same_settings(now, problem, sims, "pidc", "sbi-train", args)  # sbi-train runs 2000 epochs
    assert bench.same_settings({"c2st": [0.7]}, problem, sims, "sbi", "sbi", args)
