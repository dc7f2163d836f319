"""params.yaml parsing: the one source of every setting. Every profile resolves to a complete config; unknown keys,
missing keys and bad values are named; `pidc config check` validates without running anything."""

import dataclasses
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from pydantic import BaseModel

from components.core import seeding
from components.core.config import NAMED_MAPPINGS, PROJECT_ROOT, ConfigError, Params, load_params, parse_params

PROFILES = ["default", *sorted(f.stem for f in (PROJECT_ROOT / "profiles").glob("*.yaml"))]


def _default():
    return yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())


def _leaves(d: dict, where: str = "") -> dict[str, object]:
    """Dotted key → value of every leaf of nested mappings (lists, scalars and the named mappings a profile replaces
    whole, such as ``train.variants``, are leaves)."""
    out = {}
    for k, v in d.items():
        key = f"{where}.{k}" if where else str(k)
        out |= _leaves(v, key) if isinstance(v, dict) and v and key not in NAMED_MAPPINGS else {key: v}
    return out


def _section_models() -> set[type[BaseModel]]:
    """Params and every section model reachable from it."""
    seen: set[type[BaseModel]] = set()
    todo = [Params]
    while todo:
        model = todo.pop()
        if model in seen:
            continue
        seen.add(model)
        for _name, field in model.model_fields.items():
            todo += [t for t in _types_in(field.annotation) if isinstance(t, type) and issubclass(t, BaseModel)]
    return seen


def _types_in(annotation) -> list:
    import typing

    return [annotation, *(t for a in typing.get_args(annotation) for t in _types_in(a))]


def test_no_setting_has_a_default_in_the_code():
    """params.yaml is the only place a setting is written: no section model field has a default."""
    models = _section_models()
    assert {"Params", "TrainConfig", "FlowParams", "VariantConfig", "Task3Config", "BagConfig", "CarlaConfig"} <= {
        m.__name__ for m in models
    }
    defaulted = [f"{m.__name__}.{n}" for m in models for n, f in m.model_fields.items() if not f.is_required()]
    assert defaulted == []


@pytest.mark.parametrize("profile", PROFILES)
def test_every_profile_resolves_to_a_complete_config(profile):
    p = load_params(PROJECT_ROOT / "params.yaml", profile=profile)
    assert p.profile == profile
    assert max(p.train.sizes) <= p.data.splits["train"]
    assert p.box.contains(p.box.low[None])[0]

    def every_field_set(model: BaseModel, where: str) -> None:
        assert model.model_fields_set == set(type(model).model_fields), where
        for name in type(model).model_fields:
            values = getattr(model, name)
            values = values.values() if isinstance(values, dict) else values if isinstance(values, tuple) else [values]
            for v in values:
                if isinstance(v, BaseModel):
                    every_field_set(v, f"{where}.{name}")

    every_field_set(p, profile)
    # the dumped config is the complete settings: it parses on its own, without any profile
    assert parse_params(p.model_dump(mode="json")) == p


@pytest.mark.parametrize("profile", [n for n in PROFILES if n != "default"])
def test_a_profile_holds_only_its_overrides(profile):
    """The profile differs from the default settings exactly in the keys its file sets."""
    overrides = yaml.safe_load((PROJECT_ROOT / "profiles" / f"{profile}.yaml").read_text()) or {}
    base = _leaves(load_params(PROJECT_ROOT / "params.yaml", profile="default").model_dump(mode="json"))
    resolved = _leaves(load_params(PROJECT_ROOT / "params.yaml", profile=profile).model_dump(mode="json"))
    assert set(base) == set(resolved)
    changed = {k for k in base if base[k] != resolved[k]} - {"profile"}
    assert changed == set(_leaves(overrides)), "a profile sets exactly the keys whose values differ from params.yaml"


def test_the_profile_key_of_the_file_picks_the_profile(tmp_path: Path):
    shutil.copytree(PROJECT_ROOT / "profiles", tmp_path / "profiles")
    d = _default()
    d["profile"] = "paper"
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(d, sort_keys=False))
    p = load_params(tmp_path / "params.yaml")
    assert p == load_params(PROJECT_ROOT / "params.yaml", profile="paper")
    assert p.profile == "paper" and p.export.exporter == "dynamo"
    assert load_params(tmp_path / "params.yaml", profile="default") == load_params(PROJECT_ROOT / "params.yaml")


