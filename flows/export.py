"""The ``export@<backbone>-<size>`` and ``export-variant@<name>`` stages: a trained model → ``registry/<model>/`` and
the MLflow Model Registry.

``python -m flows.export --model cues-1000 [--params params.yaml]``. The model's graphs are exported to ONNX
(:func:`components.export.onnx.export_posterior`, checked against torch in onnxruntime) with a model card (backbone,
training size, θ order, units and bijection, input spec, training metrics, data hash, git commit, opset,
onnxruntime version), then registered (:func:`flows.tracking.register_model`). The champion alias comes after the
evaluation (the ``evaluate`` stage).
"""

from __future__ import annotations

import time

from prefect import flow

from components.export.onnx import export_posterior
from components.features.backbones import get_backbone
from components.posterior.store import load_npe
from flows import tracking
from flows.stage import open_stage, parse_stage_args, use_all_cores


@flow(name="export", log_prints=True)
def export_model(model_id: str, params_path: str) -> dict:
    """Export ``models/<model_id>`` into ``registry/<model_id>`` and register it in MLflow."""
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
        "metrics": extra.get("metrics", {}),
        "data_hash": extra.get("data_hash"),
        "git_commit": tracking.git_commit(paths.root),
        "registered_model": tracking.registered_model(params),
    }
    t0 = time.perf_counter()
    folder = export_posterior(model, paths.registry / model_id, card=card, exporter=params.export.exporter)
    seconds = time.perf_counter() - t0
    entry = tracking.register_model(folder, params, paths.root, model_id)
    stage.logger.info(
        "%s → %s (%s exporter, %.1f s); registered as %s version %s",
        model_id,
        folder,
        params.export.exporter,
        seconds,
        entry["name"],
        entry["version"],
    )
    return {"folder": str(folder), "export_seconds": seconds, **entry}


def main(argv: list[str] | None = None) -> None:
    args, _ = parse_stage_args(
        "Export one trained model to registry/ and the MLflow Model Registry.",
        argv,
        [(["--model"], {"required": True, "help": "model id, e.g. cues-1000 or cues-10000-ensemble"})],
    )
    use_all_cores()
    export_model(args.model, str(args.params))


if __name__ == "__main__":
    main()
