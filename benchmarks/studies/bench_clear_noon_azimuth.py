"""The sun at ClearNoon by the sun's azimuth: is the named weather's 0° azimuth the hard case?

CARLA's presets leave the sun's azimuth as the world had it (−1, "unchanged"); pidc renders them at
:data:`components.core.presets.PRESET_SUN_AZIMUTH` (0° from the scene's heading), while the training prior draws the
azimuth uniformly. This script renders CARLA's ``ClearNoon`` (sun altitude 45°, cloudiness 5, fog 2, no rain) on the
named weathers' 24 scenes (:func:`components.evaluate.named.scene_seeds`) at azimuths 0°, 45°, …, 315° and at a
uniform azimuth per scene (and, at those uniform azimuths, with each of its near-face parameters moved to 30), characterizes each image with a registry model (the champion by default; its backbone's
inputs, ``--draws`` posterior draws), and prints per azimuth the sun's median absolute error of the posterior median,
the 68.27 % HDI's coverage of the truth with its Clopper–Pearson interval and the HDI's median width; beside them the
same figures on the test split's daytime images whose true sun lies in 36–54° and cloudiness below 20 %.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/studies/bench_clear_noon_azimuth.py
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

from components.core import presets, seeding  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.evaluate.local import clopper_pearson  # noqa: E402
from components.evaluate.named import scene_seeds  # noqa: E402
from components.evaluate.summary import HDI_MASS, hdi  # noqa: E402

SUN = 3  # θ's index of the sun's altitude


def figures(draws: np.ndarray, truth: np.ndarray) -> dict:
    """The sun's figures of ``draws (n, m, 6)`` at truths ``(n,)``: median |error|, 68 % HDI coverage [CP], width."""
    bounds = np.array([hdi(d[:, SUN : SUN + 1], HDI_MASS) for d in draws])[:, :, 0]
    covered = (bounds[:, 0] <= truth) & (truth <= bounds[:, 1])
    lo, hi = clopper_pearson(np.array([covered.sum()]), len(covered))
    return {
        "images": len(truth),
        "median_abs_error": float(np.median(np.abs(np.median(draws[:, :, SUN], axis=1) - truth))),
        "coverage68": float(covered.mean()),
        "ci68": [float(lo[0]), float(hi[0])],
        "median_width68": float(np.median(bounds[:, 1] - bounds[:, 0])),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="champion", help="a registry model id, or champion")
    parser.add_argument("--registry", default=str(ROOT / "registry"))
    parser.add_argument("--scenes", type=int, default=24)
    parser.add_argument("--draws", type=int, default=500)
    args = parser.parse_args()
    from components.export.lookup import load_registered
    from components.features.cache import inputs_from_cached, open_features, posterior_inputs
    from components.simulate import dataset
    from components.simulate.base import make_simulator

    start = time.perf_counter()
    params = load_params(ROOT / "params.yaml")
    model = load_registered(args.model, args.registry)
    post, seed = model.posterior, params.seed
    simulator = make_simulator(params.simulator)
    seeds = scene_seeds(seed, "ClearNoon", args.scenes)
    azimuths: dict[str, list[float]] = {f"{a}°": [float(a)] * args.scenes for a in range(0, 360, 45)}
    g = seeding.rng(seed, "clear-noon-azimuth", "uniform")
    azimuths["uniform"] = g.uniform(0, 360, args.scenes).tolist()
    rows = {}
    for label, values in azimuths.items():
        images = np.stack(
            [
                simulator.render(presets.preset_weather("ClearNoon", sun_azimuth_angle=a), s)
                for a, s in zip(values, seeds, strict=True)
            ]
        )
        draws = post.sample(posterior_inputs(model.backbone, images), args.draws, seeding.derive_seed(seed, label))
        rows[label] = figures(draws, np.full(args.scenes, 45.0))
    # which of ClearNoon's near-face values costs the sun: each moved to 30 (one at a time), uniform azimuths
    for name in ("cloudiness", "fog_density", "precipitation", "wind_intensity", "precipitation_deposits"):
        images = np.stack(
            [
                simulator.render({**presets.preset_weather("ClearNoon", sun_azimuth_angle=a), name: 30.0}, s)
                for a, s in zip(azimuths["uniform"], seeds, strict=True)
            ]
        )
        draws = post.sample(posterior_inputs(model.backbone, images), args.draws, seeding.derive_seed(seed, name))
        rows[f"uniform, {name} 30"] = figures(draws, np.full(args.scenes, 45.0))
    test = dataset.open_split(ROOT / "data", "test")
    theta = test.theta
    pick = np.flatnonzero((theta[:, SUN] >= 36) & (theta[:, SUN] <= 54) & (theta[:, 0] < 20))
    x = inputs_from_cached(model.backbone, open_features(ROOT / "features", post.card["backbone"], test))[pick]
    draws = post.sample(x, args.draws, seeding.derive_seed(seed, "test-36-54"))
    rows["test 36–54°, cloud < 20"] = figures(draws, theta[pick, SUN])
    print(f"{model.name}: the sun's altitude at ClearNoon (45°) by the sun's azimuth, {args.draws} draws an image")
    print("| azimuth | images | median abs error | 68 % HDI coverage [95 % CP] | median HDI width |")
    print("|---|---:|---:|---:|---:|")
    for label, r in rows.items():
        print(
            f"| {label} | {r['images']} | {r['median_abs_error']:.2f}° | {r['coverage68']:.2f} "
            f"[{r['ci68'][0]:.2f}, {r['ci68'][1]:.2f}] | {r['median_width68']:.1f}° |"
        )
    from benchmarks.machine import machine_info

    print(json.dumps({"model": model.name, "rows": rows, "seconds": time.perf_counter() - start, **machine_info()}))


if __name__ == "__main__":
    main()
