"""Named weathers: a model's intervals and local test at the conditions users name, beside a correct model's.

The average calibration of Task I looks at the prior as a whole; users try named conditions (a clear noon, a hard rain
at sunset) whose values sit on or near the box's faces. This module takes a model to such a set of weathers:

- :func:`named_weathers` — the weathers ``evaluate.named`` names: CARLA's usable presets
  (:data:`components.core.presets.USABLE`) and one's own (sun azimuth 0°), complete (13 parameters);
- :func:`scene_seeds` — each rendered weather's new scenes, ``derive_seed(seed, "scene", "named-weathers", name, j)``:
  a key path the dataset's plan cannot make (it draws ``derive_seed(seed, "scene", split, j)``), checked by
  :func:`check_new_scenes`;
- :func:`weather_row` — per parameter the coverage of the 68.27 % and 95 % marginal HDIs with their Clopper–Pearson
  intervals (:func:`components.evaluate.local.named_coverage`), the median absolute error, and beside them the same
  coverage of an exact posterior on a toy with the same faces (θ uniform on the box, x = θ + σ·ε with σ taken from
  the model's own 68 % HDIs there, the posterior a normal truncated to the box: :func:`exact_truncated_draws`) and
  the 95 % range of that coverage on as many images as the model had: a model's cell outside it is not the prior's
  doing;
- :func:`fit_local_tests`, :func:`local_rejections` — the L-C2ST (:class:`components.evaluate.local.LocalTest`),
  joint and per parameter, fitted on validation images with x summarized by the model's posterior
  (:func:`components.evaluate.local.posterior_summary`), run per weather, on all named images together and on test
  images (the control).

Used by the ``evaluate`` stage (:mod:`components.evaluate.evaluation`) and ``benchmarks/studies/bench_named_weathers.py``.

References:
    Linhart, Gramfort and Rodrigues (2023), "L-C2ST: Local diagnostics for posterior approximations in
    simulation-based inference", NeurIPS.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.stats import binom

from components.core import presets, seeding, weather
from components.core.files import sha256_file
from components.core.weather import Box
from components.evaluate.local import LocalTest, clopper_pearson, named_coverage
from components.evaluate.summary import HDI_MASS, hdi

__all__ = [
    "MASSES",
    "NamedSet",
    "named_weathers",
    "scene_seeds",
    "check_new_scenes",
    "render_sets",
    "exact_truncated_draws",
    "toy_sigma",
    "weather_row",
    "fit_local_tests",
    "local_rejections",
    "pooled",
    "folder_fingerprint",
]

#: the credible masses whose HDIs are counted
MASSES = (HDI_MASS, 0.95)


@dataclass(frozen=True)
class NamedSet:
    """The images of one named weather.

    Attributes:
        name: the weather's name (a CARLA preset's, one's own, or a recorded folder's).
        kind: ``preset``, ``own`` or ``recorded``.
        truth: ``(n, 6)`` each image's true θ, physical units (n equal rows for a rendered weather).
        images: ``(n, H, W, 3)`` uint8 RGB.
    """

    name: str
    kind: str
    truth: np.ndarray
    images: np.ndarray


def named_weathers(presets_kind: str, own: Mapping[str, Mapping[str, float]]) -> dict[str, tuple[str, dict]]:
    """Name → (kind, complete weather of 13 parameters): CARLA's usable presets when ``presets_kind`` is ``carla``,
    then ``own`` (the six predicted parameters each, sun azimuth :data:`~components.core.presets.PRESET_SUN_AZIMUTH`)."""
    out = {}
    if presets_kind == "carla":
        out = {name: ("preset", presets.preset_weather(name)) for name in presets.USABLE}
    for name, values in own.items():
        full = weather.complete_weather(
            {**values, "sun_azimuth_angle": presets.PRESET_SUN_AZIMUTH}, where=f"evaluate.named.weathers.{name}: "
        )
        out[name] = ("own", full)
    return out


def scene_seeds(seed: int, name: str, scenes: int) -> list[int]:
    """The scenes of weather ``name``: ``derive_seed(seed, "scene", "named-weathers", name, j)``, j < ``scenes``."""
    return [seeding.derive_seed(seed, "scene", "named-weathers", name, j) for j in range(scenes)]


def check_new_scenes(used: set[int], seed: int, names: list[str], scenes: int) -> None:
    """Raise ``ValueError`` when a scene seed of the named weathers is one the dataset uses (``used``) or two of them
    coincide."""
    mine = [s for name in names for s in scene_seeds(seed, name, scenes)]
    if set(mine) & used or len(set(mine)) != len(mine):
        raise ValueError(
            f"{len(set(mine) & used)} scene seeds of the named weathers are the dataset's; pick other keys"
        )


def render_sets(
    render: Callable[[Mapping[str, float], int], np.ndarray],
    weathers: Mapping[str, tuple[str, dict]],
    seed: int,
    scenes: int,
) -> list[NamedSet]:
    """Each weather of :func:`named_weathers` rendered by ``render(weather, scene_seed)`` on its :func:`scene_seeds`."""
    out = []
    for name, (kind, w) in weathers.items():
        images = np.stack([render(w, s) for s in scene_seeds(seed, name, scenes)])
        truth = np.broadcast_to(weather.theta_from_weather(w), (scenes, len(weather.PREDICTED))).copy()
        out.append(NamedSet(name, kind, truth, images))
    return out


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


def _intervals(draws: np.ndarray, mass: float) -> tuple[np.ndarray, np.ndarray]:
    """Each image's marginal HDIs of ``mass``: ``(n, m, d)`` draws → ``(n, d)`` lower and upper ends."""
    bounds = [hdi(d, mass) for d in draws]
    return np.array([b[0] for b in bounds]), np.array([b[1] for b in bounds])


