"""Deconvolution of a bag (components.domains.deconvolution) on a problem whose answer is known: x = θ + σε with the
exact posterior q(θ | x) = 𝒩(θ; x, σ²) (flat prior), θ drawn from a population G of narrow modes. The mixture of
posteriors is G blurred by σ; the deconvolved estimate must recover G's modes, and EM must behave as EM."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from components.core.seeding import rng
from components.domains.absolute import Domain
from components.domains.deconvolution import _proposal_log_v0, deconvolve, em_path, one_standard_error, select_steps
from components.domains.distances import wasserstein_1d


class GaussianPosterior:
    """q(θ | x) = 𝒩(θ; x, σ² I): the exact posterior of x = θ + σε under a flat prior."""

    def __init__(self, sigma: float) -> None:
        self.sigma = sigma

    def log_prob(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        return stats.norm.logpdf(theta, x, self.sigma).sum(axis=1)

    def sample(self, x: np.ndarray, n: int, seed: int) -> np.ndarray:
        return x[:, None, :] + self.sigma * rng(seed, "test", "gauss").standard_normal((len(x), n, x.shape[1]))


def _population(n: int, seed: int) -> np.ndarray:
    """G: modes at 30 and 70 (weights 0.6 / 0.4), sd 3, in the first coordinate; a point mass at 50 in the second."""
    r = rng(seed, "test", "population")
    first = np.where(r.uniform(size=n) < 0.6, 30.0, 70.0) + 3.0 * r.standard_normal(n)
    return np.stack([first, np.full(n, 50.0)], axis=1)


def _bag(n: int, sigma: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    theta = _population(n, seed)
    return theta, theta + sigma * rng(seed, "test", "noise").standard_normal(theta.shape)


def test_deconvolution_recovers_the_population_the_mixture_blurs():
    _, x = _bag(400, 10.0, 0)
    domain = Domain(GaussianPosterior(10.0), x)
    result = deconvolve(domain, draws_per_image=8, max_steps=200, folds=4, seed=1)
    truth = _population(20000, 99)
    est = result.density.sample(20000, seed=2)
    mix = domain.sample(20000, seed=3)
    w_est, w_mix = wasserstein_1d(est, truth), wasserstein_1d(mix, truth)
    # the mixture is G ⊛ 𝒩(0, 10²): W₁ ≈ 6–8 in both coordinates; deconvolved, well under half of that
    assert np.all(w_mix > 5.0)
    assert np.all(w_est < 0.45 * w_mix), (w_est, w_mix)
    assert result.steps > 1  # the data asked for more than the mixture (step 1)
    # the two modes stand apart: little mass between them, each with about its weight
    first = est[:, 0]
    assert np.mean((first > 42) & (first < 58)) < 0.1
    assert np.mean(first < 50) == pytest.approx(0.6, abs=0.06)


def test_an_uninformative_estimator_is_not_deconvolved_into_spikes():
    """σ = 200 ≫ the population's spread: held-out images cannot tell one G from another; the estimate stays broad."""
    _, x = _bag(200, 200.0, 4)
    domain = Domain(GaussianPosterior(200.0), x)
    result = deconvolve(domain, draws_per_image=8, max_steps=100, folds=4, seed=5)
    est = result.density.sample(5000, seed=6)
    assert est[:, 1].std() > 50.0  # nothing like the point mass at 50 it has no evidence for


def test_em_increases_the_likelihood_and_starts_at_the_prior_then_the_mixture():
    _, x = _bag(150, 8.0, 7)
    post = GaussianPosterior(8.0)
    draws = post.sample(x, 6, 8).reshape(-1, 2)
    log_r = Domain(post, x).member_log_prob(draws)
    w = np.full(150, 1 / 150)
    path = em_path(log_r, w, _proposal_log_v0(log_r), 50)
    assert np.all(np.diff(path.log_likelihood) >= -1e-9)
    v1 = np.exp(path.log_v[1])
    # step 1 is the mixture of posteriors: the support is a sample of it, so its weights are nearly equal
    assert 1.0 / np.sum(v1**2) > 0.9 * len(v1)


def test_the_one_standard_error_rule_on_scores_whose_answer_is_known():
    """Candidates 0…4 whose per-image scores are the best's minus a known mean gap, with a known spread across the
    images: the rule picks the first whose gap is within the standard error of the paired differences (0.1 / √N for
    a spread 0.1) — here candidate 2 (gap 0.01 ≤ 0.0141 < 0.02); with the spread ten times as large (error 0.141), candidate 1 (gap 0.02;
    candidate 0's 0.2 is still beyond it); with image weights the standard error is the weighted one."""
    n = 50
    z = np.tile([1.0, -1.0], n // 2)  # mean 0, standard deviation exactly 1 over the images
    gaps = np.array([0.2, 0.02, 0.01, 0.0, 0.005])
    best = np.linspace(-3.0, -2.0, n)
    for spread, expected in ((0.1, 2), (1.0, 1)):
        scores = best[None, :] - gaps[:, None] + spread * np.abs(gaps[:, None] > 0) * z[None, :]
        assert one_standard_error(scores, np.full(n, 1 / n)) == expected, spread
    # weights: half the images carry 0.9 of the weight; the weighted spread, not the plain one, sets the error
    w = np.where(np.arange(n) < n // 2, 0.9, 0.1) / (n // 2)
    scores = best[None, :] - gaps[:, None] + 0.1 * np.abs(gaps[:, None] > 0) * z[None, :]
    diff = scores - scores[3][None, :]
    mean = diff @ w
    se = np.sqrt((diff**2 @ w - mean**2) / n)
    assert one_standard_error(scores, w) == int(np.flatnonzero(mean >= -se)[0]) == 2


def test_select_steps_is_seeded_and_refuses_bad_folds():
    _, x = _bag(60, 8.0, 9)
    post = GaussianPosterior(8.0)
    log_r = Domain(post, x).member_log_prob(post.sample(x, 4, 10).reshape(-1, 2))
    owner = np.repeat(np.arange(60), 4)
    w = np.full(60, 1 / 60)
    a = select_steps(log_r, w, owner, 20, 3, seed=11)
    b = select_steps(log_r, w, owner, 20, 3, seed=11)
    assert a[0] == b[0] and np.array_equal(a[1], b[1])
    with pytest.raises(ValueError, match="folds must be between 2"):
        select_steps(log_r, w, owner, 20, 1, seed=11)
    with pytest.raises(ValueError, match="draws_per_image must be a positive integer"):
        deconvolve(Domain(post, x), 0, 10, 3, 0)
