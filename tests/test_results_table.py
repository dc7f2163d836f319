"""scripts/results_table.py on a small reports folder written as the stages write it: Task I's metrics, champion
pointer and table from the evaluate stage's own functions (:func:`components.evaluate.task1.task1_metrics`,
:func:`components.evaluate.champion.champion_pointer`, :func:`components.evaluate.report.results_table`), Task II's from
:func:`components.domains.task2.task2_metrics` on a closed-form posterior, Task III's from
:func:`components.domains.task3.task3_metrics` on a small sweep. The blocks land between their markers and nowhere
else, ``--check`` tells a stale file, ``--print`` writes nothing, and a missing report or marker is a clear error."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from components.core.config import PROJECT_ROOT, parse_params
from components.core.seeding import rng
from components.domains.absolute import Domain
from components.domains.sweep import NoiseSweep
from components.domains.task2 import task2_metrics as score_task2
from components.domains.task2 import true_distribution, width_floor
from components.domains.task3 import BagSplit
from components.domains.task3 import task3_metrics as score_task3
from components.evaluate import marginals, profile, report
from components.evaluate.champion import champion_pointer, choose_champion
from components.evaluate.task1 import task1_metrics
from tests.conftest import micro_params
from tests.test_domain import GaussianPosterior
from tests.test_relative import OUT_BOX, SOURCE_BOXES, uniform_in

sys.path.insert(0, str(PROJECT_ROOT / "scripts"))
import results_table  # noqa: E402

#: models of the small grid: (test NLL in nats, the truth's log-density shift against the draws': 0 calibrated, > 0
#: conservative) → calibrated models of different sharpness and one outside its band
MODELS = {
    "cues-5000": (20.0, 0.0),
    "cues-20000": (19.0, 0.0),
    "tiny-5000": (24.0, 1.5),
    "cues-20000-balanced": (19.5, 0),
}
README = """# a project

Some text above.

<!-- results:begin -->
stale content
<!-- results:end -->

