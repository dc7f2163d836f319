"""Scheduled monitoring's parts on problems with known answers: the calibration alarm of a calibrated and of
miscalibrated synthetic posteriors, the ODD false-alarm interval against simulated exchangeable gaps, the recorded
folder's validation, and the draws of a date."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from components.core import seeding, weather
from components.core.config import load_params
from components.domains.relative import OddDetector
from components.domains.sweep import FalseAlarmCheck
from components.domains.task3 import bag_of
from components.evaluate import diagnostics, task1
from components.monitor import checks, draws
from components.monitor.recorded import LABELS, RecordedError, read_recorded
from components.simulate.contact_sheet import save_png
from components.simulate.procedural import ProceduralSimulator
from tests.conftest import write_params

LEVEL = 0.95


# --- the calibration alarm --------------------------------------------------------------------------------------


def _gaussian_run(rng: np.random.Generator, n: int, draws_per_image: int, scale: float) -> tuple[np.ndarray, ...]:
    """One monitoring run of a 2-D Gaussian posterior N(μᵢ, (scale·σ)²) whose exact posterior is N(μᵢ, σ²): the truths
    are drawn from the exact posterior, the model's draws and log-densities from the model. Returns (lp, lp_truth)."""
    sigma = 1.0
    mu = rng.normal(0.0, 5.0, size=(n, 1, 2))
    truth = mu[:, 0] + sigma * rng.standard_normal((n, 2))
    s = scale * sigma
    samples = mu + s * rng.standard_normal((n, draws_per_image, 2))

    def log_q(theta, mean):
        return -0.5 * np.sum(((theta - mean) / s) ** 2, axis=-1) - 2 * np.log(s) - np.log(2 * np.pi)

    return log_q(samples, mu), log_q(truth, mu[:, 0])


def _alarm_rate(scale: float, runs: int, n: int = 60, draws_per_image: int = 200) -> float:
    band = task1.calibration_band(n, draws_per_image, LEVEL, 1000, seed=7)
    rng = seeding.rng(11, "monitoring-test", f"{scale:g}")
    alarms = 0
    for _ in range(runs):
        lp, lp_truth = _gaussian_run(rng, n, draws_per_image, scale)
        metrics, _, _ = task1.task1_metrics(lp, lp_truth, 0.0, band)
        metrics |= {"images": n, "samples": draws_per_image}
        alarms += checks.calibration_alarm("gauss", metrics) is not None
    return alarms / runs


def test_the_test_nll_standard_error_is_the_spread_of_the_test_nll_over_repeated_test_sets():
    """task1_metrics' test_nll_se: over 300 test sets of 60 images of a known posterior, the test NLL's standard
    deviation matches the mean reported standard error (±15 %: the sampling error of a standard deviation from 300
    sets is ~4 %, of a standard error from 60 images ~10 %)."""
    rng = seeding.rng(12, "monitoring-test", "nll-se")
    nll, se = [], []
    for _ in range(300):
        lp, lp_truth = _gaussian_run(rng, 60, 20, 1.0)
        metrics, _, _ = task1.task1_metrics(lp, lp_truth, 0.0, 0.1)
        nll.append(metrics["test_nll"])
        se.append(metrics["test_nll_se"])
    assert np.std(nll, ddof=1) == pytest.approx(np.mean(se), rel=0.15)


