"""Named weathers: the champion's intervals, errors and local test at CARLA's presets and at conditions on the faces.

A user tries named conditions (a clear noon, a hard rain at sunset), and their values sit on or near the prior box's
faces (no rain, no fog, a full overcast). This study runs :mod:`components.evaluate.named` (the functions the
``evaluate`` stage runs for every model, ``reports/task1/local.json``) at CARLA's 15 usable presets
(:data:`components.core.presets.USABLE`) and at the conditions ``evaluate.named.weathers`` of ``params.yaml``, on
``--scenes`` new scenes each (:func:`~components.evaluate.named.scene_seeds`, checked disjoint from every split's
seeds), with the procedural renderer at the pipeline's 128 × 128, and characterizes each image with a registry model
(the champion by default: its backbone's inputs, then ``--draws`` posterior draws). Per weather × parameter it prints
(:func:`~components.evaluate.named.weather_row`)

- the coverage of the 68.27 % and 95 % marginal HDIs (the ``pidc characterize`` intervals) with their
  Clopper–Pearson 95 % intervals (a truth on a face covered when the HDI reaches within ``--tolerance`` of it);
- beside it the same coverage of an exact posterior on a toy with the same faces (θ uniform on the box, x = θ + σ·ε,
  σ from the champion's own 68 % HDIs there, the posterior a normal truncated to the box) on ``--toy-images`` images
  at the same truth, and the 95 % range of its coverage on as many images as the champion had (a champion cell
  outside it is marked − or +);
- the median absolute error of the posterior median;
- the local test L-C2ST (:func:`~components.evaluate.named.fit_local_tests`) at level 0.05: joint and per parameter,
  fitted on the first ``--calibration`` images of the validation split, run at each weather's images, at all of them
  together and at ``--test-images`` test images (the control), each set's rejection rate beside the range the null
  classifiers give it under H₀, and its exact p-value;
- what only this study counts: each weather's training images within ±20 % of the box in every parameter.

It saves a heatmap weathers × parameters (``--figure``, :func:`components.plots.named.named_heatmap`) and prints one
JSON line with every figure and the machine.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/studies/bench_named_weathers.py
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
import time  # noqa: E402

import numpy as np  # noqa: E402

from components.core import seeding  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.core.weather import SHORT_NAMES, Box  # noqa: E402
from components.evaluate.local import Coverage, LocalTest, named_coverage, posterior_summary  # noqa: E402
from components.evaluate.named import (  # noqa: E402
    MASSES,
    NamedSet,
    check_new_scenes,
    exact_truncated_draws,
    fit_local_tests,
    local_rejections,
    named_weathers,
    pooled,
    render_sets,
    weather_row,
)
from components.evaluate.summary import hdi  # noqa: E402

#: L-C2ST: posterior draws per image summarizing x, draws per image of the statistic, the level
SUMMARY_DRAWS, TEST_DRAWS, LEVEL = 64, 500, 0.05
#: a weather's neighbourhood in the training data: within this share of the box's width in every parameter
NEIGHBOURHOOD = 0.2


def toy_coverage(
    truth: np.ndarray, sigma: np.ndarray, box: Box, n: int, m: int, rng: np.random.Generator, tolerance: float
) -> list[Coverage]:
    """The exact toy of :func:`~components.evaluate.named.weather_row` at one truth ``(d,)`` on ``n`` images: the
    coverage of its HDIs (:data:`~components.evaluate.named.MASSES`) with ``m`` draws an image (``tests/test_local.py``
    checks it)."""
    x = truth + sigma * rng.standard_normal((n, box.dim))
    draws = exact_truncated_draws(x, sigma, box, m, rng)
    out = []
    for mass in MASSES:
        bounds = [hdi(d, mass) for d in draws]
        low, high = np.array([b[0] for b in bounds]), np.array([b[1] for b in bounds])
        out.append(named_coverage(np.broadcast_to(truth, (n, box.dim)), low, high, box, tolerance, mass=mass))
    return out


def render(weathers: dict[str, tuple[str, dict]], seed: int, scenes: int) -> list[NamedSet]:
    """Each weather's images ``(scenes, 128, 128, 3)`` uint8 on its own new scenes (the procedural renderer)."""
    from tqdm import tqdm

    from components.core.opencv import ipp_off
    from components.simulate.procedural.renderer import ProceduralSimulator

    ipp_off()
    sim = ProceduralSimulator(128, 128)
    with tqdm(total=len(weathers) * scenes, desc="render", unit="image") as bar:

        def one(w: dict, s: int) -> np.ndarray:
            bar.update()
            return sim.render(w, s)

        return render_sets(one, weathers, seed, scenes)


def training_neighbours(theta_train: np.ndarray, truth: np.ndarray, box: Box, share: float = NEIGHBOURHOOD) -> int:
    """How many training truths ``(n, d)`` lie within ``share`` of the box's width of ``truth`` in every parameter
    (an interior point of a uniform prior has n·(2·share)ᵈ of them; each face it sits on halves that)."""
    return int(np.all(np.abs(theta_train - truth) <= share * box.width, axis=1).sum())