Some text below, kept.
"""


def _write(path, value) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(value, indent=1), encoding="utf-8")  # as flows/evaluate.py, task2.py and task3.py


def _task1(reports) -> dict:
    """reports/task1/: metrics.json, champion.json and table.md as the evaluate stage writes them."""
    r = rng(0, "test", "results-table")
    metrics = {}
    for model, (nll, shift) in MODELS.items():
        lp = r.standard_normal((300, 200)) - nll  # the draws' log-densities; the truth's of the same law, shifted
        lp_truth = r.standard_normal(300) + shift - nll
        m, _, _ = task1_metrics(lp, lp_truth, 28.2, band=0.1)
        metrics[model] = m | {"images": 300, "samples": 200, "ppc_score": 0.25}  # the stage adds these three
    champion, runner_up = choose_champion(metrics, 1.0)
    pointer = champion_pointer(metrics, champion, runner_up)
    _write(reports / "task1" / "metrics.json", metrics)
    _write(reports / "task1" / "champion.json", pointer)
    rows = {m: report.model_row(v, {}) for m, v in metrics.items()}
    (reports / "task1" / "table.md").write_text(report.results_table(rows, champion.model), encoding="utf-8")
    # parameters.json and profiles.json as the stage writes them (flows/evaluate.py through
    # components/evaluate/publish.py): draws around each truth, sharper for the sharper models
    params = parse_params(micro_params(), source="params.yaml")
    box = params.box
    low, width = np.asarray(box.low), np.asarray(box.width)
    truth = low + width * r.random((300, box.dim))
    parameters, profiles = {}, {}
    for model, (nll, _) in MODELS.items():
        spread = 0.004 * (nll - 15.0)  # the truth one draw of each image's law: calibrated, near 68 % covered
        centre = truth + spread * width * r.standard_normal(truth.shape)
        draws = centre[:, None, :] + spread * width * r.standard_normal((300, 60, box.dim))
        draws = np.clip(draws, low, low + width)
        scores = marginals.marginal_scores(draws, truth, box)
        parameters[model] = marginals.summarize_subsets(scores, truth, box)
        profiles[model] = profile.truth_profile(scores, truth, box, params.evaluate.profile_bins)
    _write(reports / "task1" / "parameters.json", parameters)
    _write(reports / "task1" / "profiles.json", profiles)
    local = _local(params.box, r)
    for model in MODELS:
        metrics[model] |= _local_metrics(local[model])
    _write(reports / "task1" / "metrics.json", metrics)  # the stage's metrics hold the named weathers' figures too
    _write(reports / "task1" / "local.json", local)
    return {"metrics": metrics, "pointer": pointer, "parameters": parameters, "profiles": profiles, "local": local}


def _local(box, r) -> dict:
    """reports/task1/local.json as the evaluate stage writes it: two named weathers (ClearNoon among them) of 24
    images characterized by the exact truncated posterior of a toy (scaled 0.6: overconfident), and the L-C2ST of a
    conjugate Gaussian fitted once (:mod:`components.evaluate.named`)."""
    from components.core import presets, weather
    from components.core.weather import Box
    from components.evaluate import named
    from components.evaluate.local import posterior_summary

    sets = {"ClearNoon": weather.theta_from_weather(presets.preset_weather("ClearNoon")), "own": box.low.copy()}
    g = np.random.default_rng(5)
    b2 = Box(np.full(2, -8.0), np.full(2, 8.0), names=("a", "b"))
    q = lambda x, m: x[:, None, :] / 2 + np.sqrt(0.5) * g.standard_normal((len(x), m, 2))  # noqa: E731
    theta = g.standard_normal((300, 2))
    x = theta + g.standard_normal((300, 2))
    tests = named.fit_local_tests(
        theta, posterior_summary(q(x, 8), b2), q(x, 1)[:, 0], b2, steps=20, null_trials=19, seed=1
    )
    xo = g.standard_normal((24, 2))
    lc = named.local_rejections(tests, posterior_summary(q(xo, 8), b2), q(xo, 60), 0.05)
    out = {}
    for model in MODELS:
        rows = []
        for name, t in sets.items():
            truth = np.broadcast_to(t, (24, box.dim)).copy()
            sigma = 0.05 * box.width
            xs = truth + sigma * g.standard_normal(truth.shape)
            draws = named.exact_truncated_draws(xs, 0.6 * sigma, box, 400, g)
            s = named.NamedSet(
                name, "preset" if name == "ClearNoon" else "own", truth, np.zeros((24, 1, 1, 3), np.uint8)
            )
            row = named.weather_row(s, draws, box, 0.5, 48, g)
            row["lc2st"] = {n: lc["a"] for n in box.names} | {"joint": lc["joint"]}
            rows.append(row)
        pooled = {k: named.pooled(rows, box, kind=k) for k in ("preset", "own")}
        out[model] = {
            "weathers": rows,
            "pooled": {"all": named.pooled(rows, box), **pooled},
            "lc2st": {"level": 0.05, "named": lc, "test": lc, "test_images": 24},
        }
    return out


def _local_metrics(local: dict) -> dict:
    from components.evaluate.evaluation import local_metrics

    return local_metrics(local)


def _task2(reports) -> dict:
    """reports/task2/metrics.json: the Task II scores of a bag under N(θᵢ, 2²), the mixture estimate."""
    d = micro_params()
    d["task2"].update(samples=400)
    d["task2"]["width_floor"].update(draws=16, bootstrap=40)
    params = parse_params(d, source="params.yaml")
    theta = true_distribution(params).sample(40, rng(1, "test", "results-table", "bag"))
    metrics, *_ = score_task2(Domain(GaussianPosterior(2.0), theta), params, "cues-5000")
    # as score_bag (the stage's): the estimate's name first, the width floor last
    metrics = {
        "estimate": "mixture",
        **metrics,
        "width_floor": width_floor(GaussianPosterior(2.0), theta, theta, params),
    }
    _write(reports / "task2" / "metrics.json", metrics)
    return metrics


def _task3(reports) -> dict:
    """reports/task3/metrics.json: a sweep of separable sources under N(x, 0.3²), calibrated on fresh targets."""
    r = rng(2, "test", "results-table", "task3")
    sizes, weights = (12, 10, 11), (0.2, 0.3, 0.5)
    sources = [uniform_in(box, n, r) for box, n in zip(SOURCE_BOXES, sizes, strict=True)]
    pools = [uniform_in(box, 4 * n, r) for box, n in zip(SOURCE_BOXES, sizes, strict=True)]
    sweep = NoiseSweep(GaussianPosterior(0.3), uniform_in(OUT_BOX, 30, r), sources, weights, 16, fresh_pools=pools)
    experiments = {
        kind: [sweep.run(eta, k, seed=3, fresh=kind == "fresh") for eta in (0.0, 0.1, 0.5, 1.0) for k in range(8)]
        for kind in ("paper", "fresh")
    }
    detector, _ = sweep.calibrate(60, 0.05, seed=3, fresh=True)
    check, _ = sweep.check_false_alarms(detector, 60, seed=3, fresh=True)
    split = BagSplit(
        {f"b{k}": np.arange(n) for k, n in enumerate((30, *sizes))},
        {f"b{k}": np.arange(4 * n) for k, n in enumerate(sizes, start=1)},
        {f"b{k}": n for k, n in enumerate((30, *sizes))},
        {},
    )
    metrics = score_task3("cues-5000", 16, weights, split, experiments, detector, "fresh", check, 1.0)
    _write(reports / "task3" / "metrics.json", metrics)
    return metrics


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """A project folder with the stages' reports and a README holding the results block."""
    root = tmp_path_factory.mktemp("project")
    reports = root / "reports"
    written = {"task1": _task1(reports), "task2": _task2(reports), "task3": _task3(reports)}
    return root, written


