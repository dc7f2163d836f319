"""Task III as the stage runs it (components.domains.task3): bags and fresh pools disjoint by construction, refused
when they cannot be; a whole sweep on a closed-form posterior whose sources are separable (AUC → 1 as η grows, the
calibrated false-alarm rate holding on in-ODD targets of new seeds, and a check that fails for a wrongly calibrated
detector); the metrics' naming (``<figure>_paper`` / ``<figure>_fresh``); bad params named by their key."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from scipy import stats
from scipy.stats import binomtest

from components.core.config import PROJECT_ROOT, ConfigError, parse_params
from components.core.seeding import rng
from components.domains.relative import OddDetector, false_alarm_interval
from components.domains.scenarios import in_sub_box
from components.domains.sweep import FalseAlarmCheck, NoiseSweep
from components.domains.task3 import (
    DETECTED,
    PER_ETA,
    BagSplit,
    detection_floor,
    eta_rows,
    eta_series,
    roc_rows,
    split_bags,
    task3_metrics,
)
from components.monitor.checks import FalseAlarmTest
from tests.conftest import micro_params
from tests.test_domain import GaussianPosterior
from tests.test_relative import OUT_BOX, SOURCE_BOXES, uniform_in

LAMBDA = (0.2, 0.3, 0.5)
#: probability of the false-alarm count's two-sided interval: a perfectly calibrated detector leaves it in ≤ 0.1 % of
#: seeds (each tail ≤ 0.05 %), so a failure is a finding about the detector, not bad luck
FALSE_ALARM_LEVEL = 0.999

# --- bags disjoint by construction -------------------------------------------------------------------------------

OVERLAPPING = {  # b1 ∩ b2: cloudiness in [40, 60]; b3 overlaps both, its own images have the sun in [-9°, 0°)
    "b0": {"box": {"sun_altitude_angle": [-90, -10]}, "max_images": 50},
    "b1": {"box": {"sun_altitude_angle": [0, 90], "cloudiness": [0, 60]}, "max_images": 40},
    "b2": {"box": {"sun_altitude_angle": [0, 90], "cloudiness": [40, 100]}, "max_images": 40},
    "b3": {"box": {"sun_altitude_angle": [-9, 90], "precipitation": [0, 50]}, "max_images": 15},
}


def _params(bags: dict, **task3):
    d = micro_params()
    d["task3"].update(bags=bags, **task3)
    return parse_params(d, source="params.yaml")


@pytest.fixture(scope="module")
def theta() -> np.ndarray:
    """3000 weathers uniform on the prior (the test split's distribution)."""
    return _params(OVERLAPPING).box.sample(rng(0, "test", "task3", "theta"), 3000)


def test_overlapping_boxes_give_disjoint_bags_and_pools(theta):
    bags = _params(OVERLAPPING).task3.bags
    split = split_bags(bags, theta, fresh=True)
    sets = {f"bag {n}": i for n, i in split.members.items()} | {f"pool {n}": i for n, i in split.pools.items()}
    names = list(sets)
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            assert np.intersect1d(sets[names[a]], sets[names[b]]).size == 0, (names[a], names[b])
    inside = {n: in_sub_box(theta, bags[n].box) for n in bags}
    assert np.any(inside["b1"] & inside["b2"]) and np.any(inside["b2"] & inside["b3"]), "the boxes do overlap"
    # the rule: an image in several sub-boxes belongs to the first bag (b1 before b2 before b3)
    taken = inside["b0"].copy()
    for name in ("b1", "b2", "b3"):
        own = np.flatnonzero(inside[name] & ~taken)
        mine = np.concatenate([split.members[name], split.pools[name]])
        np.testing.assert_array_equal(np.sort(mine), own)
        np.testing.assert_array_equal(split.members[name], own[: bags[name].max_images])
        assert split.pools[name].size >= split.members[name].size
        assert split.in_sub_box[name] == inside[name].sum()
        taken |= inside[name]
    assert split.given_to["b2"] == {"b1": int(np.sum(inside["b1"] & inside["b2"]))}
    assert set(split.given_to["b3"]) == {"b1", "b2"} and "b1" not in split.given_to
    again = split_bags(bags, theta, fresh=True)
    assert all(np.array_equal(again.members[n], split.members[n]) for n in bags), "deterministic"


def test_a_configuration_that_cannot_be_disjoint_is_refused(theta):
    inside_b1 = OVERLAPPING | {"b2": {"box": {"sun_altitude_angle": [10, 80], "cloudiness": [10, 50]}, "max_images": 5}}
    with pytest.raises(ValueError, match=r"task3\.bags\.b2\.box: .*sub-box of b1.*bags b2 and b1 cannot be disjoint"):
        split_bags(_params(inside_b1).task3.bags, theta, fresh=True)
    big = OVERLAPPING | {"b2": {"box": {"sun_altitude_angle": [0, 90], "cloudiness": [40, 100]}, "max_images": 400}}
    with pytest.raises(ValueError, match=r"task3\.bags\.b2\.max_images: bag b2 has \d+ test images of its own \(\d+ "):
        split_bags(_params(big).task3.bags, theta, fresh=True)
    assert split_bags(_params(big).task3.bags, theta, fresh=False).sizes()["b2"] == 400, "no fresh pool needed"
    empty = {"b3": {"box": {"sun_altitude_angle": [0, 0.001], "precipitation": [0, 0.01]}, "max_images": 3}}
    with pytest.raises(ValueError, match=r"task3\.bags\.b3\.box: no test image lies in its sub-box"):
        split_bags(_params(OVERLAPPING | empty).task3.bags, theta, fresh=False)


def test_check_disjoint_names_the_shared_sets():
    split = BagSplit({"b0": np.array([0, 1]), "b1": np.array([2, 3])}, {"b1": np.array([3, 4])}, {}, {})
    with pytest.raises(ValueError, match=r"bag b1 and the fresh pool of b1 share 1 test image\(s\) \(e\.g\. 3\)"):
        split.check_disjoint()


# --- a whole sweep on a closed-form posterior ------------------------------------------------------------------

ETAS = (0.0, 0.1, 0.3, 0.6, 1.0)
SIZES = (27, 21, 26)


@pytest.fixture(scope="module")
def synthetic():
    """Sources b1…b3 in three separated unit boxes under q(θ | x) = N(x, 0.3²), fresh pools of other observations of
    the same boxes, b0 in a box no source covers; both kinds of targets swept; the detector calibrated on 400 fresh
    in-ODD targets for α = 0.05 and checked on 400 of new seeds."""
    r = rng(4, "test", "task3", "synthetic")
    sources = [uniform_in(box, n, r) for box, n in zip(SOURCE_BOXES, SIZES, strict=True)]
    pools = [uniform_in(box, 4 * n, r) for box, n in zip(SOURCE_BOXES, SIZES, strict=True)]
    sweep = NoiseSweep(GaussianPosterior(0.3), uniform_in(OUT_BOX, 60, r), sources, LAMBDA, 16, fresh_pools=pools)
    experiments = {
        kind: [sweep.run(eta, k, seed=8, fresh=kind == "fresh") for eta in ETAS for k in range(30)]
        for kind in ("paper", "fresh")
    }
    detector, _ = sweep.calibrate(400, 0.05, seed=8, fresh=True)
    check, _ = sweep.check_false_alarms(detector, 400, seed=8, fresh=True)
    split = BagSplit(
        {f"b{k}": np.arange(n) for k, n in enumerate((60, *SIZES))},
        {f"b{k}": np.arange(4 * n) for k, n in enumerate(SIZES, start=1)},
        {f"b{k}": n for k, n in enumerate((60, *SIZES))},
        {},
    )
    metrics = task3_metrics("gauss", 16, LAMBDA, split, experiments, detector, "fresh", check, 1.0)
    return sweep, experiments, detector, check, metrics


def test_auc_grows_to_one_and_the_false_alarm_rate_holds_on_new_seeds(synthetic):
    """The sweep's AUC grows with η to 1; the detector calibrated for α = 0.05 on m = 400 fresh in-ODD targets flags
    n = 400 fresh in-ODD targets of new seeds as split conformal promises; a detector calibrated on the wrong targets
    fails that check; and out-of-ODD targets are detected from some η < 1 on.

    Why the false-alarm bound: the threshold is the r-th smallest of the m calibration gaps, r = ⌈(m + 1)(1 − α)⌉ =
    381. Calibration and checked targets are i.i.d. given the bags (same construction, disjoint seed streams) with
    continuous gaps, so the share of in-ODD gaps above the threshold is Beta(m + 1 − r, r) and the count flagged is
    beta-binomial BB(400, 20, 381) exactly. The binomial(n, α) interval (Clopper–Pearson) ignores the threshold's own
    spread and rejects a perfectly calibrated detector in ~14 % of seeds. The test asserts the count lies in the
    beta-binomial's central interval of probability ≥ 0.999 (``FalseAlarmTest``, [4, 44]): two-sided, so a detector
    that never flags fails as well as one that flags too often."""
    sweep, _, detector, check, metrics = synthetic
    auc = [metrics["eta"][f"{eta:g}"]["auc_fresh"] for eta in ETAS[1:]]
    assert auc[-1] == pytest.approx(1.0) and auc[-2] > 0.97, auc
    assert auc[0] < auc[-2] and np.all(np.diff(auc) > -0.05), f"AUC grows with η: {auc}"
    assert [metrics["eta"][f"{eta:g}"]["auc_paper"] for eta in ETAS[1:]] == pytest.approx([1.0] * 4), (
        "paper: δ = 0 at η = 0"
    )
    assert metrics["eta"]["0"]["d_e_median_paper"] < 1e-3 < metrics["eta"]["0"]["d_e_median_fresh"]
    # the promise: in-ODD targets of new seeds flagged within the beta-binomial interval of the calibrated threshold
    assert detector.rank == 381 and metrics["odd"]["rank"] == 381  # ⌈401 · 0.95⌉
    assert check.targets == "fresh" and check.n == 400 and detector.n_calibration == 400, check
    test = FalseAlarmTest.of(check, detector, FALSE_ALARM_LEVEL)
    assert test.distribution.startswith("beta-binomial") and test.low > 0, test
    assert not test.alarm, test.message("gauss")
    # the check can fail: a detector calibrated on the paper's targets (δ ≈ 0) flags fresh in-ODD targets wholesale
    wrong, _ = sweep.calibrate(100, 0.05, seed=9, fresh=False)
    bad, _ = sweep.check_false_alarms(wrong, 100, seed=9, fresh=True)
    assert bad.exceeds_alpha and bad.rate > 0.9
    bad_test = FalseAlarmTest.of(bad, wrong, FALSE_ALARM_LEVEL)
    assert bad_test.alarm and bad.flagged > bad_test.high, bad_test
    # its power: separable sources, so most targets with a large out-of-ODD share are flagged
    floor = metrics["odd"]["detects_from_eta"]
    rates = {eta: metrics["eta"][f"{eta:g}"]["flagged_rate_fresh"] for eta in ETAS}
    assert floor is not None and floor < ETAS[-1] and all(rates[e] >= DETECTED for e in ETAS if e >= floor), rates


@pytest.mark.parametrize(
    ("rates", "floor"),
    [
        ({0.0: 0.05, 0.1: 0.2, 0.3: 0.6, 0.5: 0.4, 0.7: 0.8, 1.0: 1.0}, 0.7),  # a dip at 0.5: detected from 0.7 only
        ({0.0: 0.05, 0.1: 0.5, 0.5: 0.9, 1.0: 1.0}, 0.1),
        ({0.0: 0.9, 0.5: 0.1, 1.0: 0.53}, 1.0),  # η = 0 is never a detection
        ({0.0: 0.05, 0.5: 0.1, 1.0: 0.2}, None),
    ],
)
def test_detection_floor_is_the_smallest_eta_flagged_from_there_on(rates, floor):
    assert detection_floor(rates) == floor


def test_the_metrics_name_the_target_kind_of_every_figure(synthetic):
    _, experiments, _, check, metrics = synthetic
    assert metrics["n_points"] == 16 and metrics["experiments"] == {"paper": 150, "fresh": 150}
    assert metrics["bags"]["b1"] == {"images": 27, "in_sub_box": 27, "given_to_earlier_bags": 0, "fresh_pool": 108}
    assert "fresh_pool" not in metrics["bags"]["b0"]
    odd = metrics["odd"]
    assert odd["calibrated_on"] == "fresh" and odd["false_alarms_new_seeds"] == check.to_dict()
    assert odd["false_alarms_sweep"]["n"] == 30 and odd["false_alarms_sweep"]["targets"] == "fresh"
    expected = {"repetitions"} | {f"{f}_{kind}" for f in PER_ETA for kind in ("paper", "fresh")}
    assert list(metrics["eta"]) == ["0", "0.1", "0.3", "0.6", "1"]
    assert all(set(row) == expected for row in metrics["eta"].values())
    assert (
        metrics["eta"]["0"]["auc_fresh"] is None
        and metrics["eta"]["0"]["flagged_rate_fresh"] == (odd["false_alarms_sweep"]["rate"])
    )
    rows = eta_rows(metrics)
    assert [r["eta"] for r in rows] == list(ETAS) and rows[2]["auc_fresh"] == metrics["eta"]["0.3"]["auc_fresh"]
    series = eta_series(rows)
    assert series["auc_fresh"] == {
        10: rows[1]["auc_fresh"],
        30: rows[2]["auc_fresh"],
        60: rows[3]["auc_fresh"],
        100: 1.0,
    }
    assert set(series["d_e_median_paper"]) == {0, 10, 30, 60, 100}
    roc = roc_rows(experiments)
    assert len(roc) == 31 and roc[0]["fpr"] == 0.0 and roc[-1] == {"fpr": 1.0} | {k: 1.0 for k in roc[-1] if k != "fpr"}
    assert set(roc[0]) == {"fpr"} | {f"{kind} η={eta:g}" for kind in ("paper", "fresh") for eta in ETAS[1:]}
    assert all(np.all(np.diff([row[k] for row in roc]) >= 0) for k in roc[0] if k != "fpr"), "ROC non-decreasing"


def test_the_stage_summary_names_the_lowest_auc_from_eta_03_on(synthetic):
    """The task3 stage's log line: each AUC below η = 0.3, then the lowest from there on (the target), with its η."""
    from components.domains.task3_report import auc_summary as _auc_summary
    from components.domains.task3_report import auc_text as _auc_text

    eta = synthetic[-1]["eta"]
    text = _auc_summary(eta, "fresh")
    assert text.startswith(f"η=0.1 {_auc_text(eta['0.1'], 'fresh')}, lowest at η ≥ 0.3 ")
    lowest = min(("0.3", "0.6", "1"), key=lambda k: (eta[k]["auc_fresh"], float(k)))
    assert text.endswith(f"{_auc_text(eta[lowest], 'fresh')} (η={float(lowest):g})")
    worse = {**eta, "0.6": {**eta["0.6"], "auc_fresh": 0.5, "auc_ci_low_fresh": 0.4, "auc_ci_high_fresh": 0.6}}
    assert _auc_summary(worse, "fresh").endswith("0.50 [0.40, 0.60] (η=0.6)")
    assert _auc_summary({"0": eta["0"]}, "fresh") == "n/a"  # η = 0 has no AUC


def test_false_alarm_check_interval_is_clopper_pearson():
    detector = OddDetector(1.0, 0.05, 400)
    c = FalseAlarmCheck.of(np.array([True] * 3 + [False] * 27), detector, "fresh")
    assert (c.n, c.flagged) == (30, 3) and c.rate == pytest.approx(0.1)
    exact = binomtest(3, 30).proportion_ci(confidence_level=0.95, method="exact")  # Clopper–Pearson, ≈ [0.0211, 0.2653]
    assert c.ci_low == pytest.approx(exact.low) and c.ci_high == pytest.approx(exact.high)
    # the range of a calibrated decision's count: the beta-binomial of its rank, not the binomial of α
    assert (c.calibrated_low, c.calibrated_high) == false_alarm_interval(30, 0.05, 0.95, 400, detector.rank)[:2]
    assert c.calibrated_distribution == "beta-binomial(n=30, m+1−r=20, r=381)"
    assert not c.exceeds_alpha and FalseAlarmCheck.of(np.ones(30, bool), detector, "fresh").exceeds_alpha
    assert c.to_dict()["exceeds_alpha"] is False and c.to_dict()["calibrated_high"] == c.calibrated_high
    with pytest.raises(ValueError, match="at least one"):
        FalseAlarmCheck.of(np.array([], bool), detector, "fresh")
    assert OddDetector(1.0, 0.05, 100).rank == 96


@pytest.mark.parametrize("m, n", [(400, 200), (100, 50)])
def test_a_calibrated_decision_exceeds_alpha_at_most_at_the_upper_tail(m, n):
    """``exceeds_alpha`` of a perfectly calibrated decision: its threshold the conformal rank of m exchangeable in-ODD
    gaps (Exp(1) here), n more of them decided on. Over 4 000 such runs it says "exceeds" in at most the upper tail
    (1 − 0.95)/2 of the count's beta-binomial law, within 4 binomial standard deviations; the Clopper–Pearson rule it
    replaced (α below the rate's interval) said so in 5.3 % of runs at m = 400, n = 200. A decision whose in-ODD gaps
    doubled says "exceeds" in most runs."""
    g = rng(17, "test", "exceeds-alpha", m, n)
    alpha, runs = 0.05, 4000
    detectors = [OddDetector.calibrate(g.exponential(size=m), alpha) for _ in range(runs)]
    thresholds = np.array([d.threshold for d in detectors])[:, None]
    gaps = g.exponential(size=(runs, n))
    counts, counts_grown = (gaps > thresholds).sum(1), (2.0 * gaps > thresholds).sum(1)
    # the check of a count does not depend on the gaps beyond it: each distinct count judged once, by the real check
    verdict = {
        int(k): FalseAlarmCheck.of(np.arange(n) < k, detectors[0], "fresh").exceeds_alpha
        for k in np.unique(np.r_[counts, counts_grown])
    }
    exceeds = sum(verdict[int(k)] for k in counts)
    grown = sum(verdict[int(k)] for k in counts_grown)
    rank = OddDetector(1.0, alpha, m).rank
    _, high, _ = false_alarm_interval(n, alpha, 0.95, m, rank)
    tail = float(stats.betabinom(n, m + 1 - rank, rank).sf(high))  # P(count > high) of a calibrated decision
    assert tail <= 0.025
    assert exceeds / runs <= tail + 4 * np.sqrt(tail * (1 - tail) / runs), (exceeds / runs, tail)
    assert exceeds / runs >= tail - 4 * np.sqrt(tail * (1 - tail) / runs), (exceeds / runs, tail)
    assert grown / runs > 0.5, grown / runs


# --- bad params are named by their key ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["prior"].update(fog_density=[0, 60]), r"task3\.bags\.b0\.box\.fog_density = \[50, 100\] lies "),
        (lambda d: d["task3"]["bags"]["b2"]["box"].update(precipitation=[60, 120]), r"'precipitation' = 120"),
        (lambda d: d["task3"].update(weights=[0.5, 0.7, -0.2]), r"task3\.weights\.2: Input should be greater"),
        (lambda d: d["task3"].update(weights=[0.5, 0.6, 0.1]), r"task3\.weights must sum to 1"),
        (lambda d: d["task3"].update(n_points=0), r"task3\.n_points: Input should be greater than 0"),
        (lambda d: d["task3"].update(false_alarm_targets=0), r"task3\.false_alarm_targets: Input should be greater"),
        (lambda d: d["task3"].update(smoothing="silverman"), r"task3\.smoothing: Input should be 'scott' or 'none'"),
        (lambda d: d["task3"].update(draws_per_image=1), r"task3\.draws_per_image: Input should be greater than or"),
        (lambda d: d["task3"].update(bandwidth_scale=0), r"task3\.bandwidth_scale: Input should be greater than 0"),
        (lambda d: d["task2"].update(sun_azimuth_angle=360), r"task2\.sun_azimuth_angle: Input should be less than"),
        (lambda d: d["task2"].pop("sun_azimuth_angle"), r"task2\.sun_azimuth_angle: missing key"),
        (lambda d: d["prior"].update(cloudiness=[50, 100]), r"task2\.fixed\.cloudiness = 30 lies outside the prior"),
    ],
)
def test_bad_task_params_are_named(edit, message):
    d = yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())
    edit(d)
    with pytest.raises(ConfigError, match=message):
        parse_params(d, source="params.yaml")


