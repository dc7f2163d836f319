"""Task III's sweep (components.domains.sweep) on a closed-form posterior: weights recovered in the ODD, detection outside,
the calibrated false-alarm rate, determinism; and the known-distribution helpers of components.domains.scenarios."""

from __future__ import annotations

import numpy as np
import pytest

from components.core import weather
from components.core.seeding import rng
from components.domains.relative import OddDetector, false_alarm_interval
from components.domains.scenarios import GaussianMixtureWeather, in_sub_box
from components.domains.sweep import NoiseSweep, experiments_by_eta, summarize_sweep
from components.evaluate.diagnostics import auc_interval
from tests.test_domain import GaussianPosterior
from tests.test_relative import OUT_BOX, SOURCE_BOXES, uniform_in

LAMBDA = (0.2, 0.3, 0.5)
#: probability of the false-alarm count's two-sided interval: a perfectly calibrated detector leaves it in ≤ 0.1 % of
#: seeds (each tail ≤ 0.05 %), so a failure is a finding about the detector, not bad luck
FALSE_ALARM_LEVEL = 0.999


@pytest.fixture(scope="module")
def sweep() -> NoiseSweep:
    r = rng(1, "test", "sweep")
    sources = [uniform_in(box, n, r) for box, n in zip(SOURCE_BOXES, (27, 21, 26), strict=False)]
    return NoiseSweep(GaussianPosterior(0.5), uniform_in(OUT_BOX, 60, r), sources, LAMBDA, n_points=16)


def test_target_weights_put_eta_on_b0_and_lambda_on_the_sources(sweep):
    w = sweep.target_weights(0.3, seed=5)
    sizes = np.cumsum([0] + sweep.sizes)
    assert w.sum() == pytest.approx(1.0) and np.all(w >= 0)
    assert w[: sizes[1]].sum() == pytest.approx(0.3)
    assert len(np.unique(np.round(w[: sizes[1]], 12))) > 1, "b0's images are randomly weighted"
    for k, lam in enumerate(LAMBDA, start=1):
        part = w[sizes[k] : sizes[k + 1]]
        assert part.sum() == pytest.approx(0.7 * lam) and np.allclose(part, part[0]), "equal inside a source bag"
    np.testing.assert_array_equal(w, sweep.target_weights(0.3, seed=5))
    with pytest.raises(ValueError, match="η must be in"):
        sweep.target_weights(1.5, seed=0)


def test_in_odd_weights_are_recovered_and_out_of_odd_targets_are_detected(sweep):
    """η = 0: the target is exactly Σ λₖ p̂ₖ, so λ̂ ≈ λ and δ ≈ 0; η ≥ 0.3: the relative gap separates (AUC ≈ 1)."""
    detector, calibration = sweep.calibrate(60, 0.1, seed=0)
    experiments = [sweep.run(eta, r, seed=0) for eta in (0.0, 0.3, 1.0) for r in range(20)]
    in_odd = [e for e in experiments if e.eta == 0.0]
    assert max(e.d_e for e in in_odd) < 0.02, "weights recovered when the target is in the ODD"
    assert max(e.relative_gap for e in in_odd) < 1e-6
    assert all(e.baseline_gap >= e.gap * (1 - 1e-6) for e in experiments), "the fitted λ̂ is never worse than chance"
    summary = summarize_sweep(experiments, detector)
    assert set(summary) == {"0", "0.3", "1"} and "auc" not in summary["0"]
    assert summary["0.3"]["auc"] > 0.99 and summary["1"]["auc"] == 1.0
    assert summary["1"]["flagged_rate"] == 1.0
    # 20 against 20 targets, every one separated: the AUC is 1, its 95 % interval is not (Newcombe: ~[0.91, 1]) and
    # is a deterministic function of the AUC and both counts
    assert summary["1"]["auc_ci_high"] == 1.0
    assert summary["1"]["auc_ci_low"] == auc_interval(1.0, 20, 20)[0] < 1.0
    assert summary["1"]["auc_gap_ci_low"] <= summary["1"]["auc_gap"] <= summary["1"]["auc_gap_ci_high"]
    # 20 of 20 flagged: Clopper–Pearson's exact lower limit (0.025)^(1/20)
    assert (
        summary["1"]["flagged_rate_ci_low"] == pytest.approx(0.025 ** (1 / 20))
        and summary["1"]["flagged_rate_ci_high"] == 1.0
    )
    assert summary["0"]["d_e_median"] < 0.02 < summary["1"]["d_e_median"]
    rel = experiments_by_eta(experiments, "relative_gap")
    assert list(rel) == [0.0, 0.3, 1.0] and rel[0.0].shape == (20,)


