"""Task I, per model: posterior draws on test images, the calibration and sharpness metrics, and the PPCs.

Used by the ``evaluate`` stage (one call per exported model) and the scheduled monitoring. Notation: for test image xᵢ with true weather θᵢ*,
q(θ | xᵢ) is the model's posterior; its samples θᵢⱼ and their log-densities log q(θᵢⱼ | xᵢ) give the HPD
credibility of θᵢ* (:mod:`components.evaluate.diagnostics`); the calibration error is judged against the band a
perfectly calibrated model shows on the same number of images (:func:`calibration_band`). Per-parameter figures are
in :mod:`components.evaluate.marginals`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from components.core import seeding, weather
from components.core.checks import whole_number
from components.core.config import Params
from components.evaluate import diagnostics
from components.evaluate.ppc import PPCResult, posterior_predictive_check

__all__ = [
    "LEVELS",
    "evaluation_order",
    "images_evaluated",
    "check_model_matches_data",
    "posterior_draws",
    "calibration_band",
    "task1_metrics",
    "posterior_predictive_checks",
]

#: the credibility levels of the expected-coverage curves
LEVELS = diagnostics.DEFAULT_LEVELS


def evaluation_order(ids: list[str], cards: dict[str, dict]) -> list[str]:
    """``ids`` with the costliest evaluations first (ensembles of more flows, then the larger contexts; ties keep
    their order), so that workers evaluating models in parallel finish together. ``cards``: model id → card."""
    cost = {m: (int(cards[m].get("ensemble", 1)), int(cards[m].get("features", 0))) for m in ids}
    return sorted(ids, key=lambda m: cost[m], reverse=True)


def images_evaluated(images: int | str, available: int) -> int:
    """The number of test images evaluated: ``images`` (``evaluate.images``: a count, or ``all``) within the
    ``available`` ones of the test split."""
    if images == "all":
        return int(available)
    whole_number("evaluate.images", images, low=1, hint=" or 'all'")
    if images > available:
        raise ValueError(f"evaluate.images is {images} but the test split has only {available} images")
    return int(images)


def check_model_matches_data(box: weather.Box, params: Params, path: Path) -> None:
    """The model's θ order, units and prior box must be the dataset's; ``ValueError`` naming ``path`` otherwise."""
    if tuple(box.names) != weather.PREDICTED:
        raise ValueError(
            f"{path}: the model's θ order {list(box.names)} differs from the dataset's {list(weather.PREDICTED)}"
        )
    units = tuple(weather.PARAMETERS[n].unit for n in weather.PREDICTED)
    if tuple(box.units) != units:
        raise ValueError(f"{path}: the model's θ units {list(box.units)} differ from the dataset's {list(units)}")
    if not (np.allclose(box.low, params.box.low) and np.allclose(box.high, params.box.high)):
        raise ValueError(f"{path}: the model's prior box differs from params.yaml's prior")


def posterior_draws(
    posterior, x: np.ndarray, theta: np.ndarray, n: int, seed: int, chunk: int = 4, context_chunk: int = 256
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples ``(N, n, d)``, their log-densities ``(N, n)`` and the truth's ``(N,)`` for N inputs ``x`` and true
    ``theta (N, d)`` (physical units, float64).

    ``posterior`` is an :class:`~components.export.runtime.OnnxPosterior` (``context``, ``on_context``,
    ``sample_from_noise``, ``log_prob``). Each input's context is computed once (``context_chunk`` inputs per call);
    the draws of ``chunk`` images go through the flow per call (small calls keep the flow's activations in the CPU's
    cache: 4 images × 1000 draws per call were ~10 % faster than 25). Image i's base noise (and ensemble
    members) come from the stream ``seeding.rng(seed, "evaluate", i)``: the draws of the i-th input depend on i only,
    not on the chunking nor on how many inputs follow it.
    """
    x = np.asarray(x)
    big_n, d, k = x.shape[0], posterior.dim, posterior.ensemble
    if np.shape(theta) != (big_n, d):
        raise ValueError(f"theta must have shape ({big_n}, {d}), one truth per input, got {np.shape(theta)}")
    context = np.concatenate([posterior.context(x[a : a + context_chunk]) for a in range(0, big_n, context_chunk)])
    flow = posterior.on_context()
    samples = np.empty((big_n, n, d))
    log_prob = np.empty((big_n, n))
    for a in range(0, big_n, chunk):
        rows = range(a, min(a + chunk, big_n))
        eps = np.empty((len(rows), n, d), dtype=np.float32)
        members = np.zeros((len(rows), n), dtype=np.int64)
        for j, i in enumerate(rows):
            rng = seeding.rng(seed, "evaluate", i)
            eps[j] = rng.standard_normal((n, d), dtype=np.float32)
            if k > 1:
                members[j] = rng.integers(k, size=n)
        samples[a : a + len(rows)], log_prob[a : a + len(rows)] = flow.sample_from_noise(
            context[a : a + len(rows)], eps, members if k > 1 else None
        )
    return samples, log_prob, flow.log_prob(np.asarray(theta, dtype=np.float64), context)


