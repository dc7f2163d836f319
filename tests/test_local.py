"""The local test L-C2ST and the named weathers' coverage, on problems whose posterior is known.

- A conjugate Gaussian: θ ~ N(0, I₂), x = θ + ε, ε ~ N(0, ½ I₂), so p(θ | x) = N(⅔ x, ⅓ I₂). The exact posterior is
  kept at the test's level (independent calibration sets, one observation each: a binomial count); a shifted and a
  too narrow one are rejected at most observations.
- A bounded toy with the weather box's faces: θ ~ U(box), x = θ + σ·ε, whose posterior is a normal truncated to the
  box (the reference model of ``benchmarks/studies/bench_named_weathers.py``): its HDIs cover their mass on average
  over the prior, and more than it at a truth on a face.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from scipy.stats import binom

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.studies.bench_named_weathers import exact_truncated_draws, toy_coverage  # noqa: E402
from components.core.seeding import rng  # noqa: E402
from components.core.weather import Box  # noqa: E402
from components.evaluate.local import LocalTest, clopper_pearson, named_coverage, posterior_summary  # noqa: E402
from components.evaluate.summary import hdi  # noqa: E402

NOISE = 0.5  # Var ε
POST_SD = np.sqrt(NOISE / (1 + NOISE))


def gaussian(g: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n pairs (θ ~ N(0, I₂), x = θ + ε): ``(n, 2)`` each."""
    theta = g.standard_normal((n, 2))
    return theta, theta + np.sqrt(NOISE) * g.standard_normal((n, 2))


def posterior_draws(g: np.random.Generator, x: np.ndarray, m: int, shift: float = 0.0, scale: float = 1.0):
    """``(n, m, 2)`` draws of N(x/(1 + σ²) + shift, scale²·σ²/(1 + σ²)): exact for shift 0 and scale 1."""
    mean = x / (1 + NOISE) + shift
    return mean[:, None, :] + scale * POST_SD * g.standard_normal((len(x), m, 2))


def fitted(seed: int, n: int, shift: float = 0.0, scale: float = 1.0, **options) -> LocalTest:
    g = rng(seed, "test", "lc2st", "calibration")
    theta, x = gaussian(g, n)
    test = LocalTest(seed=seed, **options)
    return test.fit(theta, x, posterior_draws(g, x, 1, shift, scale)[:, 0])


def test_keeps_the_exact_posterior_at_its_level():
    # 80 independent calibration sets, each tested at one new observation: under H₀ the rejections are independent
    # Bernoulli(α) and the p-values uniform on {1/20, …, 1}
    fits, level = 80, 0.05
    p = []
    for k in range(fits):
        test = fitted(k, 200, hidden=(8, 8), steps=40, null_trials=19)
        g = rng(k, "test", "lc2st", "observation")
        _, x_o = gaussian(g, 1)
        p.append(test.test(x_o[0], posterior_draws(g, x_o, 200)[0])[1])
    p = np.array(p)
    assert set(np.round(p * 20).astype(int)) <= set(range(1, 21))
    rejected = int(np.sum(p <= level))
    assert binom.ppf(0.005, fits, level) <= rejected <= binom.ppf(0.995, fits, level)
    # the mean of a uniform on {1/20, …, 1} is 0.525 with a standard deviation 0.288 (so 0.032 for the mean of 80)
    assert abs(p.mean() - 0.525) < 3 * 0.288 / np.sqrt(fits)
    assert binom.ppf(0.005, fits, 0.25) <= np.sum(p <= 0.25) <= binom.ppf(0.995, fits, 0.25)


@pytest.mark.parametrize(("shift", "scale"), [(0.5, 1.0), (0.0, 0.6)], ids=["shifted", "too narrow"])
def test_rejects_a_wrong_posterior(shift: float, scale: float):
    # shifted by 0.87 of the posterior's standard deviation, or 0.6 of its width
    test = fitted(1, 1000, shift, scale, hidden=(16, 16), steps=150, null_trials=39)
    g = rng(1, "test", "lc2st", "observations")
    _, x_o = gaussian(g, 100)
    r = test.rejections(x_o, posterior_draws(g, x_o, 200, shift, scale), level=0.05)
    assert r.rate >= 0.8
    assert r.rate > r.null_range()[1]
    assert r.p_value == pytest.approx(1 / 40)  # above every null classifier's rate: the set's smallest p-value


