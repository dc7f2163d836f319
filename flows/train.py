"""The ``train@<backbone>-<size>`` stage: one NPE of the grid, trained and logged in MLflow.

``python -m flows.train --backbone cues --size 1000 [--params params.yaml]``. The model trains on the
first ``size`` images of the train split (cached backbone outputs), stops early on the validation
loss, resumes from its checkpoint after a kill, and is evaluated on the test split (NLL and
information gain over the prior). MLflow: one experiment (``train.experiment``), one parent run per
grid (data hash + training settings), one child run per model, found or created across processes.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import time
from dataclasses import asdict
from pathlib import Path

import mlflow
import numpy as np
import torch
from prefect import flow, get_run_logger

from components.simulate import dataset
from components.features import cache as features
from components.core import seeding
from components.features.backbones import get_backbone
from components.core.config import PROJECT_ROOT, Params, VariantConfig, load_params
from components.core.files import atomic_write_bytes
from components.posterior import NPE, FlowConfig, TrainingConfig, train
from components.posterior.store import save_npe
from flows.features import backbone_options, features_root
from flows.generate import data_root


def tracking_uri(base: Path) -> str:
    """``MLFLOW_TRACKING_URI`` if set, else ``sqlite:///<project>/mlflow.db``."""
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{base / 'mlflow.db'}"


def git_commit(base: Path) -> str:
    try:
        r = subprocess.run(["git", "rev-parse", "HEAD"], cwd=base, capture_output=True, text=True, timeout=10)
        return r.stdout.strip() if r.returncode == 0 else "unknown"
    except OSError:
        return "unknown"


def training_settings(params: Params, trainable: bool, variant: VariantConfig | None = None) -> tuple[FlowConfig, TrainingConfig]:
    """The flow and training settings of a grid model, or of a calibrated variant (its balance and ensemble)."""
    t = params.train
    flow_cfg = FlowConfig(transforms=t.flow.transforms, hidden_features=t.flow.hidden_features, bins=t.flow.bins,
                          passes=t.flow.passes, ensemble=variant.ensemble if variant else t.flow.ensemble)
    cfg = TrainingConfig(
        epochs=t.embedding_epochs if trainable else t.epochs, batch_size=t.batch_size, lr=t.lr,
        weight_decay=t.weight_decay, schedule=t.schedule, patience=t.patience, clip_norm=t.clip_norm,
        seed=seeding.derive_seed(params.seed, "train") % 2**31, balance=variant.balance if variant else t.balance,
    )
    return flow_cfg, cfg


def find_variant(params: Params, name: str) -> VariantConfig:
    if name not in params.train.variants:
        raise ValueError(f"no variant {name!r} in train.variants ({', '.join(params.train.variants) or 'none'})")
    return params.train.variants[name]


def grid_key(params: Params, data_hash: str) -> str:
    """Identifies a grid: the data and every training setting except the sizes and the variants beside it."""
    settings = params.train.model_dump(exclude={"sizes", "variants"}) | {"seed": params.seed, "data": data_hash,
                                                             "backbones": list(params.backbones.names)}
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:12]


def _find_or_create_run(client: mlflow.MlflowClient, experiment_id: str, tags: dict[str, str], name: str,
                        parent: str | None = None) -> str:
    """The newest unfinished run with these tags (and parent), or a new one."""
    query = " and ".join(f"tags.`{k}` = '{v}'" for k, v in tags.items())
    if parent:
        query += f" and tags.`mlflow.parentRunId` = '{parent}'"
    for run in client.search_runs([experiment_id], query, order_by=["attributes.start_time DESC"], max_results=5):
        if parent is None or run.info.status != "FINISHED":
            return run.info.run_id
    all_tags = dict(tags) | ({"mlflow.parentRunId": parent} if parent else {})
    return client.create_run(experiment_id, tags=all_tags, run_name=name).info.run_id


def model_inputs(backbone, cached: np.ndarray) -> torch.Tensor:
    """The model input: cached features, or a trainable backbone's preprocessed cached input."""
    return backbone.preprocess(cached) if backbone.trainable else torch.from_numpy(np.ascontiguousarray(cached))


@torch.no_grad()
def mean_nll(model: NPE, x: torch.Tensor, theta: np.ndarray, batch: int = 512) -> float:
    """−mean log q(θ | x) over a split, in nats (physical units)."""
    th = torch.from_numpy(theta).to(torch.float32)
    total = 0.0
    for s in range(0, len(th), batch):
        total += float(model.log_prob(th[s : s + batch], x[s : s + batch]).double().sum())
    return -total / len(th)