def _coverages(draws: np.ndarray, truth: np.ndarray, box: Box, tolerance: float) -> list:
    return [named_coverage(truth, *_intervals(draws, mass), box, tolerance, mass=mass) for mass in MASSES]


def weather_row(
    named: NamedSet, draws: np.ndarray, box: Box, tolerance: float, toy_images: int, rng: np.random.Generator
) -> dict:
    """One weather's figures, per parameter: the model's coverage of its 68.27 % and 95 % HDIs with their 95 %
    Clopper–Pearson intervals, the exact toy's coverage at the same truths on ``toy_images`` images (cycling over the
    set's truths) with the 95 % range of its coverage on as many images as the model had, the toy's σ, and the
    median absolute error of the posterior median.

    Arguments:
        named: the weather's images and truths.
        draws: ``(n, m, d)`` the model's posterior draws for its images, physical units.
        box: the prior box.
        tolerance: a face's tolerance, θ's units (:func:`components.evaluate.local.named_coverage`).
        toy_images: the toy's images.
        rng: the toy's generator.

    Returns:
        JSON-serializable: ``weather``, ``kind``, ``images``, ``truth`` (the first image's), ``covered68``
        (per parameter, the images covered) and ``parameters`` (name → figures; ``below``/``above``: the model's 68 %
        coverage outside the toy's 95 % range).
    """
    n = len(draws)
    cov = _coverages(draws, named.truth, box, tolerance)
    low, high = _intervals(draws, HDI_MASS)
    sigma = toy_sigma(low, high, box)
    toy_truth = named.truth[np.arange(toy_images) % n]
    x = toy_truth + sigma * rng.standard_normal(toy_truth.shape)
    toy = _coverages(exact_truncated_draws(x, sigma, box, draws.shape[1], rng), toy_truth, box, tolerance)
    span = np.stack([binom.ppf(0.025, n, toy[0].rate), binom.ppf(0.975, n, toy[0].rate)], axis=1) / n
    err = np.median(np.abs(np.median(draws, axis=1) - named.truth), axis=0)
    parameters = {}
    for j, name in enumerate(box.names):
        c68 = float(cov[0].rate[j])
        parameters[name] = {
            "coverage68": c68,
            "ci68": [float(cov[0].low[j]), float(cov[0].high[j])],
            "coverage95": float(cov[1].rate[j]),
            "ci95": [float(cov[1].low[j]), float(cov[1].high[j])],
            "toy68": float(toy[0].rate[j]),
            "toy95": float(toy[1].rate[j]),
            "toy_range68": span[j].tolist(),
            "toy_sigma": float(sigma[j]),
            "below": bool(c68 < span[j, 0]),
            "above": bool(c68 > span[j, 1]),
            "median_abs_error": float(err[j]),
        }
    return {
        "weather": named.name,
        "kind": named.kind,
        "images": n,
        "truth": named.truth[0].tolist(),
        "covered68": cov[0].covered.tolist(),
        "parameters": parameters,
    }