@pytest.mark.parametrize("k", [0.5, 1.0, 2.0])
def test_task1_metrics_of_a_scaled_gaussian_posterior_have_their_closed_forms(k):
    """A 2-D Gaussian posterior k times as wide as the exact one (truths from the exact N(μᵢ, 1)): the truth lies in
    the model's HPD region of level l when χ²₂ ≤ −2k² ln(1 − l), so the expected coverage is c(l) = 1 − (1 − l)^{k²}
    (the signed coverage area is its trapezoid at the levels: k²/(k²+1) − ½ in the limit); π = U^{1/k²} for a uniform
    U, so its median is ½^{1/k²}; the test NLL is 1/k² + 2 ln k + ln 2π nats. Each figure of 2 000 images with 500
    draws is within 4.5 of its standard errors of the closed form (the coverage area's from the images' own spread,
    the median's from π's density at it, the NLL's the reported one), plus the draws' resolution 1/500 where a
    figure counts draws."""
    n, draws = 2000, 500
    rng = seeding.rng(13, "monitoring-test", "closed-forms", f"{k:g}")
    lp, lp_truth = _gaussian_run(rng, n, draws, k)
    metrics, coverage, pi = task1.task1_metrics(lp, lp_truth, 10.0, 0.1)
    levels = task1.LEVELS
    exact = 1 - (1 - levels) ** (k**2)
    area = float(np.trapezoid(exact - levels, levels))
    assert area == pytest.approx(k**2 / (k**2 + 1) - 0.5, abs=0.01)  # the levels' trapezoid is close to the integral
    cred = diagnostics.hpd_credibility(lp, lp_truth)
    per_image = np.trapezoid((cred[:, None] <= levels).astype(float) - levels, levels, axis=1)
    assert metrics["coverage_auc_gap"] == pytest.approx(float(per_image.mean()), abs=1e-12)
    se = per_image.std(ddof=1) / np.sqrt(n)
    assert abs(metrics["coverage_auc_gap"] - area) < 4.5 * se + 1 / draws, (metrics["coverage_auc_gap"], area, se)
    assert np.abs(coverage - exact).max() < 0.05  # every level, not only the area
    median = 0.5 ** (1 / k**2)
    density = k**2 * median ** (k**2 - 1)
    assert abs(metrics["pi_median"] - median) < 4.5 / (2 * density * np.sqrt(n)) + 1 / draws, (
        metrics["pi_median"],
        median,
    )
    assert np.median(pi) == metrics["pi_median"]
    nll = 1 / k**2 + 2 * np.log(k) + np.log(2 * np.pi)
    assert abs(metrics["test_nll"] - nll) < 4.5 * metrics["test_nll_se"], (metrics["test_nll"], nll)
    assert metrics["info_gain_nats"] == pytest.approx(10.0 - metrics["test_nll"], abs=1e-12)


def test_a_calibrated_posterior_raises_the_calibration_alarm_at_the_nominal_rate():
    runs = 400
    rate = _alarm_rate(1.0, runs)
    # the alarms of a calibrated model are Binomial(runs, 1 − level) (up to the band's Monte Carlo error)
    low, high = stats.binom(runs, 1 - LEVEL).ppf([0.0005, 0.9995]) / runs
    assert low <= rate <= high, (rate, low, high)


def test_a_run_of_many_calibrated_models_raises_a_calibration_alarm_at_most_at_the_nominal_rate():
    """k = 5 calibrated models judged on the same run's images: the truths θ are shared, each model reads its own
    observation x = θ + ε (flat prior, exact posterior 𝒩(x, 1): five backbones that see different things). With each
    band at model_level(level, k) a run raises any calibration alarm with probability ≤ 1 − level; with each at level
    itself, 1 − level⁵ ≈ 0.23. 300 runs of 60 images, 200 draws each."""
    runs, k, n, draws_per_image = 300, 5, 60, 200
    level = checks.model_level(LEVEL, k)
    assert level == pytest.approx(0.99)
    replicates = checks.band_replicates(1000, LEVEL, level)
    assert replicates == 5000
    bands = {
        "per model": task1.calibration_band(n, draws_per_image, level, replicates, seed=7),
        "uncorrected": task1.calibration_band(n, draws_per_image, LEVEL, 1000, seed=7),
    }
    rng = seeding.rng(17, "monitoring-test", "family")
    failed = dict.fromkeys(bands, 0)
    for _ in range(runs):
        truth = rng.normal(0.0, 5.0, size=(n, 2))
        errors = []
        for _ in range(k):
            mu = (truth + rng.standard_normal((n, 2)))[:, None]
            samples = mu + rng.standard_normal((n, draws_per_image, 2))
            lp = -0.5 * np.sum((samples - mu) ** 2, axis=-1)
            lp_truth = -0.5 * np.sum((truth - mu[:, 0]) ** 2, axis=-1)
            errors.append(diagnostics.calibration_error(diagnostics.hpd_credibility(lp, lp_truth), task1.LEVELS))
        for name, band in bands.items():
            failed[name] += max(errors) > band
    # the corrected runs' failures are at most Binomial(runs, 1 − LEVEL); the uncorrected ones' far above it
    high = stats.binom(runs, 1 - LEVEL).ppf(0.999)
    assert failed["per model"] <= high, failed
    assert failed["uncorrected"] > high, failed