def test_profiles_merge_mappings_and_replace_lists(tmp_path: Path):
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "small.yaml").write_text(
        "data:\n  splits: {test: 3000}\n  runner: {workers: 1}\nbackbones:\n  names: [cues]\n"
        "train:\n  variants: {ensemble: {backbone: cues, size: 5000, balance: 0.0, ensemble: 2}}\n"
    )
    shutil.copy(PROJECT_ROOT / "params.yaml", tmp_path / "params.yaml")
    p = load_params(tmp_path / "params.yaml", profile="small")
    base = load_params(tmp_path / "params.yaml")
    assert p.profile == "small" and p.data.splits == {**base.data.splits, "test": 3000}
    assert p.data.runner.workers == 1 and p.data.runner.kind == base.data.runner.kind
    assert p.backbones.names == ("cues",) and p.backbones.batch_size == base.backbones.batch_size
    assert base.train.variants == {}  # train.variants is replaced whole (its keys are the user's names)
    assert list(p.train.variants) == ["ensemble"] and p.train.variants["ensemble"].ensemble == 2


def test_unknown_key_in_a_profile_is_named_with_its_file(tmp_path: Path):
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "odd.yaml").write_text("train:\n  flow:\n    binz: 4\nevaluate: {images: 100}\n")
    shutil.copy(PROJECT_ROOT / "params.yaml", tmp_path / "params.yaml")
    with pytest.raises(ConfigError, match=r"profiles/odd\.yaml: train\.flow\.binz: unknown key") as e:
        load_params(tmp_path / "params.yaml", profile="odd")
    assert "evaluate" not in str(e.value)
    (tmp_path / "profiles" / "named.yaml").write_text("profile: other\n")
    with pytest.raises(ConfigError, match=r"profiles/named\.yaml: profile: unknown key"):
        load_params(tmp_path / "params.yaml", profile="named")
    (tmp_path / "profiles" / "bad.yaml").write_text("train:\n  epochs: 0\n")
    with pytest.raises(ConfigError, match=r"profiles/bad\.yaml.*\n.*train\.epochs: Input should be greater than 0"):
        load_params(tmp_path / "params.yaml", profile="bad")


@pytest.mark.parametrize("name", ["nope", "../params", None])
def test_unknown_profile_is_named(tmp_path: Path, name):
    d = _default()
    d["profile"] = name
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(d, sort_keys=False))
    with pytest.raises(ConfigError, match=r"params\.yaml: profile: unknown profile .*; profiles found: default \("):
        load_params(tmp_path / "params.yaml")
    with pytest.raises(
        ConfigError, match=r"params\.yaml: profile: unknown profile 'x'; profiles found: default, camera, gpu, paper"
    ):
        load_params(PROJECT_ROOT / "params.yaml", profile="x")


def _remove(d: dict, dotted: str) -> None:
    *path, last = dotted.split(".")
    for k in path:
        d = d[k]
    del d[last]


MISSING = [
    "seed",
    "profile",
    "prior",
    "data.shard_size",
    "data.shards_per_task",
    "data.runner.dask_address",
    "export.runner",
    "backbones.pretrained_dir",
    "train.flow.bins",
    "train.flow.standardize",
    "train.min_lr",
    "train.variants",
    "train.temperature",
    "train.temperature_regime",
    "train.temperature_regime.below",
    "task2.modes",
    "task3.bags",
    "task3.bags.b1.max_images",
    "task3.smoothing",
    "train.input_noise_max_size",
    "train.input_noise_min_features",
    "train.few_features_epochs",
    "train.few_features_recipe",
    "train.few_features_recipe.patience",
    "train.compile_min_steps",
    "train.mirror",
    "train.ensemble_min_size",
    "evaluate.samples",
    "evaluate.profile_bins",
    "evaluate.named",
    "evaluate.named.folders",
    "evaluate.named.local_test.null_trials",
    "simulator.carla.fov",
    "monitor",
    "monitor.alarm_level",
    "monitor.false_alarm_targets",
]


