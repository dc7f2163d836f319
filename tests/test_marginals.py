"""Per-parameter Task I figures on posteriors known in closed form: truncated Gaussians and the uniform prior.

Each simulated image has an exact posterior TN(μᵢ, σᵢ) on the box [0, 100] per parameter (some centred beyond a face,
so the mass piles up against it), n = 1000 draws from it and a truth drawn from it too: the central intervals must
cover at their mass within the binomial band, and the reflected KDE must give the exact log-density at the truth.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from components.core import seeding, weather
from components.evaluate import marginals

N_IMAGES, N_DRAWS = 2000, 1000
BOX2 = weather.Box(np.zeros(2), np.full(2, 100.0), ("a", "b"))


def _band(p: float, n: int, z: float = 4.0) -> float:
    """z binomial standard deviations of a share p over n images."""
    return z * math.sqrt(p * (1 - p) / n)


def _truncated(mu: np.ndarray, sd: np.ndarray, size: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    a, b = (0.0 - mu) / sd, (100.0 - mu) / sd
    return stats.truncnorm.rvs(a, b, loc=mu, scale=sd, size=size, random_state=rng)


def _exact_case(seed: int = 0, model_sd_factor: float = 1.0):
    """Draws ``(N, n, 2)`` of TN(μ, f·σ), truths ``(N, 2)`` of TN(μ, σ), and the exact log-density of the truth under
    the model's marginal ``(N, 2)``."""
    rng = seeding.rng(seed, "test", "marginals")
    mu = rng.uniform(-10.0, 110.0, size=(N_IMAGES, 1, 2))  # some beyond a face: mass piled against it
    sd = rng.uniform(2.0, 20.0, size=(N_IMAGES, 1, 2))
    draws = _truncated(mu, model_sd_factor * sd, (N_IMAGES, N_DRAWS, 2), rng)
    truth = _truncated(mu[:, 0], sd[:, 0], (N_IMAGES, 2), rng)
    f = model_sd_factor * sd[:, 0]
    exact = stats.truncnorm.logpdf(truth, (0 - mu[:, 0]) / f, (100 - mu[:, 0]) / f, loc=mu[:, 0], scale=f)
    return draws, truth, exact


def test_exact_posterior_intervals_cover_at_their_mass_and_the_kde_gives_the_exact_density():
    draws, truth, exact = _exact_case()
    scores = marginals.marginal_scores(draws, truth, BOX2)
    for i, mass in enumerate(marginals.MASSES):
        coverage = scores.covered[i].mean(axis=0)
        assert np.all(np.abs(coverage - mass) <= _band(mass, N_IMAGES)), (mass, coverage)
    # the known answer: the information gain of the exact marginal, E[log q(θ*)] − log(1/100)
    expected_gain = exact.mean(axis=0) + math.log(100.0)
    np.testing.assert_allclose(scores.log_ratio.mean(axis=0), expected_gain, atol=0.03)
    assert np.median(np.abs(scores.log_ratio - (exact + math.log(100.0)))) < 0.1  # image by image too
    assert (expected_gain > 1.0).all()  # a sharp posterior: far from the prior's 0


def test_uniform_draws_give_no_information_even_at_the_faces():
    """Draws from the prior: the reflected estimate is flat up to the faces (a plain KDE would halve it there)."""
    rng = seeding.rng(1, "test", "marginals", "uniform")
    draws = rng.uniform(0.0, 100.0, size=(N_IMAGES, N_DRAWS, 2))
    truth = rng.uniform(0.0, 100.0, size=(N_IMAGES, 2))
    scores = marginals.marginal_scores(draws, truth, BOX2)
    assert np.abs(scores.log_ratio.mean(axis=0)).max() < 0.02
    at_faces = np.tile([[0.3, 99.7]], (50, 1))
    log_q = marginals.reflected_kde_log_density(draws[:50], at_faces, BOX2)
    assert np.abs(np.median(log_q, axis=0) - math.log(1 / 100)).max() < 0.1
    # widths of the prior's central intervals: their masses, as shares of the range
    np.testing.assert_allclose(scores.width.mean(axis=(1, 2)), marginals.MASSES, atol=0.01)


