"""The evaluate stage resumes per model: each model's finished evaluation is kept under ``.cache/task1/<model>/<key>/``
and reused by a later run whose key matches, so a killed evaluate redoes only the models it had not finished, and
``reports/task1/`` is the same to the byte whether a model was evaluated or reused. Real Prefect, a real MLflow store
(SQLite) and a micro project trained and exported for the module."""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from components.core.config import PROJECT_ROOT
from tests.conftest import TINY_FLOW, write_params

MODELS = ("cues-8", "cues-16")
SETTINGS = {
    "train.epochs": 2,
    "train.embedding_epochs": 1,
    "train.sizes": [8, 16],
    "train.variants": {},
    "train.flow": TINY_FLOW,
    "train.temperature_regime": None,
    "backbones": {"names": ["cues"], "pretrained_dir": None, "batch_size": 256, "device": "cpu"},
    # one model at a time: the kill below lands after the first model is kept, while the second is evaluated
    "evaluate.runner": {"kind": "threads", "workers": 1, "dask_address": None},
    "evaluate.example_images": 0,  # a model's plots: its PPC sheet and its profile (the corner plots take seconds)
}


def _use(monkeypatch, folder: Path) -> None:
    """Run the stages of the project in ``folder``: its own MLflow store, its artifacts beside it."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{folder / 'mlflow.db'}")
    monkeypatch.chdir(folder)


@pytest.fixture(scope="module")
def built(tmp_path_factory, prefect_harness) -> Path:
    """A micro project with data, cues features and two trained and exported models (no evaluation yet)."""
    from flows.export import export_model
    from flows.features import extract_features
    from flows.generate import generate
    from flows.train import train_model

    folder = tmp_path_factory.mktemp("evaluate-resume") / "built"
    params = write_params(folder, **SETTINGS)
    with pytest.MonkeyPatch.context() as mp:
        _use(mp, folder)
        generate(str(params))
        extract_features("cues", str(params))
        for m in MODELS:
            train_model("cues", int(m.split("-")[1]), str(params))
            export_model(m, str(params))
    return folder


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, symlinks=True)
    return dst


def _reports(folder: Path) -> dict[str, bytes]:
    out = folder / "reports" / "task1"
    return {str(f.relative_to(out)): f.read_bytes() for f in sorted(out.rglob("*")) if f.is_file()}


def _kept(folder: Path) -> dict[str, Path]:
    """Model → its kept evaluation's folder (one key per model; hidden names are unfinished writes)."""
    root = folder / ".cache" / "task1"
    found = {}
    for model in sorted(root.iterdir()) if root.is_dir() else []:
        keys = [k for k in model.iterdir() if not k.name.startswith(".")]
        assert len(keys) <= 1, f"{model.name}: one kept evaluation per model, found {[k.name for k in keys]}"
        if keys:
            found[model.name] = keys[0]
    return found


def _stamp(entry: Path) -> tuple[int, int]:
    """What changes when a kept evaluation is written again: its folder (a new one replaces it) and entry.json."""
    return entry.stat().st_ino, (entry / "entry.json").stat().st_mtime_ns


@pytest.fixture(scope="module")
def baseline(built, tmp_path_factory) -> tuple[Path, dict[str, bytes]]:
    """A copy of the built project evaluated once, uninterrupted: the folder and its reports/task1/ files."""
    from flows.evaluate import evaluate

    folder = _copy(built, tmp_path_factory.mktemp("evaluate-resume") / "baseline")
    with pytest.MonkeyPatch.context() as mp:
        _use(mp, folder)
        evaluate(str(folder / "params.yaml"))
    return folder, _reports(folder)


def _start_evaluate(folder: Path, **kw) -> subprocess.Popen:
    """``python -m flows.evaluate`` on the project in ``folder``, in a process group of its own, reporting to the
    tests' Prefect server."""
    from prefect.settings import PREFECT_API_URL

    env = {
        **os.environ,
        "PYTHONPATH": str(PROJECT_ROOT),
        "PREFECT_API_URL": str(PREFECT_API_URL.value()),
        "MLFLOW_TRACKING_URI": f"sqlite:///{folder / 'mlflow.db'}",
        "COLUMNS": "1000",  # Prefect's console log lines unwrapped
    }
    cmd = [sys.executable, "-m", "flows.evaluate", "--params", str(folder / "params.yaml")]
    return subprocess.Popen(cmd, cwd=folder, env=env, start_new_session=True, text=True, **kw)