def _readme(root, text: str = README):
    path = root / "README.md"
    path.write_text(text, encoding="utf-8")
    return path


def _row(block: str, model: str) -> list[str]:
    lines = [
        line for line in block.splitlines() if line.startswith(f"| {model} |") or line.startswith(f"| **{model}** |")
    ]
    assert len(lines) == 1, (model, block)
    return [c.strip() for c in lines[0].strip("|").split("|")]


def test_the_block_holds_every_model_in_order_with_its_figures_and_the_champion_marked(project):
    root, written = project
    path = _readme(root)
    assert results_table.main(["--reports", str(root / "reports"), "--files", str(path)]) == 0
    text = path.read_text(encoding="utf-8")
    head, _, rest = text.partition("<!-- results:begin -->")
    block, _, tail = rest.partition("<!-- results:end -->")
    assert head == README.partition("<!-- results:begin -->")[0] and tail == "\n\nSome text below, kept.\n"
    assert "stale content" not in block
    metrics, pointer = written["task1"]["metrics"], written["task1"]["pointer"]
    first_cells = [line.split("|")[1].strip().strip("*") for line in block.splitlines() if line.startswith("| ")]
    assert [m for m in first_cells if m in metrics] == list(metrics), "the grid's order of reports/task1/metrics.json"
    for model, m in metrics.items():
        cells = _row(block, model)
        backbone, size, variant = results_table.MODEL_ID.match(model).groups()
        assert cells[1] == (backbone if variant is None else f"{backbone} ({variant})")
        assert cells[2] == f"{int(size):,}".replace(",", " ")
        assert cells[3] == f"{m['info_gain_nats']:.2f} ± {m['test_nll_se']:.2f}".replace("-", "−")
        assert cells[4] == (
            f"{m['calibration_error']:.3f} ({m['calibration_band']:.3f}) {'within' if m['within_band'] else 'outside'}"
        )
        assert cells[5] == f"{m['test_nll']:.2f}".replace("-", "−")
        role = {pointer["model"]: "**champion**", (pointer["runner_up"] or {}).get("model"): "runner-up"}
        assert cells[6] == role.get(model, "")
        assert (cells[0] == f"**{model}**") == (model == pointer["model"])
    within = [m for m, v in metrics.items() if v["within_band"]]
    assert within and not all(v["within_band"] for v in metrics.values()), "the grid shows both kinds of model"
    assert pointer["rule"] == "within_band", "the calibrated models qualify"
    assert '`"rule": "within_band"`' in block and results_table.RULE_TEXT["within_band"] in block
    assert "300 images, 200 posterior draws each" in block


