"""The ``train`` stage: every NPE of the grid and its calibrated variants, trained in parallel and logged in MLflow.

``python -m flows.train [--model ID ...] [--params params.yaml]``. Each model (``<backbone>-<size>`` of the grid,
``<backbone>-<size>-<variant>`` of ``train.variants``) trains on the first ``size`` images of the train split (cached
backbone outputs), keeps its best validation epoch (early stopping only with ``train.patience``), resumes from its
checkpoint after a kill, and is scored on the test split (NLL and information gain over the prior).
``train.runner.workers`` models train at a time, the largest first, with ``cores // workers`` torch threads each (of
the cores this process may use, :mod:`components.core.hardware`): a training step of these small flows is no faster
on two threads than on one, so one model per core halves the stage (docs/studies/parallel-grid.md). Each trains on
``train.device`` (several processes share one GPU, each with its own CUDA context) and is calibrated and tested on
the CPU. A model whose configuration, data, features and code are unchanged finds its finished
checkpoint (keyed by all four: :func:`training_code`) and costs seconds; an edit of the code that trains it retrains it.
MLflow (:mod:`flows.tracking`): one parent run per grid, one child run per model.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
import zuko
from prefect import flow, task

from components.core import seeding
from components.core.code import code_fingerprint
from components.core.config import Params, VariantConfig
from components.core.files import atomic_write_bytes, remove_stale_temps
from components.core.hardware import threads_per_worker, usable_cores
from components.core.paths import ProjectPaths
from components.features import cache as features
from components.features.backbones import get_backbone
from components.features.backbones.base import Backbone
from components.features.options import backbone_options
from components.posterior import NPE, train
from components.posterior.metrics import mean_nll
from components.posterior.model import FlowConfig
from components.posterior.settings import ensemble_for, flow_config, temperature_regime, training_config
from components.posterior.store import save_npe
from components.posterior.temperature import calibrate_post_hoc
from components.posterior.train import History, TrainingConfig
from components.simulate import dataset
from flows import tracking
from flows.stage import at_most, open_stage, parse_stage_args, share_api_with_workers, task_runner

#: the stage's name in dvc.yaml (tagged on every model's MLflow run)
STAGE = "train"


def training_code(backbone) -> str:
    """The fingerprint of the code that decides a model's trained weights: the project modules the training imports
    (:mod:`components.posterior.train`, the model, its flows, loss and optimisation, and their imports), the module of
    a backbone trained with the flow (the ``cnn``: its network is part of the model; a frozen backbone enters through
    its features' fingerprint instead), and the versions of torch and zuko. Part of the checkpoint's key: a
    checkpoint — finished or cut short by a kill — made by other code is never resumed."""
    modules = ["components.posterior.train"]
    if backbone.trainable:
        modules.append(type(backbone).__module__)
    return code_fingerprint(modules, extra=[f"torch {torch.__version__}", f"zuko {zuko.__version__}"])


def find_variant(params: Params, name: str) -> VariantConfig:
    if name not in params.train.variants:
        raise ValueError(f"no variant {name!r} in train.variants ({', '.join(params.train.variants) or 'none'})")
    return params.train.variants[name]


def training_order(params: Params, ids: list[str]) -> list[str]:
    """``ids`` with the largest training sets first, then the ensembles of more flows (ties keep their order), so
    that parallel workers finish together."""

    def cost(model_id: str) -> tuple[int, int]:
        _, size, variant = params.model_cell(model_id)
        return size, ensemble_for(params.train, size) if not variant else find_variant(params, variant).ensemble

    return sorted(ids, key=cost, reverse=True)


def _check_cell(params: Params, backbone_name: str, size: int, variant_name: str | None) -> VariantConfig | None:
    """The variant ``variant_name`` of cell ``<backbone>-<size>`` (None for the grid's own model); ``ValueError``
    naming the setting when the backbone, the size or the variant is not configured for it."""
    if backbone_name not in params.backbones.names:
        raise ValueError(f"backbone {backbone_name!r} is not in backbones.names ({', '.join(params.backbones.names)})")
    if size not in params.train.sizes:
        raise ValueError(f"size {size} is not in train.sizes {list(params.train.sizes)}")
    variant = find_variant(params, variant_name) if variant_name else None
    if variant and (variant.backbone, variant.size) != (backbone_name, size):
        raise ValueError(
            f"variant {variant_name!r} is defined for {variant.backbone}-{variant.size}, not {backbone_name}-{size}"
        )
    return variant


def _inputs(
    params: Params, paths: ProjectPaths, backbone_name: str, size: int
) -> tuple[dict[str, dataset.Split], dict, Backbone, dict[str, torch.Tensor], dict[str, np.ndarray]]:
    """The splits, the backbone's options, the backbone, its cached outputs ``x`` (split → tensor, the first ``size``
    images of the train split) and the true θ (split → ``(n, 6)`` float32)."""
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
    return splits, options, backbone, x, theta


def _new_model(
    params: Params,
    backbone: Backbone,
    x: dict[str, torch.Tensor],
    size: int,
    variant: VariantConfig | None,
    model_id: str,
) -> tuple[NPE, FlowConfig, TrainingConfig, int]:
    """The untrained NPE of a model and its settings: ``(model, flow config, training config, model seed)``."""
    ensemble = variant.ensemble if variant else None
    flow_cfg = flow_config(params.train, size=size, trainable=backbone.trainable, ensemble=ensemble)
    cfg = training_config(
        params.train,
        size=size,
        trainable=backbone.trainable,
        features=backbone.dim,
        parameters=len(params.box.names),
        seed=seeding.derive_seed(params.seed, "train") % 2**31,
        balance=variant.balance if variant else None,
        ensemble=ensemble,
        spared=backbone.spared_index(),
    )
    model_seed = seeding.derive_seed(params.seed, "model", model_id) % 2**31
    if backbone.trainable:
        model = NPE(
            backbone, backbone.dim, params.box, flow_cfg, input_shape=tuple(x["train"].shape[1:]), seed=model_seed
        )
    else:
        model = NPE(None, backbone.dim, params.box, flow_cfg, seed=model_seed)
    return model, flow_cfg, cfg, model_seed


def _on_device(model: NPE, device: str) -> torch.device:
    """Move ``model`` to ``device`` (a resolved ``train.device``: ``cpu``, ``cuda`` or ``cuda:N``), making a GPU this
    process's current CUDA device (its kernels and caches go there); the device."""
    where = torch.device(device)
    if where.type == "cuda" and where.index is not None:
        torch.cuda.set_device(where)
    model.to(where)
    return where


def _run_key(
    cfg: TrainingConfig, flow_cfg: FlowConfig, model_seed: int, data_hash: str, options: dict, backbone: Backbone
) -> str:
    """The key of a model's checkpoint (12 hex digits): its configuration, seed, data, backbone options, the version
    of the backbone's features (their fingerprint) and the training code (:func:`training_code`)."""
    return hashlib.sha256(
        json.dumps(
            [
                asdict(cfg),
                asdict(flow_cfg),
                model_seed,
                data_hash,
                options,
                features.output_fingerprint(backbone),
                training_code(backbone),
            ],
            sort_keys=True,
            default=str,
        ).encode()
    ).hexdigest()[:12]


def _calibrate_and_test(
    params: Params, model: NPE, x: dict[str, torch.Tensor], theta: dict[str, np.ndarray], history: History, t0: float
) -> dict:
    """Calibrate the trained ``model`` post hoc on the validation split (with a regime, its gate fitted on the
    training pairs first; deterministic: resuming re-fits the same τ) and score it on the test split; its metrics."""
    model.eval()
    pairs = {k: (x[k], torch.from_numpy(theta[k])) for k in ("train", "val")}
    regime = temperature_regime(params.train, params.box)
    tempered = calibrate_post_hoc(model, pairs["train"], pairs["val"], regime) if params.train.temperature else {}
    test_nll = mean_nll(model, x["test"], theta["test"])
    return {
        "test_nll": test_nll,
        # E[log q(θ|x) − log p(θ)] over the test split: nats gained over the uniform prior
        "info_gain_nats": -test_nll + params.box.log_volume(),
        "best_val_loss": history.best_val_loss,
        # counted from 1, as the epoch log lines and the loss plot count it (the history's index is from 0)
        "best_epoch": history.best_epoch + 1,
        "epochs_run": len(history.records),
        # the epochs' seconds, summed over the runs that trained them: a model resumed from its finished
        # checkpoint keeps its training time (wall_seconds is this call's: loading, calibrating, testing)
        "training_seconds": float(sum(history.wall_time)),
        "wall_seconds": time.perf_counter() - t0,
        **tempered,
    }


def _save(
    out: Path,
    report: Path,
    model: NPE,
    model_id: str,
    size: int,
    data_hash: str,
    backbone_name: str,
    options: dict,
    metrics: dict,
    history: History,
) -> None:
    """Write ``models/<id>/`` (``out``: model, history, metrics, loss plot) and ``reports/train/<id>.json``
    (``report``)."""
    from components.plots import loss_curves, save_figure

    # the model's files hold only what the model is: this run's wall_seconds (reports/train, MLflow) would change
    # models/ on every re-run of an unchanged model, and with it every stage after train
    kept = {k: v for k, v in metrics.items() if k != "wall_seconds"}
    save_npe(
        out / "model.pt",
        model,
        backbone=backbone_name,
        backbone_options=options,
        extra={"model_id": model_id, "size": size, "data_hash": data_hash, "metrics": kept},
    )
    atomic_write_bytes(out / "history.json", json.dumps(history.to_dict(), indent=1).encode())
    atomic_write_bytes(out / "metrics.json", json.dumps(kept, indent=1).encode())
    atomic_write_bytes(report, json.dumps(metrics, indent=1).encode())
    save_figure(
        loss_curves({"train": history.train_loss, "val": history.val_loss}, title=f"{model_id}: NPE loss"),
        out / "loss.png",
    )


@task(name="train-model")
def train_model(
    backbone_name: str, size: int, params_path: str, variant_name: str | None = None, threads: int | None = None
) -> dict:
    """Train model ``<backbone>-<size>`` of the grid, or the calibrated variant ``<backbone>-<size>-<variant>``, with
    ``threads`` torch threads (None: torch's default); write ``models/<id>/`` and ``reports/train/<id>.json`` and log
    to MLflow. Returns the model's metrics."""
    if threads:
        torch.set_num_threads(threads)
    stage = open_stage(params_path)
    params, paths = stage.params, stage.paths
    variant = _check_cell(params, backbone_name, size, variant_name)
    model_id = f"{backbone_name}-{size}" + (f"-{variant_name}" if variant else "")
    out = paths.models / model_id
    out.mkdir(parents=True, exist_ok=True)
    splits, options, backbone, x, theta = _inputs(params, paths, backbone_name, size)
    model, flow_cfg, cfg, model_seed = _new_model(params, backbone, x, size, variant, model_id)

    # a checkpoint belongs to one configuration: a params change, new data, a new version of the backbone's features
    # (their fingerprint) or an edit of the training code starts afresh instead of resuming (or returning, finished)
    # what other settings or other code trained
    data_hash = splits["train"].content_hash
    run_key = _run_key(cfg, flow_cfg, model_seed, data_hash, options, backbone)
    checkpoint = out / f"checkpoint-{run_key}.pt"
    for stale in out.glob("checkpoint-*.pt"):
        if stale != checkpoint:
            stale.unlink()
    remove_stale_temps(out)  # a checkpoint, model or history cut short by a kill (one trainer per model at a time)

    t0 = time.perf_counter()
    tags = {"pidc.backbone": backbone_name, "pidc.size": str(size), "dvc_stage": STAGE}
    with tracking.model_run(paths.root, params, model_id, data_hash, tags, run_key) as run:
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
        _on_device(model, params.train.device)
        history = train(
            model,
            (x["train"], theta["train"]),
            (x["val"], theta["val"]),
            cfg,
            checkpoint=checkpoint,
            callback=_reporting(run.log_epoch, stage.logger, model_id, cfg.epochs),
            progress=False,  # parallel workers: one log line per tenth of the epochs instead of interleaved bars
            mirror=backbone.mirror_inputs if cfg.mirror else None,
        )
        # the epochs this run lacks: a finished checkpoint found by a new run, an epoch whose callback a kill cut off
        run.log_history(history.records)
        model.cpu()  # calibrated, tested and saved on the CPU wherever it trained
        metrics = _calibrate_and_test(params, model, x, theta, history, t0)
        run.log_metrics(metrics)
        report = paths.reports("train", f"{model_id}.json")
        _save(out, report, model, model_id, size, data_hash, backbone_name, options, metrics, history)
        run.log_artifacts([out / name for name in ("loss.png", "metrics.json", "model.pt")])
    stage.logger.info(
        "%s: test NLL %.3f nats, information gain %.2f nats, best epoch %d of %d",
        model_id,
        metrics["test_nll"],
        metrics["info_gain_nats"],
        metrics["best_epoch"],
        len(history.records),
    )
    return metrics


def _reporting(log_epoch, logger, model_id: str, epochs: int):
    """The training callback: ``log_epoch`` (MLflow) every epoch, a log line every tenth of ``epochs``."""
    every = max(1, epochs // 10)

    def callback(record) -> None:
        log_epoch(record)
        if (record.epoch + 1) % every == 0 or record.epoch == 0:
            logger.info(
                "%s: epoch %d of at most %d, validation loss %.3f (best at epoch %d), %.1f s an epoch",
                model_id,
                record.epoch + 1,
                epochs,
                record.val_loss,
                record.best_epoch + 1,
                record.wall_time,
            )

    return callback


@flow(name="train", log_prints=True)
def train_grid(params_path: str, models: list[str] | None = None) -> dict[str, dict]:
    """Train ``models`` (default: the grid and its variants, ``params.model_ids()``), ``train.runner.workers`` at a
    time, the costliest first. Returns model id → metrics."""
    stage = open_stage(params_path)
    params, paths = stage.params, stage.paths
    ids = list(models) if models else params.model_ids()
    cells = {m: params.model_cell(m) for m in ids}  # an unknown id fails here, before any work
    data_hash = dataset.open_split(paths.data, "train").content_hash
    tracking.grid_run(paths.root, params, data_hash)  # created once, before the workers look it up
    workers = min(params.train.runner.workers, len(ids))  # one model alone gets every core
    threads = threads_per_worker(usable_cores(), workers)
    stage.logger.info(
        "training %d models on %s, %d at a time with %d torch threads each",
        len(ids),
        params.train.device,
        workers,
        threads,
    )
    share_api_with_workers()
    results = at_most(
        workers,
        training_order(params, ids),
        lambda m: train_model.submit(cells[m][0], cells[m][1], str(stage.params_file), cells[m][2], threads),
        "train models",
    )
    results = {m: results[m] for m in ids}
    for m, r in results.items():
        stage.logger.info(
            "%s: information gain %.2f nats, best epoch %d of %d, trained in %.0f s (%.0f s in this run)",
            m,
            r["info_gain_nats"],
            r["best_epoch"],
            r["epochs_run"],
            r["training_seconds"],
            r["wall_seconds"],
        )
    return results


def main(argv: list[str] | None = None) -> None:
    args, params = parse_stage_args(
        "Train the NPEs of the backbone × size grid and the calibrated variants (the train stage).",
        argv,
        [
            (
                ["--model"],
                {
                    "action": "append",
                    "help": "a model id of the grid or train.variants, e.g. cues-5000 (repeatable; default: all)",
                },
            )
        ],
    )
    train_grid.with_options(task_runner=task_runner(params.train.runner))(str(args.params), args.model)


if __name__ == "__main__":
    main()
