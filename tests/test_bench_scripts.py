"""The ablation benchmarks' own claims: ``bench_rain_pool`` changes only the rain's two named constants; ``bench_levers`` and ``bench_scale`` read their settings strictly, and
``bench_scale`` renders exactly the pipeline's images (the same plan and renderer as the ``generate`` stage), so that
its figures compare with the pipeline's on the same images; ``bench_splits`` renders other scenes and weathers under
another root seed, the same ones every time."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_splits import fresh_features, summarize  # noqa: E402
from benchmarks.studies.bench_conditional_coverage import MASS, coverage_cells  # noqa: E402
from benchmarks.studies.bench_levers import mirror_map, parse_setting, tiny_columns  # noqa: E402
from benchmarks.studies.bench_puddles import LEVELS, ideal_errors  # noqa: E402
from benchmarks.studies.bench_rain import exact_features, knn_error  # noqa: E402
from benchmarks.studies.bench_rain_pool import calibration_of  # noqa: E402
from benchmarks.studies.bench_resolution import paired_difference  # noqa: E402
from benchmarks.studies.bench_resolution_training import render, render_resized  # noqa: E402
from benchmarks.studies.bench_scale import SMALL_WIDTHS, WIDTHS, FullResolutionCNN, _parse  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.core.weather import PREDICTED  # noqa: E402
from components.features.backbones import get_backbone  # noqa: E402
from components.simulate.in_memory import render_split  # noqa: E402
from components.simulate.procedural import ProceduralSimulator  # noqa: E402


def test_levers_settings_grammar() -> None:
    s = parse_setting("cues-v3+tiny-50000-ens2-e60-n0.094-t")
    assert s == {
        "version": "v3",
        "tiny": True,
        "sky_rows": 0,
        "size": 50000,
        "ensemble": 2,
        "context_layers": None,
        "epochs": 60,
        "lr": None,
        "weight_decay": None,
        "noise": 0.094,
        "mirror": False,
        "temperature": True,
    }
    assert parse_setting("cues-v1-5000")["tiny"] is False
    sky = parse_setting("cues-v3+sky3-50000-n0.094-t")
    assert (sky["tiny"], sky["sky_rows"]) == (False, 3)
    assert parse_setting("cues-v3-20000-n0.106-m-t")["mirror"] is True
    assert parse_setting("cues-v3-50000-c256x256x128-n0.094-t")["context_layers"] == (256, 256, 128)
    assert parse_setting("cues-v3-50000-c0-t")["context_layers"] == ()
    tuned = parse_setting("cues-v3-50000-e48-lr2e-3-wd0.001-n0.094-t")
    assert (tuned["epochs"], tuned["lr"], tuned["weight_decay"], tuned["noise"]) == (48, 2e-3, 1e-3, 0.094)
    bad_names = (
        "cues-v8-5000",
        "cues-v3+sky9-5000",
        "cues-v3+sky-5000",
        "cues-v3-tiny-5000",
        "tiny-v3-5000",
        "cues-v3-5000-x",
        "cues-v3-5000-t-m",
    )
    for bad in (*bad_names, "cues-v3-5000-c256x", "cues-v3-5000-t-c0", "cues-v3-5000-wd0.1-lr0.1", "cues-v3-5000-lr-"):
        with pytest.raises(ValueError, match="expected cues-"):
            parse_setting(bad)


def test_levers_mirror_map_is_the_features_of_the_mirrored_images() -> None:
    """``-m`` on cues joined by the tiny thumbnail: the composed permutation maps the joined features of rendered
    images to those of their mirror images (to float rounding)."""
    sim = ProceduralSimulator(128, 128)
    w = {"cloudiness": 30.0, "fog_density": 20.0, "precipitation": 60.0, "sun_altitude_angle": 25.0}
    w |= {"wind_intensity": 70.0, "precipitation_deposits": 40.0, "sun_azimuth_angle": 60.0}
    images = np.stack([sim.render(w, seed) for seed in (1, 2, 3)])
    mirrored = np.ascontiguousarray(images[:, :, ::-1])

    def joined(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.concatenate([get_backbone(b).extract(x) for b in ("cues", "tiny")], axis=1))

    every = tiny_columns(parse_setting("cues-v3+tiny-5000"))
    np.testing.assert_allclose(mirror_map("v7", every)(joined(images)), joined(mirrored), rtol=1e-3, atol=2e-3)
    sky = tiny_columns(parse_setting("cues-v3+sky3-5000"))  # the L*a*b* of the upper three lattice rows
    assert len(sky) == 72

    def joined_sky(x: np.ndarray) -> torch.Tensor:
        cues = get_backbone("cues").extract(x)[:, :273]  # version 3
        return torch.from_numpy(np.concatenate([cues, get_backbone("tiny").extract(x)[:, sky]], 1))

    np.testing.assert_allclose(mirror_map("v3", sky)(joined_sky(images)), joined_sky(mirrored), rtol=1e-3, atol=2e-3)
    # version 4 is version 3 joined by +sky3: the same columns, and the same mirror permutation
    np.testing.assert_array_equal(
        get_backbone("cues").extract(images)[:, 273:345], get_backbone("tiny").extract(images)[:, sky]
    )
    columns = torch.arange(345.0)[None]
    assert torch.equal(mirror_map("v4", None)(columns), mirror_map("v3", sky)(columns))
    v5 = torch.arange(363.0)[None]  # version 5 adds the wet road's bands, each its own mirror image
    assert torch.equal(mirror_map("v5", None)(v5)[:, 345:], v5[:, 345:])
    v6 = torch.arange(375.0)[None]  # version 6 adds the reader's guesses, each its own mirror image
    assert torch.equal(mirror_map("v6", None)(v6)[:, 345:], v6[:, 345:])
    v7 = torch.arange(377.0)[None]  # version 7 adds the sun head's guess, its own mirror image
    assert torch.equal(mirror_map("v7", None)(v7)[:, 345:], v7[:, 345:])
    v1 = torch.arange(80.0)[None]  # the version-1 columns mirror among themselves (edge orientations)
    assert sorted(mirror_map("v1", None)(v1)[0].tolist()) == v1[0].tolist()


def test_scale_models_grammar() -> None:
    params = load_params(ROOT / "params.yaml")
    kind, size, _, flip, setting = _parse("cues-200000", 12, params)
    assert (kind, size, flip) == ("cues", 200000, False)
    # the pipeline's settings: its flows, no input noise above train.input_noise_max_size, the fitted temperature
    assert (setting["ensemble"], setting["noise"], setting["temperature"]) == (params.train.flow.ensemble, 0.0, True)
    _, _, _, _, setting = _parse("cues-50000", 12, params)
    assert setting["noise"] == pytest.approx(params.train.input_noise * (10000 / 50000) ** 0.5)  # one flow or two
    _, _, _, _, setting = _parse("cues-v4-100000-ens3-n0.05-t", 12, params)
    assert (setting["size"], setting["ensemble"], setting["noise"]) == (100000, 3, 0.05)
    assert _parse("hybrid-50000", 12, params) == ("image", 50000, 12, False, {"with_cues": True, "widths": WIDTHS})
    assert _parse("hybrid-50000-e6-f", 12, params)[:4] == ("image", 50000, 6, True)
    # the CNN alone, and at half its widths
    assert _parse("cnn-200000-e6-f", 12, params)[4] == {"with_cues": False, "widths": WIDTHS}
    assert _parse("hybrid-50000-e6-f-s", 12, params)[4] == {"with_cues": True, "widths": SMALL_WIDTHS}
    for bad in ("cues-50000-e6", "cues-50000-f", "cues-50000-s", "hybrid-50000-f-e6", "cnn-50000-s-f", "tiny-50000"):
        with pytest.raises(ValueError, match="expected cues-<size>, a bench_levers setting"):
            _parse(bad, 12, params)
    for bad in ("cues-v3-50000", "cues-v4+sky3-50000", "cues-v4-50000-m"):
        with pytest.raises(ValueError, match="version-4 cues alone"):
            _parse(bad, 12, params)


def test_full_resolution_cnn_shapes() -> None:
    cnn = FullResolutionCNN(dim=16, widths=(8, 8, 8, 8, 8, 16))
    images = torch.randint(0, 256, (3, 128, 128, 3), dtype=torch.uint8)
    out = cnn(images)
    assert out.shape == (3, 16) and bool(torch.isfinite(out).all())


def test_puddles_ideal_reader_on_a_known_problem() -> None:
    """bench_puddles' ideal reader: exact without spread; with Gaussian spread σ on a linear curve, its median error is
    the median |noise| (0.674 σ), in deposits units."""
    levels = len(LEVELS)
    curve = LEVELS / 100.0
    exact = np.broadcast_to(curve, (50, 1, levels)).copy()
    assert ideal_errors(exact, [0]).max() == 0.0
    sigma = 0.05
    noisy = curve + np.random.default_rng(0).normal(0.0, sigma, (400, 1, levels))
    err = ideal_errors(noisy, [0])[:, 40:-40]  # away from the ends, where the grid clips the guess
    assert abs(np.median(err) - 0.674 * sigma * 100) < 0.25
    # two independent bands of the same spread: the error shrinks by √2
    two = curve + np.random.default_rng(1).normal(0.0, sigma, (400, 2, levels))
    assert abs(np.median(ideal_errors(two, [0, 1])[:, 40:-40]) - 0.674 * sigma * 100 / np.sqrt(2)) < 0.25


def test_rain_exact_reader_on_known_problems() -> None:
    """``bench_rain``: a scene's exact streak opacity grows with precipitation (common random numbers: more rain only
    adds drops, each more opaque), none at 0, and at 100 % the total is the scene's capacity; its k-NN reader recovers
    a target that is a function of the features and not one that is independent of them."""
    sim = ProceduralSimulator(128, 128, cache_size=2)
    rows = np.array([exact_features(sim, 3_000_000, p, 20.0) for p in (0.0, 10.0, 40.0, 100.0)])
    assert rows[0, 0] == pytest.approx(np.log(1e-3)) and np.all(rows[0, 1:7] == 0.0)
    assert np.all(np.diff(rows[:, 0]) > 0.0), "the total opacity grows with precipitation"
    assert rows[3, 0] == pytest.approx(rows[3, -1]) and np.all(rows[:, -1] == rows[0, -1]), (
        "the capacity is the scene's"
    )
    assert np.all(np.diff(rows[1:, 6]) > 0.0), "more streak pixels with more rain"
    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 1.0, (600, 2))
    fit = np.arange(600) < 400
    assert knn_error(x, 100.0 * x[:, 0], fit) < 3.0
    assert knn_error(x, rng.uniform(0.0, 100.0, 600), fit) > 15.0  # ~25 for a guess at random


def test_splits_fresh_split_is_another_plan_the_same_every_time(tmp_path: Path) -> None:
    """A fresh split (root seed + 1) holds other weathers and images than the pipeline's test split, the same ones on
    every call, and its features come back from the cache."""
    params = load_params(ROOT / "params.yaml")
    images, theta = render_split(params, "test", 8, workers=1)
    fresh_images, fresh_theta = render_split(params, "test", 8, workers=1, seed=params.seed + 1)
    assert not np.allclose(theta, fresh_theta) and (images != fresh_images).mean() > 0.5
    again_images, again_theta = render_split(params, "test", 8, workers=1, seed=params.seed + 1)
    np.testing.assert_array_equal(fresh_images, again_images)
    np.testing.assert_array_equal(fresh_theta, again_theta)
    backbone = get_backbone("tiny").eval()
    x, th = fresh_features(params, backbone, params.seed + 1, 8, 1, tmp_path)
    np.testing.assert_array_equal(x, backbone.extract(fresh_images))
    np.testing.assert_array_equal(th, fresh_theta)
    (kept,) = tmp_path.glob("tiny-*.npz")
    assert kept.name.endswith(f"-{params.seed + 1}-8.npz")
    x2, th2 = fresh_features(params, backbone, params.seed + 1, 8, 1, tmp_path)
    np.testing.assert_array_equal(x2, x)


def test_splits_cache_is_keyed_by_the_renderer(tmp_path: Path) -> None:
    """Features of one seed and size rendered by another renderer (here camera-like renders, ``render_sizes``; a new
    algorithm version or calibration alike) are rendered anew, not read from the cache of the first."""
    import yaml

    from tests.conftest import write_params

    section = yaml.safe_load((ROOT / "params.yaml").read_text())["simulator"] | {"height": 32, "width": 32}
    native = load_params(write_params(tmp_path / "native", simulator=section))
    camera = load_params(write_params(tmp_path / "camera", simulator=section | {"render_sizes": [40, 64]}))
    backbone = get_backbone("tiny").eval()
    cache = tmp_path / "cache"
    x, _ = fresh_features(native, backbone, native.seed + 1, 8, 1, cache)
    y, _ = fresh_features(camera, backbone, camera.seed + 1, 8, 1, cache)
    assert len(list(cache.glob("tiny-*.npz"))) == 2
    np.testing.assert_array_equal(
        y, backbone.extract(render_split(camera, "test", 8, workers=1, seed=camera.seed + 1)[0])
    )
    assert not np.array_equal(x, y)


def test_splits_summary_is_the_mean_and_spread_over_splits() -> None:
    def row(v: float) -> dict:
        block = dict.fromkeys(PREDICTED, v)
        return {
            "info_gain_nats": v,
            "test_nll": -v,
            "calibration_error": v / 10,
            "day_median_abs_error": block,
            "night_coverage68": block,
            "day_coverage68": block,
        }

    out = summarize([row(1.0), row(2.0), row(6.0)])
    assert out["info_gain_nats"]["mean"] == pytest.approx(3.0)
    assert out["info_gain_nats"]["sd"] == pytest.approx(np.std([1.0, 2.0, 6.0], ddof=1))
    assert out["night_coverage68"]["wind_intensity"]["mean"] == pytest.approx(3.0)
    assert summarize([row(1.0)])["test_nll"] == {"mean": -1.0, "sd": None}


def test_resolution_paired_difference_holds_the_true_mean_difference() -> None:
    """``bench_resolution``'s ΔNLL interval: on pairs whose differences have a known mean, the 95 % interval holds it in
    about 95 % of 400 replicates (the normal interval of a mean of 200 values); a constant shift gives a zero-width
    interval at the shift; unequal or too short inputs are refused."""
    rng = np.random.default_rng(0)
    held = 0
    for _ in range(400):
        a = rng.normal(0.0, 3.0, 200)
        b = a - 1.5 + rng.standard_exponential(200) - 1.0  # differences: mean 1.5, skewed
        mean, low, high = paired_difference(a, b)
        held += low <= 1.5 <= high
        assert low <= mean <= high
    assert 0.92 <= held / 400 <= 0.98
    assert paired_difference(np.arange(5.0) + 2, np.arange(5.0)) == (2.0, 2.0, 2.0)
    with pytest.raises(ValueError, match="paired values"):
        paired_difference(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match="paired values"):
        paired_difference(np.zeros(1), np.zeros(1))


def test_rain_pool_variants_change_only_the_rain() -> None:
    """``bench_rain_pool``'s variants: ``native`` is the renderer's own table; ``pool=N,alpha=A`` changes exactly
    ``rain_drop_pool`` and ``streak_alpha``; its renders equal the renderer's own where it does not rain (the pool
    is the scene's own random stream) and differ where it does; the renderer's own values give its own images; a
    malformed variant is refused naming the item."""
    from components.simulate.procedural.calibration import CALIBRATION

    assert calibration_of("native") is None
    table = calibration_of("pool=1400,alpha=0.275")
    assert (table.rain_drop_pool, table.streak_alpha) == (1400, 0.275)
    changed = {n for n in CALIBRATION.__dataclass_fields__ if getattr(table, n) != getattr(CALIBRATION, n)}
    assert changed == {"rain_drop_pool", "streak_alpha"}
    own = ProceduralSimulator(64, 64)
    same = ProceduralSimulator(64, 64, calibration=calibration_of(f"pool={CALIBRATION.rain_drop_pool}"))
    other = ProceduralSimulator(64, 64, calibration=table)
    dry = {
        "cloudiness": 20.0,
        "fog_density": 10.0,
        "precipitation": 0.0,
        "precipitation_deposits": 60.0,
        "sun_altitude_angle": 30.0,
        "wind_intensity": 40.0,
        "sun_azimuth_angle": 120.0,
    }
    wet = {**dry, "precipitation": 70.0}
    assert np.array_equal(other.render(dry, 3), own.render(dry, 3))
    assert np.array_equal(same.render(wet, 3), own.render(wet, 3))
    assert not np.array_equal(other.render(wet, 3), own.render(wet, 3))
    for bad in ("pool", "drops=3", "pool=2800,alpha"):
        with pytest.raises(ValueError, match="expected native or pool=N,alpha=A"):
            calibration_of(bad)


def test_resolution_training_renders_the_pipelines_resized_renders() -> None:
    """``bench_resolution_training``'s ``vary`` renders are the pipeline's (``simulator.render_sizes``), whatever the
    processes; ``render`` with a size per image gives each image its own size's render, area-resized as the CLI
    resizes a camera's image."""
    from components.core import weather
    from components.features.backbones.imageops import resize_area
    from components.simulate.resized import ResizedRenders

    row = weather.weather_from_theta(np.array([20.0, 10.0, 60.0, 30.0, 40.0, 50.0]), 120.0)
    weathers = np.stack([weather.weather_array(row)] * 3)
    seeds = np.array([5, 6, 7])
    images = render_resized(weathers, seeds, (40, 56), 32)
    sim = ResizedRenders(32, 32, (40, 56))
    assert np.array_equal(images, np.stack([sim.render(row, int(s)) for s in seeds]))
    images = render(weathers[:2], np.array([5, 6]), np.array([32, 48]), 32)
    assert images.shape == (2, 32, 32, 3)
    assert np.array_equal(images[0], ProceduralSimulator(32, 32).render(row, 5))
    assert np.array_equal(images[1], resize_area(ProceduralSimulator(48, 48).render(row, 6)[None], (32, 32))[0])