def test_the_task_lines_quote_the_stage_reports(project):
    root, written = project
    block = results_table.results_block(results_table.read_reports(root / "reports"))
    task2, task3 = written["task2"], written["task3"]
    (line2,) = [line for line in block.splitlines() if line.startswith("- **Task II**")]
    assert f"{task2['energy_distance_sq']['all']['ratio']:.2f} × the prior's" in line2
    varying = [n for n, p in task2["parameters"].items() if p["fixed_value"] is None]
    assert varying == ["fog_density", "precipitation"], "the paper's setting: two free parameters"
    for name in varying:
        assert f"{name.replace('_', ' ')} {task2['parameters'][name]['wasserstein_ratio']:.2f}" in line2
    assert f"{100 * task2['true_mass_in_hdr']:.1f} % of the true mass" in line2
    (line3,) = [line for line in block.splitlines() if line.startswith("- **Task III**")]
    odd, check = task3["odd"], task3["odd"]["false_alarms_new_seeds"]
    assert f"flags {check['flagged']} of {check['n']} in-ODD targets" in line3
    assert (
        f"threshold {odd['threshold']:.4f}" in line3
        and f"{check['calibrated_low']}–{check['calibrated_high']}" in line3
    )
    floor = odd["detects_from_eta"]
    assert ("detects no out-of-ODD share" in line3) == (floor is None)
    assert floor is None or f"from η = {floor:g} on" in line3
    first, later = task3["eta"]["0.1"], [task3["eta"][k] for k in ("0.5", "1")]
    low = min(later, key=lambda row: row["auc_fresh"])

    def auc(row) -> str:
        return f"{row['auc_fresh']:.2f} [{row['auc_ci_low_fresh']:.2f}, {row['auc_ci_high_fresh']:.2f}]"

    assert f"AUC {auc(first)} at η = 0.1, at least {auc(low)} from η = 0.3 on" in line3


def test_check_tells_a_stale_file_and_print_writes_nothing(project, capsys):
    root, _ = project
    path = _readme(root)
    args = ["--reports", str(root / "reports"), "--files", str(path)]
    assert results_table.main([*args, "--check"]) == 1
    assert "stale" in capsys.readouterr().err and path.read_text(encoding="utf-8") == README, "--check writes nothing"
    assert results_table.main([*args, "--print"]) == 0
    out = capsys.readouterr().out
    assert "| model | backbone |" in out and "<!--" not in out and path.read_text(encoding="utf-8") == README
    assert results_table.main(args) == 0
    assert results_table.main([*args, "--check"]) == 0, "fresh after the write"
    written = path.read_text(encoding="utf-8")
    assert results_table.main(args) == 0 and path.read_text(encoding="utf-8") == written, "idempotent"


def test_the_full_task1_table_block_is_the_stage_table(project):
    root, _ = project
    path = _readme(root, "x\n<!-- task1-table:begin -->\n<!-- task1-table:end -->\ny\n")
    assert results_table.main(["--reports", str(root / "reports"), "--files", str(path)]) == 0
    table = (root / "reports" / "task1" / "table.md").read_text(encoding="utf-8")
    assert (
        path.read_text(encoding="utf-8")
        == f"x\n<!-- task1-table:begin -->\n{table.strip()}\n<!-- task1-table:end -->\ny\n"
    )


def test_missing_reports_say_to_run_the_pipeline(tmp_path, project, capsys):
    path = _readme(tmp_path)
    assert results_table.main(["--reports", str(tmp_path / "reports"), "--files", str(path)]) == 2
    err = capsys.readouterr().err
    assert "no reports folder" in err and "run `bash run.sh` first" in err
    root, _ = project
    partial = tmp_path / "partial"
    (partial / "task1").mkdir(parents=True)
    for name in ("metrics.json", "champion.json", "table.md"):
        (partial / "task1" / name).write_bytes((root / "reports" / "task1" / name).read_bytes())
    assert results_table.main(["--reports", str(partial), "--files", str(path), "--check"]) == 2
    err = capsys.readouterr().err
    assert "task2/metrics.json is missing" in err and "run `bash run.sh` first" in err
    assert path.read_text(encoding="utf-8") == README


def test_lost_or_broken_markers_are_errors(project):
    root, _ = project
    reports = results_table.read_reports(root / "reports")
    with pytest.raises(results_table.ReportsError, match=r"holds no block \(<!-- results:begin -->"):
        results_table.fill("no markers here\n", reports)
    with pytest.raises(results_table.ReportsError, match="must appear once each, in that order"):
        results_table.fill("<!-- results:end -->\n<!-- results:begin -->\n", reports)
    with pytest.raises(results_table.ReportsError, match="must appear once each"):
        results_table.fill("<!-- results:begin -->\n", reports)


def test_a_champion_absent_from_the_metrics_is_refused(project, tmp_path):
    root, _ = project
    reports = results_table.read_reports(root / "reports")
    bad = dict(reports) | {"champion": {"model": "resnet50-500000", "rule": "within_band"}}
    with pytest.raises(
        results_table.ReportsError, match="names 'resnet50-500000', which reports/task1/metrics.json lacks"
    ):
        results_table.results_block(bad)


