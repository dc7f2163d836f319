"""Render a split's plan into memory, without shards: more images of the pipeline's kind for scripts and benchmarks.

:func:`render_split` renders the first images of a split's plan (:func:`components.simulate.dataset.plan_split`) with
the embedded renderer, in ``workers`` processes, under any root seed: under ``params.yaml``'s seed they are byte for
byte the images of the ``generate`` stage's shards (``tests/test_dataset.py`` holds it); under another seed they
are images the pipeline never sees (the cue networks' training sets, ``benchmarks/bench_splits.py``'s test-like
splits). Nothing is written; the caller keeps what it needs.

Used by ``scripts/train_sun_head.py``, ``benchmarks/studies/bench_scale.py`` and ``benchmarks/bench_splits.py``.
"""

from __future__ import annotations

import multiprocessing as mp

import numpy as np

from components.core import weather
from components.simulate import dataset
from components.simulate.base import Simulator, make_simulator

__all__ = ["render_split"]

#: the worker process's simulator and its config (its scene cache is reused across the jobs of one process)
_SIM: tuple[object, Simulator] | None = None


def _render_rows(job: tuple[object, np.ndarray, np.ndarray]) -> np.ndarray:
    """Worker: images ``(k, H, W, 3)`` uint8 of weather rows ``(k, 13)`` in scenes ``(k,)``; job (simulator config,
    rows, scenes)."""
    global _SIM
    config, rows, seeds = job
    if _SIM is None or _SIM[0] != config:
        _SIM = (config, make_simulator(config))
    return np.stack(
        [
            _SIM[1].render({n: float(v) for n, v in zip(weather.ALL_NAMES, r, strict=True)}, int(s))
            for r, s in zip(rows, seeds, strict=True)
        ]
    )


def render_split(
    params, name: str, size: int, workers: int, seed: int | None = None, start: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Images ``(size, H, W, 3)`` uint8 and θ ``(size, 6)`` float32 (physical units,
    :data:`~components.core.weather.PREDICTED`) of rows ``start … start + size − 1`` of split ``name``'s plan under
    root seed ``seed`` (default: ``params.seed``, the pipeline's images), as ``params.simulator`` renders them (its
    size and ``render_sizes``; the embedded renderer only), rendered by ``workers`` processes. Plans are nested
    prefixes, so a large split can be rendered in consecutive pieces."""
    if size < 1 or workers < 1 or start < 0:
        raise ValueError(
            f"render_split: size and workers must be ≥ 1 and start ≥ 0, got size={size}, workers={workers}, "
            f"start={start}"
        )
    if params.simulator.backend != "procedural":
        raise ValueError(
            f"render_split renders with the embedded renderer, not simulator.backend {params.simulator.backend!r}"
        )
    sim = make_simulator(params.simulator)
    plan = dataset.plan_split(
        name,
        start + size,
        seed=params.seed if seed is None else seed,
        box=params.box,
        images_per_scene=params.data.images_per_scene,
        shard_size=params.data.shard_size,
        renderer_version=sim.version,
        resolution=(sim.height, sim.width),
    )
    chunk = 40 * params.data.images_per_scene  # whole scenes per job: the workers' scene cache is hit
    stop = start + size
    jobs = [
        (params.simulator, plan.weather[i : min(i + chunk, stop)], plan.scene_seed[i : min(i + chunk, stop)])
        for i in range(start, stop, chunk)
    ]
    with mp.get_context("fork").Pool(workers) as pool:
        images = np.concatenate(list(pool.imap(_render_rows, jobs, chunksize=1)))
    return images, plan.weather[start:stop, : len(weather.PREDICTED)].astype(np.float32)