def test_the_exact_posterior_sits_inside_its_null_range():
    test = fitted(1, 1000, hidden=(16, 16), steps=150, null_trials=39)
    g = rng(1, "test", "lc2st", "observations")
    _, x_o = gaussian(g, 100)
    r = test.rejections(x_o, posterior_draws(g, x_o, 200), level=0.05)
    low, high = r.null_range(0.99)
    assert low <= r.rate <= high
    assert r.p_value > 1 / 40
    # each null classifier's rate is counted like the observed one's: at every observation exactly 2 of the 40
    # classifiers have p ≤ 0.05 (no ties), so the 40 rates average to 2/40
    assert (r.null_rates.sum() + r.rate) / 40 == pytest.approx(2 / 40)


def test_p_values_count_the_null_statistics_and_are_seeded():
    test = fitted(3, 100, hidden=(4, 4), steps=20, null_trials=9)
    g = rng(3, "test", "lc2st", "one")
    _, x_o = gaussian(g, 3)
    draws = posterior_draws(g, x_o, 50)
    t = test.statistics(x_o[0], draws[0])
    assert t.shape == (10,) and np.all((t >= 0) & (t <= 0.25))
    statistic, p = test.test(x_o[0], draws[0])
    assert statistic == t[0] and p == (1 + np.sum(t[1:] >= t[0])) / 10
    many = test.statistics(x_o, draws)
    np.testing.assert_allclose(many[0], t, rtol=1e-6, atol=1e-12)
    np.testing.assert_array_equal(fitted(3, 100, hidden=(4, 4), steps=20, null_trials=9).statistics(x_o, draws), many)
    assert not np.array_equal(fitted(4, 100, hidden=(4, 4), steps=20, null_trials=9).statistics(x_o, draws), many)


def test_local_test_refuses_bad_input():
    with pytest.raises(RuntimeError, match="fit"):
        LocalTest().test(np.zeros(2), np.zeros((5, 2)))
    with pytest.raises(ValueError, match=r"draws_cal must have shape \(3, 2\)"):
        LocalTest().fit(np.zeros((3, 2)), np.zeros((3, 1)), np.zeros((3, 1)))
    with pytest.raises(ValueError, match="null_trials"):
        LocalTest(null_trials=0)
    test = fitted(0, 20, hidden=(2, 2), steps=1, null_trials=1)
    with pytest.raises(ValueError, match="x_o must have shape"):
        test.test(np.zeros(3), np.zeros((5, 2)))
    with pytest.raises(ValueError, match="draws_o"):
        test.test(np.zeros(2), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="finite"):
        test.fit(np.full((3, 2), np.nan), np.zeros((3, 2)), np.zeros((3, 2)))


def test_posterior_summary_is_median_and_spread_in_logit_space():
    box = Box(np.array([0.0, -90.0]), np.array([100.0, 90.0]))
    draws = np.stack([np.linspace(10, 90, 101), np.linspace(-45, 45, 101)], axis=1)[None]  # (1, 101, 2)
    s = posterior_summary(draws, box)
    assert s.shape == (1, 4)
    np.testing.assert_allclose(s[0, :2], [0.0, 0.0], atol=1e-12)  # medians 50 and 0: the boxes' centres
    # quartiles at 30 % and 70 % of the first box, 37.5 % and 62.5 % of the second: logit(0.7) − logit(0.3) = 2 log 7/3
    np.testing.assert_allclose(s[0, 2:], np.log([2 * np.log(7 / 3), 2 * np.log(5 / 3)]), rtol=1e-12)
    with pytest.raises(ValueError, match="draws must have shape"):
        posterior_summary(draws[0], box)


def test_clopper_pearson_covers_at_least_its_level():
    low, high = clopper_pearson(17, 24)
    assert (round(float(low), 3), round(float(high), 3)) == (0.489, 0.874)
    for n in (24, 100):
        k = np.arange(n + 1)
        lo, hi = clopper_pearson(k, n, 0.95)
        assert lo[0] == 0.0 and hi[-1] == 1.0 and np.all(np.diff(lo) > 0) and np.all(np.diff(hi) > 0)
        for p in np.linspace(0.01, 0.99, 49):  # the exact coverage of the interval at every rate p
            assert binom.pmf(k, n, p)[(lo <= p) & (p <= hi)].sum() >= 0.95 - 1e-9
    with pytest.raises(ValueError, match="covered"):
        clopper_pearson(25, 24)


