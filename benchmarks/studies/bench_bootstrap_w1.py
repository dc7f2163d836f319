"""Task II's bootstrap of W₁: one sort and a cumulative sum per resampled bag, against a sort per resampled bag.

The ``task2`` stage's interval of the mixture's W₁ ratio minus the calibrated one's (``width_floor.interval``) resamples
the bag's images ``task2.width_floor.bootstrap`` times and takes, for each resampled bag and each varying parameter,
the W₁ between the pooled draws and the truth's sample. Side by side on data of the stage's size (``--images`` images
of ``--draws`` draws, a truth sample of ``--truth`` points, ``--replicates`` resampled bags; a Gaussian posterior per
image, seeded):

* ``scipy``: ``scipy.stats.wasserstein_distance(points[idx].ravel(), truth)`` for each resampled bag — what the stage
  did before (a sort of the bag's Nn + m values each time);
* ``sorted``: :func:`components.domains.distances.resampled_wasserstein_1d` — the points and the truth sorted once,
  each resampled bag a weighted cumulative sum.

Prints the seconds of each (best of ``--repeats``), their ratio and the largest difference, and one JSON line with the
machine's details.

    .venv/bin/python benchmarks/studies/bench_bootstrap_w1.py [--images 1000] [--draws 64] [--truth 20000] [--replicates 200]
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import wasserstein_distance

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from components.core.seeding import rng  # noqa: E402
from components.domains.distances import resampled_wasserstein_1d  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--images", type=int, default=1000)
    ap.add_argument("--draws", type=int, default=64)
    ap.add_argument("--truth", type=int, default=20000)
    ap.add_argument("--replicates", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    if min(args.images, args.draws, args.truth, args.replicates, args.repeats) < 1:
        ap.error("--images, --draws, --truth, --replicates and --repeats must be ≥ 1")

    r = rng(0, "bench", "bootstrap-w1")
    centers = r.uniform(0, 100, args.images)
    points = np.clip(centers[:, None] + 6.0 * r.standard_normal((args.images, args.draws)), 0, 100)
    truth = r.uniform(0, 100, args.truth)
    idx = r.integers(args.images, size=(args.replicates, args.images))
    counts = np.stack([np.bincount(i, minlength=args.images) for i in idx])

    def scipy_way() -> np.ndarray:
        return np.array([wasserstein_distance(points[i].ravel(), truth) for i in idx])

    def sorted_way() -> np.ndarray:
        return resampled_wasserstein_1d(points, truth, counts)

    seconds, values = {}, {}
    for name, fn in (("scipy", scipy_way), ("sorted", sorted_way)):
        best = float("inf")
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            values[name] = fn()
            best = min(best, time.perf_counter() - t0)
        seconds[name] = best
    ratio = seconds["scipy"] / seconds["sorted"]
    diff = float(np.max(np.abs(values["scipy"] - values["sorted"])))
    print(f"{args.replicates} resampled bags of {args.images} images × {args.draws} draws against {args.truth} points")
    print(f"  scipy (a sort per bag)        {seconds['scipy']:8.3f} s")
    print(f"  sorted once, cumulative sums  {seconds['sorted']:8.3f} s   ({ratio:.1f}× faster)")
    print(
        f"  largest difference            {diff:.1e} (W₁ values {values['scipy'].min():.3f}–{values['scipy'].max():.3f})"
    )
    print(
        json.dumps(
            {
                "benchmark": "bootstrap_w1",
                **vars(args),
                "seconds": seconds,
                "ratio": ratio,
                "max_abs_difference": diff,
                "machine": machine_info(),
            }
        )
    )


if __name__ == "__main__":
    main()
