"""Every MLflow call of the pipeline: runs, params, metrics, artifacts, the Model Registry and its aliases.

The flows never call ``mlflow`` themselves (nor does the CLI, which tracks nothing); they use this module, so that
what is tracked, and how runs and registered models are named, is written in one place:

- one experiment (``train.experiment``), tagged as model development (``mlflow.experimentKind``) so that the UI opens
  on its runs; a parent run per grid (:func:`grid_key`: the data and every training setting) and a child run per
  model, tagged ``pidc.model``, found or created across processes (:func:`model_run`); every run gets the data as an
  MLflow dataset input (name, digest = the data's content hash, source = ``data/manifest.json``, split sizes);
- each exported model is logged in its training run (ONNX flavor: the whole-density graph, the card and the other
  graphs as extra files) and registered as a new version of the one registered model ``export.registered_model``
  (``pidc``), the version tagged ``pidc.model`` (:func:`register_model`);
- after the evaluation each model's run gets its Task I metrics, headline and per parameter (:func:`log_task1`),
  every registered version is tagged with the headline ones, the chosen model's version gets the alias ``champion``
  and the runner-up's ``challenger`` (:func:`set_champion_alias`), so ``models:/pidc@champion``
  (:func:`champion_uri`) always loads the current best (:func:`registered_folder`); the grid run gets the cross-model
  figures and a description naming the champion, each model run a description with its own figures
  (:func:`describe_grid`);
- each ``task2``/``task3`` run is a run ``<task>-<model>`` nested under the model's training run, its metrics named
  as in ``reports/<task>/metrics.json`` (:func:`log_domain_task`);
- scheduled monitoring (``flows/monitor.py``) judges the registered versions :func:`monitored_models` names (the
  champion by its alias URI, or every model's newest version) and logs one run per scheduled run, ``monitor-<date>``,
  in an experiment of its own (``monitor.experiment``): tagged with the date, the model ids and their versions, its
  metrics at the date (step = days since 1970-01-01) so that the runs form time series, status FAILED on an alarm
  (:func:`log_monitoring`).

The tracking store is ``MLFLOW_TRACKING_URI`` or ``sqlite:///<project>/mlflow.db``.

Used by the ``train``, ``export``, ``evaluate``, ``task2`` and ``task3`` stages and the
scheduled monitoring (``flows/monitor.py``, no stage).
"""

from __future__ import annotations

import atexit
import hashlib
import json
import os
import shutil
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
    "registered_model",
    "champion_uri",
    "registered_versions",
    "registered_folder",
    "model_source",
    "register_model",
    "task1_metric_names",
    "log_task1",
    "set_champion_alias",
    "describe_grid",
    "download_registered_model",
    "clear_champion_aliases",
    "flatten_numbers",
    "log_domain_task",
    "MonitoredModel",
    "monitored_models",
    "log_monitoring",
]

CHAMPION_ALIAS = "champion"
CHALLENGER_ALIAS = "challenger"
#: the aliases a task's ``model`` setting may name (loaded from the registered model)
ALIASES = (CHAMPION_ALIAS, CHALLENGER_ALIAS)
#: ``mlflow.experimentKind`` of the pidc experiments: the MLflow UI opens them on their runs (not the GenAI views)
EXPERIMENT_KIND = "custom_model_development"
#: the tag MLflow shows as a run's (or an experiment's) description
DESCRIPTION = "mlflow.note.content"


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
    """The id of experiment ``name`` (created when missing), tagged as model development."""
    experiment = client.get_experiment_by_name(name)
    if experiment is None:
        return client.create_experiment(name, tags={"mlflow.experimentKind": EXPERIMENT_KIND})
    if experiment.tags.get("mlflow.experimentKind") != EXPERIMENT_KIND:
        client.set_experiment_tag(experiment.experiment_id, "mlflow.experimentKind", EXPERIMENT_KIND)
    return experiment.experiment_id


