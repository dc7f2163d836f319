"""Rendering speed of the procedural simulator, single process, one OpenCV thread.

Three settings per resolution (images/s on one core):
- cached scene: the same scene under many weathers (posterior predictive checks);
- fresh scene: every image in a new scene (geometry built every time);
- dataset: ``--per-scene`` consecutive weathers per scene (the generate stage; default 8).

Weathers are drawn from the uniform prior. Prints a table and one JSON line with machine info.

    .venv/bin/python benchmarks/bench_render.py --images 400 --sizes 128 256
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import os
import platform
import time

import cv2
import numpy as np

from components.core.weather import Box, sample_azimuth, weather_from_theta
from components.simulate.procedural import ProceduralSimulator


def _weathers(n: int, seed: int) -> list[dict[str, float]]:
    rng = np.random.default_rng(seed)
    theta = Box.full().sample(rng, n)
    az = sample_azimuth(rng, n)
    return [weather_from_theta(t, a) for t, a in zip(theta, az, strict=False)]


def _rate(fn, n: int) -> tuple[float, float]:
    """(images/s by wall clock, images/s by this process's CPU time): on a shared machine the
    second is the better per-core figure."""
    w0, c0 = time.perf_counter(), time.process_time()
    fn()
    return n / (time.perf_counter() - w0), n / (time.process_time() - c0)


def bench(size: int, n: int, per_scene: int, seed: int) -> dict[str, tuple[float, float]]:
    ws = _weathers(n, seed)
    sim = ProceduralSimulator(size, size, cache_size=4)
    sim.render(ws[0], 0)  # warm-up (imports, LUTs)

    def cached() -> None:
        for w in ws:
            sim.render(w, 0)

    def fresh() -> None:
        for i, w in enumerate(ws):
            sim.render(w, 10_000 + i)

    def dataset() -> None:
        for i, w in enumerate(ws):
            sim.render(w, 100_000 + i // per_scene)

    return {
        "cached_scene": _rate(cached, n),
        "fresh_scene": _rate(fresh, n),
        f"{per_scene}_per_scene": _rate(dataset, n),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=400, help="images per setting (default 400)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256], help="square image sizes (pixels)")
    ap.add_argument("--per-scene", type=int, default=8, help="weathers per scene in the dataset setting")
    ap.add_argument("--seed", type=int, default=0, help="seed of the weather draws")
    args = ap.parse_args()
    if args.images < 1 or args.per_scene < 1:
        ap.error("--images and --per-scene must be >= 1")
    cv2.setNumThreads(1)
    results = {}
    for size in args.sizes:
        r = bench(size, args.images, args.per_scene, args.seed)
        results[f"{size}x{size}"] = r
        print(
            f"{size}x{size}: " + ", ".join(f"{k} {v[0]:6.1f} img/s wall ({v[1]:6.1f} per CPU-s)" for k, v in r.items()),
            flush=True,
        )
    info = {
        "benchmark": "render",
        "version": ProceduralSimulator().version,
        "images": args.images,
        "per_scene": args.per_scene,
        "results_images_per_s_per_core": {
            k: {s: {"wall": v[0], "cpu": v[1]} for s, v in r.items()} for k, r in results.items()
        },
        "machine": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "opencv": cv2.__version__,
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "load_avg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        },
    }
    print(json.dumps(info))


if __name__ == "__main__":
    main()
