"""The train stage: a model of the grid trained from cached features, saved, and logged in a real MLflow store."""

from __future__ import annotations

import json
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch

from components.posterior.store import load_npe
from tests.conftest import TINY_FLOW, write_params

FAST = {
    "train.epochs": 3,
    "train.embedding_epochs": 2,
    "train.patience": 5,
    "train.flow": TINY_FLOW,
}


@pytest.fixture(scope="module")
def project(tmp_path_factory, prefect_harness):
    from flows.features import extract_features
    from flows.generate import generate

    folder = tmp_path_factory.mktemp("train")
    params = write_params(folder, **FAST)
    generate(str(params))
    for backbone in ("cues", "cnn"):
        extract_features(backbone, str(params))
    return folder, params


def test_train_logs_the_grid_in_mlflow_and_saves_a_loadable_model(project, monkeypatch):
    from flows.train import train_model

    folder, params = project
    uri = f"sqlite:///{folder / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    metrics = train_model("cues", 16, str(params))
    assert np.isfinite(metrics["test_nll"]) and metrics["epochs_run"] == 3
    # the best epoch is counted from 1, as the loss plot and the log lines count it
    history = json.loads((folder / "models/cues-16/history.json").read_text())
    assert (
        metrics["best_epoch"]
        == int(np.argmin([r["val_loss"] for r in history["records"]])) + 1
        == history["best_epoch"] + 1
    )
    reported = json.loads((folder / "reports/train/cues-16.json").read_text())
    assert reported.pop("wall_seconds") > 0 and reported == json.loads(
        (folder / "models/cues-16/metrics.json").read_text()
    )

    model, header = load_npe(folder / "models/cues-16/model.pt")
    assert header["backbone"] == "cues" and not header["trainable_backbone"]
    theta = torch.tensor([[50.0, 10.0, 20.0, 30.0, 40.0, 50.0]])
    x = torch.zeros(1, header["features"])
    assert torch.isfinite(model.log_prob(theta, x)).all()
    # the reported test NLL recomputed apart from the stage: the saved model on features of the test split's images
    # computed now by the backbone (not read from the feature cache), −mean log q(θ | x) over the whole split
    from components.features.backbones import get_backbone
    from components.simulate import dataset

    test = dataset.open_split(folder / "data", "test")
    fresh = torch.from_numpy(get_backbone("cues").extract(test.images()))
    with torch.no_grad():
        lp = model.log_prob(torch.from_numpy(test.theta.astype(np.float32)), fresh).double()
    assert len(test) == 48 and -float(lp.mean()) == pytest.approx(metrics["test_nll"], rel=1e-5)
    # the base scales τ fitted on the validation split (train.temperature), outside and inside the regime
    # (train.temperature_regime: night), are saved with the model and reported, with the gate's accuracy
    names = header["box"]["names"]
    tau = [[metrics[f"{prefix}.{name}"] for name in names] for prefix in ("temperature", "temperature_night")]
    np.testing.assert_allclose(model.temperature.numpy(), tau, rtol=1e-6)
    # (the NLL that τ saves is reported; its value is tested where the true τ is known: tests/test_temperature.py)
    assert all(t > 0 for row in tau for t in row) and tau[0] != tau[1] and np.isfinite(metrics["heldout_nll_gain"])
    assert 0 < metrics["regime_share"] < 1 and 0 <= metrics["regime_gate_accuracy"] <= 1

    train_model("cnn", 8, str(params))  # a backbone trained jointly with the flow
    cnn, h = load_npe(folder / "models/cnn-8/model.pt")
    assert h["trainable_backbone"] and tuple(h["input_shape"]) == (3, 64, 64)  # the cnn's input size

    client = mlflow.MlflowClient(uri)
    exp = client.get_experiment_by_name("pidc-grid")
    runs = client.search_runs([exp.experiment_id])
    children = {r.data.tags["pidc.model"]: r for r in runs if "mlflow.parentRunId" in r.data.tags}
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    assert {"cues-16", "cnn-8"} <= set(children) and len(parents) == 1, (
        "one parent run for the grid, one child per model"
    )
    assert parents[0].info.status == "FINISHED" and all(r.info.status == "FINISHED" for r in children.values())
    child = children["cues-16"]
    assert child.data.tags["mlflow.parentRunId"] == parents[0].info.run_id
    assert child.data.params["backbone"] == "cues" and child.data.params["size"] == "16"
    metrics = set(child.data.metrics)
    assert {"test_nll", "info_gain_nats", "training_seconds", "wall_seconds", "temperature.cloudiness"} <= metrics
    assert len(client.get_metric_history(child.info.run_id, "val_loss")) == 3
    assert {a.path for a in client.list_artifacts(child.info.run_id)} >= {"loss.png", "metrics.json", "model.pt"}
    assert child.data.tags["data_hash"] and child.data.tags["dvc_stage"] == "train"


