"""Which training images keep the posteriors calibrated on images of other resolutions? Three cues NPEs, one test.

``bench_resolution.py`` shows the champion overconfident on the renderer's own images made larger than 128 × 128 and
area-resized to it. Is that the 128-pixel renders' aliasing, which renders made larger and resized (2 × 2 supersampled
pixels, as a camera integrates light over a pixel) would cure? Three cues NPEs of ``--size`` training images, the
pipeline's settings for that size (``params.yaml`` ``train``: flow, epochs, input noise, the night regime's
temperature fitted on the validation split), on the *same* weathers and scenes (the pipeline's train and validation
splits), rendered three ways:

- ``native128``: as the pipeline renders them (its cues cache, ``features/cues``);
- ``aa256``: at 256 × 256, area-resized to 128 × 128;
- ``mix``: each image (training and validation) the one or the other, with probability ½ (seeded);
- ``vary``: the pipeline's resized renders (``simulator.render_sizes: [LOW, HIGH]`` of ``--vary``, 128..384 by default,
  :class:`components.simulate.resized.ResizedRenders`): each scene rendered at a height uniform in LOW..HIGH, drawn from
  its seed, and area-resized to 128 × 128.

Each is scored (:func:`benchmarks.studies.bench_levers.score`) on ``--test-images`` weathers from the prior, one scene each
(seeds the dataset splits do not use), rendered at every ``--test-sizes`` s and area-resized to 128 × 128: test NLL,
calibration error with the band of a perfectly calibrated model, daytime errors and central-68 % coverage.

The cues of the renders are cached in ``benchmarks/results/resolution/<renderer version>/`` (~30 MB per 20 000 images;
delete it to start over). Needs the pipeline's data and cues cache (``dvc repro features@cues``). ~25 min on 2 cores:

    .venv/bin/python benchmarks/studies/bench_resolution_training.py --size 20000
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import sys
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from benchmarks.studies.bench_levers import score  # noqa: E402
from components.core import seeding, weather  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.features import cache  # noqa: E402
from components.posterior import NPE, train  # noqa: E402
from components.posterior.settings import flow_config, temperature_regime, training_config  # noqa: E402
from components.posterior.temperature import calibrate_post_hoc  # noqa: E402
from components.simulate import dataset  # noqa: E402
from components.simulate.procedural.calibration import calibration_hash  # noqa: E402
from components.simulate.procedural.renderer import ALGORITHM_VERSION  # noqa: E402

MODELS = ("native128", "aa256", "mix", "vary")
SCENE_BASE = 5_000_000  # scene seeds of the test weathers (the dataset splits and the other benchmarks use others)
CHUNK = 400  # images per rendering task: 50 scenes of the splits' 8 images
RENDERER = f"procedural-{ALGORITHM_VERSION}+{calibration_hash()}"  # the renderer's version: caches are kept per version
RESULTS = ROOT / "benchmarks" / "results" / "resolution" / RENDERER


def _render(job: tuple) -> np.ndarray:
    """Render rows of complete weathers ``(n, 13)`` in their scenes, each at its ``sizes[i] × sizes[i]``, area-resized to
    ``out × out`` (with the renderer's calibration table ``calibration``, or its own when ``None``)."""
    from components.features.backbones.imageops import resize_area
    from components.simulate.procedural import ProceduralSimulator
    from components.simulate.procedural.calibration import CALIBRATION

    sizes, out, rows, seeds, calibration = job
    sims: dict[int, ProceduralSimulator] = {}
    images = []
    for size, r, s in zip(sizes.tolist(), rows, seeds, strict=True):
        if size not in sims:
            sims[size] = ProceduralSimulator(size, size, cache_size=2, calibration=calibration or CALIBRATION)
        image = sims[size].render(dict(zip(weather.ALL_NAMES, r, strict=True)), int(s))
        images.append(resize_area(image[None], (out, out))[0])
    return np.stack(images)


def render(rows: np.ndarray, seeds: np.ndarray, size, out: int, calibration=None) -> np.ndarray:
    """Complete weathers ``(n, 13)`` and scene seeds ``(n,)`` → uint8 images ``(n, out, out, 3)``, in 2 processes;
    ``size`` one render size for all or one per image ``(n,)``; ``calibration``: a
    :class:`~components.simulate.procedural.Calibration` other than the renderer's own."""
    sizes = np.broadcast_to(np.asarray(size, dtype=np.int64), (len(rows),))
    jobs = [
        (sizes[i : i + CHUNK], out, rows[i : i + CHUNK], seeds[i : i + CHUNK], calibration)
        for i in range(0, len(rows), CHUNK)
    ]
    with Pool(2) as pool:
        return np.concatenate(pool.map(_render, jobs))


def _render_resized(job: tuple) -> np.ndarray:
    """Render rows ``(n, 13)`` in their scenes as the pipeline does with ``simulator.render_sizes: [low, high]``."""
    from components.simulate.resized import ResizedRenders

    sizes, out, rows, seeds = job
    sim = ResizedRenders(out, out, sizes)
    return np.stack(
        [sim.render(dict(zip(weather.ALL_NAMES, r, strict=True)), int(s)) for r, s in zip(rows, seeds, strict=True)]
    )


def render_resized(rows: np.ndarray, seeds: np.ndarray, sizes: tuple[int, int], out: int) -> np.ndarray:
    """Complete weathers ``(n, 13)`` and scene seeds ``(n,)`` → uint8 images ``(n, out, out, 3)`` of the pipeline's
    resized renders (:class:`~components.simulate.resized.ResizedRenders`: each scene rendered at a height uniform in
    ``sizes`` = (low, high), drawn from its seed, and area-resized), in 2 processes."""
    jobs = [(tuple(sizes), out, rows[i : i + CHUNK], seeds[i : i + CHUNK]) for i in range(0, len(rows), CHUNK)]
    with Pool(2) as pool:
        return np.concatenate(pool.map(_render_resized, jobs))


def _cues(images: np.ndarray) -> np.ndarray:
    from components.features.backbones import get_backbone
    from components.features.cache import posterior_inputs

    torch.set_num_threads(1)
    return posterior_inputs(get_backbone("cues"), images)


def cues(images: np.ndarray) -> np.ndarray:
    """The cues of uint8 images, in 2 processes (each in the backbone's own batches and chunks)."""
    half = len(images) // 2
    with Pool(2) as pool:
        return np.concatenate(pool.map(_cues, [images[:half], images[half:]]))


def cached(name: str, make, folder: Path = RESULTS) -> np.ndarray:
    """``folder/<name>.npy`` (by default :data:`RESULTS`), made by ``make()`` when missing."""
    path = folder / f"{name}.npy"
    if path.is_file():
        return np.load(path)
    t0 = time.perf_counter()
    value = make()
    folder.mkdir(parents=True, exist_ok=True)
    np.save(path, value)
    print(f"  {name}: {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return value


def test_weathers(params, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The test weathers: θ ``(n, 6)`` from the prior, complete weathers ``(n, 13)`` (a random sun azimuth each) and
    scene seeds ``(n,)`` (from :data:`SCENE_BASE`, one scene each), seeded from ``params.seed``."""
    box = params.box
    rng = seeding.rng(params.seed, "bench_resolution_training", "test")
    theta = (box.low + rng.random((n, box.dim)) * (box.high - box.low)).astype(np.float32)
    azimuth = weather.sample_azimuth(rng, n)
    rows = np.stack(
        [weather.weather_array(weather.weather_from_theta(t, a)) for t, a in zip(theta, azimuth, strict=True)]
    )
    return theta, rows, SCENE_BASE + np.arange(n)


def fit(params, x: dict[str, np.ndarray], theta: dict[str, np.ndarray], size: int) -> NPE:
    """A cues NPE with the pipeline's settings for ``size`` training images, its temperature fitted as the pipeline."""
    fc = flow_config(params.train, size=size, trainable=False)
    tc = training_config(
        params.train,
        size=size,
        trainable=False,
        features=x["train"].shape[1],
        parameters=len(params.box.names),
        seed=params.seed,
    )
    model = NPE(None, x["train"].shape[1], params.box, fc, parameters=len(params.box.names), seed=params.seed)
    xt = {k: torch.as_tensor(v) for k, v in x.items()}
    tt = {k: torch.as_tensor(v) for k, v in theta.items()}
    train(model, (xt["train"], tt["train"]), (xt["val"], tt["val"]), tc, progress=False)
    model.eval()
    regime = temperature_regime(params.train, params.box)
    calibrate_post_hoc(model, (xt["train"], tt["train"]), (xt["val"], tt["val"]), regime)
    return model


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=20000, help="training images (a prefix of the train split)")
    ap.add_argument("--test-images", type=int, default=1000)
    ap.add_argument("--test-sizes", type=int, nargs="+", default=[128, 160, 192, 256, 384])
    ap.add_argument("--draws", type=int, default=500)
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    ap.add_argument(
        "--vary", type=int, nargs=2, default=[128, 384], metavar=("LOW", "HIGH"), help="vary's render sizes (pixels)"
    )
    ap.add_argument("--params", type=Path, default=ROOT / "params.yaml")
    args = ap.parse_args(argv)
    params = load_params(args.params)
    if not 128 <= args.vary[0] <= args.vary[1] <= 2048:
        ap.error(f"--vary LOW HIGH must satisfy 128 <= LOW <= HIGH <= 2048, got {args.vary}")
    side = params.simulator.height
    if (params.simulator.height, params.simulator.width) != (128, 128):
        ap.error(f"the pipeline's images must be 128 × 128 (aa256 supersamples them 2 × 2), got {side}")
    if args.size > params.data.splits["train"] or args.size < 1000:
        ap.error(f"--size must lie in 1000..{params.data.splits['train']} (the train split), got {args.size}")
    box = params.box
    splits = {k: dataset.open_split(ROOT / params.data.root, k) for k in ("train", "val")}
    stop = {"train": args.size, "val": None}
    theta = {k: s.theta[: stop[k]].astype(np.float32) for k, s in splits.items()}
    native = {
        k: cache.open_features(ROOT / "features", "cues", s, stop=stop[k]).astype(np.float32) for k, s in splits.items()
    }
    aa = {
        k: cached(
            f"{k}-{len(theta[k])}-aa256",
            lambda s=s, k=k: cues(render(s.weather[: stop[k]], s.scene_seed[: stop[k]], 2 * side, side)),
        )
        for k, s in splits.items()
        if {"aa256", "mix"} & set(args.models)
    }
    vary = {
        k: cached(
            f"{k}-{len(theta[k])}-resized{args.vary[0]}-{args.vary[1]}",
            lambda s=s, k=k: cues(
                render_resized(s.weather[: stop[k]], s.scene_seed[: stop[k]], tuple(args.vary), side)
            ),
        )
        for k, s in splits.items()
        if "vary" in args.models
    }
    pick = {k: seeding.rng(params.seed, "bench_resolution_training", k).random(len(theta[k])) < 0.5 for k in theta}
    inputs = {
        "native128": native,
        "aa256": aa,
        "mix": {k: np.where(pick[k][:, None], aa[k], native[k]) for k in aa},
        "vary": vary,
    }

    test_theta, rows, seeds = test_weathers(params, args.test_images)
    tests = {
        s: cached(f"test-{args.test_images}-{s}", lambda s=s: cues(render(rows, seeds, s, side)))
        for s in args.test_sizes
    }

    results: dict[str, dict] = {}
    for name in args.models:
        t0 = time.perf_counter()
        model = fit(params, inputs[name], theta, args.size)
        print(f"  {name}: trained in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
        for s, x in tests.items():
            results[f"{name}@{s}"] = score(
                model, torch.as_tensor(x), torch.as_tensor(test_theta), box, args.draws, params.seed
            )

    short = dict(zip(weather.PREDICTED, weather.SHORT_NAMES, strict=True))
    head = " ".join(f"{short[k]:>7s}" for k in box.names)
    print(
        f"cues NPEs of {args.size} images; {args.test_images} test weathers rendered at s × s, area-resized to {side}"
    )
    print(f"{'trained on':>10s} {'s':>4s} {'NLL':>6s} {'cal. err':>8s} | day error {head} | day coverage68 {head}")
    for key, r in results.items():
        name, s = key.split("@")
        err = " ".join(f"{r['day_median_abs_error'][k]:7.2f}" for k in box.names)
        cov = " ".join(f"{r['day_coverage68'][k]:7.2f}" for k in box.names)
        print(
            f"{name:>10s} {s:>4s} {r['test_nll']:6.2f} {r['calibration_error']:8.3f} |           {err} |                {cov}"
        )
    band = next(iter(results.values()))["calibration_band"]
    print(f"calibration band of a perfectly calibrated model on {args.test_images} images: {band:.3f}")
    print(
        json.dumps(
            {"benchmark": "resolution_training", "size": args.size, "results": results, "machine": machine_info()}
        )
    )


if __name__ == "__main__":
    main()
