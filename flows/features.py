"""The ``features@<backbone>`` stage: cache a backbone's output for every dataset shard.

``python -m flows.features --backbone cues [--params params.yaml]``. One Prefect task per
``data.shards_per_task`` dataset shards; shards whose cached output matches the current data and backbone are skipped.
A frozen backbone runs on ``backbones.device`` (each worker process moves its own copy there, the images batch by
batch, the features back to the CPU); the fingerprint is the device's no part. A trainable backbone's inputs (resized
images) are cached as they are, on the CPU.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

from prefect import flow, task

from components.core.files import remove_stale_temps
from components.core.hardware import threads_per_worker, usable_cores
from components.features import cache as features
from components.features.backbones import Backbone, get_backbone
from components.features.options import backbone_options
from components.simulate import dataset
from flows.stage import (
    batches,
    open_stage,
    parse_stage_args,
    share_api_with_workers,
    task_runner,
    wait_with_progress,
)


@functools.lru_cache(maxsize=4)
def _backbone(name: str, options_json: str, device: str = "cpu") -> Backbone:
    """The backbone ``name`` built with its options, its weights on ``device`` (a resolved ``backbones.device``)."""
    import torch

    where = torch.device(device)
    if where.type == "cuda" and where.index is not None:
        torch.cuda.set_device(where)
    return get_backbone(name, **json.loads(options_json)).to(where)


@functools.lru_cache(maxsize=4)
def _split(root: str, name: str) -> dataset.Split:
    return dataset.open_split(root, name)


@task(name="backbone-shards")
def shards_task(
    name: str,
    options_json: str,
    data: str,
    shards: list[tuple[str, int]],
    out: str,
    batch_size: int,
    device: str = "cpu",
    threads: int = 1,
) -> list[int]:
    """The backbone's output of a batch of ``(split, shard)`` pairs, each shard's written as it is done; their sizes.
    ``threads``: torch threads (the cores over the workers: parallelism comes from the task runner)."""
    import torch

    torch.set_num_threads(threads)
    backbone = _backbone(name, options_json, device)
    store = features.FeatureStore(Path(out), name)
    fingerprint = features.output_fingerprint(backbone)
    sizes = []
    for split_name, k in shards:
        split = _split(data, split_name)
        values = features.backbone_output(backbone, split.shard_images(k), batch_size)
        features.write_shard_features(store, split, k, values, fingerprint)
        sizes.append(len(values))
    return sizes


@flow(name="features", log_prints=True)
def extract_features(backbone_name: str, params_path: str) -> dict:
    """Cache the output of one backbone for the train, val and test splits."""
    stage = open_stage(params_path)
    params, logger = stage.params, stage.logger
    if backbone_name not in params.backbones.names:
        raise ValueError(
            f"backbone {backbone_name!r} is not in backbones.names of {stage.params_file} "
            f"({', '.join(params.backbones.names)})"
        )
    options = backbone_options(backbone_name, params, stage.paths.root)
    device = params.backbones.device  # resolved by open_stage: cpu, cuda or cuda:N
    backbone = _backbone(
        backbone_name, json.dumps(options, sort_keys=True), device
    )  # fails fast: unknown name, missing weights
    if params.train.mirror and not backbone.trainable and backbone.mirror_index() is None:
        raise ValueError(  # the train stage would refuse it, after every backbone's features
            f"train.mirror is true in {stage.params_file}, but the features of backbone {backbone_name!r} do not "
            "permute under a left-right mirror of the image; set train.mirror: false or take it out of backbones.names"
        )
    fingerprint = features.output_fingerprint(backbone)
    root = stage.paths.data
    splits = [dataset.open_split(root, s, verify=True) for s in dataset.SPLITS]
    store = features.FeatureStore(stage.paths.features, backbone_name)
    for path in remove_stale_temps(store.folder):  # a manifest's write cut short by a kill
        logger.info("removed %s (left by a killed run)", path)

    todo = [
        (s.name, k)
        for s in splits
        for k in range(len(s.shard_files))
        if not features.shard_features_done(store, s, k, fingerprint)
    ]
    logger.info(
        "backbone %s (%s, fingerprint %s): %d shards to compute on %s",
        backbone_name,
        "trainable: caching its input" if backbone.trainable else f"frozen, dim {backbone.dim}",
        fingerprint[:12],
        len(todo),
        device,
    )
    threads = threads_per_worker(usable_cores(), params.data.runner.workers)
    share_api_with_workers()
    futures = [
        shards_task.submit(
            backbone_name,
            json.dumps(options, sort_keys=True),
            str(root),
            batch,
            str(store.root),
            params.backbones.batch_size,
            device,
            threads,
        )
        for batch in batches(todo, params.data.shards_per_task)
    ]
    wait_with_progress(futures, desc=f"features@{backbone_name}", total=len(todo), unit="shard", per_item=True)
    manifest = features.write_features_manifest(
        store,
        splits,
        fingerprint=fingerprint,
        kind="inputs" if backbone.trainable else "features",
        config=backbone.config(),
    )
    logger.info("features@%s: %s", backbone_name, {k: v["count"] for k, v in manifest["splits"].items()})
    return manifest


def main(argv: list[str] | None = None) -> None:
    args, params = parse_stage_args(
        "Cache a backbone's output for every dataset shard (the features stage).",
        argv,
        [(["--backbone"], {"required": True, "help": "a name from backbones.names"})],
    )
    extract_features.with_options(task_runner=task_runner(params.data.runner))(args.backbone, str(args.params))


if __name__ == "__main__":
    main()