def _data_input(base: Path, context: str, extra: Mapping[str, str] | None = None):
    """The data (``<base>/data/manifest.json``) as an MLflow dataset input: name ``weather-images-<H>x<W>``, digest the
    data's content hash, source the manifest, tags the context and the split sizes (``split.<name>``); None when the
    project has no data yet."""
    from mlflow.data.meta_dataset import MetaDataset
    from mlflow.data.sources import LocalArtifactDatasetSource
    from mlflow.entities import DatasetInput, InputTag

    manifest_file = base / "data" / "manifest.json"
    if not manifest_file.is_file():
        return None
    manifest = json.loads(manifest_file.read_text())
    size = manifest.get("resolution", {})
    dataset = MetaDataset(
        LocalArtifactDatasetSource(str(manifest_file.resolve())),
        name=f"weather-images-{size.get('height')}x{size.get('width')}",
        digest=str(manifest["content_hash"])[:36],
    )
    tags = {"mlflow.data.context": context, "renderer": str(manifest.get("renderer"))}
    tags |= {
        f"split.{k}": str(v.get("count", v) if isinstance(v, Mapping) else v) for k, v in manifest["splits"].items()
    }
    tags |= dict(extra or {})
    return DatasetInput(dataset._to_mlflow_entity(), [InputTag(k, v) for k, v in tags.items()])


def _log_data_input(
    client: mlflow.MlflowClient, run_id: str, base: Path, context: str, extra: Mapping[str, str] | None = None
) -> None:
    found = _data_input(base, context, extra)
    if found is not None:
        client.log_inputs(run_id, datasets=[found])


def grid_key(params: Params, data_hash: str) -> str:
    """Identifies a grid: the data and every training setting except the sizes, the variants beside it, the runner and
    the device."""
    settings = params.train.model_dump(exclude={"sizes", "variants", "runner", "device"}) | {
        "seed": params.seed,
        "data": data_hash,
        "backbones": list(params.backbones.names),
    }
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:12]


def _grid_tags(key: str) -> dict[str, str]:
    """The tags that single out the parent run of grid ``key`` (its model runs share ``pidc.grid``)."""
    return {"pidc.grid": key, "mlflow.runName": f"grid-{key}"}


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


def _close_abandoned(client: mlflow.MlflowClient, experiment_id: str, tags: Mapping[str, str]) -> list[str]:
    """Mark KILLED the runs with these tags still RUNNING: a task's or a monitoring's run is created, logged and ended
    in one go, so one left RUNNING was cut off by a kill, with part of its figures; the new run replaces it. Returns
    their ids."""
    query = " and ".join(f"tags.`{k}` = '{v}'" for k, v in tags.items()) + " and attributes.status = 'RUNNING'"
    closed = [r.info.run_id for r in client.search_runs([experiment_id], query)]
    for run_id in closed:
        client.set_terminated(run_id, "KILLED")
    return closed


@dataclass(frozen=True)
class ModelRun:
    """The active MLflow run of one model's training (inside :func:`model_run`)."""

    run_id: str

    def log_params(self, params: Mapping[str, Any]) -> None:
        mlflow.log_params(dict(params))

    @staticmethod
    def _epoch_metrics(record) -> dict[str, float]:
        return {
            "train_loss": record.train_loss,
            "val_loss": record.val_loss,
            "lr": record.lr,
            "epoch_seconds": record.wall_time,
        }

    def log_epoch(self, record) -> None:
        """Per-epoch losses of :func:`components.posterior.train` (its ``callback``) at the step of the epoch."""
        mlflow.log_metrics(self._epoch_metrics(record), step=record.epoch)

    def log_history(self, records) -> int:
        """Log the epochs of ``records`` (a training's whole history) that the run does not hold yet: those trained
        before a kill whose step the callback did not reach, or all of them when the training resumed from a finished
        checkpoint into a new run. Returns how many were logged."""
        from mlflow.entities import Metric

        client = mlflow.MlflowClient()
        logged = {m.step for m in client.get_metric_history(self.run_id, "val_loss")}
        missing = [r for r in records if int(r.epoch) not in logged]
        now = int(time.time() * 1000)
        rows = [Metric(k, float(v), now, int(r.epoch)) for r in missing for k, v in self._epoch_metrics(r).items()]
        for i in range(0, len(rows), 1000):  # MLflow's batch limit
            client.log_batch(self.run_id, metrics=rows[i : i + 1000])
        return len(missing)

    def log_metrics(self, metrics: Mapping[str, float]) -> None:
        mlflow.log_metrics({k: float(v) for k, v in metrics.items()})

    def log_artifacts(self, paths: list[Path]) -> None:
        for p in paths:
            mlflow.log_artifact(str(p))