def test_a_second_run_reuses_every_model_and_gives_the_same_reports(baseline, tmp_path, monkeypatch, caplog):
    from flows.evaluate import evaluate

    first, reports = baseline
    kept = _kept(first)
    assert set(kept) == set(MODELS)
    for m, entry in kept.items():
        e = json.loads((entry / "entry.json").read_text())
        assert e["key"] == entry.name and e["parts"]["model"] == m and e["parts"]["card_sha256"]
        assert set(e["files"]) == {f.name for f in (first / "reports/task1/plots" / m).iterdir()}
        assert e["result"]["metrics"] == json.loads((first / "reports/task1/metrics.json").read_text())[m]

    folder = _copy(first, tmp_path / "again")
    _use(monkeypatch, folder)
    caplog.set_level(logging.INFO, logger="prefect")
    stamps = {m: _stamp(e) for m, e in _kept(folder).items()}
    shutil.rmtree(folder / "reports")  # what DVC does to the stage's outputs when it starts
    evaluate(str(folder / "params.yaml"))
    assert {m: _stamp(e) for m, e in _kept(folder).items()} == stamps, "nothing evaluated again"
    for m, entry in _kept(folder).items():
        assert f"{m}: kept evaluation reused (key {entry.name[:12]}…)" in caplog.text
    assert "evaluation kept" not in caplog.text
    assert _reports(folder) == reports