def _first_third_party_import(path: Path) -> str | None:
    """The top-level name of the first module-level import of a script that is neither the standard library nor
    ``__future__``, or ``None``; ``benchmarks.machine`` (also imported as ``machine`` from the script's folder) is
    standard library only."""
    import ast

    for node in ast.parse(path.read_text(), filename=str(path)).body:
        if isinstance(node, ast.Import):
            names = [alias.name.split(".")[0] for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module.split(".")[0]]
        else:
            continue
        for name in names:
            if name not in sys.stdlib_module_names and name not in ("__future__", "benchmarks", "machine"):
                return name
    return None


def _uses_pidc(path: Path) -> bool:
    text = path.read_text()
    return "from components" in text or "import components" in text or "from flows" in text


_SCRIPTS = sorted(p for d in ("benchmarks", "benchmarks/studies", "scripts") for p in (ROOT / d).glob("*.py"))


@pytest.mark.parametrize("script", [p.relative_to(ROOT).as_posix() for p in _SCRIPTS if _uses_pidc(p)])
def test_scripts_import_pidc_before_numpy(script: str) -> None:
    """A script run as ``python benchmarks/x.py`` that uses pidc imports ``components`` (or ``flows``) before any
    third-party module: importing pidc first pins numpy's SIMD kernels to the baseline, and the renderer refuses a
    process that did not (``bench_task2`` did, and failed at its first render). Scripts that never import pidc
    (the SBI problems) are free, and not collected."""
    path = ROOT / script
    first = _first_third_party_import(path)
    assert first in ("components", "flows"), f"{script}: imports {first} before components"