def test_named_coverage_counts_faces_within_the_tolerance():
    box = Box(np.array([0.0, 0.0]), np.array([100.0, 100.0]))
    truth = np.array([[50.0, 0.0], [50.0, 0.0], [50.0, 100.0], [50.0, 100.0]])
    low = np.array([[40.0, 0.4], [51.0, 0.6], [49.0, 90.0], [40.0, 90.0]])
    high = np.array([[60.0, 10.0], [60.0, 10.0], [50.0, 99.6], [49.9, 99.4]])
    c = named_coverage(truth, low, high, box, tolerance=0.5, mass=0.6827)
    np.testing.assert_array_equal(c.covered, [2, 2])  # θ0: rows 0 and 2 (a closed interval); θ1: rows 0 and 2
    assert c.images == 4 and c.mass == 0.6827 and c.to_dict(box)["parameters"]["θ1"]["covered"] == 2
    np.testing.assert_array_equal(named_coverage(truth, low, high, box, tolerance=0.0).covered, [2, 0])
    with pytest.raises(ValueError, match="outside the prior box"):
        named_coverage(truth - 1, low, high, box)


def _exact_coverage(truth: np.ndarray, sigma: np.ndarray, box: Box, mass: float, seed: int, m: int = 2000):
    g = rng(seed, "test", "toy")
    x = truth + sigma * g.standard_normal(truth.shape)
    draws = exact_truncated_draws(x, sigma, box, m, g)
    assert box.contains(draws).all()
    bounds = [hdi(d, mass) for d in draws]
    return named_coverage(truth, np.array([b[0] for b in bounds]), np.array([b[1] for b in bounds]), box, mass=mass)


def test_exact_truncated_draws_follow_the_truncated_normal():
    box = Box(np.array([0.0]), np.array([100.0]))
    for x in (-40.0, 3.0, 50.0, 160.0):  # far below a face, near it, inside, far above the other
        draws = exact_truncated_draws(np.array([[x]]), np.array([10.0]), box, 20000, rng(0, "test", "truncated"))
        a, b = (0.0 - x) / 10.0, (100.0 - x) / 10.0
        assert box.contains(draws[0]).all()
        assert stats.kstest(draws[0, :, 0], stats.truncnorm(a, b, loc=x, scale=10.0).cdf).pvalue > 1e-3


@pytest.mark.parametrize("mass", [0.6827, 0.95])
def test_the_exact_posterior_covers_its_mass_on_average_over_the_prior(mass: float):
    # 2 000 draws an image: the shortest window of m draws holds a little less than its share (0.6827 → ~0.676 at
    # m = 2000, ~0.666 at m = 400), well inside the 99 % interval of 1 000 images
    box = Box.full()
    sigma = np.array([8.0, 15.0, 5.0, 20.0, 30.0, 10.0])
    truth = box.sample(rng(0, "test", "toy", "truth"), 1000)
    c = _exact_coverage(truth, sigma, box, mass, 1)
    low, high = clopper_pearson(c.covered, c.images, 0.99)
    assert np.all((low <= mass) & (mass <= high)), c.rate


def test_the_exact_posterior_covers_more_than_its_mass_on_a_face():
    # no rain: a truth on the face, where a narrow exact posterior's intervals reach the face far more often than
    # 68 % (for every x below the face and some above). A broad one (σ ≳ 20 % of the box) need not: near a face its
    # density is flat and the shortest window of draws starts anywhere in the flat part.
    box = Box.full()
    sigma = 0.05 * box.width
    truth = np.broadcast_to(box.low, (500, 6))
    c = _exact_coverage(truth, sigma, box, 0.6827, 2, m=1000)
    assert np.all(c.low > 0.6827), c.rate
    # the study's reference at a named weather: 24 images of one truth, both masses
    toy = toy_coverage(np.array([5.0, 2.0, 0.0, 45.0, 10.0, 0.0]), sigma, box, 24, 400, rng(3, "test"), 0.5)
    assert [t.mass for t in toy] == [0.6827, 0.95] and all(t.images == 24 for t in toy)