def grid_run(base: Path, params: Params, data_hash: str) -> str:
    """The id of the grid's parent run (found, or created, with the training data as its dataset input): the train
    stage opens it before its workers start, so that models trained in parallel find one parent and one dataset
    instead of each creating its own."""
    client = _client(base)
    experiment_id = _experiment_id(client, params.train.experiment)
    key = grid_key(params, data_hash)
    # the grid run by its name too: its model runs carry the tag pidc.grid as well
    parent = _find_or_create_run(client, experiment_id, _grid_tags(key), f"grid-{key}")
    # the dataset entity is created here, once: models logging it at once from parallel workers would race to insert it
    _log_data_input(client, parent, base, "training")
    return parent


def _training_run(
    client: mlflow.MlflowClient, experiment_id: str, model_id: str, grid: str, run_key: str, parent: str
) -> str:
    """The run of this training of ``model_id``: its run under ``parent`` with the same ``pidc.run_key`` (the
    checkpoint's key: settings, data, features and code), finished or not — a killed training resumes its run, and a
    re-run that finds the training finished adds to the run that holds its curves instead of starting a second one
    without them — or a new run. Runs of ``model_id`` under ``parent`` with another key left RUNNING (a killed
    training whose settings or code have changed since) are marked KILLED: their curves belong to no model."""
    query = (
        f"tags.`pidc.model` = '{model_id}' and tags.`pidc.grid` = '{grid}' and tags.`mlflow.parentRunId` = '{parent}'"
    )
    found = None
    for run in client.search_runs([experiment_id], query, order_by=["attributes.start_time DESC"]):
        if run.data.tags.get("pidc.run_key") == run_key:
            found = found or run.info.run_id
        elif run.info.status == "RUNNING":
            client.set_terminated(run.info.run_id, "KILLED")
    if found:
        return found
    tags = {"pidc.model": model_id, "pidc.grid": grid, "pidc.run_key": run_key, "mlflow.parentRunId": parent}
    return client.create_run(experiment_id, tags=tags, run_name=model_id).info.run_id


@contextmanager
def model_run(
    base: Path, params: Params, model_id: str, data_hash: str, tags: Mapping[str, str], run_key: str
) -> Iterator[ModelRun]:
    """The MLflow run of ``model_id``'s training ``run_key`` under its grid's parent run (both found or created:
    :func:`_training_run`), active inside the block; the parent, a container, is marked finished afterwards (whenever
    none of its models is training)."""
    client = _client(base)
    experiment_id = _experiment_id(client, params.train.experiment)
    key = grid_key(params, data_hash)
    # found, not re-logged: the train stage's flow created it with its dataset input (grid_run) before any worker
    parent = _find_or_create_run(client, experiment_id, _grid_tags(key), f"grid-{key}")
    run_id = _training_run(client, experiment_id, model_id, key, run_key, parent)
    _log_data_input(client, run_id, base, "training", {"images_used": str(tags.get("pidc.size", ""))})
    with mlflow.start_run(run_id=run_id, experiment_id=experiment_id):
        mlflow.set_tags(
            {
                "pidc.model": model_id,
                "pidc.grid": key,
                "pidc.run_key": run_key,
                "git_commit": git_commit(base),
                "data_hash": data_hash,
                **tags,
            }
        )
        yield ModelRun(run_id)
    client.set_terminated(parent, "FINISHED")


def newest_model_run(client: mlflow.MlflowClient, experiment_id: str, model_id: str) -> str | None:
    """The id of the MLflow run of ``model_id`` (tag ``pidc.model``) in the experiment that ended last (MLflow orders
    runs not ended after those that did; among those, the newest), or None: the run of the model's latest training,
    also when a re-run reopened an older run of the same training (:func:`model_run`), whose start time is older than
    another training's."""
    runs = client.search_runs(
        [experiment_id],
        f"tags.`pidc.model` = '{model_id}'",
        order_by=["attributes.end_time DESC", "attributes.start_time DESC"],
        max_results=1,
    )
    return runs[0].info.run_id if runs else None


def registered_model(params: Params) -> str:
    """The one registered model whose versions are the exported models: ``export.registered_model``."""
    return params.export.registered_model


def champion_uri(params: Params, alias: str = CHAMPION_ALIAS) -> str:
    """``models:/<registered model>@<alias>``: the URI that always loads the current champion (or challenger)."""
    return f"models:/{registered_model(params)}@{alias}"


def _all_versions(client: mlflow.MlflowClient, name: str) -> list[Any]:
    """Every version of registered model ``name`` (none when it is not registered)."""
    try:
        return list(client.search_model_versions(f"name = '{name}'"))
    except mlflow.exceptions.MlflowException:
        return []