def cached_inputs(model, split, n: int) -> np.ndarray:
    """The model's inputs for the first ``n`` images of an opened split, from their cached features."""
    from components.features import cache

    return cache.inputs_from_cached(
        model.backbone, cache.open_features(ROOT / "features", model.posterior.card["backbone"], split, stop=n)
    )


def fit_tests(model, seed: int, n: int, steps: int, null_trials: int) -> list[LocalTest]:
    """The joint L-C2ST and one per parameter, fitted on the first ``n`` images of the validation split: their cached
    features, labels, one model draw per image, x summarized by the model's posterior (:data:`SUMMARY_DRAWS` draws)."""
    from tqdm import tqdm

    from components.simulate import dataset

    post = model.posterior
    split = dataset.open_split(ROOT / "data", "val")
    x = cached_inputs(model, split, n)
    theta = split.theta[: len(x)].astype(np.float64)
    draws = post.sample(x, 1, seeding.derive_seed(seed, "named-weathers", "calibration"))[:, 0]
    summary = posterior_summary(
        post.sample(x, SUMMARY_DRAWS, seeding.derive_seed(seed, "named-weathers", "summary")), post.box
    )
    return fit_local_tests(
        theta,
        summary,
        draws,
        post.box,
        steps=steps,
        null_trials=null_trials,
        seed=seed,
        progress=lambda rows: tqdm(rows, desc="L-C2ST fits", unit="fit"),
    )


def characterize(model, images: np.ndarray, seed: int, key: str, draws: int) -> tuple[np.ndarray, np.ndarray]:
    """The model's draws ``(n, draws, d)`` for images, and the L-C2ST's x: their posterior summaries ``(n, 2d)``."""
    post = model.posterior
    x = model.inputs(images)
    d = post.sample(x, draws, seeding.derive_seed(seed, "named-weathers", key, "draws"))
    s = post.sample(x, SUMMARY_DRAWS, seeding.derive_seed(seed, "named-weathers", key, "summary"))
    return d, posterior_summary(s, post.box)