@pytest.mark.parametrize("name", results_table.TARGETS)
def test_the_repository_files_hold_the_results_block(name):
    """README.md and docs/results.md carry the markers the script fills (an edit that loses them fails here)."""
    text = (PROJECT_ROOT / name).read_text(encoding="utf-8")
    assert text.count("<!-- results:begin -->") == 1 and text.count("<!-- results:end -->") == 1
    assert text.index("<!-- results:begin -->") < text.index("<!-- results:end -->")


def _reports(project) -> dict:
    root, _ = project
    return results_table.read_reports(root / "reports")


def _with(reports: dict, key: str, path: tuple, value) -> dict:
    """A deep copy of ``reports`` with ``reports[key][path…]`` set to ``value`` (``None``: the key removed)."""
    out = json.loads(json.dumps({k: v for k, v in reports.items() if k != "table"})) | {"table": reports["table"]}
    node = out[key]
    for k in path[:-1]:
        node = node[k]
    if value is None:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return out


def _fmt(value: float, digits: int) -> str:
    return f"{value:.{digits}f}".replace("-", "−")


def test_the_champion_block_quotes_the_metrics_and_judges_the_targets(project):
    _, written = project
    reports = _reports(project)
    metrics, pointer = written["task1"]["metrics"], written["task1"]["pointer"]
    champion = pointer["model"]
    m = metrics[champion]
    block = results_table.champion_block(reports)
    assert f"The prior's log-volume is {m['info_gain_nats'] + m['test_nll']:.1f} nats" in block
    assert f"- **The champion is {champion}**: information gain {_fmt(m['info_gain_nats'], 2)} ± " in block
    assert f"test NLL {_fmt(m['test_nll'], 2)}, calibration error {_fmt(m['calibration_error'], 3)}" in block
    assert "on 300 images × 200 draws" in block
    met = m["info_gain_nats"] >= 8 and m["test_nll"] <= 20.2 and m["within_band"] and m["calibration_error"] <= 0.03
    assert met is False, "the small grid's champion misses its calibration target: the verdict is put to the test"
    assert f"are not all met: the calibration ({_fmt(m['calibration_error'], 3)}) misses" in block
    good = _with(reports, "task1", (champion, "calibration_error"), 0.02)
    assert "— are met." in results_table.champion_block(good)
    worse = _with(good, "task1", (champion, "test_nll"), 25.0)
    assert "are not all met: the NLL (25.00) misses" in results_table.champion_block(worse)
    runner = pointer["runner_up"]["model"]
    assert f"- **The runner-up** (MLflow alias `challenger`) is {runner}, within its band" in block
    under = [n for n, v in metrics.items() if v["calibration_error"] <= 0.10]
    assert 0 < len(under) < len(metrics), "the grid holds a model above the 0.10 ceiling"
    assert f"**{len(under)} of {len(metrics)} models have a calibration error ≤ 0.10**" in block
    gains = [metrics[f"cues-{n}"]["info_gain_nats"] for n in (5000, 20000)]
    assert gains[0] < gains[1] and f"every backbone: cues {_fmt(gains[0], 2)} / {_fmt(gains[1], 2)} nats" in block
    falling = _with(reports, "task1", ("cues-20000", "info_gain_nats"), gains[0] - 1)
    assert "does not rise with the training size for cues" in results_table.champion_block(falling)
    gap = metrics["tiny-5000"]["coverage_auc_gap"]
    lean = "lean" if gap < 0 else "do not all lean"
    assert f"The `tiny` models {lean} overconfident (coverage gap {_fmt(gap, 3)})." in block
    flipped = results_table.champion_block(_with(reports, "task1", ("tiny-5000", "coverage_auc_gap"), -gap))
    assert ("do not all lean" in flipped) == (gap < 0), "the lean is computed from the gap's sign"