def test_conditional_coverage_of_exact_posteriors_is_the_mass_in_every_cell() -> None:
    """``bench_conditional_coverage``'s cells on a problem whose answer is known: independent Gaussian posteriors per
    parameter and truths drawn from them, so that a parameter's coverage does not depend on another's truth. Every
    cell's coverage lies within its binomial range but for about 5 % of the cells (the cells binned by their own truth
    left out, as the script leaves them out), and posteriors 0.7× too narrow fall below the range in most cells."""
    rng = np.random.default_rng(3)
    low = np.array([0.0, 0.0, 0.0, -90.0, 0.0, 0.0])
    high = np.array([100.0, 100.0, 100.0, 90.0, 100.0, 100.0])
    n, draws = 4000, 400
    centre = rng.uniform(low, high, (n, 6))
    sd = 0.05 * (high - low)
    theta = centre + sd * rng.standard_normal((n, 6))  # a truth beyond the box falls in no bin
    noise = rng.standard_normal((n, draws, 6))
    for scale, check in ((1.0, "exact"), (0.7, "narrow")):
        samples = centre[:, None] + scale * sd * noise
        rows, covered = coverage_cells(samples, theta)
        assert covered.shape == (n, 6) and len(rows) == 14
        cross = [(c, r["range"]) for r in rows for k, c in enumerate(r["coverage"]) if k != r["parameter"]]
        outside = sum(not lo <= c <= hi for c, (lo, hi) in cross)
        below = sum(c < lo for c, (lo, _) in cross)
        if check == "exact":
            assert abs(covered.mean() - MASS) < 0.01
            assert outside <= 9, outside  # 70 cells: 3.5 expected, P(> 9) < 1 % were they independent
        else:
            assert below >= 60, below


