"""Task I by true value (components.evaluate.profile) on posteriors known in closed form.

A calibrated posterior must cover at 68 % in every bin of the truth; a posterior equal to the prior must score the
prior's error and width; a posterior twice as sharp on one half of the range must show it there and only there.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from components import plots
from components.core import seeding, weather
from components.evaluate import marginals, profile

N_IMAGES, N_DRAWS, BINS = 2000, 400, 10
BOX = weather.Box(np.zeros(2), np.full(2, 100.0), ("a", "b"))


def _calibrated(sd_of_truth, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Draws ``(N, n, 2)`` from N(μ, σ) and truths ``(N, 2)`` from the same N(μ, σ) (clipped to the box), with μ
    uniform in [20, 80] and σ = ``sd_of_truth(μ)``: a posterior calibrated by construction."""
    rng = seeding.rng(seed, "test", "profile")
    mu = rng.uniform(20.0, 80.0, size=(N_IMAGES, 1, 2))
    sd = sd_of_truth(mu)
    draws = np.clip(mu + sd * rng.standard_normal((N_IMAGES, N_DRAWS, 2)), 0.0, 100.0)
    truth = np.clip(mu[:, 0] + sd[:, 0] * rng.standard_normal((N_IMAGES, 2)), 0.0, 100.0)
    return draws, truth


def _profile(draws: np.ndarray, truth: np.ndarray, box: weather.Box = BOX) -> dict:
    return profile.truth_profile(marginals.marginal_scores(draws, truth, box), truth, box, BINS)


def test_a_calibrated_posterior_covers_at_68_percent_where_the_truths_prior_is_flat():
    """μ ~ U[20, 80], σ = 5: in the bins [30, 70) the truths' prior is flat around each truth, and a sharp calibrated
    posterior covers at its mass there; in [10, 20) only truths from the tails of μ near 20 land: under-covered."""
    p = _profile(*_calibrated(lambda mu: np.full_like(mu, 5.0)))["all"]
    for name in ("a", "b"):
        fig = p[name]
        for n, cover in zip(fig["images"][3:7], fig["coverage68"][3:7], strict=True):
            assert abs(cover - 0.68) <= 4 * math.sqrt(0.68 * 0.32 / n), (name, n, cover)
        assert fig["coverage68_high"][1] < 0.68  # conditional on the truth, not promised: see the module docstring
        assert sum(fig["images"]) == N_IMAGES
        np.testing.assert_allclose(fig["edges"], np.linspace(0, 100, BINS + 1))


def test_the_profile_shows_where_the_posterior_is_sharp():
    """σ = 2 below μ = 50 and 8 above: the median error is ≈ 0.674 σ and the 68 % interval ≈ 1.99 σ wide on each side,
    in the bins that only one side's truths reach ([20, 30): 2.5 σ below the switch for σ = 8; [60, 80): 5 σ above it
    for σ = 2). The error is taken where the truths' prior is flat too ([70, 80) lies against μ's upper end, 80)."""
    draws, truth = _calibrated(lambda mu: np.where(mu < 50.0, 2.0, 8.0))
    fig = _profile(draws, truth)["all"]["a"]
    errors, widths = np.array(fig["median_abs_error"], dtype=float), np.array(fig["width68"], dtype=float)
    n = np.array(fig["images"])
    assert abs(errors[2] - 0.674 * 2.0) < 0.3 and abs(widths[2] - 1.989 * 2.0) < 0.3, (errors[2], widths[2])
    assert abs(errors[6] - 0.674 * 8.0) < 1.0 and np.all(np.abs(widths[6:8] - 1.989 * 8.0) < 1.0), (errors, widths)
    assert n[2] > 200 and (n[6:8] > 200).all()


