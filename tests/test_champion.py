"""The champion rule on hand-made Task I metrics, its params, and the MLflow aliases in a temporary SQLite store."""

from __future__ import annotations

import copy
import math

import mlflow
import pytest
import yaml

from components.core.config import PROJECT_ROOT, ConfigError, parse_params
from components.core.files import sha256_file
from components.evaluate.champion import NoChampionError, champion_pointer, choose_champion


def _m(error: float, band: float, nll: float, gain: float = 3.0) -> dict:
    return {
        "calibration_error": error,
        "calibration_band": band,
        "within_band": error <= band,
        "test_nll": nll,
        "info_gain_nats": gain,
        "pi_median": 0.5,
    }


def test_lowest_nll_within_the_band_wins_and_a_sharper_miscalibrated_model_loses():
    metrics = {
        "sharp-but-overconfident": _m(0.20, 0.03, 21.0),  # the lowest NLL, far outside its band
        "calibrated": _m(0.025, 0.03, 23.5),
        "calibrated-sharper": _m(0.029, 0.03, 22.9),
        "calibrated-vague": _m(0.01, 0.03, 26.0),
    }
    champion, runner_up = choose_champion(metrics, 0.10)
    assert (champion.model, champion.rule) == ("calibrated-sharper", "within_band")
    assert (runner_up.model, runner_up.rule) == ("calibrated", "within_band")
    assert "22.900" in champion.reason and "sharp-but-overconfident" not in champion.reason
    pointer = champion_pointer(metrics, champion, runner_up)
    assert pointer["model"] == "calibrated-sharper" and pointer["rule"] == "within_band"
    assert pointer["metrics"] == {
        "calibration_error": 0.029,
        "calibration_band": 0.03,
        "within_band": True,
        "test_nll": 22.9,
        "info_gain_nats": 3.0,
    }
    assert pointer["runner_up"]["model"] == "calibrated" and pointer["runner_up"]["metrics"]["test_nll"] == 23.5


def test_without_a_model_in_its_band_the_ceiling_branch_is_taken_and_recorded():
    metrics = {"a": _m(0.12, 0.03, 20.0), "b": _m(0.08, 0.03, 24.0), "c": _m(0.05, 0.03, 25.0)}
    champion, runner_up = choose_champion(metrics, 0.10)
    assert (champion.model, champion.rule) == ("b", "ceiling")
    assert "no model's calibration error lies within its band" in champion.reason and "0.1" in champion.reason
    assert (runner_up.model, runner_up.rule) == ("c", "ceiling")
    # the runner-up follows the same rule once the champion is set aside: here the only one in the band wins,
    # and the runner-up comes from the ceiling branch
    metrics["d"] = _m(0.02, 0.03, 30.0)
    champion, runner_up = choose_champion(metrics, 0.10)
    assert (champion.model, champion.rule, runner_up.model, runner_up.rule) == ("d", "within_band", "b", "ceiling")
    assert champion_pointer(metrics, *choose_champion({"d": metrics["d"]}, 0.1))["runner_up"] is None


def test_no_eligible_model_is_a_clear_error():
    metrics = {"a": _m(0.30, 0.03, 20.0), "b": _m(0.15, 0.03, 24.0)}
    with pytest.raises(
        NoChampionError, match=r"no champion: .*≤ export.champion_max_calibration_error = 0.1 .*a: 0.300"
    ):
        choose_champion(metrics, 0.10)
    with pytest.raises(NoChampionError, match="no model was evaluated"):
        choose_champion({}, 0.10)
    with pytest.raises(KeyError, match="'a' has no Task I metric 'test_nll'"):
        choose_champion({"a": {"calibration_error": 0.0, "within_band": True}}, 0.10)


def test_ties_are_broken_by_model_id_and_non_finite_scores_never_win():
    metrics = {"z": _m(0.01, 0.03, 22.0), "y": _m(0.01, 0.03, 22.0), "x": _m(0.01, 0.03, math.nan)}
    champion, runner_up = choose_champion(metrics, 0.10)
    assert (champion.model, runner_up.model) == ("y", "z")


def _params() -> dict:
    return yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())


