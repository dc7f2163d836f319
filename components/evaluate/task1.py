"""Task I, per model: posterior draws on test images, the calibration and sharpness metrics, and the PPCs.

Used by the ``evaluate`` stage (one call per exported model). Notation: for test image xᵢ with true weather θᵢ*,
q(θ | xᵢ) is the model's posterior; its samples θᵢⱼ and their log-densities log q(θᵢⱼ | xᵢ) give the HPD
credibility of θᵢ* (:mod:`components.evaluate.diagnostics`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from components.core import seeding, weather
from components.core.config import Params
from components.evaluate import diagnostics
from components.evaluate.ppc import PPCResult, posterior_predictive_check

__all__ = [
    "LEVELS",
    "model_ids",
    "check_model_matches_data",
    "posterior_draws",
    "task1_metrics",
    "posterior_predictive_checks",
]

#: the credibility levels of the expected-coverage curves
LEVELS = diagnostics.DEFAULT_LEVELS


def model_ids(params: Params) -> list[str]:
    """The grid's models (``<backbone>-<size>``), then the calibrated variants (``<backbone>-<size>-<name>``)."""
    grid = [f"{b}-{s}" for b in params.backbones.names for s in params.train.sizes]
    return grid + [f"{v.backbone}-{v.size}-{name}" for name, v in params.train.variants.items()]


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


def posterior_draws(posterior, x: np.ndarray, theta: np.ndarray, n: int, seed: int, chunk: int = 25):
    """Samples ``(N, n, 6)``, their log-densities ``(N, n)`` and the truth's ``(N,)`` for N inputs ``x`` and true
    ``theta (N, 6)``; ``posterior`` has ``sample_and_log_prob`` and ``log_prob`` (e.g. the ONNX runtime posterior).
    Chunk s draws with seed ``derive_seed(seed, "evaluate", s)``."""
    out_s, out_lp, out_lt = [], [], []
    for s in range(0, len(x), chunk):
        xs = x[s : s + chunk]
        th, lp = posterior.sample_and_log_prob(xs, n, seed=seeding.derive_seed(seed, "evaluate", s))
        out_s.append(th)
        out_lp.append(lp)
        out_lt.append(posterior.log_prob(theta[s : s + chunk], xs))
    return np.concatenate(out_s), np.concatenate(out_lp), np.concatenate(out_lt)


def task1_metrics(
    lp: np.ndarray, lp_truth: np.ndarray, prior_log_volume: float
) -> tuple[dict[str, float], np.ndarray, np.ndarray]:
    """Calibration and sharpness from the samples' log-densities ``lp (N, n)`` and the truth's ``lp_truth (N,)``.

    Returns ``(metrics, coverage, pi)``: the metrics (calibration error, signed coverage area — < 0 overconfident,
    > 0 conservative —, median superiority π, test NLL, information gain over the uniform prior of log-volume
    ``prior_log_volume``, in nats), the expected coverage at :data:`LEVELS`, and π per image.
    """
    cred = diagnostics.hpd_credibility(lp, lp_truth)
    coverage = diagnostics.expected_coverage(cred, LEVELS)
    pi = diagnostics.superiority(lp, lp_truth)
    test_nll = float(-lp_truth.mean())
    metrics = {
        "calibration_error": diagnostics.calibration_error(cred, LEVELS),
        "coverage_auc_gap": float(np.trapezoid(coverage - LEVELS, LEVELS)),
        "pi_median": float(np.median(pi)),
        "test_nll": test_nll,
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