def test_model_level_and_band_replicates():
    assert checks.model_level(0.99, 1) == pytest.approx(0.99)
    assert checks.model_level(0.99, 9) == pytest.approx(1 - 0.01 / 9)
    assert checks.band_replicates(2000, 0.95, 0.99) == 10000  # 100 replicates above the band, as at 95 %
    assert checks.band_replicates(2000, 0.95, 0.9) == 2000  # never fewer
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="models must be a positive integer"):
            checks.model_level(0.99, bad)
    with pytest.raises(ValueError, match=r"level must be in \(0, 1\)"):
        checks.model_level(1.0, 2)


@pytest.mark.parametrize("scale, what", [(0.5, "overconfident"), (2.0, "underconfident")])
def test_a_miscalibrated_posterior_raises_the_calibration_alarm(scale, what):
    assert _alarm_rate(scale, 40) >= 0.95, what


def test_the_calibration_alarm_names_the_model_and_the_band():
    within = {"calibration_error": 0.05, "calibration_band": 0.09, "images": 300, "samples": 500}
    assert checks.calibration_alarm("cues-5000", within) is None
    message = checks.calibration_alarm("cues-5000", within | {"calibration_error": 0.2})
    assert message.startswith("calibration alarm: cues-5000") and "0.200 on 300 images" in message
    assert "band 0.090" in message and "resized" not in message
    resized = checks.calibration_alarm("cues-5000", within | {"calibration_error": 0.2, "resized_images": 12})
    assert resized.startswith(message) and "; 12 of the images were resized from another size" in resized
    assert checks.calibration_alarm("cues-5000", within | {"resized_images": 12}) is None
    weekly = checks.calibration_alarm(
        "cues-5000", within | {"calibration_error": 0.2, "calibration_level": 1 - 0.01 / 9}
    )
    assert "outside the band 0.090 (its 99.89 % quantile) of a perfectly calibrated model" in weekly
    odd = checks.FalseAlarmTest(
        FalseAlarmCheck.of(np.ones(10, bool), OddDetector(1.0, 0.1, 100), "fresh"), LEVEL, 0, 4, "binomial", (0, 4)
    )
    found = checks.alarms({"a": within, "b": within | {"calibration_error": 0.5}}, odd, "a")
    assert [m.split(":")[0] for m in found] == ["calibration alarm", "ODD false-alarm alarm"]
    assert "b has" in found[0] and "a's ODD decision flagged 10 of 10" in found[1] and "more than" in found[1]


# --- the ODD decision's false-alarm interval --------------------------------------------------------------------


@pytest.mark.parametrize("n, alpha", [(20, 0.1), (100, 0.05), (1000, 0.05)])
def test_the_binomial_interval_holds_its_level_with_tails_of_at_most_half_the_rest(n, alpha):
    low, high, name = checks.false_alarm_interval(n, alpha, LEVEL)
    dist = stats.binom(n, alpha)
    tail = (1 - LEVEL) / 2
    assert dist.cdf(low - 1) <= tail and dist.sf(high) <= tail
    assert dist.cdf(high) - dist.cdf(low - 1) >= LEVEL
    # and it is the narrowest such: one step in from either end breaks a tail
    assert dist.cdf(low) > tail or low == high
    assert dist.sf(high - 1) > tail
    assert name.startswith("binomial")