def test_the_rule_and_the_evaluation_size_are_validated_params():
    p = _params()
    assert parse_params(p).export.champion_max_calibration_error == pytest.approx(0.10)
    old = copy.deepcopy(p)
    old["export"]["champion_metric"] = "calibration_error"
    with pytest.raises(ConfigError, match=r"export\.champion_metric: unknown key"):
        parse_params(old, source="params.yaml")
    missing = copy.deepcopy(p)
    del missing["export"]["champion_max_calibration_error"]
    with pytest.raises(
        ConfigError, match=r"params\.yaml: invalid params\n  export\.champion_max_calibration_error: missing"
    ):
        parse_params(missing, source="params.yaml")
    bad = copy.deepcopy(p)
    bad["export"]["champion_max_calibration_error"] = 0
    with pytest.raises(ConfigError, match=r"export\.champion_max_calibration_error: Input should be greater than 0"):
        parse_params(bad)
    for value, ok in (("all", True), (2000, True), (1, True), ("most", False), (0, False), (True, False)):
        q = copy.deepcopy(p)
        q["evaluate"]["images"] = value
        if ok:
            assert parse_params(q).evaluate.images == value
        else:
            with pytest.raises(ConfigError, match=r"evaluate\.images: .*positive integer or 'all'"):
                parse_params(q)
    q = copy.deepcopy(p)
    q["evaluate"]["images"] = 2001
    with pytest.raises(ConfigError, match=r"evaluate.images is 2001 but the test split has only 2000"):
        parse_params(q)
    for key in ("band_level", "band_replicates", "runner"):
        q = copy.deepcopy(p)
        del q["evaluate"][key]
        with pytest.raises(ConfigError, match=rf"evaluate\.{key}: missing key"):
            parse_params(q)


def test_aliases_champion_and_challenger_move_between_versions_of_one_registered_model(tmp_path, monkeypatch):
    from flows import tracking

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    params = parse_params(_params())
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    experiment = client.create_experiment("pidc-grid", artifact_location=str(tmp_path / "artifacts"))
    metrics = {m: _m(0.02, 0.03, nll) for m, nll in (("a", 20.0), ("b", 21.0), ("c", 22.0))}
    metrics["unregistered"] = _m(0.02, 0.03, 19.0)
    name = tracking.registered_model(params)
    assert name == "pidc" and tracking.champion_uri(params) == "models:/pidc@champion"
    client.create_registered_model(name)
    runs = {}

    def export(m: str, card: str) -> str:
        """registry/<m> with this card, registered as a new version of ``name`` (tagged as register_model tags)."""
        folder = tmp_path / "registry" / m
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "card.json").write_text(card)
        runs[m] = client.create_run(experiment, tags={"pidc.model": m}).info.run_id
        tags = {"pidc.model": m, "card_sha256": sha256_file(folder / "card.json")}
        return client.create_model_version(name, source=str(folder), run_id=runs[m], tags=tags).version

    for m, card in (("a", "a1"), ("b", "b"), ("c", "c"), ("a", "a2")):  # a exported twice: registry/a holds the 2nd
        export(m, card)
    assert tracking.registered_versions(tmp_path, params) == {"a": "4", "b": "2", "c": "3"}

    found = tracking.set_champion_alias(tmp_path, params, metrics, "a", "b")
    assert found == {
        "champion": {"version": "4", "uri": "models:/pidc@champion"},
        "challenger": {"version": "2", "uri": "models:/pidc@challenger"},
    }
    version = client.get_model_version_by_alias(name, "challenger")
    assert float(version.tags["task1.test_nll"]) == 21.0 and version.tags["task1.within_band"] == "1"
    roles = {m: client.get_run(r).data.tags["pidc.role"] for m, r in runs.items()}
    assert roles == {"a": "champion", "b": "challenger", "c": "candidate"}
    found = tracking.set_champion_alias(tmp_path, params, metrics, "c", "unregistered")  # the next evaluation
    assert set(found) == {"champion"} and found["champion"]["version"] == "3"
    assert client.get_registered_model(name).aliases == {"champion": 3}, "the challenger alias left with no holder"

    # the version of the export in registry/, not the newest: a was registered again by other code (a 5th version)
    # while registry/a went back to the first export's files (e.g. DVC restored them from its cache)
    export("a", "a3")
    (tmp_path / "registry" / "a" / "card.json").write_text("a1")
    found = tracking.set_champion_alias(tmp_path, params, metrics, "a", "c")
    assert found["champion"]["version"] == "1" and found["challenger"]["version"] == "3"
    # an export in registry/ that no version registered: an error naming it, and the aliases stay where they were
    (tmp_path / "registry" / "b" / "card.json").write_text("b, exported again but not registered")
    with pytest.raises(LookupError, match=r"registry/b: the export there is not registered as a version of 'pidc'"):
        tracking.set_champion_alias(tmp_path, params, metrics, "b", "a")
    assert client.get_registered_model(name).aliases == {"champion": 1, "challenger": 3}
    (tmp_path / "registry" / "b" / "card.json").write_text("b")
    (tmp_path / "registry" / "a" / "card.json").write_text("a2")

    result = {
        "model": "a",
        "metrics": metrics["a"],
        "parameters": {"day": {"fog_density": {"median_abs_error": 4.5, "coverage95": 0.93}}},
    }
    (tmp_path / "plots" / "a").mkdir(parents=True)
    tracking.log_task1(tmp_path, "pidc-grid", [result], tmp_path / "plots")
    run = client.search_runs([experiment], "tags.`pidc.model` = 'a'")[0]
    assert run.data.metrics["task1.fog_density.day.median_abs_error"] == 4.5
    assert run.data.metrics["task1.within_band"] == 1.0 and run.data.metrics["task1.test_nll"] == 20.0
