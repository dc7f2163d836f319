"""The generate stage end to end: the real Prefect flow, resume after damage, and `dvc repro` in a temp git repo."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from components import dataset
from components.config import PROJECT_ROOT, load_params
from tests.conftest import write_params


def test_flow_generates_and_resumes_after_damage(tmp_path, prefect_harness):
    from flows.generate import generate

    params = write_params(tmp_path)
    first = generate(str(params))
    assert {k: v["count"] for k, v in first["splits"].items()} == {"train": 24, "val": 8, "test": 8}
    assert (tmp_path / "reports/data/contact_sheet.png").stat().st_size > 1000
    train = dataset.open_split(tmp_path / "data", "train", verify=True)
    assert train.images().shape == (24, 32, 32, 3)
    snapshot = {p: p.read_bytes() for p in (tmp_path / "data").rglob("shard-*.npz")}

    # a killed run: one shard deleted, one truncated, a temp file left behind
    shards = sorted((tmp_path / "data/train").glob("shard-*.npz"))
    shards[0].unlink()
    shards[1].write_bytes(shards[1].read_bytes()[:1000])
    (tmp_path / "data/train/.shard-00002.npz.tmp-1234").write_bytes(b"partial")
    untouched = tmp_path / "data/val/shard-00000.npz"
    mtime = untouched.stat().st_mtime_ns

    second = generate(str(params))
    assert second["content_hash"] == first["content_hash"]
    for p, data in snapshot.items():
        assert p.read_bytes() == data, p
    assert untouched.stat().st_mtime_ns == mtime, "a finished shard was rendered again"
    assert not list((tmp_path / "data/train").glob(".shard-*")), "temporary files must be cleaned up"


@pytest.mark.parametrize("kind", ["processes", "dask"])
def test_every_task_runner_gives_the_same_data(tmp_path, prefect_harness, kind):
    from flows.generate import generate
    from flows.runtime import task_runner

    reference = generate(str(write_params(tmp_path / "threads")))  # threads (micro params' default)
    params = write_params(tmp_path / kind, **{"data.runner": {"kind": kind, "workers": 2, "dask_address": None}})
    runner = task_runner(load_params(params).data.runner)
    other = generate.with_options(task_runner=runner)(str(params))
    assert other["content_hash"] == reference["content_hash"]


def test_flow_rejects_bad_params_before_work(tmp_path, prefect_harness):
    from components.config import ConfigError
    from flows.generate import generate

    params = write_params(tmp_path, **{"data.splits": {"train": 24, "val": -1, "test": 8}})
    with pytest.raises(ConfigError, match=r"data\.splits\.val"):
        generate(str(params))
    assert not (tmp_path / "data").exists()


FAST_TRAINING = {"train.epochs": 2, "train.embedding_epochs": 1, "train.sizes": [8, 24],
                 "train.variants": {"ensemble": {"backbone": "cues", "size": 24, "ensemble": 2}},
                 "backbones": {"names": ["cues", "cnn"], "pretrained_dir": None, "batch_size": 256},
                 "train.flow": {"transforms": 1, "hidden_features": [16], "bins": 4, "passes": 2, "ensemble": 1}}


def _run(cmd, cwd, **kw):
    # DVC runs stage commands through the shell: `python` must be this interpreter
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    env = dict(os.environ, PYTHONPATH=str(cwd), PATH=path)
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600, **kw)


@pytest.mark.slow
def test_dvc_repro_pipeline_in_a_temp_git_repo(tmp_path, prefect_server, monkeypatch):
    """`dvc repro` runs every stage through its Prefect flow; a second run does nothing; a params change reruns."""
    repo = tmp_path / "repo"
    repo.mkdir()
    for name in ("components", "flows"):
        shutil.copytree(PROJECT_ROOT / name, repo / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(PROJECT_ROOT / "dvc.yaml", repo / "dvc.yaml")
    write_params(repo, **FAST_TRAINING)
    dvc = [sys.executable, "-m", "dvc"]
    monkeypatch.setenv("PREFECT_API_URL", prefect_server)  # every stage reports to one server (as run.sh does)
    for cmd in (["git", "init", "-q"], dvc + ["init", "-q"], dvc + ["config", "core.analytics", "false"]):
        assert _run(cmd, repo).returncode == 0

    r = _run(dvc + ["repro"], repo)
    assert r.returncode == 0, r.stdout + r.stderr
    manifest = json.loads((repo / "data/manifest.json").read_text())
    assert manifest["splits"]["train"]["count"] == 24
    lock = (repo / "dvc.lock").read_text()
    stages = ["generate", "evaluate", "features@cues", "features@cnn", "variant@ensemble"]
    stages += [f"train@{b}-{n}" for b in ("cues", "cnn") for n in (8, 24)]
    for stage in stages:
        assert f"{stage}:" in lock, stage
    for backbone in ("cues", "cnn"):
        fm = json.loads((repo / f"features/{backbone}/manifest.json").read_text())
        assert fm["dataset_content_hash"] == manifest["content_hash"]
    task1 = json.loads((repo / "reports/task1/metrics.json").read_text())
    assert set(task1) == {"cues-8", "cues-24", "cnn-8", "cnn-24", "cues-24-ensemble"} and all(np.isfinite(m["test_nll"]) for m in task1.values())
    assert (repo / "reports/task1/plots/coverage.png").is_file() and (repo / "mlflow.db").is_file()

    r = _run(dvc + ["repro"], repo)
    assert r.returncode == 0 and "Data and pipelines are up to date" in (r.stdout + r.stderr), r.stdout + r.stderr

    # a params change reruns the stage, and the data follow the new seed
    write_params(repo, seed=7, **FAST_TRAINING)
    r = _run(dvc + ["repro", "generate"], repo)
    assert r.returncode == 0, r.stdout + r.stderr
    new = json.loads((repo / "data/manifest.json").read_text())
    assert new["content_hash"] != manifest["content_hash"] and new["seed"] == 7
    theta = dataset.open_split(repo / "data", "train").theta
    assert np.isfinite(theta).all()
