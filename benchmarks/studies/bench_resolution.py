"""Images of another resolution: the champion on renders made larger than its training images and resized to them.

The models learned from the embedded renderer's images at ``simulator.height × simulator.width`` (128 × 128). A camera
gives other sizes, and every consumer (the ``pidc`` CLI, the monitoring's recorded folders) converts them to the
model's input size by area interpolation (:func:`components.features.backbones.imageops.resize_area`). Is a posterior
of such an image still sharp and calibrated? The renderer can answer for its own world: the same scene under the same
weather, rendered at ``s × s`` for each ``--sizes`` s, then area-resized to the training size (s equal to it: the
images the models learned from).

``--images`` weathers from the prior (the sun azimuth uniform), one scene each (seeds the dataset splits do not use);
the same weathers, scenes and posterior seeds at every size, so the differences are paired. Per size, with the
``evaluate`` stage's own functions (:func:`components.evaluate.task1.task1_metrics`,
:func:`components.evaluate.marginals.parameter_report`):

- the test NLL and its paired difference to the training size (a 95 % interval from the per-image differences);
- the calibration error beside the band of a perfectly calibrated model on as many images and draws;
- per parameter: the central 68 % interval's coverage (all images; Clopper–Pearson 95 % interval) and the daytime
  median |posterior median − truth|.

Prints a table and one JSON line with machine info (``--out`` writes the JSON):

    .venv/bin/python benchmarks/studies/bench_resolution.py --images 500 --sizes 128 192 256 384
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
from components.core import seeding, weather  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.evaluate import marginals, task1  # noqa: E402
from components.export.lookup import load_registered, read_champion  # noqa: E402
from components.features.backbones.imageops import resize_area  # noqa: E402
from components.simulate.procedural import ProceduralSimulator  # noqa: E402

SCENE_BASE = 4_000_000  # scene seeds of this benchmark (the dataset splits and bench_rain.py use others)
Z95 = 1.959963984540054  # the standard normal's 97.5 % quantile


def paired_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """The mean of ``a − b`` over paired values and its normal 95 % interval (the per-pair differences' standard error):
    ``(mean, low, high)``. ``ValueError`` for unequal shapes or fewer than two pairs."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1 or a.size < 2:
        raise ValueError(f"paired values must be two 1-D arrays of one length ≥ 2, got {a.shape} and {b.shape}")
    d = a - b
    mean, se = float(d.mean()), float(d.std(ddof=1) / np.sqrt(d.size))
    return mean, mean - Z95 * se, mean + Z95 * se


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=500, help="weathers from the prior, one scene each (≥ 20)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 192, 256, 384], help="render sizes s (s × s pixels)")
    ap.add_argument("--draws", type=int, default=500, help="posterior draws per image (the evaluate stage's 500)")
    ap.add_argument("--params", type=Path, default=ROOT / "params.yaml")
    ap.add_argument("--model", default="champion", help="champion or a model id of registry/")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.images < 20:
        ap.error(f"--images must be at least 20, got {args.images}")
    if args.draws < 10:
        ap.error(f"--draws must be at least 10, got {args.draws}")
    if any(s < 16 or s > 1024 for s in args.sizes):
        ap.error(f"--sizes must lie in 16..1024 pixels, got {args.sizes}")
    params = load_params(args.params)
    train_size = (params.simulator.height, params.simulator.width)
    if train_size[0] not in args.sizes or train_size[0] != train_size[1]:
        ap.error(f"--sizes must include the (square) training size {train_size[0]}, got {args.sizes}")
    registry = ROOT / "registry"
    name = read_champion(registry)["model"] if args.model == "champion" else args.model
    model = load_registered(name, registry, threads=2)
    posterior, box = model.posterior, params.box

    rng = seeding.rng(params.seed, "bench_resolution")
    theta = box.low + rng.random((args.images, box.dim)) * (box.high - box.low)
    azimuth = weather.sample_azimuth(rng, args.images)
    masks = marginals.subset_masks(theta, box)
    band = task1.calibration_band(args.images, args.draws, 0.95, 2000, params.seed)
    prior_log_volume = float(np.log(box.width).sum())

    results: dict[int, dict] = {}
    lp_truth: dict[int, np.ndarray] = {}
    for size in args.sizes:
        t0 = time.perf_counter()
        sim = ProceduralSimulator(size, size, cache_size=2)
        images = np.stack(
            [sim.render(weather.weather_from_theta(theta[i], azimuth[i]), SCENE_BASE + i) for i in range(args.images)]
        )
        if (size, size) != train_size:
            images = resize_area(images, train_size)
        flow = posterior.on_context()
        context = posterior.context(model.inputs(images))
        draws, lp = flow.sample_and_log_prob(context, args.draws, params.seed)
        lp_truth[size] = flow.log_prob(theta, context)
        metrics, _, _ = task1.task1_metrics(lp, lp_truth[size], prior_log_volume, band)
        report = marginals.parameter_report(draws, theta, box)
        results[size] = {
            "test_nll": metrics["test_nll"],
            "calibration_error": metrics["calibration_error"],
            "calibration_band": band,
            "coverage68": {k: report["all"][k]["coverage68"] for k in box.names},
            "coverage68_interval": {
                k: [report["all"][k]["coverage68_low"], report["all"][k]["coverage68_high"]] for k in box.names
            },
            "day_median_abs_error": {k: report["day"][k]["median_abs_error"] for k in box.names},
            "seconds": round(time.perf_counter() - t0, 1),
        }
        print(f"  {size}×{size}: {results[size]['seconds']} s", file=sys.stderr, flush=True)
    ref = train_size[0]
    for size in args.sizes:
        results[size]["nll_minus_training_size"] = list(paired_difference(-lp_truth[size], -lp_truth[ref]))

    short = dict(zip(weather.PREDICTED, weather.SHORT_NAMES, strict=True))
    print(
        f"{name} on {args.images} weathers from the prior, rendered at s × s and area-resized to {ref} × {ref};"
        f" {args.draws} draws each; days {int(masks['day'].sum())}"
    )
    head = " ".join(f"{short[k]:>7s}" for k in box.names)
    print(f"{'s':>4s} {'NLL':>6s} {'ΔNLL [95 %]':>20s} {'cal. err':>8s} | coverage68 {head} | day error {head}")
    for size in args.sizes:
        r = results[size]
        d = r["nll_minus_training_size"]
        cov = " ".join(f"{r['coverage68'][k]:7.2f}" for k in box.names)
        err = " ".join(f"{r['day_median_abs_error'][k]:7.2f}" for k in box.names)
        print(
            f"{size:4d} {r['test_nll']:6.2f} {d[0]:+6.2f} [{d[1]:+5.2f}, {d[2]:+5.2f}] {r['calibration_error']:8.3f} |"
            f"            {cov} |           {err}"
        )
    print(f"calibration band of a perfectly calibrated model on {args.images} images: {band:.3f}")
    out = {
        "benchmark": "resolution",
        "model": name,
        "images": args.images,
        "draws": args.draws,
        "training_size": ref,
        "results": {str(k): v for k, v in results.items()},
        "machine": machine_info(),
    }
    print(json.dumps(out))
    if args.out:
        args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
