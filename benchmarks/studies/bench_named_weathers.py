"""Named weathers: the champion's intervals, errors and local test at CARLA's presets and at conditions on the faces.

A user tries named conditions (a clear noon, a hard rain at sunset), and their values sit on or near the prior box's
faces (no rain, no fog, a full overcast). This script renders each of CARLA's 15 usable presets
(:data:`components.core.presets.USABLE`) and the conditions of :data:`OWN` on ``--scenes`` new scenes each (scene seeds
``derive_seed(seed, "scene", "named-weathers", name, j)``: a key path the dataset's plan cannot make, which draws
``derive_seed(seed, "scene", split, j)`` for split train/val/test; checked disjoint from every split's seeds), with the
procedural renderer at the pipeline's 128 × 128, and characterizes each image with a registry model (the champion by
default: its backbone's inputs, then ``--draws`` posterior draws). Per weather × parameter it prints

- the coverage of the 68.27 % and 95 % marginal HDIs (:func:`components.evaluate.summary.hdi`, the ``pidc
  characterize`` intervals) with their Clopper–Pearson 95 % intervals (:func:`components.evaluate.local.named_coverage`,
  a truth on a face covered when the HDI reaches within ``--tolerance`` of it);
- beside it the same coverage of an exact posterior on a toy with the same faces: θ uniform on the same box, x = θ +
  σ·ε with one σ per weather × parameter taken from the champion's own 68 % HDIs there (half the median width, the
  whole width where the interval touches a face), the posterior a normal truncated to the box, drawn and summarized
  like the champion's (as many draws, the same HDIs and tolerance), at the same truth on ``--toy-images`` images: what
  a correct model gives at that weather, and the 95 % range of its coverage on as many images as the champion had
  (a champion cell outside it is marked − or +);
- the median absolute error of the posterior median;
- the local test L-C2ST (:class:`components.evaluate.local.LocalTest`) at level 0.05: joint and per parameter, fitted
  on the first ``--calibration`` images of the validation split (their cached features, their labels, one draw of
  the model per image; x summarized by the model's own posterior medians and spreads,
  :func:`components.evaluate.local.posterior_summary`), run at each weather's images, at all of them together and at
  ``--test-images`` test images, each set's rejection rate beside the range the null classifiers give it under H₀,
  and its exact p-value.

It saves a heatmap weathers × parameters (``--figure``) and prints one JSON line with every figure and the machine.

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
from scipy.stats import binom  # noqa: E402

from components.core import presets, seeding, weather  # noqa: E402
from components.core.weather import SHORT_NAMES, Box  # noqa: E402
from components.evaluate.local import (  # noqa: E402
    Coverage,
    LocalTest,
    clopper_pearson,
    named_coverage,
    posterior_summary,
)
from components.evaluate.summary import HDI_MASS, hdi  # noqa: E402

#: conditions of this study, on or near the box's faces (the six predicted parameters; sun azimuth 0° as the presets)
OWN: dict[str, dict[str, float]] = {
    "pidc:ClearHighSun": {
        "cloudiness": 0,
        "fog_density": 0,
        "precipitation": 0,
        "sun_altitude_angle": 85,
        "wind_intensity": 0,
        "precipitation_deposits": 0,
    },
    "pidc:ClearLowSun": {
        "cloudiness": 0,
        "fog_density": 0,
        "precipitation": 0,
        "sun_altitude_angle": 3,
        "wind_intensity": 0,
        "precipitation_deposits": 0,
    },
    "pidc:FoggyNoon": {
        "cloudiness": 30,
        "fog_density": 95,
        "precipitation": 0,
        "sun_altitude_angle": 45,
        "wind_intensity": 10,
        "precipitation_deposits": 0,
    },
    "pidc:StormNoon": {
        "cloudiness": 100,
        "fog_density": 100,
        "precipitation": 100,
        "sun_altitude_angle": 45,
        "wind_intensity": 100,
        "precipitation_deposits": 100,
    },
    "pidc:ClearDeepNight": {
        "cloudiness": 0,
        "fog_density": 0,
        "precipitation": 0,
        "sun_altitude_angle": -85,
        "wind_intensity": 0,
        "precipitation_deposits": 0,
    },
}
#: the credible masses whose HDIs are counted
MASSES = (HDI_MASS, 0.95)
#: L-C2ST: posterior draws per image summarizing x, draws per image of the statistic, the level
SUMMARY_DRAWS, TEST_DRAWS, LEVEL = 64, 500, 0.05
#: a weather's neighbourhood in the training data: within this share of the box's width in every parameter
NEIGHBOURHOOD = 0.2


def named_weathers() -> dict[str, dict[str, float]]:
    """Name → complete weather (13 parameters): CARLA's usable presets, then :data:`OWN` (azimuth 0°)."""
    out = {name: presets.preset_weather(name) for name in presets.USABLE}
    for name, values in OWN.items():
        out[name] = weather.complete_weather(
            {**values, "sun_azimuth_angle": presets.PRESET_SUN_AZIMUTH}, where=f"{name}: "
        )
    return out


