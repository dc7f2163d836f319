"""What the visible road's wet share can tell of ``precipitation_deposits``: the best error of an ideal reader.

The renderer floods a road pixel where the static puddle noise under it (a quantile u, one 64-texel tile of
``calibration.puddle_scale`` metres repeated over the world, shifted and turned per scene) lies below
q = deposits/100 · (1 + edge), with a soft edge: wet weight a = clip((q − u)/edge, 0, 1)
(:mod:`components.simulate.procedural.reflections`, the renderer's step 6). A reader that sees only *how much* of the
road is wet, per distance band, and knows the mean wet share of each band at every deposits level, can do no better
than invert that mean curve. Its error comes from the scenes alone: a camera sees a few noise periods near the car and
many far away. This script computes, from each scene's own puddle lookups (no image, no detector: the wet share is
exact):

- the spread of the wet share across scenes at deposits 30 and 60, per band (near < 10 m, mid 10–25 m, far ≥ 25 m,
  all road pixels);
- the median |d̂ − d| of the ideal reader over scenes × deposits 0…100, from one band and from the three together
  (a least-squares fit of the three bands' mean curves, each weighted by its variance at that level).

Prints a table and one JSON line with machine info (``--out`` writes the JSON):

    .venv/bin/python benchmarks/studies/bench_puddles.py --scenes 200
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

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from components.simulate.procedural import ProceduralSimulator  # noqa: E402
from components.simulate.procedural.calibration import CALIBRATION  # noqa: E402

#: distance bands (m) of the road pixels
BANDS = {"near": (0.0, 10.0), "mid": (10.0, 25.0), "far": (25.0, np.inf), "all": (0.0, np.inf)}
LEVELS = np.linspace(0.0, 100.0, 401)  # deposits (%), in steps of 0.25


def wet_shares(sim: ProceduralSimulator, scene_seed: int) -> dict[str, np.ndarray]:
    """Per band, the wet share of the road pixels at each deposits level: ``(len(LEVELS),)``, NaN where empty."""
    sc = sim.scene(scene_seed)
    refl = sc.reflections
    depth = sc.depth[refl.pixels]
    edge = CALIBRATION.puddle_edge
    q = LEVELS[:, None] / 100.0 * (1.0 + edge)
    wet = np.clip((q - refl.quantile[None, :]) / edge, 0.0, 1.0)  # (levels, road pixels)
    out = {}
    for name, (lo, hi) in BANDS.items():
        m = (depth >= lo) & (depth < hi)
        out[name] = wet[:, m].mean(axis=1) if m.sum() >= 20 else np.full(len(LEVELS), np.nan)
    return out


def ideal_errors(shares: np.ndarray, bands: list[int]) -> np.ndarray:
    """|d̂ − d| of the ideal reader for every scene and level: ``shares`` (scenes, bands, levels) → (scenes, levels).

    d̂ minimizes Σ_b (f_b − μ_b(d'))² / σ²_b(d') over the level grid d', with μ_b, σ_b the bands' mean and spread
    across the scenes (a scene missing a band leaves it out).
    """
    s = shares[:, bands]
    mu = np.nanmean(s, axis=0)  # (bands, levels)
    var = np.nanvar(s, axis=0) + 1e-4  # the floor keeps the dry and flooded ends finite
    err = np.empty((s.shape[0], len(LEVELS)))
    for i in range(s.shape[0]):
        f = s[i]  # (bands, levels): the scene's shares at each true level
        ok = np.isfinite(f[:, 0])
        # cost[d_true, d_guess] = Σ_b (f_b(d_true) − μ_b(d_guess))² / σ²_b(d_guess)
        diff = f[ok][:, :, None] - mu[ok][:, None, :]
        cost = (diff**2 / var[ok][:, None, :] + np.log(var[ok][:, None, :])).sum(axis=0)
        err[i] = np.abs(LEVELS[np.argmin(cost, axis=1)] - LEVELS)
    return err


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=200, help="scenes (default 200)")
    ap.add_argument("--first-scene", type=int, default=0, help="seed of the first scene (default 0)")
    ap.add_argument("--size", type=int, default=128, help="image height and width in pixels (default 128)")
    ap.add_argument("--out", type=Path, default=None, help="write the JSON here too")
    args = ap.parse_args(argv)
    if args.scenes < 10:
        ap.error(f"--scenes must be at least 10, got {args.scenes}")
    sim = ProceduralSimulator(args.size, args.size, cache_size=1)
    t0 = time.perf_counter()
    per_scene = [wet_shares(sim, args.first_scene + i) for i in range(args.scenes)]
    shares = np.stack([[s[b] for b in BANDS] for s in per_scene])  # (scenes, bands, levels)
    names = list(BANDS)
    result: dict = {
        "benchmark": "puddles",
        "scenes": args.scenes,
        "size": args.size,
        "puddle_scale_m": CALIBRATION.puddle_scale,
        "bands": {},
    }
    print(f"{'band':<22} {'scenes':>6} {'sd at 30':>9} {'sd at 60':>9} {'ideal reader: median |d̂ − d|':>30}")
    rows = [([i], name) for i, name in enumerate(names)] + [([0, 1, 2], "near + mid + far")]
    for bands, label in rows:
        err = ideal_errors(shares, bands)
        present = np.isfinite(shares[:, bands, 0]).all(axis=1)
        sd30 = [float(np.nanstd(shares[:, b, 120])) for b in bands]
        sd60 = [float(np.nanstd(shares[:, b, 240])) for b in bands]
        median = float(np.median(err[present]))
        result["bands"][label] = {
            "scenes": int(present.sum()),
            "sd_at_30": sd30,
            "sd_at_60": sd60,
            "ideal_median_abs_error": median,
            "ideal_median_abs_error_20_80": float(np.median(err[present][:, 80:321])),
        }
        sd = "" if len(bands) > 1 else f"{sd30[0]:>9.3f} {sd60[0]:>9.3f}"
        print(f"{label:<22} {int(present.sum()):>6} {sd:>19} {median:>30.1f}")
    result["seconds"] = time.perf_counter() - t0
    line = json.dumps(result | machine_info())
    print(line)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(line + "\n")


if __name__ == "__main__":
    main()