def test_bad_grid_cell_is_named(project):
    from flows.export import export_all
    from flows.train import train_grid, train_model

    _, params = project
    with pytest.raises(ValueError, match=r"size 5 is not in train.sizes"):
        train_model("cues", 5, str(params))
    with pytest.raises(ValueError, match=r"backbone 'resnet50' is not in backbones.names"):
        train_model("resnet50", 8, str(params))
    with pytest.raises(ValueError, match=r"no model 'cues-5' in the grid or train.variants \(known: cues-8, "):
        train_grid(str(params), ["cues-5"])
    with pytest.raises(ValueError, match=r"no model 'cues-16-wide' in the grid"):
        export_all(str(params), ["cues-16-wide"])


def test_train_grid_trains_every_model_in_parallel_processes_and_resumes(project, monkeypatch, tmp_path):
    """The train stage's flow: the grid and its variants in two worker processes, the largest first, one MLflow parent
    run for the grid; run again, every model resumes from its finished checkpoint to the same figures."""
    import yaml

    from components.core.config import load_params
    from flows.stage import task_runner
    from flows.train import train_grid, training_order

    folder, params = project
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"  # a store of its own: the parents of this test's grid only
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    p = yaml.safe_load(params.read_text())
    p["backbones"]["names"] = ["cues", "cnn"]
    p["train"]["sizes"] = [24]
    p["train"]["variants"] = {"pair": {"backbone": "cues", "size": 24, "balance": 0.0, "ensemble": 2}}
    p["train"]["runner"] = {"kind": "processes", "workers": 2, "dask_address": None}
    grid = folder / "parallel.yaml"
    grid.write_text(yaml.safe_dump(p))
    loaded = load_params(grid)
    assert training_order(loaded, loaded.model_ids()) == ["cues-24-pair", "cues-24", "cnn-24"]

    run = train_grid.with_options(task_runner=task_runner(loaded.train.runner))
    first = run(str(grid))
    assert list(first) == ["cues-24", "cnn-24", "cues-24-pair"]
    for m, metrics in first.items():
        assert np.isfinite(metrics["test_nll"]) and metrics["epochs_run"] == (2 if m.startswith("cnn") else 3), m
        assert json.loads((folder / f"reports/train/{m}.json").read_text()) == metrics
        assert (folder / f"models/{m}/model.pt").is_file()
    _, header = load_npe(folder / "models/cues-24-pair/model.pt")
    assert header["flow"]["ensemble"] == 2

    files = {f: f.read_bytes() for m in first for f in sorted((folder / "models" / m).iterdir()) if f.is_file()}
    client = mlflow.MlflowClient(uri)
    experiment = client.get_experiment_by_name("pidc-grid").experiment_id
    # a training of cues-24 killed under other settings or code (another run key) left its run RUNNING
    mine = client.search_runs([experiment], "tags.`pidc.model` = 'cues-24'")[0]
    stale = client.create_run(
        experiment,
        tags={k: mine.data.tags[k] for k in ("pidc.model", "pidc.grid", "mlflow.parentRunId")} | {"pidc.run_key": "0"},
    ).info.run_id
    again = run(str(grid))  # finished checkpoints: nothing is trained again, the figures are the same
    # and the models' files to the byte (what DVC hashes: an unchanged model does not re-run the stages after train)
    assert {f: f.read_bytes() for f in files} == files
    assert sorted(f for m in first for f in (folder / "models" / m).iterdir() if f.is_file()) == sorted(files)
    for m in first:
        assert again[m]["test_nll"] == first[m]["test_nll"] and again[m]["best_val_loss"] == first[m]["best_val_loss"]
        # the training time is the epochs' (kept from the first run), not the second run's loading and testing
        assert again[m]["training_seconds"] == first[m]["training_seconds"] > 0, m

    assert client.get_run(stale).info.status == "KILLED", "a killed training's run of another key is closed"
    client.delete_run(stale)
    runs = client.search_runs([experiment])
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert len(parents) == 1, "models trained in parallel share one parent run"
    # the second run added to each model's run (its run key: the checkpoint's) instead of a second run without curves
    assert sorted(r.data.tags["pidc.model"] for r in children) == sorted(first)
    assert all(r.data.tags["mlflow.parentRunId"] == parents[0].info.run_id for r in children)
    for r in children:
        steps = [m.step for m in client.get_metric_history(r.info.run_id, "val_loss")]
        assert sorted(steps) == list(range(first[r.data.tags["pidc.model"]]["epochs_run"])), "each epoch once"
        assert r.info.status == "FINISHED"