@pytest.mark.parametrize("key", MISSING)
def test_a_missing_key_is_named(key, tmp_path: Path):
    d = _default()
    _remove(d, key)
    with pytest.raises(ConfigError, match=rf"params\.yaml: invalid params\n  {key.replace('.', r'[.]')}: missing key$"):
        parse_params(d, source="params.yaml")
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    with pytest.raises(ConfigError, match=rf"{key.replace('.', r'[.]')}: missing key"):
        load_params(path)


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
        (lambda d: d["train"].update(sizes=[1000, 60000]), r"train split must cover the largest training size"),
        (lambda d: d["data"]["runner"].update(kind="mpi"), r"data\.runner\.kind"),
        (lambda d: d["data"].update(shards_per_task=0), r"data\.shards_per_task: Input should be greater than 0"),
        (
            lambda d: d["export"]["runner"].update(kind="threads"),
            r"export\.runner: .*parallel exports need kind: processes",
        ),
        (
            lambda d: d["train"]["variants"].update(
                x={"backbone": "resnet50", "size": 10000, "balance": 0, "ensemble": 2}
            ),
            r"train.variants.x needs a backbone in backbones.names",
        ),
        (
            lambda d: d["train"]["variants"].update(
                {"Bad Name": {"backbone": "cues", "size": 10000, "balance": 0, "ensemble": 2}}
            ),
            r"train\.variants",
        ),
        (lambda d: d["train"].update(min_lr=0.01), r"train: .*min_lr \(0\.01\) must not exceed lr \(0\.001\)"),
        (lambda d: d["train"].update(plateau_factor=1.0), r"train\.plateau_factor: Input should be less than 1"),
        (lambda d: d["train"]["flow"].update(standardize="maybe"), r"train\.flow\.standardize"),
        (
            lambda d: d["train"]["temperature_regime"].update(parameter="sun"),
            r"train\.temperature_regime\.parameter is 'sun', not one of the prior's parameters",
        ),
        (
            lambda d: d["train"]["temperature_regime"].update(below=-90),
            r"train\.temperature_regime\.below = -90 must lie inside the prior of sun_altitude_angle, \(-90, 90\)",
        ),
        (lambda d: d["train"]["temperature_regime"].update(name="Night!"), r"train\.temperature_regime\.name"),
        (
            lambda d: d["evaluate"].update(samples=100),
            r"evaluate\.samples: Input should be greater than or equal to 400",
        ),
        (lambda d: d["evaluate"].update(images=5000), r"evaluate.images is 5000 but the test split has only 2000"),
        (
            lambda d: d["evaluate"].update(profile_bins=0),
            r"evaluate\.profile_bins: Input should be greater than or equal to 1",
        ),
        (lambda d: d.pop("seed") and d.update(seed=None), r"seed"),
        (lambda d: d["export"].update(exporter="tf"), r"export\.exporter"),
        (lambda d: d["task2"]["fixed"].pop("cloudiness"), r"task2\.fixed: .*must give exactly"),
        (lambda d: d["task2"]["modes"][0].update(std=[0, 1]), r"task2\.modes\.0\.std"),
        (lambda d: d["task2"]["width_floor"].update(draws=1), r"task2\.width_floor\.draws: Input should be greater"),
        (lambda d: d["task2"]["width_floor"].pop("bootstrap"), r"task2\.width_floor\.bootstrap: missing key"),
        (lambda d: d["task2"]["width_floor"].update(bootstrap=10), r"task2\.width_floor\.bootstrap: Input should be"),
        (
            lambda d: d["task2"]["width_floor"].update(scales=[1.0, 0]),
            r"task2\.width_floor\.scales\.1: Input should be",
        ),
        (lambda d: d["task2"]["width_floor"].update(scales=[]), r"task2\.width_floor\.scales: .*at least 1"),
        (lambda d: d["task2"]["width_floor"].update(scales=[0.8]), r"task2\.width_floor\.scales: .*must include 1"),
        (lambda d: d["task2"].pop("width_floor"), r"task2\.width_floor: missing key"),
        (
            lambda d: d["task3"]["bags"]["b0"]["box"].update(sun_altitude_angle=[-90, 30]),
            r"bags\.b0\.box overlaps bags\.b1\.box",
        ),
        (lambda d: d["task3"].update(weights=[0.5, 0.6, 0.1]), r"weights must sum to 1"),
        (lambda d: d["task3"].update(weights=[0.5, 0.5]), r"weights has 2 entries for 3 sources"),
        (lambda d: d["task3"].update(etas=[0.5, 1.0]), r"etas must contain 0"),
        (lambda d: d["task3"]["bags"].pop("b2"), r"bags must be b0 \(out of the ODD\), b1, b2"),
        (lambda d: d["task3"]["bags"]["b1"]["box"].update(fog=[0, 1]), r"bags\.b1\.box: prior box: unknown"),
        (lambda d: d["monitor"].update(models="best"), r"monitor\.models: Input should be 'champion' or 'all'"),
        (lambda d: d["monitor"].update(samples=10), r"monitor\.samples: Input should be greater than or equal to 100"),
        (lambda d: d["monitor"].update(alarm_level=1.0), r"monitor\.alarm_level: Input should be less than 1"),
        (lambda d: d["monitor"].update(false_alarm_targets=-1), r"monitor\.false_alarm_targets"),
        (lambda d: d["monitor"].update(source=" recorded/"), r"monitor\.source: .*without surrounding spaces"),
        (lambda d: d["monitor"].update(images=0), r"monitor\.images: Input should be greater than 0"),
        # numbers are finite, counts integers and switches booleans: YAML's yes/no and quoted numbers are refused
        (lambda d: d["train"].update(lr=math.inf), r"train\.lr: Input should be a finite number"),
        (lambda d: d["task2"]["modes"][0].update(mean=[math.nan, 20]), r"task2\.modes\.0\.mean\.0: .*finite"),
        (lambda d: d["train"].update(compile_min_steps=False), r"train\.compile_min_steps: .*valid integer"),
        (lambda d: d["train"].update(epochs=True), r"train\.epochs: .*valid integer"),
        (lambda d: d["data"]["splits"].update(val="6000"), r"data\.splits\.val: .*valid integer"),
        (lambda d: d["train"].update(mirror="yes"), r"train\.mirror: .*valid boolean"),
        (lambda d: d["train"].update(lr=True), r"train\.lr: must be a number, got True"),
        (lambda d: d["simulator"].update(height=8), r"simulator\.height: .*greater than or equal to 16"),
        (lambda d: d["simulator"].update(width=4096), r"simulator\.width: .*less than or equal to 2048"),
        (lambda d: d["simulator"].update(render_sizes=[200]), r"simulator\.render_sizes: too few items"),
        (lambda d: d["prior"].pop("wind_intensity"), r"prior: missing wind_intensity: the prior needs"),
        (lambda d: d["backbones"].update(names=["cues", "abc"]), r"backbones\.names\.1: Input should be 'cues'"),
        (lambda d: d["backbones"].update(names=[]), r"backbones\.names: .*at least 1"),
        (lambda d: d["backbones"].update(names=["cues", "cues"]), r"backbones\.names: each value at most once"),
        (lambda d: d["train"].update(sizes=[]), r"train\.sizes: .*at least 1"),
        (lambda d: d["train"].update(sizes=[5000, 5000]), r"train\.sizes: each value at most once"),
        (lambda d: d["train"]["flow"].update(passes=1), r"train\.flow\.passes: .*greater than or equal to 2"),
        (lambda d: d["train"].update(experiment=""), r"train\.experiment: .*at least 1 character"),
        (lambda d: d["data"].update(root=""), r"data\.root: .*at least 1 character"),
        (lambda d: d["task3"].update(model=" champion"), r"task3\.model: .*without surrounding spaces"),
        (
            lambda d: d["data"]["runner"].update(dask_address="tcp://x:8786"),
            r"data\.runner: dask_address 'tcp://x:8786' is set but kind is 'processes'",
        ),
        (lambda d: d["task2"].update(modes=[]), r"task2\.modes: .*at least 1"),
        (
            lambda d: d["task2"]["modes"][1].update(mean=[60, 140]),
            r"task2\.modes\.1\.mean: precipitation = 140 lies outside the prior \[0, 100\]",
        ),
        (
            lambda d: d["task2"].update(estimate="deconvolved", images=3),
            r"task2: deconvolution\.folds = 5 exceeds images = 3",
        ),
        (lambda d: d["task3"].update(etas=[0, 0.1, 0.1000001]), r"task3: etas repeats 0\.1"),
        (
            lambda d: d["evaluate"]["named"]["weathers"].update(
                ClearNoon=d["evaluate"]["named"]["weathers"]["pidc:ClearLowSun"]
            ),
            r"evaluate\.named: .*weathers\.ClearNoon: the name of a CARLA preset",
        ),
        (
            lambda d: d["evaluate"]["named"]["weathers"]["pidc:FoggyNoon"].pop("wind_intensity"),
            r"weathers\.pidc:FoggyNoon: needs exactly the six predicted parameters .*missing \['wind_intensity'\]",
        ),
        (
            lambda d: d["evaluate"]["named"]["weathers"]["pidc:FoggyNoon"].update(fog_density=120),
            r"evaluate\.named\.weathers\.pidc:FoggyNoon\.fog_density = 120, outside the prior \[0, 100\]",
        ),
        (
            lambda d: (d["prior"].update(sun_altitude_angle=[-60, 60]), d["evaluate"]["named"].update(weathers={})),
            r"evaluate\.named\.presets: CARLA's \w+ has sun_altitude_angle = -?\d+, outside the prior \[-60, 60\] "
            r"\(set evaluate\.named\.presets: none\)",
        ),
        (
            lambda d: d["evaluate"]["named"].update(folders={"pidc:StormNoon": "x"}),
            r"evaluate\.named: .*folders: pidc:StormNoon already name a weather",
        ),
        (
            lambda d: d["evaluate"]["named"]["local_test"].update(calibration_images=7000),
            r"evaluate\.named\.local_test\.calibration_images is 7000 but the val split has only 6000 images",
        ),
        (
            lambda d: d["evaluate"]["named"]["local_test"].update(test_draws=2000),
            r"local_test\.test_draws \(2000\) exceeds draws \(500\)",
        ),
        (
            lambda d: d["task3"].update(calibration_targets=18),
            r"task3: calibration_targets = 18 is too few for false_alarm_rate = 0\.05: .*needs n ≥ 19",
        ),
    ],
)
def test_bad_values_are_named(edit, message):
    d = _default()
    edit(d)
    with pytest.raises(ConfigError, match=message):
        parse_params(d, source="params.yaml")


