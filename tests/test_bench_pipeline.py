"""The pipeline benchmark's own arithmetic and input checks (``benchmarks/bench_pipeline.py``); no pipeline runs.

Known answers: a job that halves on two cores has efficiency 1 and one that does not speed up 1/2; the overhead is the
wall less the flow runs' sum; scaling the data by s keeps every model's training settings (epochs, widths, noise,
ensemble) those of the full-scale model it stands for, which ``components/posterior/settings.py`` computes
independently. Deterministic: nothing here is random.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks import bench_pipeline as bench  # noqa: E402
from components.core.config import ConfigError, load_params, parse_params  # noqa: E402
from components.posterior import settings  # noqa: E402


@pytest.fixture(scope="module")
def raw() -> dict:
    """The project's params, resolved as the benchmark resolves them."""
    return load_params(ROOT / "params.yaml").model_dump(mode="json")


def test_cpu_sets_parse_as_taskset_takes_them() -> None:
    assert bench.parse_cpus("0") == (0,)
    assert bench.parse_cpus("1,0") == (0, 1)
    assert bench.parse_cpus("0-2,5,2") == (0, 1, 2, 5)
    for bad in ("", "a", "0,,1", "-1", "3-1", "0;1"):
        with pytest.raises(ValueError, match="--cpus"):
            bench.parse_cpus(bad)


def test_cpu_sets_outside_the_affinity_or_repeated_are_refused() -> None:
    bench.check_cpus([(0,), (0, 1)], {0, 1})
    with pytest.raises(ValueError, match=r"CPU 2, 7 not in this process's affinity .* = 0,1\)"):
        bench.check_cpus([(0,), (0, 2, 7)], {0, 1})
    with pytest.raises(ValueError, match="0,1 given more than once"):
        bench.check_cpus([(0, 1), (0, 1)], {0, 1})


def test_scaling_multiplies_exactly_the_counted_settings(raw: dict) -> None:
    """Every key of SCALED is n·s rounded half up (at least 1), every other setting is params.yaml's, and the result
    is valid params."""
    s = 0.2
    out = bench.scale_params(raw, s)
    assert out["train"]["sizes"] == [max(1, int(n * s + 0.5)) for n in raw["train"]["sizes"]]
    assert out["data"]["splits"] == {k: max(1, int(n * s + 0.5)) for k, n in raw["data"]["splits"].items()}
    assert out["data"]["shard_size"] == max(1, int(raw["data"]["shard_size"] * s + 0.5))
    for bag, cfg in raw["task3"]["bags"].items():
        assert out["task3"]["bags"][bag]["max_images"] == max(1, int(cfg["max_images"] * s + 0.5))
    assert raw["train"]["sizes"] != out["train"]["sizes"]  # a copy: the input is not changed in place
    undone = yaml.safe_load(yaml.safe_dump(out))
    for key in bench.SCALED:
        for path in bench._expand(raw, key.split(".")):
            src, dst = bench._parent(raw, path, key), bench._parent(undone, path, key)
            dst[0][dst[1]] = src[0][src[1]]
    assert undone == raw
    parse_params(out)
    assert bench.scaled_count(2, 0.25) == 1 and bench.scaled_count(3, 0.5) == 2 and bench.scaled_count(7, 0.01) == 1


@pytest.mark.parametrize("s", [0.1, 0.2, 0.5])
def test_scaled_models_train_as_the_full_scale_ones(raw: dict, s: float) -> None:
    """A model of s·n images trains as many epochs (and patience), as wide, with the same input noise and ensemble as
    the model of n images it stands for (counts set here so that every scaled one is whole)."""
    raw = bench.apply_settings(
        raw,
        [
            "train.sizes=[5000, 20000, 50000]",
            "data.splits={train: 50000, val: 6000, test: 2000}",
            "train.scale_to=10000",
            "train.sample_budget=3000000",
            "train.embedding_sample_budget=60000",
            "train.input_noise_max_size=20000",
            "train.ensemble_min_size=50000",
        ],
    )
    full, small = parse_params(raw).train, parse_params(bench.scale_params(raw, s)).train
    for n, m in zip(full.sizes, small.sizes, strict=True):
        for trainable in (False, True):
            assert settings.epochs_for(small, m, trainable=trainable) == settings.epochs_for(
                full, n, trainable=trainable
            )
            noise = {"trainable": trainable, "features": 377}
            assert settings.input_noise_for(small, m, **noise) == pytest.approx(
                settings.input_noise_for(full, n, **noise)
            )
        assert settings.hidden_for(small, m) == settings.hidden_for(full, n)
        assert settings.ensemble_for(small, m) == settings.ensemble_for(full, n)
        assert settings.patience_for(small, m) == settings.patience_for(full, n)