def test_the_beta_binomial_interval_tends_to_the_binomial_one_with_many_calibration_targets():
    n, alpha = 200, 0.05
    m = 200_000
    rank = OddDetector(1.0, alpha, m).rank
    assert checks.false_alarm_interval(n, alpha, LEVEL, m, rank)[:2] == checks.false_alarm_interval(n, alpha, LEVEL)[:2]
    # with few calibration targets the threshold's own spread widens it
    small = checks.false_alarm_interval(n, alpha, LEVEL, 20, OddDetector(1.0, alpha, 20).rank)
    binomial = checks.false_alarm_interval(n, alpha, LEVEL)
    assert small[0] <= binomial[0] and small[1] > binomial[1]


def _false_alarm_counts(m: int, n: int, alpha: float, reps: int, shift: float = 1.0) -> tuple[np.ndarray, OddDetector]:
    """Flags of a threshold calibrated on m exchangeable in-ODD gaps (Exp(1)), counted on n new ones (× ``shift``)."""
    rng = seeding.rng(5, "false-alarm-counts", m, n)
    counts = np.empty(reps, dtype=int)
    for i in range(reps):
        detector = OddDetector.calibrate(rng.exponential(size=m), alpha)
        counts[i] = int(detector.decide_many(shift * rng.exponential(size=n)).sum())
    return counts, detector


def test_the_false_alarm_count_of_exchangeable_targets_stays_in_its_interval_at_the_nominal_rate():
    m, n, alpha, reps = 20, 100, 0.1, 4000
    counts, detector = _false_alarm_counts(m, n, alpha, reps)
    low, high, name = checks.false_alarm_interval(n, alpha, LEVEL, m, detector.rank)
    assert name.startswith("beta-binomial")
    rate = np.mean((counts < low) | (counts > high))
    assert rate <= (1 - LEVEL) + 3 * np.sqrt(LEVEL * (1 - LEVEL) / reps), rate
    # the count's distribution is the beta-binomial: its mean and variance
    bb = stats.betabinom(n, m + 1 - detector.rank, detector.rank)
    assert abs(counts.mean() - bb.mean()) < 4 * bb.std() / np.sqrt(reps)
    assert 0.85 < counts.var() / bb.var() < 1.15
    # the binomial interval of α ignores the threshold's spread: it alarms far more often than 1 − level
    b_low, b_high, _ = checks.false_alarm_interval(n, alpha, LEVEL)
    assert np.mean((counts < b_low) | (counts > b_high)) > 3 * (1 - LEVEL)


def test_grown_in_odd_gaps_raise_the_false_alarm_alarm():
    m, n, alpha = 100, 100, 0.05
    counts, detector = _false_alarm_counts(m, n, alpha, 200, shift=2.0)  # gaps twice as large: a drift
    low, high, _ = checks.false_alarm_interval(n, alpha, LEVEL, m, detector.rank)
    assert np.mean(counts > high) > 0.9
    test = checks.FalseAlarmTest.of(FalseAlarmCheck.of(np.arange(n) < counts[0], detector, "fresh"), detector, LEVEL)
    assert test.alarm == (counts[0] > test.high) and test.message("m").startswith("ODD false-alarm alarm")
    row = test.to_dict()
    assert row["interval_low"] == low and row["interval_high"] == high and row["flagged"] == counts[0]
    assert (row["binomial_interval_low"], row["binomial_interval_high"]) == checks.false_alarm_interval(
        n, alpha, LEVEL
    )[:2]


def test_the_false_alarm_interval_refuses_bad_arguments():
    for bad, message in (
        ({"n": 0}, r"n must be a positive integer \(a number of targets\), got 0"),
        ({"alpha": 1.0}, r"alpha must be in \(0, 1\), got 1.0"),
        ({"level": 1.5}, r"level must be in \(0, 1\), got 1.5"),
        ({"calibration_targets": 20}, "give both calibration_targets and rank, or neither"),
        ({"calibration_targets": 20, "rank": 21}, "rank must lie in 1…20 .calibration_targets., got 21"),
    ):
        args = {"n": 10, "alpha": 0.1, "level": LEVEL} | bad
        with pytest.raises(ValueError, match=message):
            checks.false_alarm_interval(**args)