# --- bench_watch: `pidc watch` on simulated drives, at a tiny scale with a tiny model -----------------------------

#: ``bench_watch.py``'s smoke scale shrunk further for a 32×32 model: three sources of 24 s (one block cycle of 60
#: frames each), one in-ODD drive of 20 s, one fog and one dusk exit of 35 s (a 10 s ramp from 20 s on), a 20 s
#: "hour", small watch options.
TINY_WATCH = [
    *("--quick", "--size", "32", "--source-seconds", "24", "--in-odd-seconds", "20", "--exits", "30=1"),
    *("--dusk-drives", "1", "--hour-seconds", "20", "--exit-seconds", "20,10,5"),
    *("--set", "window=20", "--set", "block=60", "--set", "false_alarm_rate=0.05", "--set", "samples=100"),
    *("--set", "draws_per_image=16", "--set", "n_points=16", "--set", "source_centres=256", "--set", "batch=32"),
]


@pytest.fixture(scope="module")
def watch_registry(tmp_path_factory) -> Path:
    from tests.tiny_registry import build_registry

    return build_registry(tmp_path_factory.mktemp("bench-watch"), "bench-watch")


def test_bench_watch_runs_every_mode_on_the_known_weather_and_resumes(watch_registry, tmp_path, capsys) -> None:
    """Every mode of ``bench_watch`` at a tiny scale: the in-ODD hours are the drives' driving before they leave the
    sources' range (known from their own weather), each exit is where the drive's weather first leaves that range, the
    one-hour mode measured a child process; the JSON line is strict JSON; a second run reads the records instead of
    watching again."""
    from benchmarks.bench_watch import exit_drives, in_odd_drives, main, parse
    from components.simulate.drive import first_exit

    args = ["all", "--registry", str(watch_registry), "--out", str(tmp_path), *TINY_WATCH]
    scale = parse(args).scale
    line = main(args)
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == line  # strict JSON: no NaN, no inf
    hull = {n: tuple(v) for n, v in line["hull"].items()}
    assert hull["precipitation"] == (0.0, 0.0) and hull["fog_density"][1] <= 10.0
    exits = [first_exit(d.weather_table(), hull) for _, d in in_odd_drives(scale, 32, 0)]
    measured = line["in_odd"]["measured"]
    assert measured["hours"] == pytest.approx(sum(20.0 if e is None else e.time_s for e in exits) / 3600)
    assert line["in_odd"]["left_hull"] == sum(e is not None for e in exits)
    assert measured["low"] <= measured["per_hour"] <= measured["high"]
    assert line["in_odd"]["stated"]["windows"] > 0
    records = [json.loads(r)["record"] for r in (tmp_path / "exits.jsonl").read_text().splitlines()]
    drives = exit_drives(scale, 32, 0, hull)
    assert [d.kind for d in drives] == ["fog", "dusk"] and len(records) == 2
    for d, r in zip(drives, records, strict=True):
        first = first_exit(d.drive.weather_table(), hull)
        assert r["exit_s"] == pytest.approx(first.time_s) and r["exit_parameters"] == list(first.parameters)
        assert r["exit_s"] <= 30.0  # out by the ramp's end at the latest (tiny sources may not reach their faces)
        if r["exit_s"] > 20.0:  # left during the ramp: by the ramped parameter
            assert r["exit_parameters"] == [{"fog": "fog_density", "dusk": "sun_altitude_angle"}[d.kind]]
    kinds = line["exits"]["kinds"]
    assert set(kinds) == {"fog+30", "dusk-30"} and all(k["left"] == 1 for k in kinds.values())
    hour = line["hour"]
    assert hour["frames"] == 200 and hour["truth"]["exit_s"] is None
    assert 0 < hour["max_rss_bytes"] < 2e9 and hour["cpu_seconds"] > 0 and hour["realtime_factor"] > 0
    lines = {p.name: p.read_text() for p in tmp_path.glob("*.jsonl")}
    again = main(args)
    assert {p.name: p.read_text() for p in tmp_path.glob("*.jsonl")} == lines  # nothing watched again
    for mode in ("in_odd", "exits"):
        assert again[mode] | {"sources_seconds_so_far": None} == line[mode] | {"sources_seconds_so_far": None}
    assert again["hour"] == line["hour"]