def scene_seeds(seed: int, name: str, scenes: int) -> list[int]:
    """The scenes of weather ``name``: ``derive_seed(seed, "scene", "named-weathers", name, j)``, j < ``scenes``."""
    return [seeding.derive_seed(seed, "scene", "named-weathers", name, j) for j in range(scenes)]


def exact_truncated_draws(x: np.ndarray, sigma: np.ndarray, box: Box, m: int, rng: np.random.Generator) -> np.ndarray:
    """Draws of the exact posterior of the toy θ ~ U(box), x = θ + σ·ε (ε ~ N(0, I)): per parameter a normal of
    mean xⱼ and scale σⱼ truncated to [lowⱼ, highⱼ], by the inverse CDF.

    A standard normal truncated to [a, b] is Φ⁻¹(U(Φ(a), Φ(b))); where a > 0 it is drawn as minus its mirror image on
    [−b, −a], so that Φ is always evaluated in its lower tail (accurate to the smallest doubles, far beyond a face).

    Arguments:
        x: ``(n, d)`` observations (unbounded).
        sigma: ``(d,)`` the noise scales, > 0, θ's units.
        box: the prior box (d parameters).
        m: draws per observation.
        rng: the draws' generator.

    Returns:
        ``(n, m, d)`` draws inside the box.
    """
    from scipy.special import ndtr, ndtri

    x = np.asarray(x, dtype=np.float64)[:, None, :]
    a, b = (box.low - x) / sigma, (box.high - x) / sigma
    flip = a > 0
    lo, hi = np.where(flip, -b, a), np.where(flip, -a, b)
    u = rng.random((x.shape[0], m, box.dim))
    z = ndtri(ndtr(lo) + u * (ndtr(hi) - ndtr(lo)))
    z = np.clip(np.where(flip, -z, z), a, b)
    return np.clip(x + sigma * z, box.low, box.high)


def toy_sigma(low: np.ndarray, high: np.ndarray, box: Box) -> np.ndarray:
    """The toy's σ ``(d,)`` matching 68.27 % HDIs ``(n, d)``: per image half the width (a normal's ±1σ), the whole
    width where the interval touches a face (within 1 % of the box: a half-normal's 68.27 % is [0, σ]); the median
    over images, at least 0.1 % of the box."""
    width = high - low
    touch = (low - box.low < 0.01 * box.width) | (box.high - high < 0.01 * box.width)
    return np.maximum(np.median(np.where(touch, width, width / 2), axis=0), 1e-3 * box.width)


def toy_coverage(
    truth: np.ndarray, sigma: np.ndarray, box: Box, n: int, m: int, rng: np.random.Generator, tolerance: float
) -> list[Coverage]:
    """The coverage of an exact posterior's HDIs (:data:`MASSES`) at one truth ``(d,)`` on ``n`` simulated images."""
    x = truth + sigma * rng.standard_normal((n, box.dim))
    draws = exact_truncated_draws(x, sigma, box, m, rng)
    return [_coverage(draws, np.broadcast_to(truth, (n, box.dim)), box, mass, tolerance) for mass in MASSES]


def _coverage(draws: np.ndarray, truth: np.ndarray, box: Box, mass: float, tolerance: float) -> Coverage:
    bounds = [hdi(d, mass) for d in draws]
    low, high = np.array([b[0] for b in bounds]), np.array([b[1] for b in bounds])
    return named_coverage(truth, low, high, box, tolerance, mass=mass)


def render(weathers: dict[str, dict[str, float]], seed: int, scenes: int) -> dict[str, np.ndarray]:
    """Each weather's images ``(scenes, 128, 128, 3)`` uint8 on its own new scenes."""
    from tqdm import tqdm

    from components.core.opencv import ipp_off
    from components.simulate.procedural.renderer import ProceduralSimulator

    ipp_off()
    sim = ProceduralSimulator(128, 128)
    return {
        name: np.stack([sim.render(w, s) for s in scene_seeds(seed, name, scenes)])
        for name, w in tqdm(weathers.items(), desc="render", unit="weather")
    }