def test_a_checkpoint_of_other_code_is_not_resumed(project, monkeypatch, tmp_path):
    """An edit of the training code (its fingerprint, :func:`flows.train.training_code`) retrains a model whose
    finished checkpoint was made by the code before; its new run holds its own curves, and the code's run is found
    as the model's newest."""
    import flows.train
    from flows import tracking

    folder, params = project  # cues-16: trained by the first test (cues-8 must stay untrained for the export test)
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    first = flows.train.train_model("cues", 16, str(params))
    checkpoints = sorted((folder / "models/cues-16").glob("checkpoint-*.pt"))
    again = flows.train.train_model("cues", 16, str(params))
    assert again["training_seconds"] == first["training_seconds"], "unchanged code: the finished checkpoint"
    assert sorted((folder / "models/cues-16").glob("checkpoint-*.pt")) == checkpoints
    code = flows.train.training_code
    monkeypatch.setattr(flows.train, "training_code", lambda backbone: code(backbone) + "-edited")
    edited = flows.train.train_model("cues", 16, str(params))
    assert edited["training_seconds"] != first["training_seconds"], "trained again, not resumed"
    now = sorted((folder / "models/cues-16").glob("checkpoint-*.pt"))
    assert len(now) == 1 and now != checkpoints, "the other code's checkpoint is gone"
    assert edited["test_nll"] == pytest.approx(first["test_nll"], abs=1e-6), "the same code trains the same model"

    client = mlflow.MlflowClient(uri)
    experiment = client.get_experiment_by_name("pidc-grid").experiment_id
    runs = client.search_runs([experiment], "tags.`pidc.model` = 'cues-16'")
    assert len(runs) == 2 and len({r.data.tags["pidc.run_key"] for r in runs}) == 2
    newest = tracking.newest_model_run(client, experiment, "cues-16")
    assert client.get_run(newest).data.tags["pidc.run_key"] == now[0].stem.removeprefix("checkpoint-")
    # back to the first code: its run is reopened (no third run) and is again the newest
    monkeypatch.setattr(flows.train, "training_code", code)
    flows.train.train_model("cues", 16, str(params))
    runs = client.search_runs([experiment], "tags.`pidc.model` = 'cues-16'")
    assert len(runs) == 2
    assert client.get_run(tracking.newest_model_run(client, experiment, "cues-16")).data.tags["pidc.run_key"] == (
        checkpoints[0].stem.removeprefix("checkpoint-")
    )


