"""How much rain an image can tell: the renderer's drop pool against the streaks' opacity, at 128 × 128.

``bench_resolution_training.py`` found cues NPEs trained on 2 × 2 supersampled renders (256 × 256, area-resized) reading
the daytime rain far better than on the pipeline's 128-pixel ones. A 256-pixel render differs in two ways: its streaks
are anti-aliased (half a 128-pixel wide), and its scene holds 4× the drops (``rain_drop_pool`` scales with the pixel
area). This benchmark separates the two at 128 × 128 through the renderer's calibration table only
(:class:`~components.simulate.procedural.calibration.Calibration`: ``rain_drop_pool`` drops per scene, each streak of
peak opacity ``streak_alpha``): a variant ``pool=N,alpha=A`` renders the pipeline's train and validation weathers and
scenes (prefixes) and the test weathers of ``bench_resolution_training.py`` with that table, computes the cues, trains a
cues NPE with the pipeline's settings for ``--size`` images (temperature fitted as the pipeline) and scores it (test NLL,
calibration error and its band, daytime errors and central-68 % coverage, night coverage). ``native`` is the renderer's
own table on the pipeline's own cues cache.

Renders' cues are cached in ``benchmarks/results/rain_pool/<renderer version>/<variant>/`` (~40 MB each). ~6 min a variant on 2 cores:

    .venv/bin/python benchmarks/studies/bench_rain_pool.py --size 20000 --variants native pool=2800,alpha=0.1375
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from benchmarks.studies import bench_resolution_training as resolution  # noqa: E402
from benchmarks.studies.bench_levers import score  # noqa: E402
from components.core import weather  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.features import cache  # noqa: E402
from components.simulate import dataset  # noqa: E402
from components.simulate.procedural.calibration import CALIBRATION, Calibration  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "rain_pool"
KEYS = {"pool": ("rain_drop_pool", int), "alpha": ("streak_alpha", float)}


def calibration_of(variant: str) -> Calibration | None:
    """``native`` → ``None`` (the renderer's own table); ``pool=N,alpha=A`` (either or both) → the table with those."""
    if variant == "native":
        return None
    changes = {}
    for item in variant.split(","):
        key, _, value = item.partition("=")
        if key not in KEYS or not value:
            raise ValueError(
                f"variant {variant!r}: expected native or pool=N,alpha=A (keys {sorted(KEYS)}), got {item!r}"
            )
        name, kind = KEYS[key]
        changes[name] = kind(value)
    return dataclasses.replace(CALIBRATION, **changes)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=20000, help="training images (a prefix of the train split)")
    ap.add_argument("--variants", nargs="+", default=["native", "pool=2800", "pool=2800,alpha=0.1375"])
    ap.add_argument("--test-images", type=int, default=1000)
    ap.add_argument("--draws", type=int, default=500)
    ap.add_argument("--params", type=Path, default=ROOT / "params.yaml")
    args = ap.parse_args(argv)
    params = load_params(args.params)
    if (params.simulator.height, params.simulator.width) != (128, 128):
        ap.error("the pipeline's images must be 128 × 128 (the test cache of bench_resolution_training.py is)")
    if not 1000 <= args.size <= params.data.splits["train"]:
        ap.error(f"--size must lie in 1000..{params.data.splits['train']} (the train split), got {args.size}")
    try:
        tables = {v: calibration_of(v) for v in args.variants}
    except ValueError as exc:
        ap.error(str(exc))
    splits = {k: dataset.open_split(ROOT / params.data.root, k) for k in ("train", "val")}
    stop = {"train": args.size, "val": None}
    theta = {k: s.theta[: stop[k]].astype(np.float32) for k, s in splits.items()}
    test_theta, rows, seeds = resolution.test_weathers(params, args.test_images)

    results: dict[str, dict] = {}
    for variant, table in tables.items():
        if table is None:  # the pipeline's cues cache, and bench_resolution_training's test renders at 128
            x = {k: cache.open_features(ROOT / "features", "cues", s, stop=stop[k]) for k, s in splits.items()}
            folder, name = resolution.RESULTS, f"test-{args.test_images}-128"
        else:
            folder, name = (
                RESULTS / resolution.RENDERER / variant.replace(",", "_").replace("=", ""),
                f"test-{args.test_images}",
            )
            x = {
                k: resolution.cached(
                    f"{k}-{len(theta[k])}",
                    lambda s=s, k=k, table=table: resolution.cues(
                        resolution.render(s.weather[: stop[k]], s.scene_seed[: stop[k]], 128, 128, table)
                    ),
                    folder,
                )
                for k, s in splits.items()
            }
        xt = np.array(
            resolution.cached(
                name, lambda t=table: resolution.cues(resolution.render(rows, seeds, 128, 128, t)), folder
            )
        )
        t0 = time.perf_counter()
        model = resolution.fit(params, {k: v.astype(np.float32) for k, v in x.items()}, theta, args.size)
        print(f"  {variant}: trained in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
        results[variant] = score(
            model, torch.as_tensor(xt), torch.as_tensor(test_theta), params.box, args.draws, params.seed
        )

    short = dict(zip(weather.PREDICTED, weather.SHORT_NAMES, strict=True))
    names = params.box.names
    head = " ".join(f"{short[k]:>6s}" for k in names)
    print(f"cues NPEs of {args.size} images at 128 × 128; {args.test_images} test weathers")
    print(f"{'variant':>24s} {'NLL':>6s} {'cal.err':>7s} | day error {head} | night coverage68 {head}")
    for variant, r in results.items():
        err = " ".join(f"{r['day_median_abs_error'][k]:6.2f}" for k in names)
        cov = " ".join(f"{r['night_coverage68'][k]:6.2f}" for k in names)
        print(
            f"{variant:>24s} {r['test_nll']:6.2f} {r['calibration_error']:7.3f} |           {err} |                  {cov}"
        )
    band = next(iter(results.values()))["calibration_band"]
    print(f"calibration band of a perfectly calibrated model on {args.test_images} images: {band:.3f}")
    print(json.dumps({"benchmark": "rain_pool", "size": args.size, "results": results, "machine": machine_info()}))


if __name__ == "__main__":
    main()