def test_the_champion_parameters_block_quotes_the_day_night_and_profile_figures(project):
    _, written = project
    reports = _reports(project)
    champion = written["task1"]["pointer"]["model"]
    p = written["task1"]["parameters"][champion]
    block = results_table.champion_parameters_block(reports)
    (day,) = [line for line in block.splitlines() if line.startswith("- **Daytime median errors**")]
    for name, target in results_table.DAY_TARGETS.items():
        e = p["day"][name]["median_abs_error"]
        assert e <= target, "the small grid's champion meets every daytime target"
        assert f"{results_table.SHORT[name]} {_fmt(e, 2)}" in day
    sun = p["day"]["sun_altitude_angle"]
    assert f"(95 % interval {_fmt(sun['median_abs_error_low'], 2)}–{_fmt(sun['median_abs_error_high'], 2)}°)" in day
    assert f"all are met on the test split, the sun's by {_fmt(3 - sun['median_abs_error'], 2)}°" in day
    missed = _with(reports, "parameters", (champion, "day", "sun_altitude_angle", "median_abs_error"), 3.5)
    assert "not met on the test split: sun altitude (3.50° against 3°)" in results_table.champion_parameters_block(
        missed
    )
    (night,) = [line for line in block.splitlines() if line.startswith("- **At night**")]
    cover = {n: v["coverage68"] for n, v in p["night"].items()}
    outside = [results_table.SHORT[n] for n, c in cover.items() if not 0.63 <= c <= 0.73]
    assert outside, "the small champion's night coverage leaves the range somewhere: the verdict is put to the test"
    assert f"{100 * min(cover.values()):.1f}–{100 * max(cover.values()):.1f} % of the time" in night
    assert f"outside the target range of 63–73 % for {results_table._join(outside)}:" in night
    inside = reports
    for name in cover:
        inside = _with(inside, "parameters", (champion, "night", name, "coverage68"), 0.68)
    assert "inside the target range of 63–73 % for every marginal" in results_table.champion_parameters_block(inside)
    assert f"wind's cover {100 * p['all']['wind_intensity']['coverage68']:.1f} %" in night
    prof = written["task1"]["profiles"][champion]["day"]["sun_altitude_angle"]
    bins = [(e, n) for e, n in zip(prof["median_abs_error"], prof["images"], strict=True) if n]
    (sharp,) = [line for line in block.splitlines() if line.startswith("- **Where it is sharp")]
    assert f"{len(prof['images'])} bins of each range" in sharp
    first, last = bins[0][0], bins[-1][0]
    assert f"is {first:.{2 if first < 1 else 1}f}° below {prof['edges'][6]:g}° of altitude" in sharp
    assert f"and {last:.{2 if last < 1 else 1}f}° above {prof['edges'][-2]:g}°" in sharp


def test_the_task2_block_quotes_the_scores_and_the_width_floor(project):
    _, written = project
    reports = _reports(project)
    t = written["task2"]
    block = results_table.task2_block(reports)
    assert block.startswith(f"{t['model']}, {t['images']} images, the paper's setting, the mixture of posteriors:")
    assert f"- energy distance ratio estimate / prior {t['energy_distance_sq']['all']['ratio']:.2f};" in block
    for name in ("fog_density", "precipitation"):
        assert f"{results_table.SHORT[name]} {t['parameters'][name]['wasserstein_ratio']:.2f}" in block
    assert f"true mass in the 95 % HDR {t['true_mass_in_hdr']:.3f}" in block
    floor = t["width_floor"]
    assert f"would give has a W₁ ratio of {floor['calibrated']['1']['precipitation']:.2f}" in block
    assert f"the estimate's {floor['mixture']['precipitation']:.2f}" in block
    assert f"moved onto its truth, {floor['wasserstein_ratio']['1']['precipitation']:.2f}" in block
    intervals = floor["interval"]["mixture_minus_calibrated"]
    assert all(d["low"] <= 0 <= d["high"] for d in intervals.values()), "the toy's posteriors are calibrated"
    assert ": no bias to find." in block and "with nothing left for bias" in block
    d = intervals["precipitation"]
    assert f"precipitation {'+' if d['difference'] >= 0 else ''}{_fmt(d['difference'], 3)} [" in block
    biased = _with(
        reports, "task2", ("width_floor", "interval", "mixture_minus_calibrated", "fog_density", "low"), 0.01
    )
    text = results_table.task2_block(biased)
    assert ": a bias in fog." in text and "nothing left for bias" not in text
    sd = floor["posterior_sd_median"]
    assert f"{sd['precipitation']:.1f} units for precipitation, {sd['fog_density']:.1f} for fog" in block


