"""Task II: weighted bags as mixtures of posteriors, mixtures of mixtures, and the exponential temporal filter.

The posterior is closed-form, q(θ | x) = N(θ; x, σ²I) on ℝ², so every density and every draw has an exact reference.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from components.core.seeding import rng
from components.domains.absolute import Domain, ExponentialFilter, Posterior, mixture_of, normalized_weights


class GaussianPosterior:
    """q(θ | x) = N(θ; x, σ² I): the observation x ∈ ℝᵈ is the posterior mean (implements the Posterior protocol)."""

    def __init__(self, sigma: float) -> None:
        self.sigma = sigma
        self.calls = 0

    def log_prob(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        self.calls += 1
        z = (theta - x) / self.sigma
        d = theta.shape[1]
        return -0.5 * np.sum(z**2, axis=1) - d * np.log(self.sigma) - 0.5 * d * np.log(2 * np.pi)

    def sample(self, x: np.ndarray, n: int, seed: int) -> np.ndarray:
        eps = rng(seed, "gaussian-posterior").standard_normal((x.shape[0], n, x.shape[1]))
        return x[:, None, :] + self.sigma * eps


def direct_log_mixture(theta: np.ndarray, centers: np.ndarray, weights: np.ndarray, sigma: float) -> np.ndarray:
    """log Σᵢ wᵢ N(θ; cᵢ, σ²I), computed independently of Domain (dense, no batching)."""
    d = theta.shape[1]
    sq = np.sum((theta[:, None, :] - centers[None, :, :]) ** 2, axis=2)
    comp = -0.5 * sq / sigma**2 - d * np.log(sigma) - 0.5 * d * np.log(2 * np.pi)
    with np.errstate(divide="ignore"):
        return np.logaddexp.reduce(comp + np.log(weights)[None, :], axis=1)


def test_gaussian_posterior_satisfies_protocol():
    assert isinstance(GaussianPosterior(1.0), Posterior)
    assert not isinstance(object(), Posterior)


def test_log_prob_matches_direct_mixture_and_batches():
    post = GaussianPosterior(0.7)
    centers = rng(1, "test", "centers").uniform(-3, 3, size=(37, 2))
    w = rng(1, "test", "weights").uniform(0, 1, size=37)
    w[5] = 0.0  # a zero-weight member is never evaluated but keeps its place
    theta = rng(1, "test", "theta").normal(size=(50, 2)) * 2
    dom = Domain(post, centers, w)
    expected = direct_log_mixture(theta, centers, w / w.sum(), 0.7)
    np.testing.assert_allclose(dom.log_prob(theta), expected, rtol=1e-12, atol=1e-12)
    assert len(dom) == 37 and dom.weights.sum() == pytest.approx(1.0)
    # many θ: the (θ, x) pairs are split over several posterior calls, same values
    big = rng(1, "test", "big").normal(size=(70_000, 2))
    post.calls = 0
    np.testing.assert_allclose(
        dom.log_prob(big)[::997], direct_log_mixture(big[::997], centers, w / w.sum(), 0.7), rtol=1e-12
    )
    assert post.calls > 1


def test_mixture_density_integrates_to_one_on_a_grid():
    post = GaussianPosterior(0.5)
    centers = np.array([[0.0, 0.0], [2.0, 1.0], [-1.0, 2.5]])
    dom = Domain(post, centers, [0.5, 0.3, 0.2])
    g = np.linspace(-5.0, 7.0, 241)  # ≥ 8σ margin around every center
    tx, ty = np.meshgrid(g, g, indexing="ij")
    dens = np.exp(dom.log_prob(np.column_stack([tx.ravel(), ty.ravel()]))).reshape(tx.shape)
    integral = np.trapezoid(np.trapezoid(dens, g, axis=1), g)
    assert integral == pytest.approx(1.0, abs=1e-6)


def test_sample_picks_members_by_weight_within_binomial_tolerance():
    post = GaussianPosterior(0.05)
    centers = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    w = np.array([0.1, 0.2, 0.3, 0.4])
    n = 20_000
    draws = Domain(post, centers, w).sample(n, seed=3)
    assert draws.shape == (n, 2)
    # σ = 0.05 and centers 10 apart: the nearest center is the member that produced the draw
    member = np.argmin(np.sum((draws[:, None, :] - centers[None]) ** 2, axis=2), axis=1)
    counts = np.bincount(member, minlength=4)
    sd = np.sqrt(n * w * (1 - w))
    assert np.all(np.abs(counts - n * w) < 4 * sd), (counts, n * w)
    chi2 = stats.chisquare(counts, n * w)
    assert chi2.pvalue > 1e-4


def test_sample_follows_the_mixture_two_sample_test():
    post = GaussianPosterior(0.8)
    centers = np.array([[0.0, 0.0], [3.0, -1.0], [-2.0, 2.0]])
    w = np.array([0.6, 0.3, 0.1])
    n = 4000
    draws = Domain(post, centers, w).sample(n, seed=11)
    r = rng(12, "test", "direct")
    direct = centers[r.choice(3, size=n, p=w)] + 0.8 * r.standard_normal((n, 2))
    for proj in (np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([0.6, 0.8])):
        assert stats.ks_2samp(draws @ proj, direct @ proj).pvalue > 1e-3
    # and the draws' log-likelihood under the mixture matches that of direct draws (same distribution)
    dom = Domain(post, centers, w)
    assert dom.log_prob(draws).mean() == pytest.approx(dom.log_prob(direct).mean(), abs=0.1)


class PatchPosterior:
    """A posterior on image-like observations x (n, 2, 3): q(θ | x) = N(θ; mean of x's rows, I) in ℝ²."""

    def __init__(self) -> None:
        self.inner = GaussianPosterior(1.0)

    def log_prob(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        return self.inner.log_prob(theta, x.mean(axis=2))

    def sample(self, x: np.ndarray, n: int, seed: int) -> np.ndarray:
        return self.inner.sample(x.mean(axis=2), n, seed)


def test_bag_of_image_like_observations():
    images = rng(13, "test", "images").normal(size=(6, 2, 3))
    dom = Domain(PatchPosterior(), images, np.arange(1.0, 7.0))
    theta = rng(13, "test", "theta").normal(size=(9, 2))
    w = np.arange(1.0, 7.0) / 21.0
    np.testing.assert_allclose(dom.log_prob(theta), direct_log_mixture(theta, images.mean(axis=2), w, 1.0), rtol=1e-12)
    assert dom.sample(7, seed=1).shape == (7, 2)


def test_sample_is_deterministic_in_seed():
    dom = Domain(GaussianPosterior(1.0), np.zeros((5, 2)))
    np.testing.assert_array_equal(dom.sample(100, seed=4), dom.sample(100, seed=4))
    assert not np.array_equal(dom.sample(100, seed=4), dom.sample(100, seed=5))


def test_mixture_of_domains_equals_weighted_mixture_of_densities():
    post = GaussianPosterior(0.6)
    r = rng(2, "test", "mixture_of")
    doms = [Domain(post, r.normal(k, 1, size=(n, 2)), r.uniform(0.1, 1, size=n)) for k, n in enumerate((4, 7, 3))]
    lam = np.array([0.2, 0.3, 0.5])
    mix = mixture_of(doms, lam)
    theta = r.normal(1, 2, size=(64, 2))
    direct = np.logaddexp.reduce(
        np.stack([np.log(l) + d.log_prob(theta) for l, d in zip(lam, doms, strict=False)]), axis=0
    )
    np.testing.assert_allclose(mix.log_prob(theta), direct, rtol=1e-12)
    assert len(mix) == 14 and mix.weights.sum() == pytest.approx(1.0)
    # a mixture of mixtures is again one: nesting equals flattening
    nested = mixture_of([mixture_of(doms[:2], [0.4, 0.6]), doms[2]], [0.5, 0.5])
    flat = mixture_of(doms, [0.2, 0.3, 0.5])
    np.testing.assert_allclose(nested.log_prob(theta), flat.log_prob(theta), rtol=1e-12)


def test_mixture_of_rejects_mismatched_domains():
    a = Domain(GaussianPosterior(1.0), np.zeros((2, 2)))
    b = Domain(GaussianPosterior(1.0), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="another posterior"):
        mixture_of([a, b], [0.5, 0.5])
    with pytest.raises(ValueError, match="mixture weights must have shape"):
        mixture_of([a, a], [1.0])
    with pytest.raises(ValueError, match="at least one domain"):
        mixture_of([], [])
    c = Domain(a.posterior, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="observations of shape"):
        mixture_of([a, c], [0.5, 0.5])


@pytest.mark.parametrize(
    ("weights", "message"),
    [
        ([1.0, 2.0], r"shape \(3,\)"),
        ([1.0, np.nan, 1.0], "finite"),
        ([1.0, np.inf, 1.0], "finite"),
        ([1.0, -0.5, 1.0], "non-negative"),
        ([0.0, 0.0, 0.0], "all zero"),
        ([[1.0, 1.0, 1.0]], r"shape \(3,\)"),
    ],
)
def test_bad_weights_are_named(weights, message):
    with pytest.raises(ValueError, match=message):
        Domain(GaussianPosterior(1.0), np.zeros((3, 2)), weights)


def test_bad_bags_and_inputs():
    post = GaussianPosterior(1.0)
    with pytest.raises(ValueError, match="bag is empty"):
        Domain(post, np.zeros((0, 2)))
    with pytest.raises(TypeError, match="Posterior protocol"):
        Domain(object(), np.zeros((3, 2)))  # type: ignore[arg-type]
    dom = Domain(post, np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"theta must have shape \(m, d\)"):
        dom.log_prob(np.zeros(2))
    with pytest.raises(ValueError, match="finite"):
        dom.log_prob(np.array([[np.nan, 0.0]]))
    with pytest.raises(ValueError, match="positive integer"):
        dom.sample(0, seed=1)
    np.testing.assert_allclose(normalized_weights([1, 3], 2), [0.25, 0.75])


def closed_form_filter_weights(batch_sizes: list[int], decay: float) -> np.ndarray:
    ages = np.concatenate([np.full(b, len(batch_sizes) - 1 - t) for t, b in enumerate(batch_sizes)])
    w = decay ** ages.astype(float)
    return w / w.sum()


def test_filter_weights_equal_closed_form_decay():
    post = GaussianPosterior(1.0)
    sizes = [3, 1, 4, 1, 5, 9, 2, 6]
    filt = ExponentialFilter(post, decay=0.8)
    r = rng(5, "test", "stream")
    batches = [r.normal(size=(b, 2)) for b in sizes]
    for x in batches:
        filt.update(x)
    np.testing.assert_allclose(filt.weights, closed_form_filter_weights(sizes, 0.8), rtol=1e-12)
    assert len(filt) == sum(sizes) and filt.steps == len(sizes)
    dom = filt.domain()
    expected = Domain(post, np.concatenate(batches), closed_form_filter_weights(sizes, 0.8))
    theta = r.normal(size=(20, 2))
    np.testing.assert_allclose(dom.log_prob(theta), expected.log_prob(theta), rtol=1e-12)


def test_filter_half_life_halves_weights():
    filt = ExponentialFilter(GaussianPosterior(1.0), half_life=4)
    for t in range(9):
        filt.update(np.full((1, 2), float(t)))
    w = filt.weights  # oldest first: ages 8, 7, ..., 0
    assert w[-1] / w[-5] == pytest.approx(2.0) and w[-1] / w[0] == pytest.approx(4.0)
    np.testing.assert_array_equal(filt.ages, np.arange(8, -1, -1))


def test_filter_with_decay_one_is_the_equally_weighted_bag():
    post = GaussianPosterior(0.9)
    filt = ExponentialFilter(post, decay=1.0)
    r = rng(6, "test", "stream")
    batches = [r.normal(size=(b, 2)) for b in (2, 5, 1, 3)]
    for x in batches:
        filt.update(x)
    plain = Domain(post, np.concatenate(batches))
    np.testing.assert_allclose(filt.weights, plain.weights, rtol=1e-12)
    theta = r.normal(size=(30, 2))
    np.testing.assert_allclose(filt.domain().log_prob(theta), plain.log_prob(theta), rtol=1e-12)


def test_filter_long_stream_stays_exact_and_bounded():
    # 2000 updates with decay 0.5: the running log-scale is folded several times and pruning bounds the size
    filt = ExponentialFilter(GaussianPosterior(1.0), decay=0.5, tolerance=1e-6)
    for t in range(2000):
        filt.update(np.full((2, 2), float(t)))
    keep = int(np.floor(np.log(1e-6) / np.log(0.5))) + 1  # ages 0..19 have 0.5^age ≥ 1e-6
    assert len(filt) == 2 * keep
    np.testing.assert_allclose(filt.weights, closed_form_filter_weights([2] * keep, 0.5), rtol=1e-10)
    np.testing.assert_array_equal(filt.domain().bag[-1], [1999.0, 1999.0])


def test_filter_max_size_keeps_the_newest():
    filt = ExponentialFilter(GaussianPosterior(1.0), decay=0.9, max_size=5)
    for t in range(4):
        filt.update(np.column_stack([np.arange(3.0) + 10 * t, np.zeros(3)]))
    dom = filt.domain()
    np.testing.assert_array_equal(dom.bag[:, 0], [21.0, 22.0, 30.0, 31.0, 32.0])
    w = 0.9 ** np.array([1, 1, 0, 0, 0.0])
    np.testing.assert_allclose(dom.weights, w / w.sum(), rtol=1e-12)


def test_filter_bad_arguments():
    post = GaussianPosterior(1.0)
    with pytest.raises(ValueError, match="exactly one"):
        ExponentialFilter(post)
    with pytest.raises(ValueError, match="exactly one"):
        ExponentialFilter(post, half_life=2, decay=0.5)
    with pytest.raises(ValueError, match="decay must be in"):
        ExponentialFilter(post, decay=1.5)
    with pytest.raises(ValueError, match="half_life"):
        ExponentialFilter(post, half_life=0)
    with pytest.raises(ValueError, match="max_size"):
        ExponentialFilter(post, decay=0.5, max_size=0)
    filt = ExponentialFilter(post, decay=0.5)
    with pytest.raises(ValueError, match="no observation yet"):
        filt.domain()
    filt.update(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="observations of shape"):
        filt.update(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="non-empty batch"):
        filt.update(np.zeros((0, 2)))