def test_bench_watch_reads_sources_once_with_the_watchs_own_numbers(watch_registry, tmp_path) -> None:
    """With ``SourcesOnce`` two watches read the sources and calibrate once (``prepare_sources``), and give the same
    tables, to the bit, as a watch that reads them itself."""
    from benchmarks.bench_watch import SourcesOnce, in_odd_drives, parse, render_sources, source_drives, watch_drive
    from components.export.lookup import load_registered
    from components.watch.settings import WatchOptions

    args = parse(["in-odd", *TINY_WATCH])
    options = WatchOptions(**dict(args.set))
    sources = render_sources(source_drives(24.0, 32, 0), tmp_path / "sources", progress=False)
    model = load_registered("champion", watch_registry)
    _, drive = in_odd_drives(args.scale, 32, 0)[0]
    plain = watch_drive(model, drive, sources, options, tmp_path)
    once = SourcesOnce()
    first = watch_drive(model, drive, sources, options, tmp_path, once)
    second = watch_drive(model, drive, sources, options, tmp_path, once)
    assert len(once.prepared) == 1 and once.seconds["prepare_sources"] > 0
    for result in (first, second):
        assert result.windows.keys() == plain.windows.keys()
        for key, column in plain.windows.items():
            np.testing.assert_array_equal(result.windows[key], column, err_msg=key)
        np.testing.assert_array_equal(result.frames["fog_density_median"], plain.frames["fog_density_median"])
        assert result.stated == plain.stated


def test_paper_scale_counts_the_profiles_models() -> None:
    """The paper-scale extrapolation counts the work of the profile's own models: its grid and its variants, with
    the epochs, flows and samples the train stage would give them."""
    from benchmarks.studies.bench_paper_scale import DIMS, paper_models

    params = load_params(profile="paper")
    models = {m["model"]: m for m in paper_models(params)}
    assert set(DIMS) == set(params.backbones.names)
    assert len(models) == len(params.backbones.names) * len(params.train.sizes) + len(params.train.variants)
    big = models["resnet50-500000-ensemble"]
    assert (big["flows"], big["epochs"], big["samples"]) == (3, 200, 100_000_000)
    assert models["resnet50-50000-balanced"]["flows"] == 1
    assert all(m["samples"] == m["epochs"] * m["size"] <= params.train.sample_budget for m in models.values())
    assert models["clip-5000"]["epochs"] > models["clip-500000"]["epochs"]
