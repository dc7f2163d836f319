"""Does the weather reader's frozen convolution read the sun under a clear, haze-free sky? A sun head trained there.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/studies/bench_sun_head_faces.py [--images 60000] [--validation 2000]
        [--uniform-validation 4000] [--head LABEL=PATH ...] [--scenes 96] [--workers 2] [--epochs 15] [--out DIR]

Renders ``--images`` training and ``--validation`` validation images of the prior's *clear-sky face*
(``train_sun_head.FACE``: cloudiness 0–20 %, fog 0–5 %, precipitation 0–5 %, deposits 0–10 %, wind and sun over their
whole ranges; the face plans of ``train_sun_head.py --faces``, root seeds 9101 and 9102, scenes the pipeline never
uses), passes them through the reader's frozen convolutions and reports each sun head's daytime error (median
|μ − altitude| of its mirror-averaged guess, by 18° bin) on that validation set, on the uniform plan's validation
(``train_sun_head.py``'s, root seed 9002; ``--out``/cache holds the maps of both, in ``train_sun_head.py --cache``'s
files) and on CARLA's ClearNoon (45°) over ``--scenes``
of the named weathers' scenes, at their 0° azimuth and at uniform azimuths. The heads: the shipped one, any
``--head LABEL=PATH`` (e.g. an earlier version's weights), and one trained here on the face images alone (the
probe: is the sun in the frozen convolutions at the face?). Writes ``faces.json`` into ``--out``.
Study: docs/studies/sun-head-faces.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

# isort: off
import components  # noqa: E402,F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from train_sun_head import FACE, FACE_SEED_OFFSET, SUN, maps, mirrored_guess, rendered_maps, train_head  # noqa: E402

from components.core.config import load_params  # noqa: E402
from components.core.weather import Box  # noqa: E402
from components.features.backbones import weather_reader as wr  # noqa: E402


def clear_noon_maps(params, net, scenes: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Maps and θ of CARLA's ClearNoon (sun 45°) on ``scenes`` of the named weathers' scenes, at the sun azimuth of
    the named weathers (0°) and at a uniform azimuth per scene (``bench_clear_noon_azimuth.py``'s images)."""
    from components.core import presets, seeding
    from components.evaluate.named import scene_seeds
    from components.simulate.base import make_simulator

    simulator = make_simulator(params.simulator)
    seeds = scene_seeds(params.seed, "ClearNoon", scenes)
    uniform = seeding.rng(params.seed, "clear-noon-azimuth", "uniform").uniform(0, 360, scenes)
    out = {}
    for label, azimuths in (("ClearNoon, azimuth 0°", np.zeros(scenes)), ("ClearNoon, uniform azimuth", uniform)):
        images = np.stack(
            [
                simulator.render(presets.preset_weather("ClearNoon", sun_azimuth_angle=float(a)), int(s))
                for a, s in zip(azimuths, seeds, strict=True)
            ]
        )
        theta = np.zeros((scenes, 6), np.float32)
        theta[:, SUN] = 45.0
        out[label] = (maps(net, images), theta)
    return out


def day_errors(head: wr.SunHead, m: np.ndarray, theta: np.ndarray) -> dict:
    """Daytime median |μ − altitude| (°) of ``head`` on maps ``m``: overall and by 18° bin, with counts."""
    box = Box.full()
    scale = box.high[SUN] - box.low[SUN]
    with torch.no_grad():
        g = mirrored_guess(head, torch.from_numpy(m))
    mu = box.low[SUN] + g[:, 0, 0].numpy().astype(np.float64) * scale
    sun = theta[:, SUN].astype(np.float64)
    err = np.abs(mu - sun)
    day = sun > 0
    out = {"day": float(np.median(err[day])), "n_day": int(day.sum())}
    for a in range(0, 90, 18):
        sel = day & (sun >= a) & (sun < a + 18)
        out[f"{a}-{a + 18}"] = float(np.median(err[sel])) if sel.any() else None
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=60000)
    ap.add_argument("--validation", type=int, default=2000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--epochs", type=int, default=15)
    ap.add_argument("--scenes", type=int, default=96, help="ClearNoon scenes (the named weathers' first 24 and more)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument(
        "--uniform-validation",
        type=int,
        default=4000,
        help="images of the uniform plan's validation (train_sun_head.py's, root seed 9002) to score on",
    )
    ap.add_argument("--head", action="append", default=[], help="LABEL=PATH: another sun head to score (repeatable)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "sun_head_faces")
    a = ap.parse_args()
    params = load_params(ROOT / "params.yaml")
    t0 = time.perf_counter()
    net = wr.load_reader()
    cache = a.out / "cache"
    seed = 9001 + FACE_SEED_OFFSET  # train_sun_head.py's face plans under its default --root-seed
    m, theta = rendered_maps(params, net, "train", a.images, seed, a.workers, cache, faces=True)
    vm, vtheta = rendered_maps(params, net, "val", a.validation, seed + 1, a.workers, cache, faces=True)
    print(f"face maps: {len(m)} + {len(vm)} in {time.perf_counter() - t0:.0f} s", flush=True)
    uni_val = rendered_maps(params, net, "val", a.uniform_validation, 9002, a.workers, cache)
    heads = {"shipped": wr.load_sun_head()}
    for spec in a.head:
        label, _, path = spec.partition("=")
        if not path:
            ap.error(f"--head takes LABEL=PATH (a weights file with its card beside it), got {spec!r}")
        heads[label] = wr.load_sun_head(Path(path), Path(path).with_suffix(".json"))
    kw = dict(epochs=a.epochs, seed=a.seed, batch_size=512, lr=5e-4, log=lambda s: print(s, flush=True))
    heads["faces only"] = train_head(m, theta, vm, vtheta, **kw)[0]
    noon = clear_noon_maps(params, net, a.scenes)
    rows = {}
    for name, head in heads.items():
        rows[name] = {"faces": day_errors(head, vm, vtheta)}
        for label, (cm, ct) in noon.items():
            rows[name][label] = day_errors(head, cm, ct)["day"]
        rows[name]["uniform"] = day_errors(head, *uni_val)
        print(name, json.dumps(rows[name]), flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "faces.json").write_text(
        json.dumps({"face_box": FACE, "images": a.images, "validation": a.validation, "heads": rows}, indent=1)
    )


if __name__ == "__main__":
    main()