def test_export_evaluate_champion(project, monkeypatch, capsys):
    """A 2 × 2 grid and a variant: exported to registry/ and the MLflow Model Registry; Task I on the exported models
    (every metric per model, the plots, the metrics in each model's MLflow run); the champion alias and pointer;
    ``models:/<name>@champion`` loads and runs."""
    import mlflow.pyfunc
    import yaml

    from components.core.config import load_params
    from components.export.runtime import OnnxPosterior
    from flows.evaluate import evaluate
    from flows.export import export_model
    from flows.tracking import download_registered_model
    from flows.train import train_model

    folder, params = project
    uri = f"sqlite:///{folder / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    p = yaml.safe_load(params.read_text())
    p["backbones"]["names"] = ["cues", "cnn"]
    p["train"]["sizes"] = [8, 16]
    grid = folder / "grid.yaml"
    grid.write_text(yaml.safe_dump(p))
    with pytest.raises(FileNotFoundError, match="no exported model in registry/ for cues-8, cues-16, cnn-8, cnn-16"):
        evaluate(str(grid))
    with pytest.raises(FileNotFoundError, match="no trained model 'cues-8'"):
        export_model("cues-8", str(grid))
    for m, s in (("cues", 8), ("cues", 16), ("cnn", 8), ("cnn", 16)):
        if not (folder / f"models/{m}-{s}/model.pt").exists():
            train_model(m, s, str(grid))
        export_model(f"{m}-{s}", str(grid))
    with pytest.raises(FileNotFoundError, match="no exported model in registry/ for cues-16-balanced"):
        evaluate(str(grid))
    with pytest.raises(ValueError, match="variant 'balanced' is defined for cues-16, not cues-8"):
        train_model("cues", 8, str(grid), "balanced")
    variant = train_model("cues", 16, str(grid), "balanced")  # the calibrated variant beside the grid
    assert (folder / "models/cues-16-balanced/model.pt").is_file()
    exported = export_model("cues-16-balanced", str(grid))
    assert exported["name"] == "pidc" and exported["version"] == "5", "the fifth version of the one registered model"
    assert not exported["reused"]
    # exported again, the same files (the same card, which holds the graphs' sha256): the version is found, not added
    again = export_model("cues-16-balanced", str(grid))
    assert again["reused"] and again["version"] == "5" and again["run_id"] == exported["run_id"]
    assert len(mlflow.MlflowClient(uri).search_model_versions("name = 'pidc'")) == 5

    # the registry folder: card with what the issue names; the runtime agrees with the torch model
    card = json.loads((folder / "registry/cnn-16/card.json").read_text())
    assert card["backbone"] == "cnn" and card["size"] == 16 and card["theta"]["names"][0] == "cloudiness"
    assert card["opset"] == 18 and card["versions"]["onnxruntime"] and card["git_commit"] and card["data_hash"]
    assert set(card["metrics"]) >= {"test_nll", "info_gain_nats"} and card["input"]["shape"][1:] == [3, 64, 64]
    sim = load_params(grid).simulator  # the renders the model learned from (pidc's CLI names them when it resizes)
    assert card["training_renders"] == {
        "simulator": sim.backend,
        "height": sim.height,
        "width": sim.width,
        "render_sizes": None,
    }
    model, _ = load_npe(folder / "models/cnn-16/model.pt")
    posterior = OnnxPosterior.load(folder / "registry/cnn-16")
    x = torch.rand(3, 3, 64, 64)
    theta = torch.tensor([[50.0, 10.0, 20.0, 30.0, 40.0, 50.0]]).repeat(3, 1)
    with torch.no_grad():
        expected = model.log_prob(theta, x).double().numpy()
    assert np.abs(posterior.log_prob(theta.numpy(), x.numpy()) - expected).max() <= 1e-4

    metrics = evaluate(str(grid))
    assert set(metrics) == {"cues-8", "cues-16", "cnn-8", "cnn-16", "cues-16-balanced"}
    assert np.isfinite(variant["test_nll"])
    for m in metrics.values():
        assert 0 <= m["calibration_error"] <= 1 and -1 <= m["coverage_auc_gap"] <= 1 and 0 <= m["pi_median"] <= 1
        assert np.isfinite(m["test_nll"]) and np.isfinite(m["info_gain_nats"]) and m["ppc_score"] <= 1
    assert json.loads((folder / "reports/task1/metrics.json").read_text()) == metrics
    plots = folder / "reports/task1/plots"
    for f in (
        "coverage.png",
        "superiority.png",
        "cues-8/ppc.png",
        "cues-8/histograms-0.png",
        "cnn-16/corner-zoom-0.png",
    ):
        assert (plots / f).stat().st_size > 5000, f
    rows = json.loads((folder / "reports/task1/coverage.json").read_text())
    assert len(rows) == 5 * 101 and {"model", "level", "coverage"} == set(rows[0])

    client = mlflow.MlflowClient(uri)
    exp = client.get_experiment_by_name("pidc-grid")
    run = client.search_runs(
        [exp.experiment_id], "tags.`pidc.model` = 'cues-8'", order_by=["attributes.start_time DESC"]
    )[0]
    assert run.data.metrics["task1.calibration_error"] == pytest.approx(
        metrics["cues-8"]["calibration_error"], rel=1e-5
    )

    # the experiment opens in the UI's model-training view; every run names the data it saw (dataset input)
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"
    inputs = run.inputs.dataset_inputs
    assert len(inputs) == 1 and inputs[0].dataset.name == "weather-images-32x32"
    manifest = json.loads((folder / "data/manifest.json").read_text())
    assert inputs[0].dataset.digest == manifest["content_hash"][:36]
    input_tags = {t.key: t.value for t in inputs[0].tags}
    assert input_tags["mlflow.data.context"] == "training" and input_tags["images_used"] == "8"
    assert {k: int(v) for k, v in input_tags.items() if k.startswith("split.")} == {
        f"split.{k}": v["count"] for k, v in manifest["splits"].items()
    }

    # the MLflow Model Registry: one registered model, a version per exported model tagged with its id and metrics
    names = {m.name for m in client.search_registered_models()}
    assert names == {"pidc"}
    tagged = {v.tags["pidc.model"] for v in client.search_model_versions("name = 'pidc'")}
    assert tagged == set(metrics)
    # the champion rule (components.evaluate.champion): lowest test NLL within the band, else below the ceiling
    eligible = [m for m in metrics if metrics[m]["within_band"]]
    ceiling = yaml.safe_load(grid.read_text())["export"]["champion_max_calibration_error"]
    eligible = eligible or [m for m in metrics if metrics[m]["calibration_error"] <= ceiling]
    best = min(sorted(eligible), key=lambda m: metrics[m]["test_nll"])
    champion = json.loads((folder / "reports/task1/champion.json").read_text())
    assert champion["model"] == best and champion["uri"] == "models:/pidc@champion"
    assert (
        champion["rule"] in ("within_band", "ceiling") and champion["metrics"]["test_nll"] == metrics[best]["test_nll"]
    )
    rows = {p.stem: json.loads(p.read_text()) for p in (folder / "reports/task1/models").glob("*.json")}
    assert set(rows) == set(metrics) and len({tuple(r) for r in rows.values()}) == 1, "one row per model, same keys"
    parameters = json.loads((folder / "reports/task1/parameters.json").read_text())
    assert sum(parameters["cnn-8"][s]["fog_density"]["images"] for s in ("day", "night")) == 8
    profiles = json.loads((folder / "reports/task1/profiles.json").read_text())
    assert set(profiles) == set(metrics) and sum(profiles["cnn-8"]["all"]["fog_density"]["images"]) == 8
    assert (folder / "reports/task1/plots/cnn-8/profile.png").is_file()
    version = client.get_model_version_by_alias("pidc", "champion")
    assert "task1/profile.png" in {f.path for f in client.list_artifacts(version.run_id, "task1")}
    assert version.tags["pidc.model"] == best
    assert float(version.tags["task1.calibration_error"]) == pytest.approx(metrics[best]["calibration_error"], rel=1e-5)
    assert (
        "train.test_nll" in version.tags
        and version.run_id
        == client.search_runs(
            [exp.experiment_id], f"tags.`pidc.model` = '{best}'", order_by=["attributes.start_time DESC"]
        )[0].info.run_id
    )

    # the grid run carries the cross-model figures and names the champion; each model run describes itself
    parent = client.get_run(run.data.tags["mlflow.parentRunId"])
    assert parent.data.tags["pidc.champion"] == best
    assert parent.data.tags["mlflow.note.content"].startswith(f"Champion: {best} — ")
    assert client.get_experiment(exp.experiment_id).tags["mlflow.note.content"].startswith(f"Champion: {best} — ")
    # every model run hangs directly under a grid run (models trained by earlier tests may belong to another grid)
    for r in client.search_runs([exp.experiment_id], "tags.`pidc.model` LIKE '%'"):
        above = client.get_run(r.data.tags["mlflow.parentRunId"])
        assert above.info.run_name.startswith("grid-") and "pidc.model" not in above.data.tags, r.info.run_name
    assert parent.data.metrics["champion.test_nll"] == pytest.approx(metrics[best]["test_nll"], rel=1e-5)
    artifacts = {f.path for f in client.list_artifacts(parent.info.run_id, "task1")}
    assert artifacts >= {"task1/coverage.png", "task1/superiority.png", "task1/parameters.png", "task1/table.md"}
    best_run = client.get_run(version.run_id)
    assert best_run.data.tags["pidc.role"] == "champion"
    assert best_run.data.tags["mlflow.note.content"].startswith(f"Champion: {best} — ")
    others = [
        client.get_run(v.run_id) for v in client.search_model_versions("name = 'pidc'") if v.run_id != version.run_id
    ]
    assert {r.data.tags["pidc.role"] for r in others} <= {"challenger", "candidate"}

    # the CLI loads the champion by its URI (through MLflow's command line)
    from PIL import Image

    from components.cli.main import main as cli

    Image.fromarray(np.full((32, 32, 3), 128, np.uint8)).save(folder / "grey.png")
    monkeypatch.chdir(folder)
    assert cli(["characterize", str(folder / "grey.png"), "--model", "models:/pidc@champion"]) == 0
    assert f"with {best} (" in capsys.readouterr().err  # "characterized 1 image with <model> (… draws …)"
    assert cli(["characterize", str(folder / "grey.png"), "--model", "models:/pidc@nobody"]) != 0
    assert "models:/pidc@nobody: not found in the MLflow store" in capsys.readouterr().err

    loaded = OnnxPosterior.load(
        download_registered_model(champion["uri"])
    )  # the torch-free posterior from the registered model's files
    local = OnnxPosterior.load(folder / "registry" / best)
    # the download is a temporary folder, gone when the process that downloaded it ends
    import os
    import subprocess
    import sys

    code = "import sys; from flows.tracking import download_registered_model as d; print(d(sys.argv[1]))"
    done = subprocess.run(
        [sys.executable, "-c", code, champion["uri"]],
        capture_output=True,
        text=True,
        env={**os.environ, "MLFLOW_TRACKING_URI": uri},
        cwd=Path(__file__).parents[1],
    )
    downloaded = Path(done.stdout.strip().splitlines()[-1]) if done.stdout.strip() else None
    assert done.returncode == 0 and downloaded and downloaded.name == "extra_files", done.stderr
    assert downloaded.parent.name.startswith("pidc-model-") and not downloaded.parent.exists()
    x = np.random.default_rng(0).normal(size=(4, *local.input_shape)).astype(np.float32)
    theta = local.sample(x, 1, seed=0)[:, 0]
    np.testing.assert_allclose(loaded.log_prob(theta, x), local.log_prob(theta, x), rtol=0, atol=1e-9)
    pyfunc = mlflow.pyfunc.load_model(champion["uri"])  # the ONNX flavor runs the whole density graph
    out = pyfunc.predict({"x": x, "theta": theta.astype(np.float32)})["log_prob"]
    np.testing.assert_allclose(out, local.log_prob(theta, x), atol=1e-3)

    # when no model qualifies, the evaluate stage takes both aliases away: no stale champion for the monitoring
    from flows import tracking

    tracking.clear_champion_aliases(folder, load_params(grid))
    for alias in ("champion", "challenger"):
        with pytest.raises(mlflow.exceptions.MlflowException, match="not found"):
            client.get_model_version_by_alias("pidc", alias)
    tracking.clear_champion_aliases(folder, load_params(grid))  # none left: nothing to take away, no error


