"""What the rain streaks can tell of ``precipitation`` at Task II's weather: an exact reader against the champion.

The renderer's streaks (:mod:`components.simulate.procedural.rain`) come from a pool of drops fixed per scene: the first
``pool·(R/R_max)^k`` drops are drawn, each with the opacity ``a = α_max (p/100)^½ · clip(Z_near/Z, floor, 1)`` over
its streak, occluded by the depth map. Given an image's *exact* streak-opacity map (no image, no detector: the
renderer's own map), how well can precipitation be read? The answer bounds every reader of the streaks, the cues'
weather reader included. Lens drops (28 per scene) and the rain's extinction (confounded with fog) add a little more.

At Task II's fixed weather (``params.yaml`` ``task2.fixed`` and ``task2.sun_azimuth_angle``), ``--images`` images with
precipitation and fog density drawn from the prior (one scene each, seeds the dataset splits do not use):

- exact readers: k-nearest-neighbour regressions (k = 15, scikit-learn, fitted on the first ⅔ of the images, scored on
  the rest) of precipitation from the map's log total opacity, from its quantiles over streak pixels, from both, and
  from the total beside the scene's total at 100 % (a reader that also knew the scene's drop pool);
- the champion (``registry/``): the median |posterior median − p| and the median posterior sd on the same scored images,
  and the same k-NN regression on its posterior median (the same regressor on both sides).

Prints a table and one JSON line with machine info (``--out`` writes the JSON):

    .venv/bin/python benchmarks/studies/bench_rain.py --images 3000
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
from sklearn.neighbors import KNeighborsRegressor
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from components.core import seeding  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.core.weather import PREDICTED  # noqa: E402
from components.export.lookup import load_registered, read_champion  # noqa: E402
from components.simulate.procedural import ProceduralSimulator  # noqa: E402
from components.simulate.procedural.calibration import CALIBRATION  # noqa: E402
from components.simulate.procedural.rain import streak_alpha  # noqa: E402

SCENE_BASE = 3_000_000  # scene seeds of this benchmark (the dataset splits use others)
QUANTILES = (0.5, 0.75, 0.9, 0.95, 0.99)  # of the opacity over streak pixels (a > 0.02)
NEIGHBOURS = 15
POSTERIOR_DRAWS = 256


def exact_features(sim: ProceduralSimulator, scene_seed: int, precipitation: float, wind: float) -> np.ndarray:
    """From the scene's exact streak-opacity map: log Σa, the quantiles :data:`QUANTILES` of a over streak pixels, the
    streak pixels' share, and log Σa of the same scene at 100 % (the drop pool's capacity) → ``(8,)``."""
    sc = sim.scene(scene_seed)
    a = streak_alpha(sc, precipitation, wind, CALIBRATION)
    full = streak_alpha(sc, 100.0, wind, CALIBRATION)
    streak = a[a > 0.02]
    q = np.quantile(streak, QUANTILES) if len(streak) > 5 else np.zeros(len(QUANTILES))
    return np.r_[np.log(a.sum() + 1e-3), q, (a > 0.02).mean(), np.log(full.sum())]


def knn_error(features: np.ndarray, target: np.ndarray, fit: np.ndarray) -> float:
    """Median |p̂ − p| of a k-NN regression fitted on the rows ``fit`` and scored on the others."""
    reg = make_pipeline(StandardScaler(), KNeighborsRegressor(NEIGHBOURS)).fit(features[fit], target[fit])
    return float(np.median(np.abs(reg.predict(features[~fit]) - target[~fit])))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=3000, help="images at Task II's weather (≥ 60)")
    ap.add_argument("--params", type=Path, default=ROOT / "params.yaml")
    ap.add_argument("--model", default="champion", help="champion or a model id of registry/")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.images < 60:
        ap.error(f"--images must be at least 60 (k-NN with k = {NEIGHBOURS} on ⅔ of them), got {args.images}")
    params = load_params(args.params)
    registry = ROOT / "registry"
    name = read_champion(registry)["model"] if args.model == "champion" else args.model
    model = load_registered(name, registry, threads=2)

    t0 = time.perf_counter()
    rng = seeding.rng(params.seed, "bench_rain")
    box = params.box
    lo, hi = box.low[PREDICTED.index("precipitation")], box.high[PREDICTED.index("precipitation")]
    p = rng.uniform(lo, hi, args.images)
    fog = rng.uniform(box.low[PREDICTED.index("fog_density")], box.high[PREDICTED.index("fog_density")], args.images)
    fixed = dict(params.task2.fixed)
    wind = float(fixed["wind_intensity"])
    sim = ProceduralSimulator(params.simulator.height, params.simulator.width, cache_size=2)
    images, exact = [], []
    for i in range(args.images):
        weather = dict(fixed, precipitation=p[i], fog_density=fog[i], sun_azimuth_angle=params.task2.sun_azimuth_angle)
        images.append(sim.render(weather, SCENE_BASE + i))
        exact.append(exact_features(sim, SCENE_BASE + i, p[i], wind))
    exact_x = np.array(exact)
    render_s = time.perf_counter() - t0

    posterior = model.posterior
    draws = np.asarray(
        posterior.on_context().sample(posterior.context(model.inputs(np.stack(images))), POSTERIOR_DRAWS, params.seed)
    )[..., PREDICTED.index("precipitation")]
    median, sd = np.median(draws, 1), draws.std(1)

    fit = np.arange(args.images) < 2 * args.images // 3
    readers = {
        "exact: log total opacity": exact_x[:, [0]],
        "exact: opacity quantiles over streak pixels": exact_x[:, 1:7],
        "exact: both": exact_x[:, :7],
        "exact: both, and the scene's total at 100 %": exact_x,
        f"{name}: k-NN on its posterior median": median[:, None],
    }
    rows = {k: round(knn_error(x, p, fit), 2) for k, x in readers.items()}
    rows[f"{name}: its posterior median"] = round(float(np.median(np.abs(median - p)[~fit])), 2)
    sd_median = round(float(np.median(sd[~fit])), 2)

    print(
        f"precipitation at Task II's weather ({fixed}, fog and precipitation from the prior): {args.images} images,"
        f" scored on {int((~fit).sum())}; median |p̂ − p| (%)"
    )
    for k, v in rows.items():
        print(f"  {k:55s} {v:6.2f}")
    print(f"  {name}'s median posterior sd: {sd_median} %")
    print(
        json.dumps(
            {
                "benchmark": "rain",
                "model": name,
                "images": args.images,
                "scored": int((~fit).sum()),
                "median_abs_error": rows,
                "posterior_sd_median": sd_median,
                "render_seconds": round(render_s, 1),
                "machine": machine_info(),
            }
        )
    )
    if args.out:
        args.out.write_text(json.dumps({"rows": rows, "posterior_sd_median": sd_median}, indent=1))


if __name__ == "__main__":
    main()
