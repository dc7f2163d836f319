"""The ``generate`` stage: render the train/val/test splits into shards, a manifest and a contact sheet.

``python -m flows.generate [--params params.yaml]``. Shards are rendered by parallel Prefect tasks
(the task runner of ``data.runner``, ``data.shards_per_task`` shards per task); finished shards are skipped, so a
killed run resumes.
"""

from __future__ import annotations

import functools
import time

from prefect import flow, task

from components.core import seeding
from components.core.config import Params, SimulatorConfig
from components.core.files import remove_stale_temps
from components.simulate import dataset
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


def plans(params: Params, renderer_version: str) -> list[dataset.SplitPlan]:
    """The deterministic plan of each split."""
    sim = params.simulator
    return [
        dataset.plan_split(
            name,
            params.data.splits[name],
            seed=params.seed,
            box=params.box,
            images_per_scene=params.data.images_per_scene,
            shard_size=params.data.shard_size,
            renderer_version=renderer_version,
            resolution=(sim.height, sim.width),
        )
        for name in dataset.SPLITS
    ]


@flow(name="generate", log_prints=True)
def generate(params_path: str) -> dict:
    """Render every unfinished shard, then write the manifest and the contact sheet."""
    stage = open_stage(params_path)
    params, logger, root = stage.params, stage.logger, stage.paths.data
    simulator = _simulator(params.simulator)
    split_plans = plans(params, simulator.version)

    todo, done = [], 0
    for plan in split_plans:
        for path in dataset.remove_orphans(root, plan):
            logger.info("removed %s (not in the current plan)", path)
        for spec in plan.shards():
            if dataset.shard_is_done(spec, root):
                done += 1
            else:
                todo.append(plan.rows(spec))
    logger.info("%d shards already done, %d to render (renderer %s)", done, len(todo), simulator.version)
    for path in remove_stale_temps(root):  # a manifest's write cut short by a kill
        logger.info("removed %s (left by a killed run)", path)
    if todo and (root / "manifest.json").exists():
        # the manifest describes the shards as they were: while any is rendered anew (a new plan, or a damaged shard)
        # it must not vouch for them, or a kill would leave it naming new shards of the same size (readers check sizes,
        # not hashes) beside features of the old images; written again below once every shard is done
        (root / "manifest.json").unlink()
        logger.info("removed %s until every shard is done", root / "manifest.json")

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


def main(argv: list[str] | None = None) -> None:
    args, params = parse_stage_args("Render the simulated dataset (the generate stage).", argv)
    generate.with_options(task_runner=task_runner(params.data.runner))(str(args.params))


if __name__ == "__main__":
    main()