def test_evaluate_refuses_a_model_with_another_theta_order(project, tmp_path):
    from components.core import weather
    from components.core.config import load_params
    from components.evaluate.task1 import check_model_matches_data

    folder, params = project
    box = load_params(params).box
    reordered = weather.Box(box.low[::-1], box.high[::-1], tuple(reversed(box.names)), tuple(reversed(box.units)))
    with pytest.raises(ValueError, match="θ order"):
        check_model_matches_data(reordered, load_params(params), folder / "registry/cues-16/card.json")


def test_models_from_the_ensemble_size_are_ensembles_with_less_noise(project, monkeypatch, tmp_path):
    """train.flow.ensemble flows for the grid's models of at least train.ensemble_min_size images, one flow below;
    the ensemble trains with one flow's input noise (both recorded in the model's MLflow run)."""
    import yaml

    from flows.train import train_model

    folder, params = project
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    p = yaml.safe_load(params.read_text())
    p["train"]["flow"]["ensemble"] = 2
    p["train"]["ensemble_min_size"] = 24
    grid = folder / "ensembles.yaml"
    grid.write_text(yaml.safe_dump(p))
    for size, flows in ((24, 2), (8, 1)):
        train_model("cues", size, str(grid))
        _, header = load_npe(folder / f"models/cues-{size}/model.pt")
        assert header["flow"]["ensemble"] == flows, size
    client = mlflow.MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("pidc-grid").experiment_id])
    noise = {
        r.data.tags["pidc.model"]: float(r.data.params["train.input_noise"])
        for r in runs
        if "pidc.model" in r.data.tags
    }
    one = p["train"]["input_noise"] * (p["train"]["scale_to"] / 24) ** 0.5
    assert noise["cues-24"] == pytest.approx(one, rel=1e-6) and noise["cues-8"] > noise["cues-24"]  # flows or not