def fit_local_tests(
    theta: np.ndarray,
    summary: np.ndarray,
    draws: np.ndarray,
    box: Box,
    *,
    steps: int,
    null_trials: int,
    seed: int,
    progress: Callable | None = None,
) -> list[LocalTest]:
    """The joint L-C2ST and one per parameter (1 + d tests), fitted on a calibration set.

    Arguments:
        theta: ``(n, d)`` the calibration images' truths.
        summary: ``(n, 2d)`` their x (:func:`components.evaluate.local.posterior_summary` of the model's draws).
        draws: ``(n, d)`` one model draw per image.
        box: the prior box.
        steps: each classifier's Adam steps.
        null_trials: H, the null classifiers of each test.
        seed: the tests' root; test j's is ``derive_seed(seed, "lc2st", j)`` (j = 0 joint, j ≥ 1 parameter j − 1).
        progress: wraps the range of tests (e.g. tqdm), or None.

    Returns:
        The fitted tests, the joint first.
    """
    tests, rows = [], range(-1, box.dim)
    for j in progress(rows) if progress else rows:
        cols = slice(None) if j < 0 else slice(j, j + 1)
        sub = box if j < 0 else Box(box.low[cols], box.high[cols], names=box.names[cols])
        test = LocalTest(box=sub, steps=steps, null_trials=null_trials, seed=seeding.derive_seed(seed, "lc2st", j + 1))
        tests.append(test.fit(theta[:, cols], summary, draws[:, cols]))
    return tests


def local_rejections(tests: list[LocalTest], summary: np.ndarray, draws: np.ndarray, level: float) -> dict:
    """The tests of :func:`fit_local_tests` on one set of images (``summary (k, 2d)``, ``draws (k, m, d)``): for the
    joint test and each parameter, the share of images rejected at ``level``, the 95 % range of that share under H₀
    (the null classifiers') and the set's exact p-value. Returns ``{"joint": {...}, <parameter>: {...}}``."""
    out = {}
    names = ["joint", *(t.box.names[0] for t in tests[1:])]
    for j, (name, test) in enumerate(zip(names, tests, strict=True)):
        cols = slice(None) if j == 0 else slice(j - 1, j)
        r = test.rejections(summary, draws[:, :, cols], level)
        out[name] = {"rate": r.rate, "null_range": list(r.null_range()), "p_value": r.p_value}
    return out


def pooled(rows: list[dict], box: Box, *, kind: str | None = None) -> dict | None:
    """The 68 % coverage pooled over weathers (of ``kind``, or all), per parameter, with its Clopper–Pearson interval
    and the toy's mean beside it; None when no weather is of that kind."""
    sel = [r for r in rows if kind is None or r["kind"] == kind]
    if not sel:
        return None
    k = np.sum([r["covered68"] for r in sel], axis=0)
    n = int(sum(r["images"] for r in sel))
    lo, hi = clopper_pearson(k, n)
    return {
        "images": n,
        "parameters": {
            name: {
                "coverage68": float(k[j] / n),
                "ci68": [float(lo[j]), float(hi[j])],
                "toy68": float(np.mean([r["parameters"][name]["toy68"] for r in sel])),
            }
            for j, name in enumerate(box.names)
        },
    }


def folder_fingerprint(folder: str | Path) -> str | None:
    """sha256 hex over the relative path and sha256 of every file under a recorded ``folder`` (``labels.csv`` and its
    images), in sorted order: what identifies a recorded named weather's images; None when ``folder`` is not a folder
    (its evaluation then fails naming it)."""
    folder = Path(folder)
    if not folder.is_dir():
        return None
    h = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        h.update(f"{path.relative_to(folder).as_posix()}\0{sha256_file(path)}\n".encode())
    return h.hexdigest()