def _versions(client: mlflow.MlflowClient, name: str) -> dict[str, Any]:
    """The newest version of ``name`` per model id (version tag ``pidc.model``)."""
    newest: dict[str, Any] = {}
    for v in _all_versions(client, name):
        model_id = v.tags.get("pidc.model")
        if model_id and (model_id not in newest or int(v.version) > int(newest[model_id].version)):
            newest[model_id] = v
    return newest


def exported_version(client: mlflow.MlflowClient, name: str, model_id: str, folder: Path) -> Any | None:
    """The newest version of ``name`` that registered the export in ``folder`` (``registry/<model id>``): tagged
    ``pidc.model`` = ``model_id`` and ``card_sha256`` = the SHA-256 of its ``card.json`` (which records the sha256 of
    every graph), or None. Not "the newest version of the model": a re-export by other code, or a registry folder
    that DVC restored from its cache without running the export, would make that another export than the one here."""
    sha = sha256_file(folder / "card.json")
    found = [
        v
        for v in _all_versions(client, name)
        if v.tags.get("pidc.model") == model_id and v.tags.get("card_sha256") == sha
    ]
    return max(found, key=lambda v: int(v.version)) if found else None


def registered_versions(base: Path, params: Params) -> dict[str, str]:
    """``{model id: newest version}`` of the registered model (every exported model, with the version numbers as
    strings)."""
    return {m: str(v.version) for m, v in _versions(_client(base), registered_model(params)).items()}


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
    run and register it as a new version of ``export.registered_model`` (or reuse the version of the same card's SHA-256);
    returns ``{"name", "version", "run_id"}``."""
    import onnx
    import onnxruntime

    card = json.loads((folder / "card.json").read_text())
    client = _client(base)
    experiment_id = _experiment_id(client, params.train.experiment)
    name = registered_model(params)
    same = exported_version(client, name, model_id, folder)
    if same is not None:  # this very export is registered (a re-run of the stage, a kill after its registration)
        return {"name": name, "version": str(same.version), "run_id": same.run_id, "reused": True}
    run_id = newest_model_run(client, experiment_id, model_id)
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
        version = str(info.registered_model_version)
        mlflow.set_tags(
            {
                "pidc.registered_model": name,
                "pidc.registered_version": version,
                "pidc.registry_folder": str(folder.relative_to(base)),
            }
        )
        run = mlflow.active_run().info.run_id
    tags = {
        "backbone": str(card.get("backbone")),
        "size": str(card.get("size")),
        "data_hash": str(card.get("data_hash")),
        "git_commit": str(card.get("git_commit")),
        "card_sha256": sha256_file(folder / "card.json"),
        **{f"train.{k}": f"{v:.6g}" for k, v in metrics.items()},
        # last: a version counts as the model's (``_versions``, :func:`exported_version`) only once it is complete
        "pidc.model": model_id,
    }
    for k, v in tags.items():
        client.set_model_version_tag(name, version, k, v)
    client.update_model_version(
        name,
        version,
        description=f"{model_id}: backbone {card.get('backbone')}, {card.get('size')} training images "
        f"(data {str(card.get('data_hash'))[:12]}, commit {str(card.get('git_commit'))[:12]})",
    )
    client.update_registered_model(
        name,
        description="pidc posteriors q(θ | image) of the six weather parameters: one version per exported model (tag "
        "`pidc.model`), ONNX density graph + card + sampling graphs. `@champion` is the sharpest model calibrated "
        "within noise (reports/task1/champion.json says why), `@challenger` the runner-up.",
    )
    return {"name": name, "version": version, "run_id": run, "reused": False}


def task1_metric_names(result: Mapping[str, Any]) -> dict[str, float]:
    """The MLflow metrics of one model's Task I ``result``: ``task1.<metric>`` for its headline metrics (booleans as
    0/1) and ``task1.<parameter>.<subset>.<figure>`` for its per-parameter figures (``result["parameters"]``:
    subset → parameter → figure, e.g. ``task1.fog_density.night.median_abs_error``), to 6 significant digits (the UI
    shows them as they are stored)."""
    values = {f"task1.{k}": _digits(v) for k, v in result["metrics"].items()}
    for subset, per_parameter in (result.get("parameters") or {}).items():
        for name, figures in per_parameter.items():
            values |= {f"task1.{name}.{subset}.{k}": _digits(v) for k, v in figures.items()}
    return values


def _digits(value: Any) -> float:
    """``value`` as a float of 6 significant digits (0.029000000000000026 → 0.029)."""
    return float(f"{float(value):.6g}")


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


def clear_champion_aliases(base: Path, params: Params) -> None:
    """Take the aliases ``champion`` and ``challenger`` away from the registered model (when no model qualifies as
    champion): ``models:/pidc@champion`` then fails with MLflow's "alias not found" instead of loading the last
    champion, which the stages, the command line and the monitoring would keep judging as the current one."""
    client = _client(base)
    name = registered_model(params)
    try:
        client.get_registered_model(name)
    except mlflow.exceptions.MlflowException:
        return  # nothing registered, no alias
    for alias in (CHAMPION_ALIAS, CHALLENGER_ALIAS):
        _alias(client, name, alias, None)


def set_champion_alias(
    base: Path,
    params: Params,
    metrics: Mapping[str, Mapping[str, float]],
    champion: str,
    challenger: str | None = None,
    registry: Path | None = None,
) -> dict[str, dict[str, str]]:
    """Tag the registered version of every model in ``metrics`` with its Task I figures (``task1.<metric>``), give
    the alias ``champion`` to ``champion``'s version and ``challenger`` to ``challenger``'s (the runner-up; the alias
    is removed when there is none or it is not registered), and tag the models' newest runs ``pidc.role`` (champion /
    challenger / candidate). Returns ``{"champion": {"version", "uri"}, "challenger": {...}}`` for those in the Model
    Registry (a model not registered is left out).

    A model's version is the one that registered the export evaluated, ``registry/<model id>`` (``registry``; default
    ``<base>/registry``), found by its card's SHA-256 (:func:`exported_version`), not the newest version of the model
    id; a model whose folder is there but whose export is not registered is an error naming it (run the export)."""
    client = _client(base)
    name = registered_model(params)
    registry = base / "registry" if registry is None else registry
    versions: dict[str, Any] = {}
    unregistered = []
    for model_id in sorted(set(metrics) | {champion} | ({challenger} if challenger else set())):
        if not (registry / model_id / "card.json").is_file():
            continue
        version = exported_version(client, name, model_id, registry / model_id)
        if version is None:
            unregistered.append(model_id)
        else:
            versions[model_id] = version
    if unregistered:
        raise LookupError(
            f"{', '.join(f'{registry / m}' for m in unregistered)}: the export there is not registered as a version of "
            f"{name!r} in the MLflow store {tracking_uri(base)} (no version with its card's sha256); re-run the "
            "export (`dvc repro -f -s export`)"
        )
    found: dict[str, dict[str, str]] = {}
    for model_id, values in metrics.items():
        if model_id in versions:
            for k, v in values.items():
                client.set_model_version_tag(name, versions[model_id].version, f"task1.{k}", f"{float(v):.6g}")
    for alias, holder in ((CHAMPION_ALIAS, champion), (CHALLENGER_ALIAS, challenger)):
        if holder in versions:
            version = str(versions[holder].version)
            client.set_registered_model_alias(name, alias, version)
            found[alias] = {"version": version, "uri": f"models:/{name}@{alias}"}
        elif _all_versions(client, name):
            _alias(client, name, alias, None)
    experiment = client.get_experiment_by_name(params.train.experiment)
    if experiment is not None:
        for model_id in metrics:
            run_id = newest_model_run(client, experiment.experiment_id, model_id)
            if run_id:
                role = {champion: CHAMPION_ALIAS, challenger: CHALLENGER_ALIAS}.get(model_id, "candidate")
                client.set_tag(run_id, "pidc.role", role)
    return found


def _headline(values: Mapping[str, float]) -> str:
    """One line of a model's Task I headline figures."""
    return (
        f"information gain {values['info_gain_nats']:.2f} nats, calibration error {values['calibration_error']:.3f} "
        f"(band {values['calibration_band']:.3f}: {'within' if values['within_band'] else 'outside'}), "
        f"test NLL {values['test_nll']:.2f} nats"
    )


