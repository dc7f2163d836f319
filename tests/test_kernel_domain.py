"""The kernel characterization of a bag (components.domains.kernel): a proper density, its draws follow it, a
mixture of domains is the mixture of their densities, and Scott's rule."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from components.core.seeding import rng
from components.domains.kernel import KernelDomain, scott_bandwidth, sources_bandwidth


def _draws(seed: int, n: int = 5, m: int = 7, d: int = 2) -> np.ndarray:
    r = rng(seed, "test", "kernel")
    return r.uniform(0.0, 10.0, size=(n, 1, d)) + r.normal(size=(n, m, d))


def test_density_is_the_weighted_gaussian_mixture_and_integrates_to_one():
    draws, w, h = _draws(0), np.array([1.0, 2.0, 0.0, 3.0, 4.0]), np.array([0.7, 1.3])
    dom = KernelDomain(draws, w, h)
    theta = rng(1, "test", "kernel", "points").uniform(-3.0, 13.0, size=(50, 2))
    wn = w / w.sum()
    direct = sum(
        wn[i] / draws.shape[1] * stats.multivariate_normal(draws[i, j], np.diag(h**2)).pdf(theta)
        for i in range(5)
        for j in range(draws.shape[1])
    )
    np.testing.assert_allclose(dom.log_prob(theta), np.log(direct), rtol=1e-10)
    g = np.linspace(-10.0, 20.0, 301)
    grid = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    assert np.exp(dom.log_prob(grid)).sum() * (g[1] - g[0]) ** 2 == pytest.approx(1.0, abs=1e-6)


def test_the_block_size_of_log_prob_is_a_matter_of_speed(monkeypatch):
    """log p̃ in blocks of 1, 3 or all points (``_CENTRES_PER_CALL``) is the same density: rounding at most."""
    import components.domains.kernel as kernel

    draws = _draws(2, n=40, m=16, d=6)  # 640 centres
    dom = KernelDomain(draws, None, np.full(6, 0.8))
    theta = rng(3, "test", "kernel", "blocks").uniform(-1.0, 11.0, size=(64, 6))
    whole = dom.log_prob(theta)
    for pairs in (640, 3 * 640):  # blocks of one θ, of three (the last one shorter)
        monkeypatch.setattr(kernel, "_CENTRES_PER_CALL", pairs)
        np.testing.assert_allclose(dom.log_prob(theta), whole, rtol=1e-13, atol=0)


def test_draws_follow_the_density():
    dom = KernelDomain(_draws(2), None, np.array([0.5, 2.0]))
    x = dom.sample(20000, seed=3)
    np.testing.assert_array_equal(x, dom.sample(20000, seed=3))
    # the mixture's mean and covariance: the centres' plus diag h²
    c = _draws(2).reshape(-1, 2)
    assert np.all(np.abs(x.mean(0) - c.mean(0)) <= 4 * np.sqrt(np.cov(x.T).diagonal() / 20000))
    np.testing.assert_allclose(np.cov(x.T), np.cov(c.T, bias=True) + np.diag([0.25, 4.0]), rtol=0.05, atol=0.1)
    # the whole law, not only its moments: on three directions u the draws' projections follow the mixture's exact
    # CDF, the mean over the centres of Φ((t − u·c) / ‖u h‖) (Kolmogorov–Smirnov, each at 0.001: a sampler with
    # other kernel widths or centre weights fails it)
    from scipy import stats

    def mixture_cdf(centres: np.ndarray, scale: float):
        return lambda t: stats.norm.cdf((np.asarray(t)[..., None] - centres) / scale).mean(-1)

    h = np.array([0.5, 2.0])
    for u in (np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([0.6, 0.8])):
        result = stats.kstest(x @ u, mixture_cdf(c @ u, float(np.linalg.norm(u * h))))
        assert result.pvalue > 1e-3, (u, result)
    wide = KernelDomain(_draws(2), None, 1.3 * h).sample(20000, seed=3)  # the same test sees a 1.3× wider kernel
    assert stats.kstest(wide[:, 0], mixture_cdf(c[:, 0], 0.5)).pvalue < 1e-3


def test_a_reweighting_of_one_set_of_draws_is_the_mixture_of_the_parts():
    """What the paper's Task III targets rely on: the target Σ λₖ (its images) has density Σ λₖ p̃ₖ exactly."""
    draws, h = _draws(4, n=9), np.array([1.0, 1.0])
    parts = [KernelDomain(draws[a:b], None, h) for a, b in ((0, 2), (2, 5), (5, 9))]
    lam = np.array([0.2, 0.3, 0.5])
    w = np.concatenate([np.full(2, 0.2 / 2), np.full(3, 0.3 / 3), np.full(4, 0.5 / 4)])
    theta = rng(5, "test", "kernel").uniform(0.0, 10.0, size=(30, 2))
    mix = np.log(sum(lam[k] * np.exp(parts[k].log_prob(theta)) for k in range(3)))
    np.testing.assert_allclose(KernelDomain(draws, w, h).log_prob(theta), mix, rtol=1e-12)


def test_scott_bandwidth_and_errors():
    r = rng(6, "test", "kernel", "scott")
    draws = r.normal(0.0, [2.0, 5.0, 1.0], size=(40000, 1, 3))
    np.testing.assert_allclose(scott_bandwidth(draws), np.array([2.0, 5.0, 1.0]) * 40000 ** (-1 / 7), rtol=0.02)
    one, two = _draws(7), _draws(8)
    np.testing.assert_allclose(sources_bandwidth([one, two]), (scott_bandwidth(one) + scott_bandwidth(two)) / 2)
    with pytest.raises(ValueError, match="do not vary in parameter"):
        sources_bandwidth([np.ones((3, 4, 2))])
    with pytest.raises(ValueError, match=r"draws must have shape \(N images, m draws, d\)"):
        KernelDomain(np.ones((3, 2)), None, np.ones(2))
    with pytest.raises(ValueError, match="bandwidth must be 2 positive"):
        KernelDomain(_draws(0), None, np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match=r"theta must be finite of shape \(k, 2\)"):
        KernelDomain(_draws(0), None, np.ones(2)).log_prob(np.ones((3, 3)))
    with pytest.raises(ValueError, match="n must be a positive integer"):
        KernelDomain(_draws(0), None, np.ones(2)).sample(0, seed=1)
