"""The ``train@<backbone>-<size>`` and ``variant@<name>`` stages: one NPE, trained and logged in MLflow.

``python -m flows.train --backbone cues --size 1000 [--variant NAME] [--params params.yaml]``. The model trains on
the first ``size`` images of the train split (cached backbone outputs), stops early on the validation loss, resumes
from its checkpoint after a kill, and is scored on the test split (NLL and information gain over the prior).
MLflow (:mod:`flows.tracking`): one parent run per grid, one child run per model.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict

import numpy as np
import torch
from prefect import flow

from components.core import seeding
from components.core.config import Params, VariantConfig
from components.core.files import atomic_write_bytes
from components.features import cache as features
from components.features.backbones import get_backbone
from components.features.options import backbone_options
from components.posterior import NPE, train
from components.posterior.metrics import mean_nll
from components.posterior.settings import flow_config, training_config
from components.posterior.store import save_npe
from components.posterior.temperature import calibrate
from components.simulate import dataset
from flows import tracking
from flows.stage import open_stage, parse_stage_args, use_all_cores


def find_variant(params: Params, name: str) -> VariantConfig:
    if name not in params.train.variants:
        raise ValueError(f"no variant {name!r} in train.variants ({', '.join(params.train.variants) or 'none'})")
    return params.train.variants[name]


@flow(name="train", log_prints=True)
def train_model(backbone_name: str, size: int, params_path: str, variant_name: str | None = None) -> dict:
    """Train model ``<backbone>-<size>`` of the grid, or the calibrated variant ``<backbone>-<size>-<variant>``;
    write ``models/<id>/`` and ``reports/train/<id>.json`` and log to MLflow."""
    stage = open_stage(params_path)
    params, paths = stage.params, stage.paths
    if backbone_name not in params.backbones.names:
        raise ValueError(f"backbone {backbone_name!r} is not in backbones.names ({', '.join(params.backbones.names)})")
    if size not in params.train.sizes:
        raise ValueError(f"size {size} is not in train.sizes {list(params.train.sizes)}")
    variant = find_variant(params, variant_name) if variant_name else None
    if variant and (variant.backbone, variant.size) != (backbone_name, size):
        raise ValueError(
            f"variant {variant_name!r} is defined for {variant.backbone}-{variant.size}, not {backbone_name}-{size}"
        )
    model_id = f"{backbone_name}-{size}" + (f"-{variant_name}" if variant else "")
    out = paths.models / model_id
    out.mkdir(parents=True, exist_ok=True)

    splits = {s: dataset.open_split(paths.data, s) for s in dataset.SPLITS}
    if size > len(splits["train"]):
        raise ValueError(f"size {size} is larger than the train split ({len(splits['train'])} images)")
    options = backbone_options(backbone_name, params, paths.root)
    backbone = get_backbone(backbone_name, **options)
    x = {
        s: torch.from_numpy(
            features.inputs_from_cached(
                backbone,
                features.open_features(paths.features, backbone_name, splits[s], stop=size if s == "train" else None),
            )
        )
        for s in dataset.SPLITS
    }
    theta = {s: splits[s].theta[: len(x[s])].astype(np.float32) for s in dataset.SPLITS}

    flow_cfg = flow_config(params.train, size=size, ensemble=variant.ensemble if variant else None)
    cfg = training_config(
        params.train,
        size=size,
        trainable=backbone.trainable,
        seed=seeding.derive_seed(params.seed, "train") % 2**31,
        balance=variant.balance if variant else None,
    )
    model_seed = seeding.derive_seed(params.seed, "model", model_id) % 2**31
    if backbone.trainable:
        model = NPE(
            backbone, backbone.dim, params.box, flow_cfg, input_shape=tuple(x["train"].shape[1:]), seed=model_seed
        )
    else:
        model = NPE(None, backbone.dim, params.box, flow_cfg, seed=model_seed)

    # a checkpoint belongs to one configuration: a params change starts afresh instead of failing
    data_hash = splits["train"].content_hash
    run_key = hashlib.sha256(
        json.dumps(
            [asdict(cfg), asdict(flow_cfg), model_seed, data_hash, options], sort_keys=True, default=str
        ).encode()
    ).hexdigest()[:12]
    checkpoint = out / f"checkpoint-{run_key}.pt"
    for stale in out.glob("checkpoint-*.pt"):
        if stale != checkpoint:
            stale.unlink()

    t0 = time.perf_counter()
    tags = {
        "pidc.backbone": backbone_name,
        "pidc.size": str(size),
        "dvc_stage": f"variant@{variant_name}" if variant else f"train@{model_id}",
    }
    with tracking.model_run(paths.root, params, model_id, data_hash, tags) as run:
        run.log_params(
            {
                "backbone": backbone_name,
                "size": size,
                "trainable_backbone": backbone.trainable,
                "features": backbone.dim,
                "model_seed": model_seed,
                **{f"flow.{k}": v for k, v in asdict(flow_cfg).items()},
                **{f"train.{k}": v for k, v in asdict(cfg).items()},
            }
        )
        history = train(
            model,
            (x["train"], theta["train"]),
            (x["val"], theta["val"]),
            cfg,
            checkpoint=checkpoint,
            callback=run.log_epoch,
            progress=True,
        )
        model.eval()
        # post-hoc calibration on the validation split (deterministic: resuming re-fits the same τ)
        tempered = calibrate(model, x["val"], torch.from_numpy(theta["val"])) if params.train.temperature else {}
        test_nll = mean_nll(model, x["test"], theta["test"])
        metrics = {
            "test_nll": test_nll,
            # E[log q(θ|x) − log p(θ)] over the test split: nats gained over the uniform prior
            "info_gain_nats": -test_nll + params.box.log_volume(),
            "best_val_loss": history.best_val_loss,
            "best_epoch": history.best_epoch,
            "epochs_run": len(history.records),
            "wall_seconds": time.perf_counter() - t0,
            **tempered,
        }
        run.log_metrics(metrics)

        from components.plots import loss_curves, save_figure

        save_npe(
            out / "model.pt",
            model,
            backbone=backbone_name,
            backbone_options=options,
            extra={"model_id": model_id, "size": size, "data_hash": data_hash, "metrics": metrics},
        )
        atomic_write_bytes(out / "history.json", json.dumps(history.to_dict(), indent=1).encode())
        atomic_write_bytes(out / "metrics.json", json.dumps(metrics, indent=1).encode())
        atomic_write_bytes(paths.reports("train", f"{model_id}.json"), json.dumps(metrics, indent=1).encode())
        save_figure(
            loss_curves({"train": history.train_loss, "val": history.val_loss}, title=f"{model_id}: NPE loss"),
            out / "loss.png",
        )
        run.log_artifacts([out / name for name in ("loss.png", "metrics.json", "model.pt")])
    stage.logger.info(
        "%s: test NLL %.3f nats, information gain %.2f nats, best epoch %d of %d",
        model_id,
        test_nll,
        metrics["info_gain_nats"],
        history.best_epoch,
        len(history.records),
    )
    return metrics


def main(argv: list[str] | None = None) -> None:
    args, _ = parse_stage_args(
        "Train one NPE of the backbone × size grid (the train stage), or a calibrated variant.",
        argv,
        [
            (["--backbone"], {"required": True}),
            (["--size"], {"type": int, "required": True}),
            (["--variant"], {"help": "a name from train.variants (a calibrated model beside the grid)"}),
        ],
    )
    use_all_cores()
    train_model(args.backbone, args.size, str(args.params), args.variant)


if __name__ == "__main__":
    main()
