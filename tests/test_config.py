"""params.yaml parsing: every profile parses, unknown keys and bad values are named."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from components.core.config import PROJECT_ROOT, ConfigError, load_params, parse_params
from components.core import seeding


@pytest.mark.parametrize("path", [PROJECT_ROOT / "params.yaml", *sorted((PROJECT_ROOT / "profiles").glob("*.yaml"))])
def test_profiles_parse(path):
    p = load_params(path)
    assert max(p.train.sizes) <= p.data.splits["train"]
    assert p.box.contains(p.box.low[None])[0]


def _default():
    return yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())


def test_unknown_key_is_named():
    d = _default()
    d["data"]["shardsize"] = 3
    with pytest.raises(ConfigError, match=r"data\.shardsize: unknown key"):
        parse_params(d, source="params.yaml")


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["data"]["splits"].update(train=-5), r"data\.splits\.train"),
        (lambda d: d["simulator"].update(backend="unreal"), r"simulator\.backend"),
        (lambda d: d["prior"].update(fog_density=[0, 200]), r"'fog_density' = 200 is outside"),
        (lambda d: d["train"].update(sizes=[1000, 50000]), r"train split must cover the largest training size"),
        (lambda d: d["data"]["runner"].update(kind="mpi"), r"data\.runner\.kind"),
        (lambda d: d["train"]["variants"].update(x={"backbone": "resnet50", "size": 10000}),
         r"train.variants.x needs a backbone in backbones.names"),
        (lambda d: d["train"]["variants"].update({"Bad Name": {"backbone": "cues", "size": 10000}}), r"train\.variants"),
        (lambda d: d["evaluate"].update(samples=100), r"evaluate\.samples: Input should be greater than or equal to 400"),
        (lambda d: d["evaluate"].update(images=5000), r"evaluate.images is 5000 but the test split has only 2000"),
        (lambda d: d.pop("seed") and d.update(seed=None), r"seed"),
        (lambda d: d["export"].update(exporter="tf"), r"export\.exporter"),
        (lambda d: d["task2"]["fixed"].pop("cloudiness"), r"task2\.fixed: .*must give exactly"),
        (lambda d: d["task2"]["modes"][0].update(std=[0, 1]), r"task2\.modes\.0\.std"),
        (lambda d: d["task3"]["bags"]["b0"]["box"].update(sun_altitude_angle=[-90, 30]),
         r"bags\.b0\.box overlaps bags\.b1\.box"),
        (lambda d: d["task3"].update(weights=[0.5, 0.6, 0.1]), r"weights must sum to 1"),
        (lambda d: d["task3"].update(weights=[0.5, 0.5]), r"weights has 2 entries for 3 sources"),
        (lambda d: d["task3"].update(etas=[0.5, 1.0]), r"etas must contain 0"),
        (lambda d: d["task3"]["bags"].pop("b2"), r"bags must be b0 \(out of the ODD\), b1, b2"),
        (lambda d: d["task3"]["bags"]["b1"]["box"].update(fog=[0, 1]), r"bags\.b1\.box: prior box: unknown"),
    ],
)
def test_bad_values_are_named(edit, message):
    d = _default()
    edit(d)
    with pytest.raises(ConfigError, match=message):
        parse_params(d, source="params.yaml")


def test_unreadable_and_invalid_files(tmp_path: Path):
    with pytest.raises(ConfigError, match="cannot read params file"):
        load_params(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("data: [unclosed")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_params(bad)


def test_seed_streams_are_deterministic_and_independent():
    a = seeding.rng(7, "data", "train").random(5)
    np.testing.assert_array_equal(a, seeding.rng(7, "data", "train").random(5))
    assert not np.allclose(a, seeding.rng(7, "data", "val").random(5))
    assert not np.allclose(a, seeding.rng(8, "data", "train").random(5))
    assert seeding.derive_seed(7, "scene", 3) == seeding.derive_seed(7, "scene", 3) >= 0
    with pytest.raises(ValueError, match="non-negative"):
        seeding.rng(7, -1)


