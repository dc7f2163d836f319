"""The ``export@<backbone>-<size>`` stage: one trained model → ``registry/<model>/`` and the MLflow Model Registry.

``python -m flows.export --model cues-1000 [--params params.yaml]``. The model's graphs are exported to ONNX
(:func:`components.export.onnx.export_posterior`, checked against torch in onnxruntime) with a model card (backbone,
training size, θ order, units and bijection, input spec, training metrics, data hash, git commit, opset,
onnxruntime version). The whole-density graph ``density.onnx`` is logged as an MLflow model (ONNX flavor, the other
graphs and the card as its extra files) in the model's training run and registered as ``<prefix><model id>``,
with the training metrics as tags of the version. The champion alias comes after the evaluation
(:func:`set_champion`, called by the evaluate stage).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import mlflow
import numpy as np
import onnx
import onnxruntime
import torch
from mlflow.models import ModelSignature
from mlflow.types import Schema, TensorSpec
from prefect import flow, get_run_logger

from components.features.backbones import get_backbone
from components.core.config import PROJECT_ROOT, Params, load_params
from components.export.onnx import export_posterior
from components.core.files import atomic_write_bytes, sha256_file
from components.export.lookup import CHAMPION_POINTER
from components.posterior.store import load_npe
from flows.train import git_commit, tracking_uri

CHAMPION_ALIAS = "champion"


def registry_root(params_file: Path) -> Path:
    return params_file.resolve().parent / "registry"


def registered_name(params: Params, model_id: str) -> str:
    return f"{params.export.registered_prefix}{model_id}"


def newest_model_run(client: mlflow.MlflowClient, experiment_id: str, model_id: str) -> str | None:
    """The id of the newest MLflow run of ``model_id`` (tag ``pidc.model``) in the experiment, or None."""
    runs = client.search_runs([experiment_id], f"tags.`pidc.model` = '{model_id}'",
                              order_by=["attributes.start_time DESC"], max_results=1)
    return runs[0].info.run_id if runs else None


def _signature(card: dict[str, Any]) -> ModelSignature:
    shape = tuple(-1 if s == "batch" else int(s) for s in card["input"]["shape"])
    return ModelSignature(
        inputs=Schema([TensorSpec(np.dtype(np.float32), shape, "x"),
                       TensorSpec(np.dtype(np.float32), (-1, len(card["theta"]["names"])), "theta")]),
        outputs=Schema([TensorSpec(np.dtype(np.float64), (-1,), "log_prob")]),
    )


def register(folder: Path, params: Params, base: Path, model_id: str) -> dict[str, str]:
    """Log ``folder``'s density graph (ONNX flavor; the card and the other graphs as extra files) in the model's MLflow
    run and register it as ``<prefix><model id>``; returns ``{"name", "version", "run_id"}``."""
    card = json.loads((folder / "card.json").read_text())
    mlflow.set_tracking_uri(tracking_uri(base))
    client = mlflow.MlflowClient()
    exp = client.get_experiment_by_name(params.train.experiment)
    experiment_id = exp.experiment_id if exp else client.create_experiment(params.train.experiment)
    run_id = newest_model_run(client, experiment_id, model_id)
    name = registered_name(params, model_id)
    extra = sorted(str(p) for p in folder.iterdir() if p.is_file())
    requirements = [f"onnx=={onnx.__version__}", f"onnxruntime=={onnxruntime.__version__}", "numpy"]
    metrics = {k: float(v) for k, v in (card.get("metrics") or {}).items() if isinstance(v, (int, float))}
    with mlflow.start_run(run_id=run_id, experiment_id=None if run_id else experiment_id,
                          run_name=None if run_id else f"export-{model_id}"):
        info = mlflow.onnx.log_model(
            onnx.load(str(folder / "density.onnx")), name="posterior", signature=_signature(card),
            extra_files=extra, pip_requirements=requirements, onnx_execution_providers=["CPUExecutionProvider"],
            metadata={"pidc_card": card}, registered_model_name=name, await_registration_for=60,
        )
        mlflow.set_tags({"pidc.registered_model": name, "pidc.registry_folder": str(folder.relative_to(base))})
        run = mlflow.active_run().info.run_id
    version = str(info.registered_model_version)
    tags = {"pidc.model": model_id, "backbone": str(card.get("backbone")), "size": str(card.get("size")),
            "data_hash": str(card.get("data_hash")), "git_commit": str(card.get("git_commit")),
            "card_sha256": sha256_file(folder / "card.json"),
            **{f"train.{k}": f"{v:.6g}" for k, v in metrics.items()}}
    for k, v in tags.items():
        client.set_model_version_tag(name, version, k, v)
    client.update_registered_model(name, description=f"pidc posterior {model_id}: backbone {card.get('backbone')}, "
                                   f"{card.get('size')} training images; ONNX density graph + card + sampling graphs")
    return {"name": name, "version": version, "run_id": run}


@flow(name="export", log_prints=True)
def export_model(model_id: str, params_path: str) -> dict:
    """Export ``models/<model_id>`` into ``registry/<model_id>`` and register it in MLflow."""
    logger = get_run_logger()
    params_file = Path(params_path)
    params = load_params(params_file)
    base = params_file.resolve().parent
    path = base / "models" / model_id / "model.pt"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no trained model {model_id!r} (run `dvc repro train`)")
    model, header = load_npe(path)
    extra = header.get("extra") or {}
    backbone = get_backbone(header["backbone"], **header["backbone_options"])
    card = {
        "model_id": model_id,
        "backbone": header["backbone"],
        "backbone_options": header["backbone_options"],
        "backbone_fingerprint": backbone.fingerprint(),
        "size": extra.get("size"),
        "metrics": extra.get("metrics", {}),
        "data_hash": extra.get("data_hash"),
        "git_commit": git_commit(base),
        "registered_model": registered_name(params, model_id),
    }
    t0 = time.perf_counter()
    folder = export_posterior(model, registry_root(params_file) / model_id, card=card, exporter=params.export.exporter)
    seconds = time.perf_counter() - t0
    entry = register(folder, params, base, model_id)
    logger.info("%s → %s (%s exporter, %.1f s); registered as %s version %s", model_id, folder,
                params.export.exporter, seconds, entry["name"], entry["version"])
    return {"folder": str(folder), "export_seconds": seconds, **entry}


def set_champion(params: Params, base: Path, metrics: dict[str, dict[str, float]]) -> dict[str, Any]:
    """Give the alias ``champion`` to the model with the lowest ``export.champion_metric`` (Task I results ``metrics``
    per model id), tag every registered version with its Task I metrics, and write the champion pointer."""
    metric = params.export.champion_metric
    scored = {m: v[metric] for m, v in metrics.items() if np.isfinite(v.get(metric, np.nan))}
    if not scored:
        raise ValueError(f"no model has a finite {metric}: cannot choose a champion")
    best = min(sorted(scored), key=lambda m: scored[m])
    mlflow.set_tracking_uri(tracking_uri(base))
    client = mlflow.MlflowClient()
    pointer: dict[str, Any] = {"model": best, "metric": metric, "value": scored[best],
                               "registered_model": registered_name(params, best)}
    for model_id, values in metrics.items():
        name = registered_name(params, model_id)
        try:
            versions = client.search_model_versions(f"name = '{name}'", order_by=["version_number DESC"], max_results=1)
        except mlflow.exceptions.MlflowException:
            versions = []
        if not versions:
            continue
        version = versions[0].version
        for k, v in values.items():
            client.set_model_version_tag(name, version, f"task1.{k}", f"{float(v):.6g}")
        if model_id == best:
            client.set_registered_model_alias(name, CHAMPION_ALIAS, version)
            pointer |= {"version": str(version), "uri": f"models:/{name}@{CHAMPION_ALIAS}"}
        else:
            try:
                client.delete_registered_model_alias(name, CHAMPION_ALIAS)
            except mlflow.exceptions.MlflowException:
                pass  # no alias there
    atomic_write_bytes(base / CHAMPION_POINTER, json.dumps(pointer, indent=1).encode())
    return pointer


def load_registered_model(uri: str, base: Path | None = None):
    """Download an MLflow registered model (e.g. ``models:/pidc-cnn-3000@champion``) and open it with the torch-free
    runtime: returns :class:`components.export.runtime.OnnxPosterior` (from the model's extra files)."""
    from components.export.runtime import OnnxPosterior

    if base is not None:
        mlflow.set_tracking_uri(tracking_uri(base))
    dest = Path(tempfile.mkdtemp(prefix="pidc-model-"))
    local = Path(mlflow.artifacts.download_artifacts(artifact_uri=uri, dst_path=str(dest)))
    return OnnxPosterior.load(local / "extra_files")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Export one trained model to registry/ and the MLflow Model Registry.")
    parser.add_argument("--model", required=True, help="model id, e.g. cues-1000 or cues-10000-ensemble")
    parser.add_argument("--params", type=Path, default=PROJECT_ROOT / "params.yaml")
    args = parser.parse_args(argv)
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    export_model(args.model, str(args.params))


if __name__ == "__main__":
    main()