@flow(name="train", log_prints=True)
def train_model(backbone_name: str, size: int, params_path: str, variant_name: str | None = None) -> dict:
    """Train model ``<backbone>-<size>`` of the grid, or the calibrated variant ``<backbone>-<size>-<variant>``;
    write ``models/<id>/`` and log to MLflow."""
    logger = get_run_logger()
    params_file = Path(params_path)
    params = load_params(params_file)
    base = params_file.resolve().parent
    if backbone_name not in params.backbones.names:
        raise ValueError(f"backbone {backbone_name!r} is not in backbones.names ({', '.join(params.backbones.names)})")
    if size not in params.train.sizes:
        raise ValueError(f"size {size} is not in train.sizes {list(params.train.sizes)}")
    variant = find_variant(params, variant_name) if variant_name else None
    if variant and (variant.backbone, variant.size) != (backbone_name, size):
        raise ValueError(f"variant {variant_name!r} is defined for {variant.backbone}-{variant.size}, not {backbone_name}-{size}")
    model_id = f"{backbone_name}-{size}" + (f"-{variant_name}" if variant else "")
    out = base / "models" / model_id
    out.mkdir(parents=True, exist_ok=True)

    root = data_root(params, params_file)
    splits = {s: dataset.open_split(root, s) for s in dataset.SPLITS}
    if size > len(splits["train"]):
        raise ValueError(f"size {size} is larger than the train split ({len(splits['train'])} images)")
    options = backbone_options(backbone_name, params, params_file)
    backbone = get_backbone(backbone_name, **options)
    froot = features_root(params_file)
    x = {s: model_inputs(backbone, features.open_features(froot, backbone_name, splits[s], stop=size if s == "train" else None))
         for s in dataset.SPLITS}
    theta = {s: splits[s].theta[: len(x[s])].astype(np.float32) for s in dataset.SPLITS}

    flow_cfg, cfg = training_settings(params, backbone.trainable, variant)
    model_seed = seeding.derive_seed(params.seed, "model", model_id) % 2**31
    if backbone.trainable:
        model = NPE(backbone, backbone.dim, params.box, flow_cfg, input_shape=tuple(x["train"].shape[1:]), seed=model_seed)
    else:
        model = NPE(None, backbone.dim, params.box, flow_cfg, seed=model_seed)

    # a checkpoint belongs to one configuration: a params change starts afresh instead of failing
    run_key = hashlib.sha256(json.dumps([asdict(cfg), asdict(flow_cfg), model_seed, splits["train"].content_hash,
                                         options], sort_keys=True, default=str).encode()).hexdigest()[:12]
    checkpoint = out / f"checkpoint-{run_key}.pt"
    for stale in out.glob("checkpoint-*.pt"):
        if stale != checkpoint:
            stale.unlink()

    mlflow.set_tracking_uri(tracking_uri(base))
    client = mlflow.MlflowClient()
    experiment = client.get_experiment_by_name(params.train.experiment)
    experiment_id = experiment.experiment_id if experiment else client.create_experiment(params.train.experiment)
    data_hash = splits["train"].content_hash
    key = grid_key(params, data_hash)
    parent = _find_or_create_run(client, experiment_id, {"pidc.grid": key}, f"grid-{key}")
    run_id = _find_or_create_run(client, experiment_id, {"pidc.model": model_id, "pidc.grid": key}, model_id, parent=parent)

    t0 = time.perf_counter()
    with mlflow.start_run(run_id=run_id, experiment_id=experiment_id):
        mlflow.set_tags({"pidc.model": model_id, "pidc.grid": key, "pidc.backbone": backbone_name, "pidc.size": str(size),
                         "git_commit": git_commit(base), "data_hash": data_hash,
                         "dvc_stage": f"variant@{variant_name}" if variant else f"train@{model_id}"})
        mlflow.log_params({"backbone": backbone_name, "size": size, "trainable_backbone": backbone.trainable,
                           "features": backbone.dim, "model_seed": model_seed,
                           **{f"flow.{k}": v for k, v in asdict(flow_cfg).items()},
                           **{f"train.{k}": v for k, v in asdict(cfg).items()}})

        def log_epoch(record) -> None:
            mlflow.log_metrics({"train_loss": record.train_loss, "val_loss": record.val_loss, "lr": record.lr,
                                "epoch_seconds": record.wall_time}, step=record.epoch)

        history = train(model, (x["train"], theta["train"]), (x["val"], theta["val"]), cfg,
                        checkpoint=checkpoint, callback=log_epoch, progress=True)
        model.eval()
        test_nll = mean_nll(model, x["test"], theta["test"])
        metrics = {
            "test_nll": test_nll,
            # E[log q(θ|x) − log p(θ)] over the test split: nats gained over the uniform prior
            "info_gain_nats": -test_nll + params.box.log_volume(),
            "best_val_loss": history.best_val_loss,
            "best_epoch": history.best_epoch,
            "epochs_run": len(history.records),
            "wall_seconds": time.perf_counter() - t0,
        }
        mlflow.log_metrics(metrics)

        from components.plots import loss_curves, save_figure

        save_npe(out / "model.pt", model, backbone=backbone_name, backbone_options=options,
                 extra={"model_id": model_id, "size": size, "data_hash": data_hash, "metrics": metrics})
        atomic_write_bytes(out / "history.json", json.dumps(history.to_dict(), indent=1).encode())
        atomic_write_bytes(out / "metrics.json", json.dumps(metrics, indent=1).encode())
        atomic_write_bytes(base / "reports" / "train" / f"{model_id}.json", json.dumps(metrics, indent=1).encode())
        save_figure(loss_curves({"train": history.train_loss, "val": history.val_loss}, title=f"{model_id}: NPE loss"),
                    out / "loss.png")
        for name in ("loss.png", "metrics.json", "model.pt"):
            mlflow.log_artifact(str(out / name))
    # the grid's parent run is a container: finished whenever none of its models is training
    client.set_terminated(parent, "FINISHED")
    logger.info("%s: test NLL %.3f nats, information gain %.2f nats, best epoch %d of %d", model_id, test_nll,
                metrics["info_gain_nats"], history.best_epoch, len(history.records))
    return metrics


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Train one NPE of the backbone × size grid (the train stage).")
    parser.add_argument("--backbone", required=True)
    parser.add_argument("--size", type=int, required=True)
    parser.add_argument("--variant", help="a name from train.variants (a calibrated model beside the grid)")
    parser.add_argument("--params", type=Path, default=PROJECT_ROOT / "params.yaml")
    args = parser.parse_args(argv)
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    train_model(args.backbone, args.size, str(args.params), args.variant)


if __name__ == "__main__":
    main()