def check_new_scenes(splits: dict, seed: int, names: list[str], scenes: int) -> None:
    """Raise when a scene seed of this study is one of the dataset's (``splits``: every split of data/, opened)."""
    used = set()
    for split in splits.values():
        used |= set(split.scene_seed.tolist())
    mine = {s for name in names for s in scene_seeds(seed, name, scenes)}
    if mine & used or len(mine) != len(names) * scenes:
        raise SystemExit(f"{len(mine & used)} scene seeds of this study are the dataset's; pick other keys")


def training_neighbours(theta_train: np.ndarray, truth: np.ndarray, box: Box, share: float = NEIGHBOURHOOD) -> int:
    """How many training truths ``(n, d)`` lie within ``share`` of the box's width of ``truth`` in every parameter
    (an interior point of a uniform prior has n·(2·share)ᵈ of them; each face it sits on halves that)."""
    return int(np.all(np.abs(theta_train - truth) <= share * box.width, axis=1).sum())


def fit_tests(model, seed: int, n: int, steps: int, null_trials: int) -> list[LocalTest]:
    """The joint L-C2ST and one per parameter, fitted on the first ``n`` images of the validation split: their cached
    features, labels, one model draw per image, x summarized by the model's posterior (:data:`SUMMARY_DRAWS` draws)."""
    from tqdm import tqdm

    from components.features import cache
    from components.simulate import dataset

    post, box = model.posterior, model.posterior.box
    split = dataset.open_split(ROOT / "data", "val")
    backbone = model.backbone
    x = cache.inputs_from_cached(backbone, cache.open_features(ROOT / "features", post.card["backbone"], split, stop=n))
    theta = split.theta[: len(x)].astype(np.float64)
    draws = post.sample(x, 1, seeding.derive_seed(seed, "named-weathers", "calibration"))[:, 0]
    summary = posterior_summary(
        post.sample(x, SUMMARY_DRAWS, seeding.derive_seed(seed, "named-weathers", "summary")), box
    )
    tests = []
    for j in tqdm(range(-1, box.dim), desc="L-C2ST fits", unit="fit"):
        cols = slice(None) if j < 0 else slice(j, j + 1)
        sub = box if j < 0 else Box(box.low[cols], box.high[cols], names=box.names[cols])
        test = LocalTest(box=sub, steps=steps, null_trials=null_trials, seed=seeding.derive_seed(seed, "lc2st", j + 1))
        tests.append(test.fit(theta[:, cols], summary, draws[:, cols]))
    return tests


def characterize(model, images: np.ndarray, seed: int, key: str, draws: int) -> tuple[np.ndarray, np.ndarray]:
    """The model's draws ``(n, draws, d)`` for images, and the L-C2ST's x: their posterior summaries ``(n, 2d)``."""
    post = model.posterior
    x = model.inputs(images)
    d = post.sample(x, draws, seeding.derive_seed(seed, "named-weathers", key, "draws"))
    s = post.sample(x, SUMMARY_DRAWS, seeding.derive_seed(seed, "named-weathers", key, "summary"))
    return d, posterior_summary(s, post.box)


def local_rejections(tests: list[LocalTest], summary: np.ndarray, draws: np.ndarray) -> list[dict]:
    """Joint, then per-parameter L-C2ST on one set of images: rate, the null range, the set's p-value."""
    out = []
    for j, test in enumerate(tests):
        cols = slice(None) if j == 0 else slice(j - 1, j)
        r = test.rejections(summary, draws[:, :TEST_DRAWS, cols], LEVEL)
        out.append({"rate": r.rate, "null_range": list(r.null_range()), "p_value": r.p_value})
    return out


def correct_range(rate: np.ndarray, n: int) -> np.ndarray:
    """The central 95 % range ``(d, 2)`` of a coverage on n images when each covers with probability ``rate``."""
    return np.stack([binom.ppf(0.025, n, rate), binom.ppf(0.975, n, rate)], axis=1) / n