def test_the_calibrated_decision_is_read_from_the_task3_metrics(tmp_path):
    metrics = {
        "model": "cues-50000",
        "bags": {
            "b0": {"images": 176},
            "b1": {"images": 27, "fresh_pool": 63},
            "b2": {"images": 21, "fresh_pool": 295},
        },
        "odd": {
            "calibrated_on": "fresh",
            "false_alarm_rate": 0.05,
            "calibration_targets": 100,
            "rank": 96,
            "threshold": 0.99,
        },
    }
    odd = checks.CalibratedOdd.from_metrics(metrics, tmp_path / "metrics.json")
    assert odd.model == "cues-50000" and odd.detector == OddDetector(0.99, 0.05, 100) and odd.detector.rank == 96
    assert odd.bag_sizes == {"b1": 27, "b2": 21} and odd.pool_sizes == {"b1": 63, "b2": 295}
    del metrics["odd"]["threshold"]
    with pytest.raises(ValueError, match=r"metrics\.json: not the Task III metrics .*threshold.*dvc repro task3"):
        checks.CalibratedOdd.from_metrics(metrics, tmp_path / "metrics.json")


# --- a folder of recorded images --------------------------------------------------------------------------------


def _recorded(folder: Path, rows: list[list], header: list[str] | None = None, images: bool = True) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    header = header or ["image", *weather.PREDICTED]
    lines = [",".join(header)] + [",".join(str(v) for v in row) for row in rows]
    (folder / LABELS).write_text("\n".join(lines) + "\n")
    if images:
        for i, row in enumerate(rows):
            save_png(folder / str(row[0]), np.full((8 + i, 10, 3), 40 * i, dtype=np.uint8))
    return folder


GOOD = [["a.png", 20, 5, 0, 35.5, 10, 0], ["b.png", 90, 50, 100, -90, 0, 100]]


def test_a_recorded_folder_is_read_in_file_order(tmp_path):
    folder = _recorded(tmp_path / "rec", GOOD)
    rec = read_recorded(folder, weather.Box.full())
    assert rec.names == ["a.png", "b.png"] and rec.theta.tolist() == [row[1:] for row in GOOD]
    assert [im.shape for im in rec.images] == [(8, 10, 3), (9, 10, 3)]
    assert read_recorded(folder, weather.Box.full(), limit=1).names == ["a.png"]


@pytest.mark.parametrize(
    "rows, header, message",
    [
        (GOOD, ["image", *weather.PREDICTED[:-1]], r"labels\.csv: missing column\(s\) precipitation_deposits"),
        ([["a.png", 20, 5, "rainy", 35, 10, 0]], None, r"labels\.csv, line 2, column precipitation: 'rainy' is not a"),
        (
            [*GOOD, ["c.png", 20, 5, 0, 95, 10, 0]],
            None,
            r"line 4, column sun_altitude_angle: 95 lies outside \[-90, 90\]",
        ),
        ([GOOD[0], GOOD[0]], None, r"line 3, column image: 'a.png' is listed twice \(lines 2 and 3\)"),
        ([["", 20, 5, 0, 35, 10, 0]], None, r"line 2, column image: empty"),
        ([["a.png", 20, "", 0, 35, 10, 0]], None, r"line 2, column fog_density: empty"),
        ([], None, r"labels\.csv: no rows below the header"),
    ],
)
def test_bad_labels_are_named_with_file_line_and_column(tmp_path, rows, header, message):
    folder = _recorded(tmp_path / "rec", rows, header, images=False)
    with pytest.raises(RecordedError, match=message):
        read_recorded(folder, weather.Box.full())


def test_missing_folders_labels_and_images_are_named(tmp_path):
    with pytest.raises(RecordedError, match=r"rec: no such folder"):
        read_recorded(tmp_path / "rec", weather.Box.full())
    (tmp_path / "rec").mkdir()
    with pytest.raises(RecordedError, match=r"rec/labels\.csv: missing; .* columns image, cloudiness"):
        read_recorded(tmp_path / "rec", weather.Box.full())
    folder = _recorded(tmp_path / "rec", GOOD)
    (folder / "b.png").unlink()
    with pytest.raises(RecordedError, match=r"b\.png: no such file \(named on line 3 of .*labels\.csv\)"):
        read_recorded(folder, weather.Box.full())
    (folder / "b.png").write_bytes(b"not a png")
    with pytest.raises(RecordedError, match=r"b\.png: .*not an image"):
        read_recorded(folder, weather.Box.full())