def describe_grid(
    base: Path,
    params: Params,
    data_hash: str,
    metrics: Mapping[str, Mapping[str, float]],
    pointer: Mapping[str, Any] | None,
    table: str,
    files: list[Path],
) -> str | None:
    """After the evaluation: the grid's parent run gets the cross-model ``files`` (artifacts under ``task1/``), the
    champion's headline metrics (``champion.<metric>``) and a description naming the champion (``pointer``:
    ``reports/task1/champion.json``, None when no model qualified) above the results ``table`` (markdown); each model
    run a description with its own figures and role; the experiment a description naming the champion. Returns the
    parent run id (None without an MLflow grid run)."""
    client = _client(base)
    experiment = client.get_experiment_by_name(params.train.experiment)
    if experiment is None:
        return None
    key = grid_key(params, data_hash)
    runs = client.search_runs(
        [experiment.experiment_id],
        " and ".join(f"tags.`{k}` = '{v}'" for k, v in _grid_tags(key).items()),
        order_by=["attributes.start_time DESC"],
        max_results=1,
    )
    champion = pointer["model"] if pointer else None
    challenger = (pointer.get("runner_up") or {}).get("model") if pointer else None
    for model_id, values in metrics.items():
        run_id = newest_model_run(client, experiment.experiment_id, model_id)
        if run_id is None:
            continue
        role = {champion: "Champion", challenger: "Challenger (runner-up)"}.get(model_id, "Candidate")
        client.set_tag(  # plain text first: the runs table shows the description's first ~50 characters
            run_id,
            DESCRIPTION,
            f"{role}: {model_id} — Task I on the test split: {_headline(values)}. "
            f"Per parameter: metrics `task1.<parameter>.<all|day|night>.<figure>`; plots under artifacts `task1/`.",
        )
    if not runs:
        return None
    parent = runs[0].info.run_id
    if pointer:
        text = (
            f"Champion: {champion} — {_headline(metrics[champion])} (`{champion_uri(params)}`; rule "
            f"{pointer.get('rule')}: {pointer.get('reason')})."
        )
        if challenger:
            text += f"\n\nChallenger (`{champion_uri(params, CHALLENGER_ALIAS)}`): {challenger}: "
            text += f"{_headline(metrics[challenger])}."
        client.log_batch(
            parent,
            metrics=[
                mlflow.entities.Metric(f"champion.{k}", _digits(v), int(time.time() * 1000), 0)
                for k, v in metrics[champion].items()
            ],
        )
        client.set_tag(parent, "pidc.champion", champion)
    else:
        text = "No champion: no model is calibrated within its band or below the ceiling."
    client.set_tag(parent, DESCRIPTION, f"{text}\n\n{table}")
    # the experiment's description: a banner above its runs table and a column of the experiments list
    client.set_experiment_tag(
        experiment.experiment_id,
        DESCRIPTION,
        f"{text}\n\nOne run per model under the grid run `grid-{key}` (expand it); figures of all models in its "
        'artifacts `task1/`. docs/monitoring.md: "Compare the models in MLflow".',
    )
    for f in files:
        client.log_artifact(parent, str(f), artifact_path="task1")
    return parent