def calibration_band(images: int, samples: int, level: float, replicates: int, seed: int) -> float:
    """The ``level`` quantile of the calibration error (at :data:`LEVELS`) of a perfectly calibrated model evaluated
    on ``images`` images with ``samples`` draws each (:func:`components.evaluate.diagnostics.calibration_band`,
    ``replicates`` simulations from the stream ``(seed, "calibration-band")``); the same for every model."""
    rng = seeding.rng(seed, "calibration-band", images, samples)
    return diagnostics.calibration_band(images, samples, LEVELS, rng, quantile=level, replicates=replicates)


def task1_metrics(
    lp: np.ndarray, lp_truth: np.ndarray, prior_log_volume: float, band: float
) -> tuple[dict[str, float], np.ndarray, np.ndarray]:
    """Calibration and sharpness from the samples' log-densities ``lp (N, n)`` and the truth's ``lp_truth (N,)``.

    Returns ``(metrics, coverage, pi)``: the metrics (calibration error, the ``band`` of a perfectly calibrated model
    on N images (:func:`calibration_band`) and whether the error lies within it, signed coverage area — < 0
    overconfident, > 0 conservative —, median superiority π, test NLL and its standard error over the images,
    information gain over the uniform prior of log-volume ``prior_log_volume``, in nats), the expected coverage at :data:`LEVELS`, and π per image.
    """
    cred = diagnostics.hpd_credibility(lp, lp_truth)
    coverage = diagnostics.expected_coverage(cred, LEVELS)
    pi = diagnostics.superiority(lp, lp_truth)
    test_nll = float(-lp_truth.mean())
    error = diagnostics.calibration_error(cred, LEVELS)
    metrics = {
        "calibration_error": error,
        "calibration_band": float(band),
        "within_band": bool(error <= band),
        "coverage_auc_gap": float(np.trapezoid(coverage - LEVELS, LEVELS)),
        "pi_median": float(np.median(pi)),
        "test_nll": test_nll,
        # the standard error of that mean over the N images (also the information gain's): is a gap between two
        # models more than noise?
        "test_nll_se": float(lp_truth.std(ddof=1) / np.sqrt(lp_truth.size)) if lp_truth.size > 1 else float("nan"),
        "info_gain_nats": -test_nll + prior_log_volume,
    }
    return metrics, coverage, pi


def posterior_predictive_checks(
    simulator,
    images: np.ndarray,
    scene_seeds: np.ndarray,
    azimuths: np.ndarray,
    samples: np.ndarray,
    box: weather.Box,
    renders: int,
    rng: np.random.Generator,
) -> list[PPCResult]:
    """A PPC per image: its scene re-rendered under ``renders`` of its posterior ``samples (N, n, 6)`` (drawn without
    replacement) and ``renders`` prior draws, in that order from ``rng``."""
    results = []
    for i, image in enumerate(images):
        post = samples[i, rng.choice(samples.shape[1], renders, replace=False)]
        prior = box.sample(rng, renders)
        results.append(
            posterior_predictive_check(simulator, image, int(scene_seeds[i]), float(azimuths[i]), post, prior)
        )
    return results