def test_labels_outside_the_prior_box_are_refused(tmp_path):
    folder = _recorded(tmp_path / "rec", GOOD, images=False)
    box = weather.Box.from_mapping({"precipitation": [0, 50]})
    with pytest.raises(RecordedError, match=r"line 3, column precipitation: 100 lies outside \[0, 50\] %"):
        read_recorded(folder, box)


# --- the draws of a date ----------------------------------------------------------------------------------------


def test_the_run_date_is_the_given_day_or_the_utc_date_of_the_scheduled_start():
    assert draws.run_date("2026-11-24") == dt.date(2026, 11, 24)
    tokyo = dt.timezone(dt.timedelta(hours=9))
    assert draws.run_date(None, dt.datetime(2026, 11, 24, 5, 0, tzinfo=tokyo)) == dt.date(2026, 11, 23)
    for bad in ("24.11.2026", "2026-11-31", "2026-1-2", "yesterday"):
        with pytest.raises(ValueError, match=r"date: expected a day as YYYY-MM-DD"):
            draws.run_date(bad)
    assert draws.run_seed(1, dt.date(2026, 1, 1), "x") == draws.run_seed(1, dt.date(2026, 1, 1), "x")
    assert draws.run_seed(1, dt.date(2026, 1, 1), "x") != draws.run_seed(1, dt.date(2026, 1, 2), "x")


@pytest.fixture(scope="module")
def micro(tmp_path_factory):
    params = load_params(write_params(tmp_path_factory.mktemp("monitor-params")))
    return params, ProceduralSimulator(params.simulator.height, params.simulator.width)


def test_each_date_draws_new_images_and_the_same_date_the_same(micro):
    params, simulator = micro
    day = dt.date(2026, 11, 24)
    a = draws.simulated_draw(simulator, params, draws.run_seed(params.seed, day, "images"), 6)
    again = draws.simulated_draw(simulator, params, draws.run_seed(params.seed, day, "images"), 6)
    other = draws.simulated_draw(
        simulator, params, draws.run_seed(params.seed, day + dt.timedelta(days=1), "images"), 6
    )
    assert np.array_equal(a.images, again.images) and np.array_equal(a.theta, again.theta)
    assert not np.array_equal(a.theta, other.theta)
    assert a.images.shape == (6, params.simulator.height, params.simulator.width, 3) and a.images.dtype == np.uint8
    assert np.all(params.box.contains(a.theta))


def test_new_pools_have_the_weather_of_their_source_bag(micro):
    params, simulator = micro
    sizes = {"b1": 5, "b2": 3, "b3": 4}
    pools = draws.simulated_pools(simulator, params, 123, sizes)
    assert {s: len(p) for s, p in pools.items()} == sizes
    for name, pool in pools.items():
        assert set(bag_of(params.task3.bags, pool.theta)) == {name}
        assert pool.images.shape[0] == sizes[name]
    # recorded images are split the same way
    mixed = draws.Draw(
        [im for p in pools.values() for im in p.images],
        np.concatenate([p.theta for p in pools.values()]),
        [n for p in pools.values() for n in p.names],
    )
    assert {s: len(p) for s, p in draws.pools_of(mixed, params.task3.bags, ["b1", "b2", "b3"]).items()} == sizes


def test_a_bag_too_rare_to_draw_is_named(micro):
    params, simulator = micro
    narrow = json.loads(params.model_dump_json())
    narrow["task3"]["bags"]["b1"]["box"] = {"sun_altitude_angle": [0, 1e-3], "cloudiness": [0, 1e-3]}
    from components.core.config import parse_params

    with pytest.raises(ValueError, match=r"task3\.bags\.b1: fewer than 2 of .* belong to this bag"):
        draws.simulated_pools(simulator, parse_params(narrow), 1, {"b1": 2})