def test_mlflow_names_follow_the_metrics(synthetic, tmp_path, monkeypatch):
    """The task3 run in MLflow: the metrics.json keys flattened with dots, the per-η figures as series at step 100·η
    under the same ``<figure>_<kind>`` names, the ODD's target kind as a tag."""
    import mlflow

    from flows import tracking

    _, _, _, _, metrics = synthetic
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    flat = tracking.flatten_numbers({k: v for k, v in metrics.items() if k != "eta"}, "task3")
    assert flat["task3.odd.false_alarms_new_seeds.rate"] == metrics["odd"]["false_alarms_new_seeds"]["rate"]
    assert flat["task3.bags.b2.fresh_pool"] == 84 and flat["task3.weights.2"] == 0.5
    assert "task3.model" not in flat and "task3.odd.calibrated_on" not in flat, "strings are not metrics"
    series = {f"task3.{k}": v for k, v in eta_series(eta_rows(metrics)).items()}
    report = tmp_path / "metrics.json"
    report.write_text("{}")
    run_id = tracking.log_domain_task(
        tmp_path, "exp", "task3", "gauss", flat, series, [report], {"pidc.odd_calibrated_on": "fresh"}
    )
    client = mlflow.MlflowClient()
    run = client.get_run(run_id)
    assert run.info.run_name == "task3-gauss" and run.data.tags["pidc.odd_calibrated_on"] == "fresh"
    assert run.data.tags["pidc.evaluated_model"] == "gauss" and "pidc.model" not in run.data.tags
    assert run.data.metrics["task3.odd.threshold"] == pytest.approx(metrics["odd"]["threshold"], rel=1e-5)  # 6 digits
    history = {m.step: m.value for m in client.get_metric_history(run_id, "task3.auc_fresh")}
    assert history == pytest.approx(
        {
            10: metrics["eta"]["0.1"]["auc_fresh"],
            30: metrics["eta"]["0.3"]["auc_fresh"],
            60: metrics["eta"]["0.6"]["auc_fresh"],
            100: metrics["eta"]["1"]["auc_fresh"],
        }
    )
    assert [a.path for a in client.list_artifacts(run_id, "task3")] == ["task3/metrics.json"]

    # a run of the same task and model cut off by a kill (left RUNNING) is closed when the next one is logged; a
    # finished run and another model's unfinished run are left as they are
    experiment = client.get_experiment_by_name("exp").experiment_id
    cut = client.create_run(experiment, tags={"pidc.task": "task3", "pidc.evaluated_model": "gauss"}).info.run_id
    other = client.create_run(experiment, tags={"pidc.task": "task3", "pidc.evaluated_model": "cues"}).info.run_id
    again = tracking.log_domain_task(tmp_path, "exp", "task3", "gauss", flat, series, [report])
    assert client.get_run(cut).info.status == "KILLED" and client.get_run(again).info.status == "FINISHED"
    assert client.get_run(run_id).info.status == "FINISHED" and client.get_run(other).info.status == "RUNNING"
