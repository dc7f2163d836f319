"""The ``generate`` stage: render the train/val/test splits into shards, a manifest and a contact sheet.

``python -m flows.generate [--params params.yaml]``. Shards are rendered by parallel Prefect tasks
(the task runner of ``data.runner``, ``data.shards_per_task`` shards per task); finished shards are skipped, so a
killed run resumes. With ``simulator.backend: recorded`` the folders of ``simulator.recorded`` are checked and
imported into the same shards instead (:mod:`components.simulate.recorded`), and the contact sheet shows recorded
images along each parameter.
"""

from __future__ import annotations

import functools
import time

from prefect import flow, task

from components.core import seeding
from components.core.config import Params, SimulatorConfig
from components.core.files import remove_stale_temps
from components.simulate import dataset, recorded
from components.simulate.base import make_simulator
from flows.stage import (
    batches,
    open_stage,
    parse_stage_args,
    share_api_with_workers,
    task_runner,
    wait_with_progress,
)


@functools.lru_cache(maxsize=2)
def _simulator(cfg: SimulatorConfig):
    """One simulator per worker process (its scene cache survives across the shards it renders)."""
    return make_simulator(cfg)


@task(name="render-shards", retries=0)
def render_shards(rows: list[dataset.ShardRows], sim_cfg: SimulatorConfig, root: str) -> list[dict]:
    """Render a batch of shards one after the other (each written atomically as it is done); their receipts."""
    return [dataset.render_shard(r, _simulator(sim_cfg), root) for r in rows]


@task(name="import-shards", retries=0)
def import_shards(rows: list[recorded.RecordedRows], resolution: tuple[int, int], root: str) -> list[dict]:
    """Import a batch of shards of recorded images one after the other (each written atomically); their receipts."""
    return [recorded.import_shard(r, resolution, root) for r in rows]


def plans(params: Params, renderer_version: str) -> list[dataset.SplitPlan]:
    """The deterministic plan of each split (the one ``pidc record`` renders too)."""
    return recorded.split_plans(params, dataset.SPLITS, None, renderer_version)


@flow(name="generate", log_prints=True)
def generate(params_path: str) -> dict:
    """Render every unfinished shard, then write the manifest and the contact sheet."""
    stage = open_stage(params_path)
    params, logger, root = stage.params, stage.logger, stage.paths.data
    if params.simulator.backend == recorded.SOURCE_KIND:
        return _import(stage)
    simulator = _simulator(params.simulator)
    split_plans = plans(params, simulator.version)
    todo = _unfinished(split_plans, root, logger, simulator.version, lambda plan, spec: plan.rows(spec))

    t0 = time.perf_counter()
    share_api_with_workers()
    futures = [
        render_shards.submit(batch, params.simulator, str(root)) for batch in batches(todo, params.data.shards_per_task)
    ]
    wait_with_progress(futures, desc="generate", total=len(todo), unit="shard", per_item=True)
    n_images = sum(r.spec.stop - r.spec.start for r in todo)
    elapsed = time.perf_counter() - t0
    if n_images:
        logger.info("rendered %d images in %.1f s (%.0f images/s)", n_images, elapsed, n_images / elapsed)

    manifest = dataset.write_manifest(
        root,
        split_plans,
        renderer_version=simulator.version,
        resolution=(params.simulator.height, params.simulator.width),
        seed=params.seed,
        box=params.box,
        images_per_scene=params.data.images_per_scene,
    )

    from components.simulate.contact_sheet import contact_sheet, save_png

    sheet_seeds = [seeding.derive_seed(params.seed, "contact_sheet", j) for j in range(params.contact_sheet.scenes)]
    sheet = contact_sheet(simulator, sheet_seeds, params.contact_sheet.steps)
    sheet_path = stage.paths.resolve(params.contact_sheet.path)
    save_png(sheet_path, sheet)
    logger.info(
        "dataset %s: %s; contact sheet %s",
        manifest["content_hash"][:12],
        {k: v["count"] for k, v in manifest["splits"].items()},
        sheet_path,
    )
    return manifest


def _unfinished(split_plans: list, root, logger, source: str, rows) -> list:
    """``rows(plan, spec)`` of every shard not done (orphans of an older plan removed), and no manifest while any is
    left to write."""
    todo, done = [], 0
    for plan in split_plans:
        for path in dataset.remove_orphans(root, plan):
            logger.info("removed %s (not in the current plan)", path)
        for spec in plan.shards():
            if dataset.shard_is_done(spec, root):
                done += 1
            else:
                todo.append(rows(plan, spec))
    logger.info("%d shards already done, %d to write (%s)", done, len(todo), source)
    for path in remove_stale_temps(root):  # a manifest's write cut short by a kill
        logger.info("removed %s (left by a killed run)", path)
    if todo and (root / "manifest.json").exists():
        # the manifest describes the shards as they were: while any is rendered anew (a new plan, or a damaged shard)
        # it must not vouch for them, or a kill would leave it naming new shards of the same size (readers check sizes,
        # not hashes) beside features of the old images; written again below once every shard is done
        (root / "manifest.json").unlink()
        logger.info("removed %s until every shard is done", root / "manifest.json")
    return todo


def _import(stage) -> dict:
    """The stage with recorded data: check and plan the folders, import every unfinished shard, write the manifest
    (with its ``source``) and the contact sheet of recorded images."""
    params, logger, root = stage.params, stage.logger, stage.paths.data
    imported = recorded.plan_import(params, stage.paths.root)
    split_plans = [p.plan for p in imported.plans]
    by_name = {p.plan.name: p for p in imported.plans}
    todo = _unfinished(split_plans, root, logger, "recorded images", lambda plan, spec: by_name[plan.name].rows(spec))
    t0 = time.perf_counter()
    share_api_with_workers()
    resolution = (params.simulator.height, params.simulator.width)
    futures = [import_shards.submit(b, resolution, str(root)) for b in batches(todo, params.data.shards_per_task)]
    wait_with_progress(futures, desc="generate (import)", total=len(todo), unit="shard", per_item=True)
    n_images = sum(r.spec.stop - r.spec.start for r in todo)
    if n_images:
        logger.info("imported %d recorded images in %.1f s", n_images, time.perf_counter() - t0)
    source = recorded.source_entry(imported, root)
    manifest = dataset.write_manifest(
        root,
        split_plans,
        renderer_version=recorded.SOURCE_KIND,
        resolution=resolution,
        seed=params.seed,
        box=params.box,
        images_per_scene=None,
        source=source,
    )
    from components.simulate.contact_sheet import recorded_sheet, save_png

    train = dataset.open_split(root, "train")
    shown = min(len(train), 2000)
    sheet_path = stage.paths.resolve(params.contact_sheet.path)
    save_png(sheet_path, recorded_sheet(train.images(stop=shown), train.theta[:shown], params.contact_sheet.steps))
    logger.info(
        "dataset %s: %s imported from %d recorded images in %d sequences (%d left out, %d resized: %s); contact "
        "sheet %s",
        manifest["content_hash"][:12],
        {k: v["count"] for k, v in manifest["splits"].items()},
        source["images"],
        source["sequences"],
        source["left_out"],
        source["resized"],
        source["source_sizes"],
        sheet_path,
    )
    return manifest


def main(argv: list[str] | None = None) -> None:
    args, params = parse_stage_args("Render the simulated dataset (the generate stage).", argv)
    generate.with_options(task_runner=task_runner(params.data.runner))(str(args.params))


if __name__ == "__main__":
    main()