def test_the_least_calibration_targets_suffice():
    """The smallest count the validator accepts is one the ODD decision can calibrate on, for several α."""
    from components.domains.relative import OddDetector

    for alpha in (0.05, 0.1, 0.2, 0.01):
        d = _default()
        d["task3"]["false_alarm_rate"] = alpha
        need = next(n for n in range(1, 1000) if _accepts(d, n))
        OddDetector.calibrate(np.linspace(0.0, 1.0, need), alpha)  # does not raise
        with pytest.raises(ValueError, match="too few"):
            OddDetector.calibrate(np.linspace(0.0, 1.0, need - 1), alpha)


def _accepts(d: dict, calibration_targets: int) -> bool:
    d["task3"]["calibration_targets"] = calibration_targets
    try:
        parse_params(d)
    except ConfigError:
        return False
    return True


def test_the_backbone_names_are_the_registry_s():
    """The config's list of backbone names is components.features.backbones' registry, in its order."""
    import typing

    from components.core.config import BackboneName
    from components.features.backbones import available

    assert list(typing.get_args(BackboneName)) == available()


def test_a_key_written_twice_is_named(tmp_path: Path):
    """PyYAML keeps the last of two equal keys silently; the config refuses the file, in params.yaml and profiles."""
    text = (PROJECT_ROOT / "params.yaml").read_text()
    assert "\n  epochs: 60\n" in text
    path = tmp_path / "params.yaml"
    path.write_text(text.replace("\n  epochs: 60\n", "\n  epochs: 60\n  epochs: 3\n"))
    line = text[: text.index("\n  epochs: 60\n")].count("\n") + 2
    with pytest.raises(
        ConfigError, match=rf"params\.yaml: line {line + 1}: epochs appears twice .*first at line {line}"
    ):
        load_params(path)
    shutil.copy(PROJECT_ROOT / "params.yaml", path)
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "twice.yaml").write_text("train:\n  epochs: 5\ntrain:\n  batch_size: 64\n")
    with pytest.raises(ConfigError, match=r"twice\.yaml: line 3: train appears twice .*first at line 1"):
        load_params(path, profile="twice")


