"""Every MLflow call of the pipeline: runs, params, metrics, artifacts, the Model Registry and its aliases.

The flows never call ``mlflow`` themselves (nor does the CLI, which tracks nothing); they use this module, so that
what is tracked, and how runs and registered models are named, is written in one place:

- one experiment (``train.experiment``); a parent run per grid (:func:`grid_key`: the data and every training
  setting) and a child run per model, tagged ``pidc.model``, found or created across processes (:func:`model_run`);
- each exported model is logged in its training run (ONNX flavor: the whole-density graph, the card and the other
  graphs as extra files) and registered as ``<export.registered_prefix><model id>`` (:func:`register_model`);
- after the evaluation every registered version is tagged with its Task I metrics and the chosen model gets the
  alias ``champion`` (:func:`set_champion_alias`).

The tracking store is ``MLFLOW_TRACKING_URI`` or ``sqlite:///<project>/mlflow.db``.

Used by the ``train``, ``variant``, ``export``, ``export-variant`` and ``evaluate`` stages.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mlflow
import numpy as np
from mlflow.models import ModelSignature
from mlflow.types import Schema, TensorSpec

from components.core.config import Params
from components.core.files import sha256_file

__all__ = [
    "CHAMPION_ALIAS",
    "tracking_uri",
    "git_commit",
    "grid_key",
    "ModelRun",
    "model_run",
    "newest_model_run",
    "registered_name",
    "register_model",
    "log_task1",
    "set_champion_alias",
    "download_registered_model",
]

CHAMPION_ALIAS = "champion"


def tracking_uri(base: Path) -> str:
    """``MLFLOW_TRACKING_URI`` if set, else ``sqlite:///<project>/mlflow.db``."""
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{base / 'mlflow.db'}"


def git_commit(base: Path) -> str:
    """The checkout's commit (``unknown`` outside a git repository)."""
    try:
        r = subprocess.run(["git", "rev-parse", "HEAD"], cwd=base, capture_output=True, text=True, timeout=10)
        return r.stdout.strip() if r.returncode == 0 else "unknown"
    except OSError:
        return "unknown"


def _client(base: Path) -> mlflow.MlflowClient:
    mlflow.set_tracking_uri(tracking_uri(base))
    return mlflow.MlflowClient()


def _experiment_id(client: mlflow.MlflowClient, name: str) -> str:
    experiment = client.get_experiment_by_name(name)
    return experiment.experiment_id if experiment else client.create_experiment(name)


def grid_key(params: Params, data_hash: str) -> str:
    """Identifies a grid: the data and every training setting except the sizes and the variants beside it."""
    settings = params.train.model_dump(exclude={"sizes", "variants"}) | {
        "seed": params.seed,
        "data": data_hash,
        "backbones": list(params.backbones.names),
    }
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:12]


def _find_or_create_run(
    client: mlflow.MlflowClient, experiment_id: str, tags: dict[str, str], name: str, parent: str | None = None
) -> str:
    """The newest unfinished run with these tags (and parent), or a new one."""
    query = " and ".join(f"tags.`{k}` = '{v}'" for k, v in tags.items())
    if parent:
        query += f" and tags.`mlflow.parentRunId` = '{parent}'"
    for run in client.search_runs([experiment_id], query, order_by=["attributes.start_time DESC"], max_results=5):
        if parent is None or run.info.status != "FINISHED":
            return run.info.run_id
    all_tags = dict(tags) | ({"mlflow.parentRunId": parent} if parent else {})
    return client.create_run(experiment_id, tags=all_tags, run_name=name).info.run_id


@dataclass(frozen=True)
class ModelRun:
    """The active MLflow run of one model's training (inside :func:`model_run`)."""

    run_id: str

    def log_params(self, params: Mapping[str, Any]) -> None:
        mlflow.log_params(dict(params))

    def log_epoch(self, record) -> None:
        """Per-epoch losses of :func:`components.posterior.train` (its ``callback``)."""
        mlflow.log_metrics(
            {
                "train_loss": record.train_loss,
                "val_loss": record.val_loss,
                "lr": record.lr,
                "epoch_seconds": record.wall_time,
            },
            step=record.epoch,
        )

    def log_metrics(self, metrics: Mapping[str, float]) -> None:
        mlflow.log_metrics({k: float(v) for k, v in metrics.items()})

    def log_artifacts(self, paths: list[Path]) -> None:
        for p in paths:
            mlflow.log_artifact(str(p))


@contextmanager
def model_run(base: Path, params: Params, model_id: str, data_hash: str, tags: Mapping[str, str]) -> Iterator[ModelRun]:
    """The MLflow run of ``model_id`` under its grid's parent run (both found or created), active inside the block;
    the parent, a container, is marked finished afterwards (whenever none of its models is training)."""
    client = _client(base)
    experiment_id = _experiment_id(client, params.train.experiment)
    key = grid_key(params, data_hash)
    parent = _find_or_create_run(client, experiment_id, {"pidc.grid": key}, f"grid-{key}")
    run_id = _find_or_create_run(
        client, experiment_id, {"pidc.model": model_id, "pidc.grid": key}, model_id, parent=parent
    )
    with mlflow.start_run(run_id=run_id, experiment_id=experiment_id):
        mlflow.set_tags(
            {"pidc.model": model_id, "pidc.grid": key, "git_commit": git_commit(base), "data_hash": data_hash, **tags}
        )
        yield ModelRun(run_id)
    client.set_terminated(parent, "FINISHED")