def model_source(params: Params, model: str) -> str:
    """Where a task's ``model`` setting loads from: the registered model's alias URI (``champion``/``challenger``), a
    ``models:/`` URI, or ``registry/<model id>``."""
    if model in (CHAMPION_ALIAS, CHALLENGER_ALIAS):
        return champion_uri(params, model)
    return model if model.startswith("models:/") else f"registry/{model}"


def registered_folder(base: Path, params: Params, model: str, pointer: Mapping[str, Any] | None) -> Path | None:
    """The exported folder of a task's ``model`` setting when it lives in the MLflow Model Registry: ``champion`` /
    ``challenger`` download through the registered model's alias (``models:/pidc@champion``), which must be the model
    the champion ``pointer`` (``reports/task1/champion.json``) names, else an error; a ``models:/…`` URI downloads as
    it is. None for anything else (a model id or folder of the local ``registry/``)."""
    if model.startswith("models:/"):
        return download_registered_model(model, base)
    if model not in (CHAMPION_ALIAS, CHALLENGER_ALIAS):
        return None
    if pointer is None:
        raise ValueError(f"model {model!r}: the champion pointer (reports/task1/champion.json) is needed to check it")
    expected = pointer["model"] if model == CHAMPION_ALIAS else (pointer.get("runner_up") or {}).get("model")
    uri = champion_uri(params, model)
    try:
        folder = download_registered_model(uri, base)
    except mlflow.exceptions.MlflowException as e:
        raise FileNotFoundError(
            f"{uri}: not in the MLflow Model Registry at {tracking_uri(base)} ({e.message}); run the evaluation "
            "(`dvc repro evaluate`)"
        ) from None
    found = json.loads((folder / "card.json").read_text()).get("model_id")
    if found != expected:
        raise ValueError(
            f"{uri} is {found!r} but reports/task1/champion.json names {expected!r}: the MLflow Model Registry and the "
            "evaluation disagree; re-run the evaluation (`dvc repro evaluate`)"
        )
    # the same model id, but is it the version the evaluation chose (not a later export of it)?
    named = pointer.get("version") if model == CHAMPION_ALIAS else (pointer.get("runner_up") or {}).get("version")
    held = str(_client(base).get_model_version_by_alias(registered_model(params), model).version)
    if named is not None and str(named) != held:
        raise ValueError(
            f"{uri} is version {held} of {expected!r} but reports/task1/champion.json names version {named}: the "
            "MLflow Model Registry and the evaluation disagree; re-run the evaluation (`dvc repro evaluate`)"
        )
    return folder