def measure(name: str, truth: np.ndarray, draws: np.ndarray, box: Box, args, rng: np.random.Generator) -> dict:
    """One weather's row: per parameter the champion's coverage (68 %, 95 %, Clopper–Pearson), the exact toy's at the
    same truth on ``args.toy_images`` images with the 95 % range of its coverage on as many images as the champion's,
    and the median absolute error."""
    n = len(draws)
    t = np.broadcast_to(truth, (n, box.dim))
    cov = [_coverage(draws, t, box, mass, args.tolerance) for mass in MASSES]
    bounds = [hdi(d, HDI_MASS) for d in draws]
    sigma = toy_sigma(np.array([b[0] for b in bounds]), np.array([b[1] for b in bounds]), box)
    toy = toy_coverage(truth, sigma, box, args.toy_images, args.draws, rng, args.tolerance)
    span = correct_range(toy[0].rate, n)
    err = np.median(np.abs(np.median(draws, axis=1) - truth), axis=0)
    return {
        "weather": name,
        "preset": name in presets.USABLE,
        "truth": truth.tolist(),
        "covered68": cov[0].covered.tolist(),
        "parameters": [
            {
                "coverage68": float(cov[0].rate[j]),
                "ci68": [float(cov[0].low[j]), float(cov[0].high[j])],
                "coverage95": float(cov[1].rate[j]),
                "ci95": [float(cov[1].low[j]), float(cov[1].high[j])],
                "toy68": float(toy[0].rate[j]),
                "toy95": float(toy[1].rate[j]),
                "toy_range68": span[j].tolist(),
                "toy_sigma": float(sigma[j]),
                "median_abs_error": float(err[j]),
            }
            for j in range(box.dim)
        ],
    }


def heatmap(rows: list[dict], path: Path) -> None:
    """Weathers × parameters: the champion's 68 % coverage beside the exact toy's. A champion cell outside the range
    a correct model gives on as many images is marked − (below) or + (above); a cell whose marginal L-C2ST rejects
    the weather's images as a set at level 0.05 is outlined."""
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.patches import Rectangle

    from components.plots.canvas import new_figure, save_figure

    names = [r["weather"] for r in rows]
    fig = new_figure(13, 0.36 * len(rows) + 1.8)
    axes = fig.subplots(1, 2, sharey=True)
    titles = ("champion (− / + outside a correct model's range; box: L-C2ST rejects)", "exact posterior, same faces")
    for ax, key, title in zip(axes, ("coverage68", "toy68"), titles, strict=True):
        c = np.array([[p[key] for p in r["parameters"]] for r in rows])
        im = ax.imshow(c, cmap="RdBu", norm=TwoSlopeNorm(HDI_MASS, 0.0, 1.0), aspect="auto")
        for i, r in enumerate(rows):
            for j, p in enumerate(r["parameters"]):
                mark = ""
                if key == "coverage68":
                    lo, hi = p["toy_range68"]
                    mark = "−" if p[key] < lo else "+" if p[key] > hi else ""
                    if p["lc2st_p"] <= LEVEL:
                        ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, lw=1.6, ec="black"))
                ax.text(j, i, f"{c[i, j]:.2f}{mark}", ha="center", va="center", fontsize=7)
        ax.set_xticks(range(len(SHORT_NAMES)), SHORT_NAMES)
        ax.set_title(f"68.27 % HDI coverage — {title}", fontsize=9)
    axes[0].set_yticks(range(len(names)), names, fontsize=8)
    fig.colorbar(im, ax=axes, shrink=0.6, label="coverage (nominal 0.683)")
    save_figure(fig, path)


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
    from components.simulate import dataset

    start = time.perf_counter()
    seed = int(json.loads((ROOT / "data" / "manifest.json").read_text())["seed"])
    model = load_registered(args.model, args.registry)
    weathers = named_weathers()
    splits = {name: dataset.open_split(ROOT / "data", name) for name in dataset.SPLITS}
    check_new_scenes(splits, seed, list(weathers), args.scenes)
    images = render(weathers, seed, args.scenes)
    tests = fit_tests(model, seed, args.calibration, args.steps, args.null_trials)
    control = local_rejections(tests, *control_sample(model, seed, args.test_images))

    rows, summaries, all_draws = [], [], []
    toy_rng = seeding.rng(seed, "named-weathers", "toy")
    for name, w in weathers.items():
        draws, summary = characterize(model, images[name], seed, name, args.draws)
        truth = weather.theta_from_weather(w)
        row = measure(name, truth, draws, model.posterior.box, args, toy_rng)
        row["training_neighbours"] = training_neighbours(splits["train"].theta, truth, model.posterior.box)
        lc = local_rejections(tests, summary, draws)
        row["joint_lc2st"] = lc[0]
        for j, p in enumerate(row["parameters"]):
            p.update(lc2st_rate=lc[j + 1]["rate"], lc2st_p=lc[j + 1]["p_value"])
        rows.append(row)
        summaries.append(summary)
        all_draws.append(draws[:, :TEST_DRAWS])
    named = local_rejections(tests, np.concatenate(summaries), np.concatenate(all_draws))
    report(rows, control, named, args, len(splits["train"]))
    heatmap(rows, Path(args.figure))
    from benchmarks.machine import machine_info

    lc2st = {"steps": args.steps, "null_trials": args.null_trials, "level": LEVEL, "test": control, "named": named}
    record = {"model": model.name, "seed": seed, "scenes": args.scenes, "draws": args.draws, "lc2st": lc2st}
    record.update(tolerance=args.tolerance, weathers=rows, seconds=round(time.perf_counter() - start, 1))
    print(json.dumps({**record, **machine_info()}))