def test_the_task3_block_quotes_the_sweep_and_the_decision(project):
    from scipy import stats

    _, written = project
    reports = _reports(project)
    t = written["task3"]
    block = results_table.task3_block(reports)
    assert block.startswith(f"n_W = {t['n_points']}, kernel characterization, 8 targets per η and kind")
    eta = {float(k): v for k, v in t["eta"].items()}
    for kind in ("paper", "fresh"):
        lead = {"paper": "- paper-style targets:", "fresh": "- **fresh targets**:"}[kind]
        (line,) = [x for x in block.splitlines() if x.startswith(lead)]
        assert f"median d_E {results_table._sci(eta[0.0][f'd_e_median_{kind}'])} at η = 0" in line
        last = max(eta)
        auc = f"{eta[last][f'auc_{kind}']:.2f} [{eta[last][f'auc_ci_low_{kind}']:.2f}, "
        assert auc in line
        holds = [e for e in sorted(eta) if e > 0 and all(eta[x][f"auc_ci_low_{kind}"] >= 0.95 for x in eta if x >= e)]
        assert ("does not hold" in line) == (not holds)
        assert not holds or f"holds at 95 % confidence from η = {holds[0]:g}" in line
    high = reports
    for e in t["eta"]:
        if t["eta"][e]["auc_fresh"] is not None and float(e) >= 0.5:
            high = _with(high, "task3", ("eta", e, "auc_ci_low_fresh"), 0.96)
    assert "holds at 95 % confidence from η = 0.5" in results_table.task3_block(high)
    odd, check = t["odd"], t["odd"]["false_alarms_new_seeds"]
    assert f"calibrated on {odd['calibration_targets']} fresh in-ODD targets for α = 0.05" in block
    assert f"(threshold {odd['threshold']:.4f} on the relative gap)" in block
    assert f"It flags {check['flagged']} of {check['n']} in-ODD targets of new seeds: {check['rate']:.3f}" in block
    assert ("α inside" in block) == (check["ci_low"] <= 0.05 <= check["ci_high"])
    n, m, r = check["n"], odd["calibration_targets"], odd["rank"]
    tail = stats.betabinom(n, m + 1 - r, r).sf(check["calibrated_high"])
    assert results_table._beta_binomial_above(n, m + 1 - r, r, check["calibrated_high"]) == pytest.approx(tail)
    assert f"[{check['calibrated_low']}, {check['calibrated_high']}] of {n} at 95 % for m = {m}" in block
    assert f"in {100 * tail:.1f} % of a calibrated decision's runs" in block
    assert f"this run's {check['flagged']} is {'above' if check['exceeds_alpha'] else 'not above'} it." in block


def test_the_targets_block_sorts_every_target_into_met_or_missed(project):
    reports = _reports(project)
    judged = results_table.targets(reports)
    block = results_table.targets_block(reports)
    met = [what for what, ok, _ in judged if ok]
    missed = [f"{what} ({figure})" for what, ok, figure in judged if not ok]
    assert met and missed, "the small reports meet some targets and miss others"
    assert block.startswith(f"The latest run meets {len(met)} of the {len(judged)} targets")
    head, _, tail = block.partition("It misses ")
    assert all(what in head for what in met) and all(text in tail for text in missed)
    energy = reports["task2"]["energy_distance_sq"]["all"]["ratio"]
    assert energy <= 0.3 and "the Task II energy ratio" in head
    worse = results_table.targets_block(_with(reports, "task2", ("energy_distance_sq", "all", "ratio"), 0.5))
    assert "the Task II energy ratio (0.50, target ≤ 0.3)" in worse.partition("It misses ")[2]


@pytest.mark.parametrize(
    ("block", "key", "path", "message"),
    [
        (
            "task1-champion",
            "task1",
            ("cues-20000", "info_gain_nats"),
            "reports/task1/metrics.json has no info_gain_nats",
        ),
        ("champion-parameters", "parameters", ("cues-20000", "day"), "reports/task1/parameters.json has no day"),
        ("champion-parameters", "parameters", ("cues-20000",), "reports/task1/parameters.json has no cues-20000"),
        ("champion-parameters", "profiles", ("cues-20000",), "reports/task1/profiles.json has no cues-20000"),
        ("task2", "task2", ("width_floor",), "reports/task2/metrics.json has no width_floor"),
        ("task2", "task2", ("width_floor", "interval"), "reports/task2/metrics.json has no interval"),
        ("task3", "task3", ("odd", "rank"), "reports/task3/metrics.json has no rank"),
        ("task3", "task3", ("eta", "0"), r"reports/task3/metrics.json has no eta.0"),
        ("targets", "task2", ("true_mass_in_hdr",), "reports/task2/metrics.json has no true_mass_in_hdr"),
        ("named", "local", ("cues-20000",), "reports/task1/local.json has no cues-20000"),
        ("named", "local", ("cues-20000", "lc2st", "level"), "reports/task1/local.json has no level"),
    ],
)
def test_a_missing_key_names_its_report(project, block, key, path, message):
    reports = _reports(project)
    assert reports["champion"]["model"] == "cues-20000"
    with pytest.raises(results_table.ReportsError, match=message):
        results_table.BLOCKS[block](_with(reports, key, path, None))