def control_sample(model, seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The L-C2ST's control: the first n test images' posterior summaries ``(n, 2d)`` and draws ``(n, m, d)``."""
    from components.simulate import dataset

    post = model.posterior
    x = cached_inputs(model, dataset.open_split(ROOT / "data", "test"), n)
    draws = post.sample(x, TEST_DRAWS, seeding.derive_seed(seed, "named-weathers", "test", "draws"))
    s = post.sample(x, SUMMARY_DRAWS, seeding.derive_seed(seed, "named-weathers", "test", "summary"))
    return posterior_summary(s, post.box), draws


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="champion", help="a model id of registry/ or 'champion' (default)")
    parser.add_argument("--registry", default=str(ROOT / "registry"), help="the registry folder (default registry/)")
    parser.add_argument("--scenes", type=int, default=24, help="new scenes per weather (default 24)")
    parser.add_argument("--draws", type=int, default=1000, help="posterior draws per image (default 1000)")
    parser.add_argument("--toy-images", type=int, default=480, help="the exact toy's images per weather (480)")
    parser.add_argument("--test-images", type=int, default=96, help="test images of the L-C2ST's control (96)")
    parser.add_argument("--tolerance", type=float, default=0.5, help="a face's tolerance, θ's units (0.5)")
    parser.add_argument("--calibration", type=int, default=4000, help="validation images of the L-C2ST (4000)")
    parser.add_argument("--steps", type=int, default=200, help="L-C2ST classifiers' training steps (200)")
    parser.add_argument("--null-trials", type=int, default=39, help="L-C2ST null classifiers (39: p in k/40)")
    parser.add_argument("--figure", default=str(ROOT / "docs" / "studies" / "named-weathers.png"))
    args = parser.parse_args()
    if min(args.scenes, args.test_images, args.toy_images, args.calibration - 1) < 1 or args.draws < TEST_DRAWS:
        parser.error(f"--scenes, --test-images, --toy-images must be ≥ 1, --calibration ≥ 2, --draws ≥ {TEST_DRAWS}")
    from components.export.lookup import load_registered
    from components.plots.canvas import save_figure
    from components.plots.named import named_heatmap
    from components.simulate import dataset

    start = time.perf_counter()
    seed = int(json.loads((ROOT / "data" / "manifest.json").read_text())["seed"])
    model = load_registered(args.model, args.registry)
    box = model.posterior.box
    weathers = named_weathers("carla", load_params(ROOT / "params.yaml").evaluate.named.weathers)
    splits = {name: dataset.open_split(ROOT / "data", name) for name in dataset.SPLITS}
    used = {int(s) for split in splits.values() for s in split.scene_seed}
    try:
        check_new_scenes(used, seed, list(weathers), args.scenes)
    except ValueError as e:
        raise SystemExit(str(e)) from None
    sets = render(weathers, seed, args.scenes)
    tests = fit_tests(model, seed, args.calibration, args.steps, args.null_trials)
    control = local_rejections(tests, *control_sample(model, seed, args.test_images), LEVEL)

    rows, summaries, all_draws = [], [], []
    toy_rng = seeding.rng(seed, "named-weathers", "toy")
    for s in sets:
        draws, summary = characterize(model, s.images, seed, s.name, args.draws)
        row = weather_row(s, draws, box, args.tolerance, args.toy_images, toy_rng)
        row["training_neighbours"] = training_neighbours(splits["train"].theta, s.truth[0], box)
        row["lc2st"] = local_rejections(tests, summary, draws[:, :TEST_DRAWS], LEVEL)
        rows.append(row)
        summaries.append(summary)
        all_draws.append(draws[:, :TEST_DRAWS])
    named = local_rejections(tests, np.concatenate(summaries), np.concatenate(all_draws), LEVEL)
    report(rows, control, named, box, args, len(splits["train"]))
    title = f"{model.name}: named weathers ({sum(r['images'] for r in rows)} images)"
    save_figure(named_heatmap(rows, LEVEL, title), Path(args.figure))
    from benchmarks.machine import machine_info

    lc2st = {"steps": args.steps, "null_trials": args.null_trials, "level": LEVEL, "test": control, "named": named}
    record = {"model": model.name, "seed": seed, "scenes": args.scenes, "draws": args.draws, "lc2st": lc2st}
    record.update(tolerance=args.tolerance, weathers=rows, seconds=round(time.perf_counter() - start, 1))
    print(json.dumps({**record, **machine_info()}))


def report(rows: list[dict], control: dict, named: dict, box: Box, args, n_train: int) -> None:
    """The tables: coverage (champion | exact toy), errors, L-C2ST per weather; pooled rows; the L-C2ST sets."""
    names = box.names
    head = " ".join(f"{s:>24s}" for s in SHORT_NAMES)
    print(f"68.27 % HDI coverage on {args.scenes} images per weather: champion [95 % CP] | exact toy (− / +: outside")
    print(f"the 95 % range of a correct model's coverage on {args.scenes} images)\n{'weather':22s} {head}")
    for r in rows:
        cells = []
        for p in (r["parameters"][name] for name in names):
            mark = "−" if p["below"] else "+" if p["above"] else " "
            cells.append(f"{p['coverage68']:.2f}[{p['ci68'][0]:.2f},{p['ci68'][1]:.2f}]{mark}|{p['toy68']:.2f}")
        print(f"{r['weather']:22s} " + " ".join(f"{c:>24s}" for c in cells))
    for label, kind in (("pooled presets", "preset"), ("pooled all", None)):
        pool = pooled(rows, box, kind=kind)["parameters"]
        cells = [
            f"{p['coverage68']:.3f}[{p['ci68'][0]:.2f},{p['ci68'][1]:.2f}] |{p['toy68']:.2f}"
            for p in (pool[name] for name in names)
        ]
        print(f"{label:22s} " + " ".join(f"{c:>24s}" for c in cells))
    below = sum(r["parameters"][name]["below"] for r in rows for name in names)
    above = sum(r["parameters"][name]["above"] for r in rows for name in names)
    print(
        f"{below + above} of {len(rows) * len(names)} cells outside a correct model's range ({below} below, {above} above)"
    )
    print(f"\n95 % HDI coverage (champion | toy), median |error|, marginal L-C2ST rejections at {LEVEL} (set p); the")
    interior = round(n_train * (2 * NEIGHBOURHOOD) ** len(names))
    print(
        f"joint L-C2ST; training images within ±{NEIGHBOURHOOD:.0%} of the box in every parameter (interior: {interior})"
    )
    for r in rows:
        cells = [
            f"{p['coverage95']:.2f}|{p['toy95']:.2f} {p['median_abs_error']:6.2f} "
            f"{r['lc2st'][name]['rate']:.2f}({r['lc2st'][name]['p_value']:.3f})"
            for name, p in ((name, r["parameters"][name]) for name in names)
        ]
        j = r["lc2st"]["joint"]
        print(
            f"{r['weather']:22s} "
            + " ".join(f"{c:>26s}" for c in cells)
            + f"  joint {j['rate']:.2f}({j['p_value']:.3f}) nbrs {r['training_neighbours']}"
        )
    for title, sets in (("the named weathers' images together", named), (f"{args.test_images} test images", control)):
        print(f"\nL-C2ST at level {LEVEL} on {title}: rate, the null's 95 % range, the set's p — joint, per parameter")
        for label, key in zip(("joint", *SHORT_NAMES), ("joint", *names), strict=True):
            lo, hi = sets[key]["null_range"]
            print(f"  {label:8s} {sets[key]['rate']:.3f} [{lo:.3f}, {hi:.3f}] p {sets[key]['p_value']:.3f}")
    noon = next(r for r in rows if r["weather"] == "ClearNoon")
    print(
        f"\nClearNoon (sun 45°, clear sky): median |sun error| {noon['parameters'][names[3]]['median_abs_error']:.2f}°"
    )


if __name__ == "__main__":
    main()