def newest_model_run(client: mlflow.MlflowClient, experiment_id: str, model_id: str) -> str | None:
    """The id of the newest MLflow run of ``model_id`` (tag ``pidc.model``) in the experiment, or None."""
    runs = client.search_runs(
        [experiment_id], f"tags.`pidc.model` = '{model_id}'", order_by=["attributes.start_time DESC"], max_results=1
    )
    return runs[0].info.run_id if runs else None


def registered_name(params: Params, model_id: str) -> str:
    """The registered model name of ``model_id``: ``export.registered_prefix`` + model id."""
    return f"{params.export.registered_prefix}{model_id}"


def _signature(card: dict[str, Any]) -> ModelSignature:
    shape = tuple(-1 if s == "batch" else int(s) for s in card["input"]["shape"])
    return ModelSignature(
        inputs=Schema(
            [
                TensorSpec(np.dtype(np.float32), shape, "x"),
                TensorSpec(np.dtype(np.float32), (-1, len(card["theta"]["names"])), "theta"),
            ]
        ),
        outputs=Schema([TensorSpec(np.dtype(np.float64), (-1,), "log_prob")]),
    )


def register_model(folder: Path, params: Params, base: Path, model_id: str) -> dict[str, str]:
    """Log ``folder``'s density graph (ONNX flavor; the card and the other graphs as extra files) in the model's MLflow
    run and register it as ``<prefix><model id>``; returns ``{"name", "version", "run_id"}``."""
    import onnx
    import onnxruntime

    card = json.loads((folder / "card.json").read_text())
    client = _client(base)
    experiment_id = _experiment_id(client, params.train.experiment)
    run_id = newest_model_run(client, experiment_id, model_id)
    name = registered_name(params, model_id)
    extra = sorted(str(p) for p in folder.iterdir() if p.is_file())
    requirements = [f"onnx=={onnx.__version__}", f"onnxruntime=={onnxruntime.__version__}", "numpy"]
    metrics = {k: float(v) for k, v in (card.get("metrics") or {}).items() if isinstance(v, (int, float))}
    with mlflow.start_run(
        run_id=run_id,
        experiment_id=None if run_id else experiment_id,
        run_name=None if run_id else f"export-{model_id}",
    ):
        info = mlflow.onnx.log_model(
            onnx.load(str(folder / "density.onnx")),
            name="posterior",
            signature=_signature(card),
            extra_files=extra,
            pip_requirements=requirements,
            onnx_execution_providers=["CPUExecutionProvider"],
            metadata={"pidc_card": card},
            registered_model_name=name,
            await_registration_for=60,
        )
        mlflow.set_tags({"pidc.registered_model": name, "pidc.registry_folder": str(folder.relative_to(base))})
        run = mlflow.active_run().info.run_id
    version = str(info.registered_model_version)
    tags = {
        "pidc.model": model_id,
        "backbone": str(card.get("backbone")),
        "size": str(card.get("size")),
        "data_hash": str(card.get("data_hash")),
        "git_commit": str(card.get("git_commit")),
        "card_sha256": sha256_file(folder / "card.json"),
        **{f"train.{k}": f"{v:.6g}" for k, v in metrics.items()},
    }
    for k, v in tags.items():
        client.set_model_version_tag(name, version, k, v)
    client.update_registered_model(
        name,
        description=f"pidc posterior {model_id}: backbone {card.get('backbone')}, "
        f"{card.get('size')} training images; ONNX density graph + card + sampling graphs",
    )
    return {"name": name, "version": version, "run_id": run}


def log_task1(base: Path, experiment: str, results: list[dict], plots: Path) -> None:
    """Log each model's Task I metrics (``task1.<name>``) and plots (``plots/<model>/*.png``) to its newest run."""
    client = _client(base)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return
    for r in results:
        run_id = newest_model_run(client, exp.experiment_id, r["model"])
        if run_id is None:
            continue
        for k, v in r["metrics"].items():
            client.log_metric(run_id, f"task1.{k}", float(v))
        for f in sorted((plots / r["model"]).glob("*.png")):
            client.log_artifact(run_id, str(f), artifact_path="task1")


def set_champion_alias(
    base: Path, params: Params, metrics: Mapping[str, Mapping[str, float]], champion: str
) -> dict[str, str]:
    """Tag every registered version with its Task I ``metrics`` (per model id), give the alias ``champion`` to
    ``champion``'s newest version and remove it from every other model. Returns ``{"version", "uri"}`` of the
    champion, or ``{}`` when it is not in the Model Registry."""
    client = _client(base)
    found: dict[str, str] = {}
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
        if model_id == champion:
            client.set_registered_model_alias(name, CHAMPION_ALIAS, version)
            found = {"version": str(version), "uri": f"models:/{name}@{CHAMPION_ALIAS}"}
        else:
            try:
                client.delete_registered_model_alias(name, CHAMPION_ALIAS)
            except mlflow.exceptions.MlflowException:
                pass  # no alias there
    return found


def download_registered_model(uri: str, base: Path | None = None) -> Path:
    """Download an MLflow registered model (e.g. ``models:/pidc-cnn-3000@champion``) and return the folder of its
    exported graphs and card (the model's extra files), which :meth:`components.export.runtime.OnnxPosterior.load`
    opens without torch."""
    if base is not None:
        mlflow.set_tracking_uri(tracking_uri(base))
    dest = Path(tempfile.mkdtemp(prefix="pidc-model-"))
    local = Path(mlflow.artifacts.download_artifacts(artifact_uri=uri, dst_path=str(dest)))
    return local / "extra_files"