def test_a_missing_parameters_report_says_to_run_the_pipeline(project, tmp_path, capsys):
    root, _ = project
    partial = tmp_path / "reports"
    for rel in results_table.REPORTS.values():
        if rel != "task1/parameters.json":
            (partial / rel).parent.mkdir(parents=True, exist_ok=True)
            (partial / rel).write_bytes((root / "reports" / rel).read_bytes())
    path = _readme(tmp_path)
    assert results_table.main(["--reports", str(partial), "--files", str(path)]) == 2
    assert "task1/parameters.json is missing" in capsys.readouterr().err


@pytest.mark.parametrize(
    "name", ["task1-table", "task1-champion", "champion-parameters", "task2", "task3", "named", "targets"]
)
def test_the_results_page_holds_every_block(name):
    """docs/results.md carries each block once, in order (an edit that loses one fails here)."""
    text = (PROJECT_ROOT / "docs" / "results.md").read_text(encoding="utf-8")
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    assert text.count(begin) == 1 and text.count(end) == 1 and text.index(begin) < text.index(end)


def test_the_results_block_ends_with_the_champion_at_the_named_weathers(project):
    """README's line quotes the champion's pooled coverage beside the toy's, its cells and the sun at ClearNoon, and is
    left out (not invented) when the named weathers were skipped."""
    root, _ = project
    reports = results_table.read_reports(root / "reports")
    model = reports["champion"]["model"]
    local = reports["local"][model]
    (line,) = [line for line in results_table.results_block(reports).splitlines() if line.startswith("- **Named")]
    cov = [p["coverage68"] for p in local["pooled"]["all"]["parameters"].values()]
    toy = [p["toy68"] for p in local["pooled"]["all"]["parameters"].values()]
    assert f"({model}, 2 weathers on 48 images of new scenes" in line
    assert f"cover the truth {min(cov):.2f}–{max(cov):.2f} of the time" in line
    assert f"covers {min(toy):.2f}–{max(toy):.2f}" in line
    noon = local["weathers"][0]["parameters"]["sun_altitude_angle"]["median_abs_error"]
    assert line.endswith(f"it reads the sun at ClearNoon to {noon:.2f}°.")
    skipped = dict(reports, local={**reports["local"], model: {"skipped": "no renderer"}})
    assert not [line for line in results_table.results_block(skipped).splitlines() if "Named" in line]


def test_the_named_block_quotes_the_champions_weathers_and_judges_the_local_test(project):
    reports = _reports(project)
    model = reports["champion"]["model"]
    local = reports["local"][model]
    block = results_table.named_block(reports)
    pooled = local["pooled"]["all"]["parameters"]["cloudiness"]
    assert f"The champion ({model}) at 2 named weathers (48 images" in block
    assert f"cloudiness {pooled['coverage68']:.2f} [{pooled['ci68'][0]:.2f}, {pooled['ci68'][1]:.2f}]" in block
    cells = [c for r in local["weathers"] for c in r["parameters"].values()]
    assert f"{sum(c['below'] for c in cells)} of 12 weather × parameter cells lie below" in block
    noon = local["weathers"][0]["parameters"]["sun_altitude_angle"]["median_abs_error"]
    assert f"it reads the sun to {noon:.2f}°" in block
    assert [line.split(" | ")[0][2:] for line in block.splitlines() if line.startswith("| ")][1:] == list(MODELS)
    judged = {what: (ok, figure) for what, ok, figure in results_table.targets(reports)}
    ok, figure = judged["the sun at ClearNoon"]
    assert ok == (noon <= 5.0) and figure == f"{noon:.2f}°, target ≤ 5°"
    p = local["lc2st"]["named"]["joint"]["p_value"]
    assert judged["the local test at the named weathers"][0] == (p > 0.05)
    rejecting = _with(reports, "local", (model, "lc2st", "named", "joint", "p_value"), 0.025)
    assert not {w: ok for w, ok, _ in results_table.targets(rejecting)}["the local test at the named weathers"]
    skipped = dict(reports, local={**reports["local"], model: {"skipped": "no renderer"}})
    assert results_table.named_block(skipped) == "The named weathers were not evaluated: no renderer."
    assert "the sun at ClearNoon" not in {w for w, _, _ in results_table.targets(skipped)}