def test_kde_at_a_known_density_with_a_given_bandwidth():
    """A half-normal against the lower face (σ = 10): the reflection restores the density at the face itself."""
    rng = seeding.rng(2, "test", "marginals", "half-normal")
    draws = np.abs(rng.normal(0.0, 10.0, size=(200, 4000, 2)))
    points = np.tile([[0.0, 15.0]], (200, 1))
    log_q = marginals.reflected_kde_log_density(draws, points, BOX2)
    exact = stats.halfnorm.logpdf(points, scale=10.0)
    np.testing.assert_allclose(np.median(log_q, axis=0), exact[0], atol=0.05)
    # Silverman's rule: 0.9 · σ · n^(−1/5) for a normal sample (σ = 5, n = 1000, far from the faces)
    normal = 50.0 + 5.0 * rng.normal(size=(50, 1000, 2))
    h = marginals.silverman_bandwidth(normal, BOX2)
    assert h.shape == (50, 2) and np.median(h) == pytest.approx(0.9 * 5.0 * 1000**-0.2, rel=0.05)
    h = np.full((200, 2), 0.5)  # a given bandwidth is used as it is: a narrow kernel is noisier, not biased
    np.testing.assert_allclose(
        np.median(marginals.reflected_kde_log_density(draws, points, BOX2, bandwidth=h), axis=0), exact[0], atol=0.1
    )


def test_overconfident_posterior_undercovers_and_a_wider_one_has_wider_intervals():
    rng = seeding.rng(3, "test", "marginals", "width")
    truth = 50.0 + 5.0 * rng.normal(size=(N_IMAGES, 2))
    narrow = 50.0 + 2.5 * rng.normal(size=(N_IMAGES, N_DRAWS, 2))  # the truth's sd is 5: σ/2
    exact = 50.0 + 5.0 * rng.normal(size=(N_IMAGES, N_DRAWS, 2))
    wide = 50.0 + 10.0 * rng.normal(size=(N_IMAGES, N_DRAWS, 2))
    box = weather.Box(np.full(2, -100.0), np.full(2, 200.0), ("a", "b"))  # wide: no draw near a face
    s_narrow, s_exact, s_wide = (marginals.marginal_scores(d, truth, box) for d in (narrow, exact, wide))
    # the 68 % interval of N(50, 2.5²) holds a truth of N(50, 5²) with probability P(|Z| < 0.497) = 0.381
    p = stats.norm.cdf(0.4972) - stats.norm.cdf(-0.4972)
    assert np.all(np.abs(s_narrow.covered[0].mean(axis=0) - p) <= _band(p, N_IMAGES))
    assert np.all(s_wide.covered[1].mean(axis=0) > 0.99)
    # widths: the central 68 % (95 %) interval of N(μ, σ²) is 2 · 0.9945 σ (2 · 1.96 σ) wide
    for scores, sd in ((s_narrow, 2.5), (s_exact, 5.0), (s_wide, 10.0)):
        np.testing.assert_allclose(scores.width[0].mean(axis=0), 2 * 0.99446 * sd / 300, rtol=0.02)
        np.testing.assert_allclose(scores.width[1].mean(axis=0), 2 * 1.95996 * sd / 300, rtol=0.02)
    # |median − truth| of the exact posterior: the median of |N(0, σ²)| is 0.6745 σ (here the posterior's mean is 50)
    np.testing.assert_allclose(np.median(s_exact.abs_error, axis=0), 0.6745 * 5.0, rtol=0.06)
    # the wrong widths lose information against the exact posterior (the log score is proper)
    assert (s_exact.log_ratio.mean(0) > s_narrow.log_ratio.mean(0)).all()
    assert (s_exact.log_ratio.mean(0) > s_wide.log_ratio.mean(0)).all()


def test_a_truth_beyond_every_draw_costs_log_n_nats_not_the_kernel_tail():
    """The defensive mixture's floor: n draws far from the truth give the information gain −log n (the kernel's tail
    alone would give thousands of nats below it); truths inside the draws keep the kernel estimate."""
    rng = seeding.rng(5, "test", "marginals", "floor")
    draws = 20.0 + rng.normal(size=(40, 500, 2))  # sd 1 around 20
    truth = np.tile([[70.0, 20.0]], (40, 1))  # parameter a: 50 sd away; b: at the mode
    scores = marginals.marginal_scores(draws, truth, BOX2)
    np.testing.assert_allclose(scores.log_ratio[:, 0], -math.log(500), atol=1e-6)
    kde = marginals.reflected_kde_log_density(draws, truth, BOX2) + math.log(100.0)
    assert kde[:, 0].max() < -100  # the tail of the kernel
    np.testing.assert_allclose(scores.log_ratio[:, 1], kde[:, 1], atol=0.003)  # resolved: within ~1/n