def download_registered_model(uri: str, base: Path | None = None) -> Path:
    """Download an MLflow registered model (e.g. ``models:/pidc-cnn-3000@champion``) and return the folder of its
    exported graphs and card (the model's extra files), which :meth:`components.export.runtime.OnnxPosterior.load`
    opens without torch. The download is a temporary folder, removed when the process exits."""
    if base is not None:
        mlflow.set_tracking_uri(tracking_uri(base))
    dest = Path(tempfile.mkdtemp(prefix="pidc-model-"))
    # removed when the process ends (a stage, a monitoring run): every run downloaded anew and left ~3 MB behind
    atexit.register(shutil.rmtree, dest, ignore_errors=True)
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
            out[name] = _digits(value)
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
    description: str | None = None,
) -> str:
    """Log one ``task2``/``task3`` run: a new run ``<task>-<model>`` in ``experiment``, nested under the model's newest
    training run when there is one (the champion's, when it evaluates the champion), tagged ``pidc.task`` and
    ``pidc.evaluated_model`` (not ``pidc.model``, which names training runs); ``metrics`` as they are (e.g.
    :func:`flatten_numbers`), each ``series`` name at integer steps (Task III: the per-η figures at step 100·η), the
    ``artifacts`` files, extra ``tags``, the data as a dataset input (context ``evaluation``) and a ``description``. A
    run of the same task and model left RUNNING by a kill is marked KILLED first. Returns the run id."""
    from mlflow.entities import Metric

    client = _client(base)
    experiment_id = _experiment_id(client, experiment)
    parent = newest_model_run(client, experiment_id, model_id)
    _close_abandoned(client, experiment_id, {"pidc.task": task, "pidc.evaluated_model": model_id})
    tags = {"pidc.task": task, "pidc.evaluated_model": model_id, "git_commit": git_commit(base), **(tags or {})}
    if parent:
        tags["mlflow.parentRunId"] = parent
    if description:
        tags[DESCRIPTION] = description
    run_id = client.create_run(experiment_id, tags=tags, run_name=f"{task}-{model_id}").info.run_id
    _log_data_input(client, run_id, base, "evaluation")
    now = int(time.time() * 1000)
    rows = [Metric(k, float(v), now, 0) for k, v in metrics.items()]
    rows += [Metric(k, float(v), now, int(step)) for k, steps in series.items() for step, v in steps.items()]
    for i in range(0, len(rows), 1000):  # MLflow's batch limit
        client.log_batch(run_id, metrics=rows[i : i + 1000])
    for f in artifacts:
        client.log_artifact(run_id, str(f), artifact_path=task)
    client.set_terminated(run_id, "FINISHED")
    return run_id


# --- scheduled monitoring (flows/monitor.py) ---------------------------------------------------------------------


@dataclass(frozen=True)
class MonitoredModel:
    """A registered model version the monitoring judges: its model id (version tag ``pidc.model``), version, the URI
    it is loaded by and the aliases it holds."""

    model: str
    version: str
    uri: str
    aliases: tuple[str, ...]