def test_false_alarm_rate_holds_on_fresh_in_odd_targets():
    """The detector calibrated for α = 0.2 on m = 60 fresh in-ODD targets (η = 0, each source bag replaced by a
    random subset of its held-out pool: in the ODD but not an exact mixture, so the gaps are sampling noise, far above
    the solver's round-off of ~1e-17…1e-13 that the paper's η = 0 targets give) flags n = 200 fresh in-ODD targets of
    new seeds as often as split conformal promises.

    Why the bound: the threshold is the r-th smallest of the m calibration gaps, r = ⌈(m + 1)(1 − α)⌉ = 49. Given the
    sweep's bags, calibration and checked targets are i.i.d. (same construction, disjoint seed streams) with
    continuous gaps, so the share of in-ODD gaps above the threshold is Beta(m + 1 − r, r) and the number flagged
    among n is beta-binomial BB(n, 12, 49) exactly, whatever the gaps' distribution — not binomial(n, α), which ignores
    the threshold's own spread. The test asserts the count lies in that distribution's central interval of
    probability ≥ 0.999 (``false_alarm_interval``), [10, 83]: two-sided, so a detector that flags too many (threshold
    too low) or none (threshold too high, e.g. calibrated on round-off) fails."""
    r = rng(2, "test", "sweep", "fresh")
    sizes = (27, 21, 26)
    sources = [uniform_in(box, n, r) for box, n in zip(SOURCE_BOXES, sizes, strict=True)]
    pools = [uniform_in(box, 3 * n, r) for box, n in zip(SOURCE_BOXES, sizes, strict=True)]
    sweep = NoiseSweep(GaussianPosterior(0.5), uniform_in(OUT_BOX, 60, r), sources, LAMBDA, 16, fresh_pools=pools)
    m, alpha, n = 60, 0.2, 200
    detector, calibration = sweep.calibrate(m, alpha, seed=3, fresh=True)
    check, gaps = sweep.check_false_alarms(detector, n, seed=11, fresh=True)
    # real gaps: well above round-off, and distinct (no ties, so the beta-binomial is exact)
    assert np.median(calibration) > 1e-6 and np.median(gaps) > 1e-6, (np.median(calibration), np.median(gaps))
    assert np.unique(calibration).size == m
    assert check.targets == "fresh" and check.n == n and check.flagged == int(np.sum(gaps > detector.threshold))
    low, high, name = false_alarm_interval(n, alpha, FALSE_ALARM_LEVEL, m, detector.rank)
    assert name.startswith("beta-binomial") and detector.rank == 49
    assert low > 0, "the interval must exclude a detector that never flags"
    assert low <= check.flagged <= high, f"{check.flagged} of {n} flagged, outside [{low}, {high}] of the {name}"


def test_experiments_are_deterministic_and_errors_are_clear(sweep):
    a, b = sweep.run(0.4, 3, seed=9), sweep.run(0.4, 3, seed=9)
    assert a == b and sweep.run(0.4, 4, seed=9) != a
    with pytest.raises(ValueError, match="bag b2 is empty"):
        NoiseSweep(GaussianPosterior(0.5), np.zeros((3, 2)), [np.zeros((2, 2)), np.zeros((0, 2))], (0.5, 0.5))
    with pytest.raises(ValueError, match="weights must be 2 values on the simplex"):
        NoiseSweep(GaussianPosterior(0.5), np.zeros((3, 2)), [np.zeros((2, 2)), np.ones((2, 2))], (0.5, 0.6))
    with pytest.raises(ValueError, match="η = 0"):
        summarize_sweep([sweep.run(0.5, 0, seed=0)], OddDetector(1.0, 0.05, 100))