def test_day_night_report_of_the_weather_box():
    box = weather.Box.full()
    rng = seeding.rng(4, "test", "marginals", "report")
    truth = box.sample(rng, 300)
    draws = np.clip(truth[:, None, :] + rng.normal(size=(300, 500, 6)) * box.width / 20, box.low, box.high)
    report = marginals.parameter_report(draws, truth, box)
    assert list(report) == ["all", "day", "night"] and list(report["day"]) == list(weather.PREDICTED)
    day = int((truth[:, 3] > 0).sum())
    assert report["day"]["cloudiness"]["images"] == day and report["night"]["fog_density"]["images"] == 300 - day
    assert set(report["all"]["sun_altitude_angle"]) == set(marginals.FIGURES)
    # a sun sharper in daylight (lower error) shows up split by the true altitude
    sharp = draws.copy()
    sharp[truth[:, 3] > 0, :, 3] = np.clip(truth[truth[:, 3] > 0, None, 3] + rng.normal(size=(day, 500)), -90, 90)
    split = marginals.parameter_report(sharp, truth, box)
    assert (
        split["day"]["sun_altitude_angle"]["median_abs_error"]
        < split["night"]["sun_altitude_angle"]["median_abs_error"] / 3
    )
    flat = marginals.flat_errors(split, dict(zip(weather.PREDICTED, weather.SHORT_NAMES, strict=True)))
    assert flat["err_day_sun"] == split["day"]["sun_altitude_angle"]["median_abs_error"] and len(flat) == 12
    toy = marginals.parameter_report(draws[:, :, :2], truth[:, :2], BOX2)
    assert list(toy) == ["all"]  # no sun altitude: no day/night split


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match=r"samples must have shape \(N, n, 2\)"):
        marginals.marginal_scores(np.zeros((3, 10)), np.zeros((3, 2)), BOX2)
    with pytest.raises(ValueError, match=r"truth must have shape \(3, 2\)"):
        marginals.marginal_scores(np.zeros((3, 10, 2)), np.zeros((2, 2)), BOX2)
    with pytest.raises(ValueError, match="samples must be finite and lie inside the box"):
        marginals.marginal_scores(np.full((3, 10, 2), 150.0), np.zeros((3, 2)), BOX2)
    with pytest.raises(ValueError, match="bandwidth must be positive"):
        marginals.reflected_kde_log_density(np.ones((3, 10, 2)), np.ones((3, 2)), BOX2, bandwidth=np.zeros((3, 2)))


@pytest.mark.parametrize("n", [30, 200])
def test_the_median_interval_holds_the_median_as_often_as_promised(n: int) -> None:
    """Distribution-free: on exponential samples (median log 2) the order-statistic interval holds the true median with
    its exact binomial probability (≥ 95 %, 95.7 % at n = 30, 95.4 % at 200), measured on 4000 samples (4 binomial
    standard deviations)."""
    rng = seeding.rng(5, "test", "marginals", "median", n)
    samples = rng.exponential(size=(4000, n))
    inside = [lo <= math.log(2) <= hi for lo, hi in map(marginals.median_interval, samples)]
    low_rank = int(np.searchsorted(np.sort(samples[0]), marginals.median_interval(samples[0])[0])) + 1
    exact = 1 - 2 * stats.binom.cdf(low_rank - 1, n, 0.5)
    narrower = 1 - 2 * stats.binom.cdf(low_rank, n, 0.5)  # the next rank in: the narrowest interval that holds 95 %
    assert exact >= 0.95 > narrower, (exact, narrower)
    assert abs(np.mean(inside) - exact) < _band(exact, 4000)


def test_coverage_intervals_hold_the_coverage_and_bracket_the_share() -> None:
    """A calibrated posterior's 68 % coverage is within 4 binomial standard deviations of 0.6827 (a single 95 %
    interval would miss it in 1 of 20 seeds; its coverage over replicates is checked against scipy in
    ``test_profile.py``); the Clopper–Pearson interval brackets the share and narrows as 1/√n; a median error's interval
    brackets the median."""
    rng = seeding.rng(6, "test", "marginals", "intervals")
    mu = rng.uniform(20, 80, size=(N_IMAGES, 2))
    draws = np.clip(mu[:, None, :] + 5 * rng.normal(size=(N_IMAGES, 400, 2)), 0, 100)
    truth = np.clip(mu + 5 * rng.normal(size=(N_IMAGES, 2)), 0, 100)
    full = marginals.parameter_report(draws, truth, BOX2)["all"]["a"]
    half = marginals.parameter_report(draws[:500], truth[:500], BOX2)["all"]["a"]
    for fig in (full, half):
        assert fig["coverage68_low"] < fig["coverage68"] < fig["coverage68_high"]
        assert abs(fig["coverage68"] - 0.6827) < 4 * math.sqrt(0.6827 * 0.3173 / fig["images"]), fig["coverage68"]
        assert fig["median_abs_error_low"] < fig["median_abs_error"] < fig["median_abs_error_high"]
    width = {k: f["coverage68_high"] - f["coverage68_low"] for k, f in (("full", full), ("half", half))}
    assert width["half"] / width["full"] == pytest.approx(2.0, rel=0.1)  # √(2000 / 500)
    assert math.isnan(marginals.coverage_interval(0, 0)[0]) and math.isnan(marginals.median_interval(np.ones(5))[0])