def control_sample(model, seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The L-C2ST's control: the first n test images' posterior summaries ``(n, 2d)`` and draws ``(n, m, d)``."""
    from components.features import cache
    from components.simulate import dataset

    post = model.posterior
    split = dataset.open_split(ROOT / "data", "test")
    x = cache.inputs_from_cached(
        model.backbone, cache.open_features(ROOT / "features", post.card["backbone"], split, stop=n)
    )
    draws = post.sample(x, TEST_DRAWS, seeding.derive_seed(seed, "named-weathers", "test", "draws"))
    s = post.sample(x, SUMMARY_DRAWS, seeding.derive_seed(seed, "named-weathers", "test", "summary"))
    return posterior_summary(s, post.box), draws


def report(rows: list[dict], control: list[dict], named: list[dict], args, n_train: int) -> None:
    """The tables: coverage (champion | exact toy), errors, L-C2ST per weather; pooled rows; the L-C2ST sets."""
    head = " ".join(f"{s:>24s}" for s in SHORT_NAMES)
    print(f"68.27 % HDI coverage on {args.scenes} images per weather: champion [95 % CP] | exact toy (− / +: outside")
    print(f"the 95 % range of a correct model's coverage on {args.scenes} images)\n{'weather':22s} {head}")
    outside = [0, 0]
    for r in rows:
        cells = []
        for p in r["parameters"]:
            lo, hi = p["toy_range68"]
            mark = "−" if p["coverage68"] < lo else "+" if p["coverage68"] > hi else " "
            outside[0] += mark == "−"
            outside[1] += mark == "+"
            cells.append(f"{p['coverage68']:.2f}[{p['ci68'][0]:.2f},{p['ci68'][1]:.2f}]{mark}|{p['toy68']:.2f}")
        print(f"{r['weather']:22s} " + " ".join(f"{c:>24s}" for c in cells))
    for label, keep in (("pooled presets", lambda r: r["preset"]), ("pooled all", lambda r: True)):
        sel = [r for r in rows if keep(r)]
        k, n = np.sum([r["covered68"] for r in sel], axis=0), len(sel) * args.scenes
        lo, hi = clopper_pearson(k, n)
        toy = np.mean([[p["toy68"] for p in r["parameters"]] for r in sel], axis=0)
        cells = [f"{k[j] / n:.3f}[{lo[j]:.2f},{hi[j]:.2f}] |{toy[j]:.2f}" for j in range(len(k))]
        print(f"{label:22s} " + " ".join(f"{c:>24s}" for c in cells))
    cells = len(rows) * len(SHORT_NAMES)
    print(
        f"{outside[0] + outside[1]} of {cells} cells outside a correct model's range ({outside[0]} below, {outside[1]} above)"
    )
    print(f"\n95 % HDI coverage (champion | toy), median |error|, marginal L-C2ST rejections at {LEVEL} (set p); the")
    interior = round(n_train * (2 * NEIGHBOURHOOD) ** len(SHORT_NAMES))
    print(
        f"joint L-C2ST; training images within ±{NEIGHBOURHOOD:.0%} of the box in every parameter (interior: {interior})"
    )
    for r in rows:
        cells = [
            f"{p['coverage95']:.2f}|{p['toy95']:.2f} {p['median_abs_error']:6.2f} "
            f"{p['lc2st_rate']:.2f}({p['lc2st_p']:.3f})"
            for p in r["parameters"]
        ]
        j = r["joint_lc2st"]
        print(
            f"{r['weather']:22s} "
            + " ".join(f"{c:>26s}" for c in cells)
            + f"  joint {j['rate']:.2f}({j['p_value']:.3f})"
        )
    for title, sets in (("the named weathers' images together", named), (f"{args.test_images} test images", control)):
        print(f"\nL-C2ST at level {LEVEL} on {title}: rate, the null's 95 % range, the set's p — joint, per parameter")
        for label, c in zip(("joint", *SHORT_NAMES), sets, strict=True):
            lo, hi = c["null_range"]
            print(f"  {label:8s} {c['rate']:.3f} [{lo:.3f}, {hi:.3f}] p {c['p_value']:.3f}")
    noon = next(r for r in rows if r["weather"] == "ClearNoon")
    print(f"\nClearNoon (sun 45°, clear sky): median |sun error| {noon['parameters'][3]['median_abs_error']:.2f}°")


if __name__ == "__main__":
    main()