def test_unreadable_and_invalid_files(tmp_path: Path):
    with pytest.raises(ConfigError, match="cannot read params file"):
        load_params(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("data: [unclosed")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_params(bad)
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00seed: 1")
    with pytest.raises(ConfigError, match=r"binary\.yaml: cannot read params file: not UTF-8 text \(byte 0xff at 0\)"):
        load_params(binary)


def test_seed_streams_are_deterministic_and_independent():
    a = seeding.rng(7, "data", "train").random(5)
    np.testing.assert_array_equal(a, seeding.rng(7, "data", "train").random(5))
    assert not np.allclose(a, seeding.rng(7, "data", "val").random(5))
    assert not np.allclose(a, seeding.rng(8, "data", "train").random(5))
    assert seeding.derive_seed(7, "scene", 3) == seeding.derive_seed(7, "scene", 3) >= 0
    with pytest.raises(ValueError, match="non-negative"):
        seeding.rng(7, -1)


# --- pidc config check -------------------------------------------------------------------------------------------


def _check(*args: str, cwd: Path = PROJECT_ROOT) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "components.cli.main", "config", "check", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.parametrize("profile", [None, "paper"])
def test_config_check_prints_the_resolved_config(profile):
    r = _check("--params", str(PROJECT_ROOT / "params.yaml"), *(["--profile", profile] if profile else []))
    assert r.returncode == 0, r.stderr
    first = r.stdout.splitlines()[0]
    assert first.startswith("#") and "params.yaml" in first and f"profile {profile or 'default'}" in first
    printed = yaml.safe_load(r.stdout)
    assert parse_params(printed) == load_params(PROJECT_ROOT / "params.yaml", profile=profile)


def test_config_check_imports_no_torch():
    code = (
        "import sys; from components.cli.main import main; rc = main(['config', 'check']); "
        "assert rc == 0 and 'torch' not in sys.modules, sorted(m for m in sys.modules if 'torch' in m)"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("key", ["seed", "data.shard_size", "train.flow.bins", "task3.bags", "evaluate.samples"])
def test_config_check_names_a_missing_key_on_one_line(key, tmp_path: Path):
    d = _default()
    _remove(d, key)
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    r = _check("--params", str(path))
    assert r.returncode == 2 and r.stdout == ""
    err = r.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("pidc config: error: ") and f"{path}: invalid params; {key}: missing key" in err, err


def test_config_check_names_an_unknown_profile_and_a_missing_file(tmp_path: Path):
    r = _check("--profile", "huge")
    assert (
        r.returncode == 2
        and "params.yaml: profile: unknown profile 'huge'; profiles found: default, camera, gpu, paper" in r.stderr
    )
    r = _check("--params", str(tmp_path / "none.yaml"))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "cannot read params file" in r.stderr


# --- the pipeline's flow and training settings -------------------------------------------------------------------


def _recorded(monkeypatch, module, name: str) -> dict:
    """Replace ``module.name`` (a dataclass) by a recorder of the keywords it is called with."""
    cls, calls = getattr(module, name), {}

    class Recorder(cls):
        def __init__(self, *args, **kwargs):
            assert not args, f"{name} must be built from keywords only"
            calls.update(kwargs)
            super().__init__(**kwargs)

    monkeypatch.setattr(module, name, Recorder)
    return calls


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("trainable", [False, True])
def test_settings_set_every_field_of_the_library_classes(profile, trainable, monkeypatch):
    from components.posterior import settings
    from components.posterior.model import FlowConfig
    from components.posterior.train import TrainingConfig

    t = load_params(PROJECT_ROOT / "params.yaml", profile=profile).train
    flow_kw = _recorded(monkeypatch, settings, "FlowConfig")
    train_kw = _recorded(monkeypatch, settings, "TrainingConfig")
    flow = settings.flow_config(t, size=max(t.sizes), trainable=trainable)
    cfg = settings.training_config(t, size=t.sizes[0], trainable=trainable, features=273, parameters=6, seed=11)
    assert set(flow_kw) == {f.name for f in dataclasses.fields(FlowConfig)}
    assert set(train_kw) == {f.name for f in dataclasses.fields(TrainingConfig)}
    assert dataclasses.asdict(flow) == {
        **t.flow.model_dump(),
        "hidden_features": tuple(t.flow.hidden_features),
        # a backbone trained with the flow is its own context network
        "context_layers": () if trainable else tuple(t.flow.context_layers),
        # the base scale per regime is part of the flow's architecture
        "regime_temperature": t.temperature and t.temperature_regime is not None,
    }
    same = {f.name for f in dataclasses.fields(TrainingConfig)} - {
        "epochs",
        "seed",
        "patience",
        "input_noise",
        "compile",
        "spared",  # the backbone's (none given here)
        "spared_noise",  # train.input_noise_spared
    }
    assert {k: getattr(cfg, k) for k in same} == {k: getattr(t, k) for k in same}
    assert cfg.spared == () and cfg.spared_noise == t.input_noise_spared
    assert cfg.patience == settings.patience_for(t, t.sizes[0])
    assert cfg.input_noise == settings.input_noise_for(t, t.sizes[0], trainable=trainable, features=273)
    assert cfg.epochs == settings.epochs_for(t, t.sizes[0], trainable=trainable) and cfg.seed == 11
    assert cfg.compile == settings.compile_for(t, t.sizes[0], trainable=trainable)


@pytest.mark.parametrize("trainable", [False, True])
def test_epochs_follow_the_sample_budget(trainable):
    """A model of n images trains min(cap·s, ⌈budget / n⌉) epochs (s = scale_to / n ≥ 1 for frozen features, 1 for a
    jointly trained backbone): never (much) more samples than the budget, fewer epochs for more images, at least one."""
    from components.posterior.settings import epochs_for, small_data_scale, training_config

    t = load_params(PROJECT_ROOT / "params.yaml").train
    cap, budget = (t.embedding_epochs, t.embedding_sample_budget) if trainable else (t.epochs, t.sample_budget)
    sizes = [1, 7, 1000, 5000, 20000, 50000, budget, 10 * budget]
    epochs = [epochs_for(t, n, trainable=trainable) for n in sizes]
    scale = [1.0 if trainable else small_data_scale(t, n) for n in sizes]
    assert all(1 <= e <= math.ceil(cap * s) for e, s in zip(epochs, scale, strict=True))
    assert all((e - 1) * n < budget for e, n in zip(epochs, sizes, strict=True))  # the last epoch may overrun
    assert epochs == sorted(epochs, reverse=True) and epochs[-1] == 1
    assert training_config(t, size=5000, trainable=trainable, features=273, parameters=6, seed=1).epochs == epochs[3]
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="size must be a positive integer"):
            epochs_for(t, bad, trainable=trainable)


def test_small_training_sets_train_longer_through_a_smaller_flow():
    """Below scale_to images: s× epochs and patience, hidden widths / √s (multiples of 16, ≥ 32, never wider);
    at and above scale_to: train's settings as written."""
    from components.posterior.settings import epochs_for, flow_config, hidden_for, patience_for

    t = load_params(PROJECT_ROOT / "params.yaml").train
    big = t.scale_to
    assert hidden_for(t, big) == hidden_for(t, 10 * big) == tuple(t.flow.hidden_features)
    assert patience_for(t, big) == t.patience and epochs_for(t, big, trainable=False) <= t.epochs
    widths = [hidden_for(t, n) for n in (big // 2, big // 4, big // 100, 1)]
    for w in widths:
        assert all(32 <= h <= h0 and h % 16 == 0 for h, h0 in zip(w, t.flow.hidden_features, strict=True))
    assert [sum(w) for w in widths] == sorted((sum(w) for w in widths), reverse=True)
    ten = t.model_copy(update={"patience": 10})
    assert patience_for(ten, big) == 10 and patience_for(ten, big // 4) == 40  # × s below scale_to
    assert patience_for(t.model_copy(update={"patience": None}), big // 4) is None  # null: no early stopping
    assert epochs_for(t, big // 4, trainable=False) == min(4 * t.epochs, math.ceil(t.sample_budget / (big // 4)))
    assert flow_config(t, size=big // 4, trainable=False).hidden_features == hidden_for(t, big // 4)
    # input noise: σ ∝ 1/√n up to input_noise_max_size images, only on frozen features
    from components.posterior.settings import input_noise_for

    d = t.input_noise_min_features
    assert t.input_noise > 0 and input_noise_for(t, big, trainable=False, features=d) == t.input_noise
    assert input_noise_for(t, big // 4, trainable=False, features=d) == pytest.approx(2 * t.input_noise)  # σ ∝ 1/√n
    assert input_noise_for(t, t.input_noise_max_size + 1, trainable=False, features=d) == 0.0
    assert input_noise_for(t, big // 2, trainable=True, features=d) == 0.0


def test_input_noise_only_on_many_features():
    """No input noise below train.input_noise_min_features features (a few informative inputs, the SBI problems'),
    the rule's σ from there on; the pipeline's frozen backbones (cues 273, tiny 256) are all above the floor."""
    from components.features.backbones import get_backbone
    from components.posterior.settings import input_noise_for, training_config

    t = load_params(PROJECT_ROOT / "params.yaml").train
    d = t.input_noise_min_features
    assert 10 < d <= min(get_backbone(name).dim for name in ("cues", "tiny"))
    noise = [input_noise_for(t, 1000, trainable=False, features=f) for f in (1, 2, 10, d - 1, d, 10 * d)]
    assert noise[:4] == [0.0] * 4 and noise[4] == noise[5] == pytest.approx(
        t.input_noise * math.sqrt(t.scale_to / 1000)
    )
    assert training_config(t, size=1000, trainable=False, features=2, parameters=6, seed=0).input_noise == 0.0
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="features must be a positive integer"):
            input_noise_for(t, 1000, trainable=False, features=bad)


def test_ensembles_from_their_minimum_size():
    """ensemble_for: train.flow.ensemble flows from train.ensemble_min_size images, one below; a variant's count wins."""
    from components.posterior.settings import ensemble_for, flow_config

    t = load_params(PROJECT_ROOT / "params.yaml").train
    t3 = t.model_copy(update={"flow": t.flow.model_copy(update={"ensemble": 3}), "ensemble_min_size": 20000})
    assert [ensemble_for(t3, n) for n in (1, 19999, 20000, 50000)] == [1, 1, 3, 3]
    assert flow_config(t3, size=5000, trainable=False).ensemble == 1
    assert flow_config(t3, size=20000, trainable=True).ensemble == 3
    assert flow_config(t3, size=5000, trainable=False, ensemble=4).ensemble == 4
    # an ensemble of K flows trains with one flow's input noise, whatever its count
    from components.posterior.settings import input_noise_for, training_config

    one = t3.input_noise * math.sqrt(t3.scale_to / 20000)
    assert input_noise_for(t3, 20000, trainable=False, features=273) == pytest.approx(one)
    two = training_config(t3, size=20000, trainable=False, features=273, parameters=6, seed=0, ensemble=2)
    assert two.input_noise == pytest.approx(one)
    assert all(ensemble_for(t, n) == (t.flow.ensemble if n >= t.ensemble_min_size else 1) for n in t.sizes)
    with pytest.raises(ValueError, match="size must be a positive integer"):
        ensemble_for(t, 0)


def test_models_of_many_steps_compile_their_training_loss():
    """compile_for: at least train.compile_min_steps optimizer steps (epochs × ⌈size / batch⌉); null: never."""
    from components.posterior.settings import compile_for, epochs_for, training_config

    t = load_params(PROJECT_ROOT / "params.yaml").train
    for size in (*t.sizes, 1, 10**6):
        for trainable in (False, True):
            steps = epochs_for(t, size, trainable=trainable) * math.ceil(size / t.batch_size)
            assert compile_for(t, size, trainable=trainable) == (steps >= t.compile_min_steps)
            assert training_config(t, size=size, trainable=trainable, features=273, parameters=6, seed=0).compile == (
                steps >= t.compile_min_steps
            )
    assert compile_for(t, max(t.sizes), trainable=False)  # the default grid's largest frozen-feature models compile
    assert not compile_for(t.model_copy(update={"compile_min_steps": None}), max(t.sizes), trainable=False)
    assert compile_for(t.model_copy(update={"compile_min_steps": 0}), 1, trainable=True)


def test_settings_refuse_to_leave_a_field_to_its_default():
    from components.posterior.settings import _every_field
    from components.posterior.train import TrainingConfig

    with pytest.raises(TypeError, match=r"missing \['min_lr'\]"):
        _every_field(TrainingConfig, {f.name: 0 for f in dataclasses.fields(TrainingConfig) if f.name != "min_lr"})


def test_model_ids_and_their_cells_agree():
    """Every model id of the grid and its variants maps back to its backbone, size and variant; others are named."""
    raw = yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())
    raw["train"]["variants"] = {"pair": {"backbone": "cues", "size": 5000, "balance": 0.0, "ensemble": 2}}
    params = parse_params(raw)
    ids = params.model_ids()
    assert len(ids) == len(params.backbones.names) * len(params.train.sizes) + 1 and ids[-1] == "cues-5000-pair"
    for m in ids:
        backbone, size, variant = params.model_cell(m)
        assert m == f"{backbone}-{size}" + (f"-{variant}" if variant else "")
    with pytest.raises(ValueError, match=r"no model 'cues-7' in the grid or train.variants \(known: cues-5000, "):
        params.model_cell("cues-7")
