"""The ``export`` stage: every trained model of the grid and its variants → ``registry/<model>/`` and the MLflow Model
Registry.

``python -m flows.export [--model ID ...] [--params params.yaml]``. Each model's graphs are exported to ONNX
(:func:`components.export.onnx.export_posterior`, checked against torch in onnxruntime) with a model card (backbone,
training size, θ order, units and bijection, input spec, training metrics, data hash, git commit, opset,
onnxruntime version), then registered (:func:`flows.tracking.register_model`). The champion alias comes after the
evaluation (the ``evaluate`` stage). The exports run ``export.runner.workers`` at a time (the largest models first;
torch's ONNX exporter is single-threaded Python), the registrations one after the other in the flow, in the order of
``params.model_ids()``: the registry's version numbers are assigned by one writer, the same on every run. An export
already registered (a version with the same card's SHA-256: the same graphs, metrics and commit) is not registered
again: a re-run of the stage, or one after a kill, adds only the versions it lacks.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from prefect import flow, task
from prefect.context import FlowRunContext
from prefect.task_runners import ProcessPoolTaskRunner
from tqdm.auto import tqdm

from components.core.hardware import threads_per_worker, usable_cores
from components.export.onnx import export_posterior
from components.features.backbones import get_backbone
from components.posterior.store import load_npe
from flows import tracking
from flows.stage import open_stage, parse_stage_args, share_api_with_workers, task_runner, use_all_cores


@task(name="export-model")
def export_model(model_id: str, params_path: str) -> dict:
    """Export ``models/<model_id>`` into ``registry/<model_id>`` and register it in MLflow."""
    out = write_onnx.fn(model_id, params_path)
    return {**out, **register(model_id, params_path, out)}


def register(model_id: str, params_path: str, exported: dict) -> dict:
    """Register the exported folder of ``model_id`` (what :func:`write_onnx` returns) in MLflow; its registry entry."""
    stage = open_stage(params_path)
    entry = tracking.register_model(Path(exported["folder"]), stage.params, stage.paths.root, model_id)
    stage.logger.info(
        "%s → %s (%s exporter, %.1f s); %s as %s version %s",
        model_id,
        exported["folder"],
        stage.params.export.exporter,
        exported["export_seconds"],
        "already registered (the same card)" if entry["reused"] else "registered",
        entry["name"],
        entry["version"],
    )
    return entry


@task(name="write-onnx")
def write_onnx(model_id: str, params_path: str, threads: int | None = None) -> dict:
    """Export ``models/<model_id>`` into ``registry/<model_id>`` (``threads`` torch threads; None: torch's default):
    ``{"folder", "export_seconds"}``."""
    if threads:
        import torch

        torch.set_num_threads(threads)
    stage = open_stage(params_path)
    params, paths = stage.params, stage.paths
    path = paths.models / model_id / "model.pt"
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
        # the images the model learned from: consumers resize others to the backbone's input (pidc's CLI says so)
        "training_renders": {
            "simulator": params.simulator.backend,
            "height": params.simulator.height,
            "width": params.simulator.width,
            "render_sizes": None if params.simulator.render_sizes is None else list(params.simulator.render_sizes),
            **_recorded(paths.data),
        },
        "metrics": extra.get("metrics", {}),
        "data_hash": extra.get("data_hash"),
        "git_commit": tracking.git_commit(paths.root),
        "registered_model": tracking.registered_model(params),
    }
    t0 = time.perf_counter()
    folder = export_posterior(model, paths.registry / model_id, card=card, exporter=params.export.exporter)
    return {"folder": str(folder), "export_seconds": time.perf_counter() - t0}


def _recorded(data: Path) -> dict:
    """A recorded dataset's images as the card records them (``recorded``: the images imported, how many were
    area-resized and their source sizes, from the data manifest's ``source``); nothing for rendered data. The
    manifest is a DVC dep of the stage; a missing or unreadable one is an error naming it."""
    path = data / "manifest.json"
    try:
        source = json.loads(path.read_text()).get("source")
    except (OSError, ValueError) as e:
        raise RuntimeError(
            f"{path}: cannot read the data manifest ({e}); run the generate stage (`dvc repro`)"
        ) from None
    if not isinstance(source, dict) or source.get("kind") != "recorded":
        return {}
    keys = ("folders", "used", "resized", "source_sizes", "splits_from")
    return {"recorded": {k: source.get(k) for k in keys}}


@flow(name="export", log_prints=True)
def export_all(params_path: str, models: list[str] | None = None) -> dict[str, dict]:
    """Export ``models`` (default: the grid and its variants, ``params.model_ids()``), ``export.runner.workers`` at a
    time in worker processes (one after the other when the flow runs on another task runner, e.g. called as a
    function), and register them in that order; model id → what :func:`export_model` returns. Every model must be
    trained: the missing ones are named before any export."""
    stage = open_stage(params_path)
    params, paths = stage.params, stage.paths
    ids = list(models) if models else params.model_ids()
    for m in ids:
        params.model_cell(m)  # an unknown id fails here, naming the known ones
    missing = [m for m in ids if not (paths.models / m / "model.pt").is_file()]
    if missing:
        raise FileNotFoundError(f"no trained model for {', '.join(missing)} in {paths.models} (run `dvc repro train`)")
    if isinstance(FlowRunContext.get().task_runner, ProcessPoolTaskRunner):
        workers = min(params.export.runner.workers, len(ids))
        threads = threads_per_worker(usable_cores(), workers)
        share_api_with_workers()
        largest_first = sorted(ids, key=lambda m: params.model_cell(m)[1], reverse=True)
        futures = {m: write_onnx.submit(m, params_path, threads) for m in largest_first}
        exported = lambda m: futures[m].result()  # noqa: E731
    else:
        # the flow called as a function (Prefect's default runner: threads): torch's ONNX exporter keeps global state,
        # so two exports must not share a process; one after the other here
        exported = lambda m: write_onnx(m, params_path)  # noqa: E731
    results = {}
    for m in tqdm(ids, desc="export models", unit="model"):  # the registry's versions in the grid's order
        out = exported(m)
        results[m] = {**out, **register(m, params_path, out)}
    return results


def main(argv: list[str] | None = None) -> None:
    args, params = parse_stage_args(
        "Export the trained models to registry/ and the MLflow Model Registry (the export stage).",
        argv,
        [
            (
                ["--model"],
                {
                    "action": "append",
                    "help": "a model id, e.g. cues-5000 or cues-50000-ensemble (repeatable; default: all)",
                },
            )
        ],
    )
    use_all_cores()
    export_all.with_options(task_runner=task_runner(params.export.runner))(str(args.params), args.model)


if __name__ == "__main__":
    main()