def test_bad_scales_are_one_clear_error(raw: dict, tmp_path: Path) -> None:
    for bad in (0, -0.5, float("nan")):
        with pytest.raises(ValueError, match="--scale must be a positive number"):
            bench.scale_params(raw, bad)
    with pytest.raises(ValueError, match=r"train.sizes .* two models of one size"):
        bench.scale_params(raw, 1e-5)
    params = tmp_path / "params.yaml"
    small = bench.apply_settings(
        raw,
        [
            "train.sizes=[10000, 20000, 50000]",
            "data.splits={train: 50000, val: 6000, test: 2000}",
            "evaluate.named.local_test.calibration_images=2000",
        ],
    )
    params.write_text(yaml.safe_dump(small))
    with pytest.raises(ConfigError, match="calibration_images") as e:  # 2000 × 0.001 = 2 < its minimum, 10
        bench.scaled_params(params, 0.001, [])
    assert "\n" not in e.value.one_line()
    with pytest.raises(ConfigError, match="the train split must cover the largest training size"):
        bench.scaled_params(ROOT / "params.yaml", 0.2, ["data.splits.train=100"])


def test_settings_after_scaling(raw: dict) -> None:
    out = bench.apply_settings(raw, ["train.epochs=2", "backbones.names=[cues]", "task3.etas=[0.0, 1.0]"])
    assert (out["train"]["epochs"], out["backbones"]["names"], out["task3"]["etas"]) == (2, ["cues"], [0.0, 1.0])
    assert raw["train"]["epochs"] != 2 or raw["backbones"]["names"] != ["cues"]
    for bad, match in (("train.epochs", "expected KEY=VALUE"), ("train.nope=1", "unknown key"), ("x.y=1", "unknown")):
        with pytest.raises(ValueError, match=match):
            bench.apply_settings(raw, [bad])
    with pytest.raises(ValueError, match="not YAML"):
        bench.apply_settings(raw, ["train.epochs=[1"])


def test_efficiency_and_overhead_arithmetic() -> None:
    assert bench.efficiency(100.0, 50.0, 2) == 1.0  # halved on two cores: both used
    assert bench.efficiency(100.0, 100.0, 2) == 0.5  # no gain
    assert bench.efficiency(90.0, 50.0, 2) == pytest.approx(0.9)
    seconds, share = bench.overhead(200.0, [100.0, 60.0, 20.0])
    assert (seconds, share) == (pytest.approx(20.0), pytest.approx(0.1))


def test_stages_and_their_flow_runs_from_a_timeline() -> None:
    events = [(10.0, "generate"), (40.0, "features@cues"), (55.0, "train")]
    windows = bench.stage_windows(events, 100.0)
    assert windows == [("generate", 10.0, 40.0), ("features@cues", 40.0, 55.0), ("train", 55.0, 100.0)]
    runs = [
        {"name": "a", "flow": "generate", "start": 14.0, "end": 37.0, "seconds": 23.0},
        {"name": "b", "flow": "features", "start": 44.0, "end": 52.0, "seconds": 8.0},
        {"name": "c", "flow": "train", "start": 60.0, "end": 97.0, "seconds": 37.0},
    ]
    per = bench.assign_flow_runs(windows, runs)
    assert {k: [r["name"] for r in v] for k, v in per.items()} == {
        "generate": ["a"],
        "features@cues": ["b"],
        "train": ["c"],
    }
    with pytest.raises(ValueError, match="outside every stage"):
        bench.assign_flow_runs(windows, [{**runs[0], "start": 5.0}])
    with pytest.raises(ValueError, match="has not ended"):
        bench.assign_flow_runs(windows, [{**runs[0], "end": None, "state": "RUNNING"}])


def _run(cpus: list[int], scale: float) -> dict:
    """A synthetic record: stage times × ``scale`` after fixed phases; flow runs 80 % of each stage."""
    stages = [
        {"stage": n, "seconds": t * scale, "flow_seconds": 0.8 * t * scale}
        for n, t in (("generate", 100), ("train", 200))
    ]
    flows = sum(s["flow_seconds"] for s in stages)
    wall = 10 + sum(s["seconds"] for s in stages)
    over, share = bench.overhead(wall, [flows])
    return {
        "cpus": cpus, "workers": len(cpus), "wall_s": wall, "server_s": 4.0, "setup_s": 5.0, "dvc_start_s": 1.0,
        "stages": stages, "flow_seconds": flows, "overhead_s": over, "overhead_share": share,
    }  # fmt: skip


def test_report_table() -> None:
    """Stage times halved on two cores: efficiency 1.00; the fixed phases not at all: 0.50, named below the floor."""
    lines, eff = bench.report([_run([0], 1.0), _run([0, 1], 0.5)])
    assert lines[0].startswith("| stage | 1 core (s) | 2 cores (s) | parallel efficiency T1/(2·T2) |")
    row = next(line for line in lines if line.startswith("| train |"))
    assert row == "| train | 200.0 | 100.0 | 1.00 | 1.00 | 80% / 80% |"
    assert eff["generate"]["0,1"] == pytest.approx(1.0)
    assert eff["scripts/setup.sh"]["0,1"] == pytest.approx(0.5)
    assert eff["whole run"]["0,1"] == pytest.approx(310 / (2 * 160))
    assert not any(line.startswith("- below") for line in lines)  # the phases are not stages
    assert any("overhead = wall − Σ flow runs = 70.0 s = **22.6%**" in line for line in lines)
