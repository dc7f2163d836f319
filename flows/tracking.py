"""Every MLflow call of the pipeline: runs, params, metrics, artifacts, the Model Registry and its aliases.

The flows never call ``mlflow`` themselves (nor does the CLI, which tracks nothing); they use this module, so that
what is tracked, and how runs and registered models are named, is written in one place:

- one experiment (``train.experiment``); a parent run per grid (:func:`grid_key`: the data and every training
  setting) and a child run per model, tagged ``pidc.model``, found or created across processes (:func:`model_run`);
- each exported model is logged in its training run (ONNX flavor: the whole-density graph, the card and the other
  graphs as extra files) and registered as ``<export.registered_prefix><model id>`` (:func:`register_model`);
- after the evaluation each model's run gets its Task I metrics, headline and per parameter (:func:`log_task1`),
  every registered version is tagged with the headline ones, the chosen model gets the alias ``champion`` and the
  runner-up ``challenger`` (:func:`set_champion_alias`);
- each ``task2``/``task3`` run is a run ``<task>-<model>`` nested under the model's training run, its metrics named
  as in ``reports/<task>/metrics.json`` (:func:`log_domain_task`).

The tracking store is ``MLFLOW_TRACKING_URI`` or ``sqlite:///<project>/mlflow.db``.

Used by the ``train``, ``variant``, ``export``, ``export-variant``, ``evaluate``, ``task2`` and ``task3`` stages.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import tempfile
import time
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
    "CHALLENGER_ALIAS",
    "tracking_uri",
    "git_commit",
    "grid_key",
    "ModelRun",
    "model_run",
    "newest_model_run",
    "registered_name",
    "register_model",
    "task1_metric_names",
    "log_task1",
    "set_champion_alias",
    "download_registered_model",
    "flatten_numbers",
    "log_domain_task",
]

CHAMPION_ALIAS = "champion"
CHALLENGER_ALIAS = "challenger"


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


def task1_metric_names(result: Mapping[str, Any]) -> dict[str, float]:
    """The MLflow metrics of one model's Task I ``result``: ``task1.<metric>`` for its headline metrics (booleans as
    0/1) and ``task1.<parameter>.<subset>.<figure>`` for its per-parameter figures (``result["parameters"]``:
    subset → parameter → figure, e.g. ``task1.fog_density.night.median_abs_error``)."""
    values = {f"task1.{k}": float(v) for k, v in result["metrics"].items()}
    for subset, per_parameter in (result.get("parameters") or {}).items():
        for name, figures in per_parameter.items():
            values |= {f"task1.{name}.{subset}.{k}": float(v) for k, v in figures.items()}
    return values


def log_task1(base: Path, experiment: str, results: list[dict], plots: Path) -> None:
    """Log each model's Task I metrics (:func:`task1_metric_names`) and plots (``plots/<model>/*.png``) to its newest
    run."""
    from mlflow.entities import Metric

    client = _client(base)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return
    now = int(time.time() * 1000)
    for r in results:
        run_id = newest_model_run(client, exp.experiment_id, r["model"])
        if run_id is None:
            continue
        rows = [Metric(k, v, now, 0) for k, v in task1_metric_names(r).items()]
        for i in range(0, len(rows), 1000):  # MLflow's batch limit
            client.log_batch(run_id, metrics=rows[i : i + 1000])
        for f in sorted((plots / r["model"]).glob("*.png")):
            client.log_artifact(run_id, str(f), artifact_path="task1")


def _alias(client: mlflow.MlflowClient, name: str, alias: str, version: str | None) -> None:
    """Give ``alias`` to ``version`` of ``name``, or take it away from ``name`` (None)."""
    if version is not None:
        client.set_registered_model_alias(name, alias, version)
        return
    try:
        client.delete_registered_model_alias(name, alias)
    except mlflow.exceptions.MlflowException:
        pass  # no alias there


def set_champion_alias(
    base: Path,
    params: Params,
    metrics: Mapping[str, Mapping[str, float]],
    champion: str,
    challenger: str | None = None,
) -> dict[str, dict[str, str]]:
    """Tag every registered version with its Task I ``metrics`` (per model id), give the alias ``champion`` to
    ``champion``'s newest version and ``challenger`` to ``challenger``'s (the runner-up), and remove both aliases from
    every other model. Returns ``{"champion": {"version", "uri"}, "challenger": {...}}`` for those in the Model
    Registry (a model not registered is left out)."""
    client = _client(base)
    found: dict[str, dict[str, str]] = {}
    for model_id, values in metrics.items():
        name = registered_name(params, model_id)
        try:
            versions = client.search_model_versions(f"name = '{name}'", order_by=["version_number DESC"], max_results=1)
        except mlflow.exceptions.MlflowException:
            versions = []
        if not versions:
            continue
        version = str(versions[0].version)
        for k, v in values.items():
            client.set_model_version_tag(name, version, f"task1.{k}", f"{float(v):.6g}")
        for alias, holder in ((CHAMPION_ALIAS, champion), (CHALLENGER_ALIAS, challenger)):
            _alias(client, name, alias, version if model_id == holder else None)
            if model_id == holder:
                found[alias] = {"version": version, "uri": f"models:/{name}@{alias}"}
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


def flatten_numbers(values: Mapping[str, Any], prefix: str) -> dict[str, float]:
    """The numbers of a nested mapping as ``{"<prefix>.<dotted.key>": value}`` (list items keyed by index; booleans
    as 0/1; strings and None left out): the MLflow names of a report's metrics."""
    out: dict[str, float] = {}
    for key, value in values.items():
        name = f"{prefix}.{key}"
        if isinstance(value, Mapping):
            out |= flatten_numbers(value, name)
        elif isinstance(value, (list, tuple)):
            out |= flatten_numbers({str(i): v for i, v in enumerate(value)}, name)
        elif isinstance(value, (bool, int, float, np.integer, np.floating)) and np.isfinite(float(value)):
            out[name] = float(value)
    return out