def test_gaussian_mixture_weather_fixes_all_but_two_parameters():
    box = weather.Box.from_mapping({})
    fixed = {"cloudiness": 30.0, "sun_altitude_angle": 45.0, "wind_intensity": 20.0, "precipitation_deposits": 30.0}
    dist = GaussianMixtureWeather(
        fixed, np.array([1.0, 3.0]), np.array([[10.0, 20.0], [70.0, 80.0]]), np.array([[2.0, 2.0], [3.0, 3.0]]), box
    )
    theta = dist.sample(20000, rng(0, "test", "mixture"))
    assert theta.shape == (20000, 6) and np.all(box.contains(theta))
    for name, value in fixed.items():
        assert np.all(theta[:, box.names.index(name)] == value)
    fog = theta[:, box.names.index("fog_density")]
    share = np.mean(fog > 40)
    assert abs(share - 0.75) < 4 * np.sqrt(0.75 * 0.25 / 20000), "component weights normalized and followed"
    assert np.mean(fog[fog > 40]) == pytest.approx(70.0, abs=0.1)
    modes = dist.modes()
    assert modes.shape == (2, 6) and modes[1, box.names.index("precipitation")] == 80.0
    # truncation: a component centred on the face keeps only its inside half
    edge = GaussianMixtureWeather(fixed, np.array([1.0]), np.array([[0.0, 50.0]]), np.array([[5.0, 5.0]]), box)
    assert np.all(edge.sample(2000, rng(0, "t"))[:, box.names.index("fog_density")] >= 0)
    with pytest.raises(ValueError, match="fixed must give exactly"):
        GaussianMixtureWeather({"cloudiness": 1.0}, np.ones(1), np.zeros((1, 2)), np.ones((1, 2)), box)
    with pytest.raises(ValueError, match="outside the prior"):
        GaussianMixtureWeather(fixed | {"cloudiness": 130.0}, np.ones(1), np.zeros((1, 2)), np.ones((1, 2)), box)
    with pytest.raises(ValueError, match="positive"):
        GaussianMixtureWeather(fixed, np.ones(1), np.zeros((1, 2)), np.zeros((1, 2)), box)


def test_in_sub_box():
    theta = np.array([[50, 50, 50, -50, 50, 50], [50, 50, 50, 50, 50, 50]], dtype=float)
    np.testing.assert_array_equal(in_sub_box(theta, {"sun_altitude_angle": (-90, -15)}), [True, False])
    with pytest.raises(ValueError, match="unknown predicted parameter"):
        in_sub_box(theta, {"sunshine": (0, 1)})


def test_fresh_targets_use_held_out_images_of_the_sources_weather():
    """Fresh targets: the in-ODD part is a random same-size subset of each pool, so at η = 0 the gap is not zero
    (a new bag of the same weather) but λ is still roughly recovered, η = 1 is told apart, and the detector calibrated
    on m = 60 fresh in-ODD targets for α = 0.2 flags n = 100 fresh ones of new seeds at its rate.

    Why the false-alarm bound: the threshold is the r-th smallest of the m calibration gaps (r = ⌈(m + 1)(1 − α)⌉ =
    49), and calibration and checked targets are i.i.d. given the bags, so the count flagged is beta-binomial
    BB(n, m + 1 − r, r) = BB(100, 12, 49), not binomial(n, α). Its central interval of probability ≥ 0.999
    (``false_alarm_interval``) is [3, 44]: two-sided, so a detector that never flags fails as well as one that flags
    too often (n = 100 rather than 40 so that the lower end is above 0)."""
    r = rng(3, "test", "sweep", "pools")
    sizes = (27, 21, 26)
    sources = [uniform_in(box, n, r) for box, n in zip(SOURCE_BOXES, sizes, strict=False)]
    pools = [uniform_in(box, 3 * n, r) for box, n in zip(SOURCE_BOXES, sizes, strict=False)]
    sweep = NoiseSweep(GaussianPosterior(0.5), uniform_in(OUT_BOX, 60, r), sources, LAMBDA, 16, fresh_pools=pools)
    w = sweep.target_weights(0.0, seed=1, fresh=True)
    offsets = np.cumsum([0, 60, *sizes, *(3 * n for n in sizes)])
    assert w[: offsets[4]].sum() == 0, "the source bags themselves carry no weight in a fresh target"
    for k, (lam, n) in enumerate(zip(LAMBDA, sizes, strict=False)):
        part = w[offsets[4 + k] : offsets[5 + k]]
        assert np.count_nonzero(part) == n and part.sum() == pytest.approx(lam)
    assert not np.array_equal(w, sweep.target_weights(0.0, seed=2, fresh=True)), "a new subset per experiment"
    fresh0 = [sweep.run(0.0, k, seed=4, fresh=True) for k in range(40)]
    assert np.median([e.relative_gap for e in fresh0]) > 1e-4, "a fresh in-ODD bag is not an exact mixture"
    assert np.median([e.d_e for e in fresh0]) < 0.2
    fresh1 = [sweep.run(1.0, k, seed=4, fresh=True) for k in range(20)]
    assert min(e.relative_gap for e in fresh1) > max(e.relative_gap for e in fresh0)
    alpha = 0.2
    detector, _ = sweep.calibrate(60, alpha, seed=5, fresh=True)
    check, _ = sweep.check_false_alarms(detector, 100, seed=5, fresh=True)
    low, high, name = false_alarm_interval(check.n, alpha, FALSE_ALARM_LEVEL, 60, detector.rank)
    assert name.startswith("beta-binomial") and 0 < low
    assert low <= check.flagged <= high, f"{check.flagged} of {check.n} flagged, outside [{low}, {high}] of the {name}"
    plain = NoiseSweep(GaussianPosterior(0.5), uniform_in(OUT_BOX, 5, r), sources, LAMBDA)
    with pytest.raises(ValueError, match="fresh targets need fresh_pools"):
        plain.run(0.0, 0, seed=0, fresh=True)
    with pytest.raises(ValueError, match="fresh pool of b2 has 3 observations"):
        NoiseSweep(
            GaussianPosterior(0.5),
            uniform_in(OUT_BOX, 5, r),
            sources,
            LAMBDA,
            fresh_pools=[pools[0], pools[1][:3], pools[2]],
        )