def monitored_models(base: Path, params: Params, which: str) -> list[MonitoredModel]:
    """The registered versions to monitor: ``champion`` — the version holding the alias, loaded by its alias URI
    ``models:/<export.registered_model>@champion`` (:func:`champion_uri`); ``all`` — the newest version of every model
    id, loaded as ``models:/<name>/<version>``. ``FileNotFoundError`` naming the URI and the store when there is none
    (run the evaluation: ``dvc repro evaluate``)."""
    client = _client(base)
    name = registered_model(params)
    try:
        aliases = dict(client.get_registered_model(name).aliases or {})
    except mlflow.exceptions.MlflowException:
        raise FileNotFoundError(
            f"models:/{name}: no registered model {name!r} in the MLflow store {tracking_uri(base)}; export and "
            "evaluate the models first (`dvc repro`)"
        ) from None
    held: dict[str, list[str]] = {}
    for alias, version in aliases.items():
        held.setdefault(str(version), []).append(alias)
    if which == CHAMPION_ALIAS:
        uri = champion_uri(params)
        if CHAMPION_ALIAS not in aliases:
            raise FileNotFoundError(
                f"{uri}: registered model {name!r} has no alias {CHAMPION_ALIAS!r} in the MLflow store "
                f"{tracking_uri(base)}; run the evaluation (`dvc repro evaluate`)"
            )
        version = client.get_model_version_by_alias(name, CHAMPION_ALIAS)
        model_id = version.tags.get("pidc.model")
        if not model_id:
            raise ValueError(f"{uri}: version {version.version} of {name!r} has no tag pidc.model (re-export it)")
        return [MonitoredModel(model_id, str(version.version), uri, tuple(sorted(held.get(str(version.version), []))))]
    if which != "all":
        raise ValueError(f"models: expected 'champion' or 'all', got {which!r}")
    found = [
        MonitoredModel(m, str(v.version), f"models:/{name}/{v.version}", tuple(sorted(held.get(str(v.version), []))))
        for m, v in sorted(_versions(client, name).items())
    ]
    if not found:
        raise FileNotFoundError(f"models:/{name}: no version tagged pidc.model in {tracking_uri(base)} (`dvc repro`)")
    return found


def log_monitoring(
    base: Path,
    experiment: str,
    run_name: str,
    day: Any,
    models: list[MonitoredModel],
    metrics: Mapping[str, float],
    artifacts: list[Path],
    alarms: list[str],
    tags: Mapping[str, str] | None = None,
) -> str:
    """Log one monitoring run: a new run ``run_name`` in ``experiment`` (an experiment of its own, created tagged as
    model development), tagged ``pidc.task`` = monitor, ``pidc.date`` (``day``, a date), ``pidc.models`` (``id@version``
    of every model judged), ``pidc.version.<model id>`` = version, ``pidc.model`` and ``pidc.registered_version`` (the
    champion's, else the first model's), ``pidc.alarms`` (their count), the commit and ``tags``; ``metrics`` at the
    step ``day`` − 1970-01-01 in days and the timestamp of ``day``'s midnight (UTC), so that the runs of the experiment
    line up as time series; the ``artifacts`` under ``monitoring/``; a description listing the ``alarms``; status
    FAILED when there is an alarm, else FINISHED. A run of the same name and date left RUNNING by a kill is marked
    KILLED first. Returns the run id."""
    import datetime as dt

    from mlflow.entities import Metric

    client = _client(base)
    experiment_id = _experiment_id(client, experiment)
    lead = next((m for m in models if CHAMPION_ALIAS in m.aliases), models[0])
    all_tags = {
        "pidc.task": "monitor",
        "pidc.date": day.isoformat(),
        "pidc.models": ", ".join(f"{m.model}@{m.version}" for m in models),
        "pidc.model": lead.model,
        "pidc.registered_version": lead.version,
        "pidc.alarms": str(len(alarms)),
        "git_commit": git_commit(base),
        **{f"pidc.version.{m.model}": m.version for m in models},
        **dict(tags or {}),
    }
    all_tags[DESCRIPTION] = f"Monitoring of {all_tags['pidc.models']} on {day.isoformat()}: " + (
        "**alarms**:\n\n" + "\n".join(f"- {a}" for a in alarms) if alarms else "no alarm."
    )
    _close_abandoned(
        client, experiment_id, {"pidc.task": "monitor", "pidc.date": day.isoformat(), "mlflow.runName": run_name}
    )
    run_id = client.create_run(experiment_id, tags=all_tags, run_name=run_name).info.run_id
    midnight = dt.datetime(day.year, day.month, day.day, tzinfo=dt.UTC)
    stamp, step = int(midnight.timestamp() * 1000), (day - dt.date(1970, 1, 1)).days
    rows = [Metric(k, float(v), stamp, step) for k, v in metrics.items()]
    for i in range(0, len(rows), 1000):  # MLflow's batch limit
        client.log_batch(run_id, metrics=rows[i : i + 1000])
    for f in artifacts:
        client.log_artifact(run_id, str(f), artifact_path="monitoring")
    client.set_terminated(run_id, "FAILED" if alarms else "FINISHED")
    return run_id