def test_new_features_of_a_backbone_retrain_its_models_instead_of_failing(tmp_path, prefect_harness, monkeypatch):
    """A new version of a backbone's features (here the cues' code version, as when cues version 4 added the sky's
    thumbnail) recomputes the feature cache; the train stage then trains the backbone's models afresh under a new
    checkpoint instead of failing on the old checkpoint's data fingerprint, and removes the stale checkpoint."""
    from components.features.backbones.cues import CuesBackbone
    from flows.features import extract_features
    from flows.generate import generate
    from flows.train import train_model

    params = write_params(tmp_path, **FAST)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    generate(str(params))
    extract_features("cues", str(params))
    train_model("cues", 8, str(params))
    (old,) = (tmp_path / "models/cues-8").glob("checkpoint-*.pt")

    monkeypatch.setattr(CuesBackbone, "version", CuesBackbone.version + "-test")
    extract_features("cues", str(params))  # the cache's fingerprint no longer matches: every shard is recomputed
    metrics = train_model("cues", 8, str(params))
    (new,) = (tmp_path / "models/cues-8").glob("checkpoint-*.pt")
    assert new != old and np.isfinite(metrics["test_nll"]) and metrics["epochs_run"] == 3


def test_export_flow_called_as_a_function_exports_one_model_at_a_time(project, monkeypatch):
    """Called as a function, the export flow runs on Prefect's default task runner (threads), where two exports would
    share torch's ONNX exporter and its global state: it exports one model after the other, and the registry's
    versions follow the order of the models asked for."""
    from flows.export import export_all
    from flows.train import train_model

    folder, params = project
    monkeypatch.setenv(
        "MLFLOW_TRACKING_URI", f"sqlite:///{folder / 'mlflow-export.db'}"
    )  # its own store: versions 1, 2
    for size in (8, 16):
        if not (folder / f"models/cues-{size}/model.pt").exists():
            train_model("cues", size, str(params))
    out = export_all(str(params), ["cues-16", "cues-8"])
    assert list(out) == ["cues-16", "cues-8"]
    assert [out[m]["version"] for m in out] == ["1", "2"] and {out[m]["name"] for m in out} == {"pidc"}
    for m in out:
        card = json.loads((folder / "registry" / m / "card.json").read_text())
        assert card["model_id"] == m and out[m]["export_seconds"] > 0