def log_domain_task(
    base: Path,
    experiment: str,
    task: str,
    model_id: str,
    metrics: Mapping[str, float],
    series: Mapping[str, Mapping[int, float]],
    artifacts: list[Path],
    tags: Mapping[str, str] | None = None,
) -> str:
    """Log one ``task2``/``task3`` run: a new run ``<task>-<model>`` in ``experiment``, nested under the model's newest
    training run when there is one, tagged ``pidc.task`` and ``pidc.evaluated_model`` (not ``pidc.model``, which names
    training runs); ``metrics`` as they are (e.g. :func:`flatten_numbers`), each ``series`` name at integer steps
    (Task III: the per-η figures at step 100·η), the ``artifacts`` files and extra ``tags``. Returns the run id."""
    from mlflow.entities import Metric

    client = _client(base)
    experiment_id = _experiment_id(client, experiment)
    parent = newest_model_run(client, experiment_id, model_id)
    tags = {"pidc.task": task, "pidc.evaluated_model": model_id, "git_commit": git_commit(base), **(tags or {})}
    if parent:
        tags["mlflow.parentRunId"] = parent
    run_id = client.create_run(experiment_id, tags=tags, run_name=f"{task}-{model_id}").info.run_id
    now = int(time.time() * 1000)
    rows = [Metric(k, float(v), now, 0) for k, v in metrics.items()]
    rows += [Metric(k, float(v), now, int(step)) for k, steps in series.items() for step, v in steps.items()]
    for i in range(0, len(rows), 1000):  # MLflow's batch limit
        client.log_batch(run_id, metrics=rows[i : i + 1000])
    for f in artifacts:
        client.log_artifact(run_id, str(f), artifact_path=task)
    client.set_terminated(run_id, "FINISHED")
    return run_id