def test_a_posterior_equal_to_the_prior_scores_the_prior():
    rng = seeding.rng(1, "test", "profile", "prior")
    truth = rng.uniform(0.0, 100.0, size=(N_IMAGES, 2))
    draws = rng.uniform(0.0, 100.0, size=(N_IMAGES, N_DRAWS, 2))
    fig = _profile(draws, truth)["all"]["b"]
    errors = np.array(fig["median_abs_error"], dtype=float)
    prior = np.array(fig["prior_median_abs_error"], dtype=float)
    assert np.all(np.abs(errors - prior) < 3.0), (errors, prior)  # the draws' median ≈ 50 ± 2.5 (n = 400)
    np.testing.assert_allclose(prior[[0, -1]], [45.0, 45.0], atol=1.5)  # |50 − θ| over [0, 10) and [90, 100]
    np.testing.assert_allclose(fig["width68"], 68.0, atol=2.0)
    cover = np.array(fig["coverage68"])
    assert np.all(cover[[0, -1]] == 0.0) and np.all(cover[3:7] == 1.0)  # the prior's interval is [16, 84]


def test_bins_are_closed_on_the_left_and_the_last_on_both_sides_and_empty_bins_are_none():
    box = weather.Box.full()
    truth = np.tile(box.low, (4, 1))
    truth[:, 3] = [90.0, 90.0, 45.0, 0.0]  # the sun: two at the top face, one on an edge; all day but the last
    draws = np.repeat(truth[:, None, :], 50, axis=1)
    p = profile.truth_profile(marginals.marginal_scores(draws, truth, box), truth, box, 4)
    sun = p["all"]["sun_altitude_angle"]
    assert sun["edges"] == [-90.0, -45.0, 0.0, 45.0, 90.0]
    assert sun["images"] == [0, 0, 1, 3]  # 0° opens the third bin, 45° the fourth, 90° closes it
    assert sun["median_abs_error"][0] is None and sun["coverage68_low"][1] is None
    assert p["day"]["sun_altitude_angle"]["images"] == [0, 0, 0, 3]
    assert p["night"]["sun_altitude_angle"]["images"] == [0, 0, 1, 0]
    assert sun["median_abs_error"][3] == 0.0 and sun["coverage68"][3] == 1.0  # draws on the truth


def test_bad_inputs_are_named():
    draws, truth = _calibrated(lambda mu: np.full_like(mu, 5.0))
    scores = marginals.marginal_scores(draws[:10], truth[:10], BOX)
    with pytest.raises(ValueError, match="number of bins must be a positive integer, got 0"):
        profile.truth_profile(scores, truth[:10], BOX, 0)
    with pytest.raises(ValueError, match=r"truth must have the scores' shape \(10, 2\), got \(9, 2\)"):
        profile.truth_profile(scores, truth[:9], BOX, 5)
    only95 = marginals.marginal_scores(draws[:10], truth[:10], BOX, masses=(0.95,))
    with pytest.raises(ValueError, match="not the profile's 0.68"):
        profile.truth_profile(only95, truth[:10], BOX, 5)


def test_the_plot_draws_a_profile_and_names_what_it_lacks(tmp_path):
    box = weather.Box.full()
    rng = seeding.rng(2, "test", "profile", "plot")
    truth = box.sample(rng, 300)
    draws = np.clip(truth[:, None, :] + 5.0 * rng.standard_normal((300, 100, 6)), box.low, box.high)
    p = profile.truth_profile(marginals.marginal_scores(draws, truth, box), truth, box, 8)
    path = plots.save_figure(plots.truth_profile_plot(p, title="test"), tmp_path / "profile.png", dpi=60)
    assert path.stat().st_size > 10_000
    with pytest.raises(ValueError, match="non-empty mapping"):
        plots.truth_profile_plot({})
    with pytest.raises(ValueError, match="none of those asked for"):
        plots.truth_profile_plot(p, subsets=("dusk",))
    with pytest.raises(ValueError, match=r"profile\['day'\]\['cloudiness'\] lacks 'edges'"):
        plots.truth_profile_plot({"day": {"cloudiness": {}}})


def test_the_coverage_interval_of_a_bin_is_clopper_pearsons():
    p = _profile(*_calibrated(lambda mu: np.full_like(mu, 5.0)))["all"]["a"]
    k = 5
    hits = round(p["coverage68"][k] * p["images"][k])
    ci = stats.binomtest(hits, p["images"][k]).proportion_ci(0.95, method="exact")
    assert (p["coverage68_low"][k], p["coverage68_high"][k]) == pytest.approx((ci.low, ci.high))
