"""What a monitoring run is judged on: its date, the seeds that descend from it, and new labelled images.

A scheduled run is named by its date (the UTC date of its scheduled start, or one given): every draw of the run comes
from streams ``(seed, "monitor", "<YYYY-MM-DD>", …)`` (:mod:`components.core.seeding`), so a run re-done for the same
date draws the same images and targets, and each new date draws new ones.

* :func:`simulated_draw` — Task I images: θ uniform on the prior, the sun azimuth uniform, scenes of
  ``data.images_per_scene`` images, exactly as the test split is planned (:func:`components.simulate.dataset.plan_split`)
  but from the date's stream; rendered by the project's simulator.
* :func:`simulated_pools` — Task III: new images of each source's weather (the rows of such a plan that belong to the
  source's bag, :func:`components.domains.task3.bag_of`), the fresh pools of new in-ODD targets.
* :func:`pools_of` — the same from labelled images one has (a recorded folder): its images of each source's weather.

Used by the scheduled monitoring (``flows/monitor.py``).
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from components.core import seeding, weather
from components.core.config import BagConfig, Params
from components.domains.task3 import bag_of
from components.simulate import dataset

__all__ = ["Draw", "run_date", "run_seed", "simulated_draw", "simulated_pools", "pools_of"]

#: the most plan rows drawn looking for the images of a source's weather (its bag's share of the prior is tiny beyond)
MAX_ROWS = 1 << 20


@dataclass(frozen=True)
class Draw:
    """Labelled images: ``images`` (uint8 ``(H, W, 3)`` each; an ``(n, H, W, 3)`` array when all share a size),
    ``theta (n, 6)`` their true weather (physical units) and ``names`` (what each image is: a plan row or a file)."""

    images: Sequence[np.ndarray]
    theta: np.ndarray
    names: list[str]

    def __len__(self) -> int:
        return int(self.theta.shape[0])


def run_date(value: str | None, scheduled: dt.datetime | None = None) -> dt.date:
    """The run's date: ``value`` (``YYYY-MM-DD``), else the UTC date of ``scheduled`` (a scheduled run's start), else
    today's UTC date. ``ValueError`` naming ``date`` for anything else."""
    if value is not None:
        try:
            if not isinstance(value, str) or len(value) != 10:
                raise ValueError
            return dt.date.fromisoformat(value)
        except ValueError:
            raise ValueError(f"date: expected a day as YYYY-MM-DD (e.g. 2026-11-24), got {value!r}") from None
    when = scheduled if scheduled is not None else dt.datetime.now(dt.UTC)
    if when.tzinfo is None:
        raise ValueError(f"the scheduled start {when!r} has no time zone")
    return when.astimezone(dt.UTC).date()


def run_seed(seed: int, day: dt.date, *keys: str | int) -> int:
    """The seed of the stream ``(seed, "monitor", "<day>", *keys)``."""
    return seeding.derive_seed(seed, "monitor", day.isoformat(), *keys)


def _plan(params: Params, seed: int, n: int) -> dataset.SplitPlan:
    """``n`` rows planned as the test split is (θ ~ U(prior), azimuth, scenes), from the root ``seed``."""
    return dataset.plan_split(
        "test",
        n,
        seed=seed,
        box=params.box,
        images_per_scene=params.data.images_per_scene,
        shard_size=n,
        renderer_version="monitor",
        resolution=(params.simulator.height, params.simulator.width),
    )


def _render(simulator, rows: np.ndarray, scene_seeds: np.ndarray) -> np.ndarray:
    """The images of plan ``rows (k, 13)`` (:data:`components.core.weather.ALL_NAMES` order) in their scenes."""
    images = np.empty((len(rows), simulator.height, simulator.width, 3), dtype=np.uint8)
    for i, (row, scene_seed) in enumerate(zip(rows, scene_seeds, strict=True)):
        images[i] = simulator.render(dict(zip(weather.ALL_NAMES, map(float, row), strict=True)), int(scene_seed))
    return images


def simulated_draw(simulator, params: Params, seed: int, n: int) -> Draw:
    """``n`` new images rendered by ``simulator``: θ ~ U(prior), planned from the root ``seed`` (e.g.
    :func:`run_seed`) as the test split is."""
    plan = _plan(params, seed, n)
    return Draw(
        _render(simulator, plan.weather, plan.scene_seed),
        plan.weather[:, : len(weather.PREDICTED)].copy(),
        [f"row {i}" for i in range(n)],
    )


def simulated_pools(simulator, params: Params, seed: int, sizes: Mapping[str, int]) -> dict[str, Draw]:
    """New images of each source's weather: ``sizes`` = source bag name → images wanted; the first rows of a plan from
    the root ``seed`` that belong to that bag (:func:`~components.domains.task3.bag_of`: inside its sub-box and no
    earlier bag's), so the pools have the weather of the pipeline's fresh pools. ``ValueError`` naming the bag when
    its weather is too rare to find them."""
    bags = params.task3.bags
    n = 1024
    while True:
        plan = _plan(params, seed, n)
        owner = bag_of(bags, plan.weather[:, : len(weather.PREDICTED)])
        rows = {name: np.flatnonzero(owner == name)[:size] for name, size in sizes.items()}
        short = [name for name, size in sizes.items() if rows[name].size < size]
        if not short:
            break
        if n >= MAX_ROWS:
            raise ValueError(
                f"task3.bags.{short[0]}: fewer than {sizes[short[0]]} of {n} weathers drawn from the prior belong to "
                "this bag; its sub-box (less the earlier bags') is too small to draw new images of its weather"
            )
        n *= 4
    return {
        name: Draw(
            _render(simulator, plan.weather[idx], plan.scene_seed[idx]),
            plan.weather[idx, : len(weather.PREDICTED)].copy(),
            [f"row {i}" for i in idx],
        )
        for name, idx in rows.items()
    }


def pools_of(draw: Draw, bags: Mapping[str, BagConfig], sources: Sequence[str]) -> dict[str, Draw]:
    """The images of ``draw`` of each source's weather (those belonging to its bag, :func:`bag_of`), by source."""
    owner = bag_of(bags, draw.theta)
    out = {}
    for name in sources:
        idx = np.flatnonzero(owner == name)
        out[name] = Draw([draw.images[i] for i in idx], draw.theta[idx], [draw.names[i] for i in idx])
    return out