def test_sharp_posteriors_need_the_kernel_characterization_for_fresh_targets():
    """Posteriors 100× narrower than a source box (σ = 0.02, boxes 2 wide), bags of 21–27 images: the exact mixture is
    isolated peaks, so a fresh in-ODD target's draws miss every source peak — λ̂ lands on a vertex whatever the target
    (d_E ≈ 0.62) and out-of-ODD targets are not told apart (AUC ≈ 0.5). The kernel characterization (Scott's
    bandwidth, the same for every domain) recovers λ and separates η = 0.3 from η = 0; on the paper's targets (the
    sources' own images) both give λ̂ = λ."""
    r = rng(3, "test", "sweep", "sharp")
    sizes = (27, 21, 26)
    sources = [uniform_in(box, n, r) for box, n in zip(SOURCE_BOXES, sizes, strict=True)]
    pools = [uniform_in(box, 3 * n, r) for box, n in zip(SOURCE_BOXES, sizes, strict=True)]
    out = uniform_in(OUT_BOX, 60, r)
    summary, paper = {}, {}
    for smoothing in ("none", "scott"):
        sweep = NoiseSweep(GaussianPosterior(0.02), out, sources, LAMBDA, 16, pools, smoothing=smoothing, seed=1)
        detector, _ = sweep.calibrate(60, 0.1, seed=5, fresh=True)
        experiments = [sweep.run(eta, k, seed=4, fresh=True) for eta in (0.0, 0.3) for k in range(40)]
        summary[smoothing] = summarize_sweep(experiments, detector)
        paper[smoothing] = max(sweep.run(0.0, k, seed=4).d_e for k in range(10))
    assert summary["none"]["0"]["d_e_median"] > 0.5 and summary["none"]["0.3"]["auc"] < 0.7
    assert summary["scott"]["0"]["d_e_median"] < 0.2 and summary["scott"]["0.3"]["auc"] > 0.85
    assert paper["none"] < 0.02 and paper["scott"] < 0.02
    with pytest.raises(ValueError, match="smoothing must be one of"):
        NoiseSweep(GaussianPosterior(0.02), out, sources, LAMBDA, smoothing="silverman")
    with pytest.raises(ValueError, match="draws_per_image must be an integer ≥ 2"):
        NoiseSweep(GaussianPosterior(0.02), out, sources, LAMBDA, smoothing="scott", draws_per_image=1)
    with pytest.raises(ValueError, match="bandwidth_scale must be a positive number"):
        NoiseSweep(GaussianPosterior(0.02), out, sources, LAMBDA, smoothing="scott", bandwidth_scale=0.0)


def test_false_alarm_check_uses_new_seeds_drawn_like_the_calibration(sweep):
    """The calibration, the sweep's η = 0 and the check's in-ODD targets come from three disjoint seed streams (no
    target is reused), and the check is deterministic."""
    _, calibration = sweep.calibrate(20, 0.1, seed=3)
    swept = np.array([sweep.run(0.0, r, seed=3).relative_gap for r in range(20)])
    detector = OddDetector(float(np.median(calibration)), 0.1, 20)
    check, checked = sweep.check_false_alarms(detector, 20, seed=3)
    assert len(np.intersect1d(checked, calibration)) == 0 and len(np.intersect1d(checked, swept)) == 0
    assert check.n == 20 and check.flagged == int(np.sum(checked > detector.threshold)) and check.targets == "paper"
    again, _ = sweep.check_false_alarms(detector, 20, seed=3)
    assert again == check
    with pytest.raises(ValueError, match="n_targets must be a positive integer"):
        sweep.check_false_alarms(detector, 0, seed=3)
