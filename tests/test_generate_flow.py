"""The generate stage end to end: the real Prefect flow, resume after damage, and `dvc repro` in a temp git repo."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from components.core.config import load_params
from components.simulate import dataset
from tests.conftest import FAST_TRAINING, copy_project, run_in, write_params


def test_flow_generates_and_resumes_after_damage(tmp_path, prefect_harness):
    from flows.generate import generate

    params = write_params(tmp_path)
    first = generate(str(params))
    assert {k: v["count"] for k, v in first["splits"].items()} == {"train": 24, "val": 16, "test": 48}
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


def test_a_generate_killed_while_rendering_a_new_plan_leaves_no_manifest_to_trust(
    tmp_path, prefect_harness, monkeypatch
):
    """A new plan (another seed) re-renders shards of the same sizes: while they are rendered the old manifest is gone,
    so a run killed then leaves readers a clear error, not the old manifest vouching for new shards (readers check
    sizes, not hashes, and old features would still match it); a manifest write's temporary file left by a kill is
    removed; the next run finishes and writes the manifest of the new shards."""
    from components.simulate.dataset import DatasetError
    from flows.generate import generate

    first = generate(str(write_params(tmp_path)))
    (tmp_path / "data/.manifest.json.0123abcd.tmp").write_bytes(b"{")  # a manifest write cut short by a kill
    params = write_params(tmp_path, seed=7)
    render = dataset.render_shard
    calls = []

    def killed_after_one(*args, **kwargs):  # fault injection: the run dies after its first new shard
        if calls:
            raise KeyboardInterrupt("killed")
        calls.append(1)
        return render(*args, **kwargs)

    monkeypatch.setattr(dataset, "render_shard", killed_after_one)
    with pytest.raises(BaseException, match="killed"):
        generate(str(params))
    assert calls and not (tmp_path / "data/manifest.json").exists()
    assert not (tmp_path / "data/.manifest.json.0123abcd.tmp").exists()
    with pytest.raises(DatasetError, match="no dataset manifest; run the generate stage"):
        dataset.open_split(tmp_path / "data", "train")
    monkeypatch.setattr(dataset, "render_shard", render)
    second = generate(str(params))
    assert second["content_hash"] != first["content_hash"]
    assert dataset.open_split(tmp_path / "data", "train", verify=True).content_hash == second["content_hash"]


def test_a_killed_stage_leaves_no_process_pool_worker_behind(tmp_path):
    """The stages' process pools start each worker with :func:`flows.stage.exit_with_parent`: when the stage's
    process is killed (SIGKILL, no clean-up) its worker, busy with a long task, ends within seconds instead of
    finishing it and the next one on its own (Python's workers do not watch their parent)."""
    import os
    import signal
    import subprocess
    import time

    from flows.stage import exit_with_parent, task_runner

    runner = task_runner(
        load_params(
            write_params(tmp_path / "p", **{"data.runner": {"kind": "processes", "workers": 1, "dask_address": None}})
        ).data.runner
    )
    assert getattr(runner, "_initializer", None) is exit_with_parent  # what Prefect hands to its ProcessPoolExecutor
    script = (
        "import concurrent.futures as cf, multiprocessing as mp, os, signal, sys, time\n"
        "from flows.stage import exit_with_parent\n"
        "pool = cf.ProcessPoolExecutor(1, mp_context=mp.get_context('spawn'), initializer=exit_with_parent)\n"
        "print(pool.submit(os.getpid).result(), flush=True)\n"
        "pool.submit(time.sleep, 120); pool.submit(time.sleep, 120); time.sleep(1)\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=Path(__file__).parents[1])
    assert out.returncode == -signal.SIGKILL, out.stderr
    worker = int(out.stdout.split()[0])
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(worker, 0)
        except ProcessLookupError:
            break
        time.sleep(0.2)
    else:
        os.kill(worker, signal.SIGKILL)
        pytest.fail(f"worker {worker} outlived its killed parent by 10 s")


@pytest.mark.parametrize("kind", ["processes", "dask"])
def test_every_task_runner_gives_the_same_data(tmp_path, prefect_harness, kind):
    from flows.generate import generate
    from flows.stage import task_runner

    reference = generate(str(write_params(tmp_path / "threads")))  # threads (micro params' default)
    params = write_params(tmp_path / kind, **{"data.runner": {"kind": kind, "workers": 2, "dask_address": None}})
    runner = task_runner(load_params(params).data.runner)
    other = generate.with_options(task_runner=runner)(str(params))
    assert other["content_hash"] == reference["content_hash"]


def test_flow_rejects_bad_params_before_work(tmp_path, prefect_harness):
    from components.core.config import ConfigError
    from flows.generate import generate

    params = write_params(tmp_path, **{"data.splits": {"train": 24, "val": -1, "test": 8}})
    with pytest.raises(ConfigError, match=r"data\.splits\.val"):
        generate(str(params))
    assert not (tmp_path / "data").exists()


@pytest.mark.slow
def test_dvc_repro_pipeline_in_a_temp_git_repo(micro_project, tmp_path, prefect_server):
    """`dvc repro` runs every stage through its Prefect flow; a second run does nothing; a params change reruns."""
    repo = micro_project  # built once per session by `dvc repro` (tests/conftest.py)
    manifest = json.loads((repo / "data/manifest.json").read_text())
    assert manifest["splits"]["train"]["count"] == 24
    lock = (repo / "dvc.lock").read_text()
    stages = ["generate", "train", "export", "evaluate", "task2", "task3", "features@cues", "features@cnn"]
    for stage in stages:
        assert f"{stage}:" in lock, stage
    for backbone in ("cues", "cnn"):
        fm = json.loads((repo / f"features/{backbone}/manifest.json").read_text())
        assert fm["dataset_content_hash"] == manifest["content_hash"]
    task1 = json.loads((repo / "reports/task1/metrics.json").read_text())
    assert set(task1) == {"cues-8", "cues-24", "cnn-8", "cnn-24", "cues-24-ensemble"} and all(
        np.isfinite(m["test_nll"]) for m in task1.values()
    )
    assert (repo / "reports/task1/plots/coverage.png").is_file() and (repo / "mlflow.db").is_file()
    # export: every model in registry/ (loaded by the torch-free runtime) and the champion named
    for model in task1:
        card = json.loads((repo / "registry" / model / "card.json").read_text())
        assert (
            card["model_id"] == model
            and card["data_hash"]
            and set(card["files"]) >= {"context", "log_prob_0", "sample_0"}
        )
    champion = json.loads((repo / "reports/task1/champion.json").read_text())
    # the champion rule (components.evaluate.champion): lowest test NLL within the band, else below the ceiling
    eligible = [m for m in task1 if task1[m]["within_band"]]
    ceiling = load_params(repo / "params.yaml").export.champion_max_calibration_error
    eligible = eligible or [m for m in task1 if task1[m]["calibration_error"] <= ceiling]
    assert champion["model"] == min(sorted(eligible), key=lambda m: task1[m]["test_nll"])
    # the reported test NLL recomputed apart from the stage: the registry's model on the test split's images (its
    # backbone run on them, not the feature cache), −mean log q(θ | x) over the images the stage evaluates
    from components.export.lookup import load_registered

    n = int(task1[champion["model"]]["images"])
    test = dataset.open_split(repo / "data", "test")
    model = load_registered(repo / "registry" / champion["model"], repo / "registry")
    x = model.inputs(test.images(stop=n))
    nll = -float(np.mean(model.posterior.log_prob(test.theta[:n], x), dtype=np.float64))
    assert nll == pytest.approx(task1[champion["model"]]["test_nll"], rel=1e-5, abs=1e-5)
    # Task II: the bag's characterization against the known distribution
    task2 = json.loads((repo / "reports/task2/metrics.json").read_text())
    assert task2["model"] == champion["model"]
    assert len(task2["log_density_at_modes"]) == 3 and task2["energy_distance_sq"]["all"]["prior_to_truth"] > 0
    assert set(task2["parameters"]["fog_density"]) >= {"wasserstein_estimate", "wasserstein_prior", "true_mass_in_hdr"}
    floor = task2["width_floor"]["wasserstein_ratio"]  # the posteriors moved onto their truths, spread × s
    assert set(floor) == {"1", "0.8", "0.6"} and all(v >= 0 for s in floor.values() for v in s.values())
    calibrated = task2["width_floor"]["calibrated"]  # calibrated posteriors of these widths: located a draw away
    assert set(calibrated) == set(floor) and all(v >= 0 for s in calibrated.values() for v in s.values())
    interval = task2["width_floor"]["interval"]  # the varying parameters: mixture minus calibrated, bootstrapped
    assert (
        set(interval["mixture_minus_calibrated"]) == {"fog_density", "precipitation"} and interval["replicates"] == 200
    )
    assert all(r["low"] <= r["difference"] <= r["high"] for r in interval["mixture_minus_calibrated"].values())
    # the micro profile scores the deconvolved estimate: the mixture's figures beside it, the EM steps chosen
    curve = task2["deconvolution"]["held_out_log_likelihood"]
    assert task2["estimate"] == "deconvolved" and task2["deconvolution"]["support"] == 64
    assert len(curve) == 21 and all(np.isfinite(curve))
    assert task2["mixture"]["energy_distance_sq"]["all"]["prior_to_truth"] > 0 and "model" not in task2["mixture"]
    for name in ("corner-truth-vs-estimate.png", "corner-overlay.png", "marginals.png", "bag.png", "deconvolution.png"):
        assert (repo / "reports/task2/plots" / name).stat().st_size > 5000, name
    # Task III: per η the paper's statistics; AUC for η > 0; the ODD threshold with its false-alarm rate
    task3 = json.loads((repo / "reports/task3/metrics.json").read_text())
    assert list(task3["eta"]) == ["0", "0.5", "1"] and task3["experiments"] == {"paper": 9, "fresh": 9}
    figures = {f"{f}_{kind}" for f in ("d_e_median", "gap_median", "auc") for kind in ("paper", "fresh")}
    assert all(figures <= set(v) for v in task3["eta"].values())
    assert task3["eta"]["0"]["auc_fresh"] is None and all(0 <= task3["eta"][k]["auc_fresh"] <= 1 for k in ("0.5", "1"))
    assert task3["odd"]["false_alarm_rate"] == 0.1 and task3["odd"]["calibrated_on"] == "fresh"
    assert task3["odd"]["false_alarms_new_seeds"]["n"] == 20
    assert [r["eta"] for r in json.loads((repo / "reports/task3/eta.json").read_text())] == [0.0, 0.5, 1.0]
    for name in [f"{p}-{kind}.png" for p in ("d_e", "gap", "relative-gap", "roc") for kind in ("paper", "fresh")]:
        assert (repo / "reports/task3/plots" / name).stat().st_size > 5000, name

    # MLflow: Task II and III runs in the grid's experiment, nested under the champion's run, loaded by its alias
    import mlflow

    client = mlflow.MlflowClient(f"sqlite:///{repo / 'mlflow.db'}")
    experiment = client.get_experiment_by_name("pidc-grid")
    for task, title in (("task2", "Task II with"), ("task3", "Task III with")):
        (run,) = client.search_runs([experiment.experiment_id], f"tags.`pidc.task` = '{task}'")
        tags = run.data.tags
        assert (
            tags["pidc.model_source"] == "models:/pidc@champion" and tags["pidc.evaluated_model"] == champion["model"]
        )
        assert client.get_run(tags["mlflow.parentRunId"]).data.tags["pidc.model"] == champion["model"]
        assert tags["mlflow.note.content"].startswith(f"{title} {champion['model']}") and run.inputs.dataset_inputs
        if task == "task2":  # the held-out curve is one metric over the EM steps, not 21 metrics
            history = client.get_metric_history(run.info.run_id, "task2.deconvolution.held_out_log_likelihood")
            assert sorted(m.step for m in history) == list(range(21))
            assert not any(k.startswith("task2.deconvolution.held_out_log_likelihood.") for k in run.data.metrics)

    # `dvc metrics show`: one row per model, the same keys in each
    dvc = [sys.executable, "-m", "dvc"]
    r = run_in(dvc + ["metrics", "show", "--json"], repo)
    assert r.returncode == 0, r.stdout + r.stderr
    shown = json.loads(r.stdout)
    (files,) = [v["data"] for v in shown.values()]
    rows = {Path(f).stem: v["data"] for f, v in files.items()}
    assert set(rows) == set(task1) and all(f.startswith("reports/task1/models/") for f in files), sorted(files)
    assert len({tuple(sorted(v)) for v in rows.values()}) == 1, "the same keys in every row"

    # the rest changes the project: on a copy, so the shared micro project stays as built
    repo = copy_project(micro_project, tmp_path / "repo")
    server = {"PREFECT_API_URL": prefect_server}
    r = run_in(dvc + ["repro"], repo, env=server)
    assert r.returncode == 0 and "Data and pipelines are up to date" in (r.stdout + r.stderr), r.stdout + r.stderr

    # a params change reruns the stage, and the data follow the new seed
    write_params(repo, seed=7, **FAST_TRAINING)
    r = run_in(dvc + ["repro", "generate"], repo, env=server)
    assert r.returncode == 0, r.stdout + r.stderr
    new = json.loads((repo / "data/manifest.json").read_text())
    assert new["content_hash"] != manifest["content_hash"] and new["seed"] == 7
    theta = dataset.open_split(repo / "data", "train").theta
    assert np.isfinite(theta).all()


@pytest.mark.slow
def test_dvc_status_follows_the_code_and_a_missing_key_fails_repro(micro_project, tmp_path, prefect_server):
    """Editing a module makes exactly the stages that import it stale (a real `dvc status`); a params file with a
    key removed fails `dvc repro` with one line naming the key."""
    import yaml

    from tests.test_dvc_deps import closure

    repo = copy_project(micro_project, tmp_path / "repo")
    dvc = [sys.executable, "-m", "dvc"]
    touched = "components/evaluate/ppc.py"
    with open(repo / touched, "a") as f:
        f.write("\n# touched by the test\n")
    r = run_in(dvc + ["status", "--json"], repo)
    assert r.returncode == 0, r.stdout + r.stderr
    stale = {name for name, changes in json.loads(r.stdout).items() if any("changed deps" in c for c in changes)}
    lock = yaml.safe_load((repo / "dvc.lock").read_text())["stages"]
    modules = {name: re.search(r"python -m (flows\.\w+)", entry["cmd"]).group(1) for name, entry in lock.items()}
    expected = {name for name, module in modules.items() if (Path(__file__).parents[1] / touched) in closure(module)}
    assert expected == {"evaluate"} and stale == expected, (stale, expected)

    params = yaml.safe_load((repo / "params.yaml").read_text())
    del params["evaluate"]["samples"]
    (repo / "params.yaml").write_text(yaml.safe_dump(params))
    r = run_in(dvc + ["repro", "evaluate"], repo, env={"PREFECT_API_URL": prefect_server})
    assert r.returncode != 0 and "evaluate.samples: missing key" in r.stdout + r.stderr, r.stdout + r.stderr
