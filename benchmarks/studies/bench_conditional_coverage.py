"""Is the posterior honest within each weather, not only on average? The marginals' 68 % coverage by condition.

The evaluate stage's calibration error and coverage average over the whole test split, and its profiles
(``reports/task1/profiles.json``) split each parameter's figures by that parameter's own true value. A safety engineer
asks a third question: in overcast, in heavy rain, under a high sun, does each marginal's central 68 % interval still
cover its truth 68 % of the time? This script takes an exported model (``registry/<model>``, onnxruntime, the stage's
runtime), draws ``--draws`` posterior samples for every test image (the cached features, seeded like the stage with
``--seed``), and prints, for day images (true sun altitude > 0°) in bins of cloudiness and of precipitation and for all
images in bins of the sun's altitude, each parameter's coverage of its central 68 % interval beside the range a correct
68 % would give on as many images (the 2.5 % and 97.5 % binomial quantiles), and how many of the cells fall outside it.

Conditioning on a true parameter is not conditioning on the image, so even an exact posterior is not promised 68 % in
every cell. A parameter binned by its own truth least of all: where the image tells little its honest interval stays
in the middle of the range and covers the middle bins' truths more often, the outer ones' less (the evaluate stage's
``profiles.json`` and ``profile.png`` show it per parameter); those cells are printed in brackets and not counted. The
other cells can drift where two parameters are correlated a posteriori (the sun and the clouds, the rain and its
deposits), and they share images (a row is one set of images), so they are not independent: read the count of cells
outside their range against the 5 % a correct model would give, not as a test.

    python benchmarks/studies/bench_conditional_coverage.py --model cues-50000
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

# isort: off
import components  # noqa: E402,F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse  # noqa: E402
import json  # noqa: E402

import numpy as np  # noqa: E402
from scipy.stats import binom  # noqa: E402

from benchmarks.machine import machine_info  # noqa: E402
from components.core.weather import PREDICTED, SHORT_NAMES  # noqa: E402
from components.evaluate.task1 import posterior_draws  # noqa: E402
from components.export.runtime import OnnxPosterior  # noqa: E402
from components.features import cache  # noqa: E402
from components.features.backbones import get_backbone  # noqa: E402
from components.simulate import dataset  # noqa: E402

#: the central interval whose coverage is counted
MASS = 0.6827
#: (label, conditioning parameter, bin edges, day images only)
CONDITIONS = (
    ("cloudiness", 0, (0, 20, 40, 60, 80, 100), True),
    ("precipitation", 2, (0, 25, 50, 75, 100), True),
    ("sun altitude", 3, (-90, -30, 0, 30, 60, 90), False),
)


def coverage_cells(samples: np.ndarray, theta: np.ndarray) -> tuple[list[dict], np.ndarray]:
    """Per condition and bin: the images and each parameter's coverage of its central :data:`MASS` interval, with the
    binomial range of a correct one; and the per-image coverage ``(N, d)`` (bool)."""
    tail = (1.0 - MASS) / 2
    lo, hi = np.quantile(samples, tail, axis=1), np.quantile(samples, 1.0 - tail, axis=1)
    covered = (theta >= lo) & (theta <= hi)
    day = theta[:, 3] > 0
    rows = []
    for label, j, edges, day_only in CONDITIONS:
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            last = b == edges[-1]
            mask = (
                (theta[:, j] >= a) & ((theta[:, j] <= b) if last else (theta[:, j] < b)) & (day if day_only else True)
            )
            n = int(mask.sum())
            if n == 0:
                continue
            rows.append(
                {
                    "condition": f"{'day, ' if day_only else ''}{label} {a}–{b}",
                    "parameter": j,
                    "images": n,
                    "coverage": covered[mask].mean(0).tolist(),
                    "range": [float(binom.ppf(0.025, n, MASS) / n), float(binom.ppf(0.975, n, MASS) / n)],
                }
            )
    return rows, covered


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="cues-50000", help="a model id of registry/ (default: cues-50000)")
    parser.add_argument("--draws", type=int, default=500, help="posterior draws per test image (default 500)")
    parser.add_argument("--seed", type=int, default=7, help="the draws' seed (default 7)")
    args = parser.parse_args()
    if args.draws < 50:
        parser.error(f"--draws must be at least 50 for a 68 % interval from the draws, got {args.draws}")
    folder = ROOT / "registry" / args.model
    if not folder.is_dir():
        parser.error(f"no exported model {folder} (run `dvc repro export` first, or name one of registry/)")
    posterior = OnnxPosterior.load(folder)
    card = posterior.card
    backbone = get_backbone(card["backbone"], **card["backbone_options"])
    split = dataset.open_split(ROOT / "data", "test")
    x = cache.inputs_from_cached(backbone, cache.open_features(ROOT / "features", card["backbone"], split))
    theta = split.theta[: len(x)].astype(np.float64)
    samples, _, _ = posterior_draws(posterior, x, theta, args.draws, args.seed)
    rows, covered = coverage_cells(samples, theta)

    short = SHORT_NAMES
    print(f"{args.model}: central {MASS:.2%} intervals' coverage on {len(theta)} test images, {args.draws} draws each")
    print(f"{'condition':28s} {'images':>6s} " + " ".join(f"{s:>7s}" for s in short) + "   correct model's range")
    outside = above = 0
    for r in rows:
        lo, hi = r["range"]
        marks = []
        for k, c in enumerate(r["coverage"]):
            if k == r["parameter"]:  # by its own truth: the evaluate stage's profiles, not counted here
                marks.append(f"({c:5.3f})")
                continue
            flag = "+" if c > hi else "-" if c < lo else " "
            outside += flag != " "
            above += flag == "+"
            marks.append(f"{c:6.3f}{flag}")
        print(f"{r['condition']:28s} {r['images']:6d} " + " ".join(marks) + f"   [{lo:.3f}, {hi:.3f}]")
    cells = len(rows) * (len(PREDICTED) - 1)
    print(f"all images {'':17s} {len(theta):6d} " + " ".join(f"{c:6.3f} " for c in covered.mean(0)))
    print(
        f"{outside} of {cells} cells outside a correct model's 95 % range ({above} above, {outside - above} below; "
        f"{0.05 * cells:.1f} expected were they independent); in brackets, not counted: a parameter by its own truth"
    )
    print(json.dumps({"model": args.model, "draws": args.draws, "seed": args.seed, "cells": rows, **machine_info()}))


if __name__ == "__main__":
    main()