def test_a_killed_run_resumes_from_the_models_it_finished(built, baseline, tmp_path, monkeypatch, caplog):
    from flows.evaluate import evaluate

    folder = _copy(built, tmp_path / "killed")
    log = open(tmp_path / "killed.log", "w")
    proc = _start_evaluate(folder, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 300
        while not _kept(folder):  # a model's kept evaluation, committed (not its temporary folder)
            assert proc.poll() is None, (tmp_path / "killed.log").read_text()
            assert time.monotonic() < deadline, "no model kept in 300 s"
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
        log.close()
    finished = _kept(folder)
    assert len(finished) == 1, f"killed after the first model: {sorted(finished)}"
    (done,) = finished
    assert not (folder / "reports/task1/metrics.json").exists()
    stamp = _stamp(finished[done])

    _use(monkeypatch, folder)
    caplog.set_level(logging.INFO, logger="prefect")
    evaluate(str(folder / "params.yaml"))  # the re-run
    out = caplog.text
    assert f"{done}: kept evaluation reused (key {finished[done].name[:12]}…)" in out, out
    (other,) = set(MODELS) - {done}
    assert f"{other}: no kept evaluation for key" in out and f"{other}: evaluation kept (key" in out, out
    assert f"{done}: evaluation kept" not in out
    assert _stamp(_kept(folder)[done]) == stamp and set(_kept(folder)) == set(MODELS)
    assert not list((folder / ".cache/task1").glob("*/.*")), "what the kill left is removed"
    assert _reports(folder) == baseline[1], "the same reports as an uninterrupted run"


def test_a_changed_card_or_setting_is_evaluated_again(baseline, tmp_path, monkeypatch):
    from flows.evaluate import evaluate

    folder = _copy(baseline[0], tmp_path / "changed")
    _use(monkeypatch, folder)
    before = _kept(folder)
    stamps = {m: _stamp(e) for m, e in before.items()}

    # a model trained and exported again (another card, which records its graphs): that model only is evaluated
    # again, under a new key
    from flows.export import export_model
    from flows.train import train_model

    p = yaml.safe_load((folder / "params.yaml").read_text())
    p["train"]["epochs"] = 3  # no setting of the evaluation
    (folder / "params.yaml").write_text(yaml.safe_dump(p, sort_keys=False))
    card = folder / "registry" / MODELS[0] / "card.json"
    old_card = card.read_bytes()
    train_model("cues", int(MODELS[0].split("-")[1]), str(folder / "params.yaml"))
    export_model(MODELS[0], str(folder / "params.yaml"))
    assert card.read_bytes() != old_card
    metrics = evaluate(str(folder / "params.yaml"))
    after = _kept(folder)
    assert after[MODELS[0]].name != before[MODELS[0]].name and not before[MODELS[0]].exists()
    assert after[MODELS[1]] == before[MODELS[1]] and _stamp(after[MODELS[1]]) == stamps[MODELS[1]]
    assert metrics[MODELS[1]] == json.loads(baseline[1]["metrics.json"])[MODELS[1]]
    assert metrics[MODELS[0]] != json.loads(baseline[1]["metrics.json"])[MODELS[0]], "the new model's figures"

    # a setting of the evaluation changes: every model is evaluated again; the old keys are gone
    p["evaluate"]["samples"] = 401
    (folder / "params.yaml").write_text(yaml.safe_dump(p, sort_keys=False))
    metrics = evaluate(str(folder / "params.yaml"))
    again = _kept(folder)
    for m in MODELS:
        assert again[m].name != after[m].name and not after[m].exists(), m
        assert metrics[m]["samples"] == 401
        assert json.loads((again[m] / "entry.json").read_text())["parts"]["evaluate"]["samples"] == 401

    # the runner is no part of the key: another runner reuses every model
    stamps = {m: _stamp(e) for m, e in again.items()}
    p["evaluate"]["runner"] = {"kind": "threads", "workers": 2, "dask_address": None}
    (folder / "params.yaml").write_text(yaml.safe_dump(p, sort_keys=False))
    evaluate(str(folder / "params.yaml"))
    assert {m: _stamp(e) for m, e in _kept(folder).items()} == stamps

    # a model no longer in the grid: its kept evaluation is removed at the end of the run
    p["train"]["sizes"] = [16]
    (folder / "params.yaml").write_text(yaml.safe_dump(p, sort_keys=False))
    evaluate(str(folder / "params.yaml"))
    assert set(_kept(folder)) == {"cues-16"} and _stamp(_kept(folder)["cues-16"]) == stamps["cues-16"]


@pytest.mark.parametrize("damage", ["truncated entry", "changed plot"])
def test_a_damaged_kept_evaluation_is_evaluated_again(baseline, tmp_path, monkeypatch, caplog, damage):
    from flows.evaluate import evaluate

    folder = _copy(baseline[0], tmp_path / "damaged")
    _use(monkeypatch, folder)
    kept = _kept(folder)
    stamps = {m: _stamp(e) for m, e in kept.items()}
    bad = kept[MODELS[1]]
    if damage == "truncated entry":
        data = (bad / "entry.json").read_bytes()
        (bad / "entry.json").write_bytes(data[: len(data) // 2])
    else:
        plot = bad / "files" / "profile.png"
        plot.write_bytes(plot.read_bytes()[:-10])
    stamps[MODELS[1]] = _stamp(bad)
    shutil.rmtree(folder / "reports")
    caplog.set_level(logging.INFO, logger="prefect")
    evaluate(str(folder / "params.yaml"))
    reason = "entry.json does not parse" if damage == "truncated entry" else "file 'profile.png' is missing or differs"
    assert f"{MODELS[1]}: kept evaluation ignored, evaluating again: {bad}: {reason}" in caplog.text, caplog.text
    now = _kept(folder)
    assert now[MODELS[1]].name == bad.name and _stamp(now[MODELS[1]]) != stamps[MODELS[1]], "evaluated again"
    assert _stamp(now[MODELS[0]]) == stamps[MODELS[0]], "the sound one reused"
    json.loads((now[MODELS[1]] / "entry.json").read_text())
    assert _reports(folder) == baseline[1]


def test_the_named_weathers_are_rendered_once_and_read_by_every_model(baseline, tmp_path):
    """The stage renders the named weathers once (``.cache/named/<key>.npz``) and every model reads those images: the
    file holds what the renderer gives, a second call reads it without rendering, and another setting (more scenes)
    renders under another key."""
    from components.core.config import load_params
    from components.core.paths import ProjectPaths
    from components.evaluate import evaluation, named
    from components.simulate.base import new_scene_simulator

    folder = _copy(baseline[0], tmp_path / "named")
    (cached,) = (folder / ".cache" / "named").glob("*.npz")
    stamp = cached.stat().st_mtime_ns
    params = load_params(folder / "params.yaml")
    paths = ProjectPaths.of(params, folder / "params.yaml")
    sets, note = evaluation.named_renders(params, paths)
    assert note is None and cached.stat().st_mtime_ns == stamp, "read, not rendered again"
    nc = params.evaluate.named
    fresh = named.render_sets(
        new_scene_simulator(params.simulator).render,
        named.named_weathers(nc.presets, nc.weathers),
        params.seed,
        nc.scenes,
    )
    assert [s.name for s in sets] == [s.name for s in fresh] == list(nc.weathers)
    for mine, theirs in zip(sets, fresh, strict=True):
        assert mine.kind == theirs.kind and np.array_equal(mine.truth, theirs.truth)
        assert np.array_equal(mine.images, theirs.images)
    more = params.model_copy(
        update={"evaluate": params.evaluate.model_copy(update={"named": nc.model_copy(update={"scenes": 3})})}
    )
    assert [len(s.images) for s in evaluation.named_renders(more, paths)[0]] == [3] * len(nc.weathers)
    assert len(list((folder / ".cache" / "named").glob("*.npz"))) == 2
