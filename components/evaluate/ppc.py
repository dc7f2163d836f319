"""A quantitative posterior predictive check (beyond the paper, which only looked at re-renders).

For an observed image i of scene s with ground truth w*, re-render the SAME scene (same scene seed,
same nuisance azimuth: common random numbers) under k weathers drawn from the predicted posterior
p̂(w | i) and under k weathers drawn from the prior, and measure the image distance of each re-render
to the observation. The PPC score

    score(i) = 1 − mean_j d(i, render(w_j^post)) / mean_j d(i, render(w_j^prior))

is 0 when posterior draws reproduce the image no better than prior draws, and 1 when they reproduce
it exactly; negative when they are worse than the prior. The distance d is the mean absolute
difference of the images in [0, 1] (per pixel and channel).

Used by the ``evaluate`` stage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from components.core import weather

__all__ = ["image_distance", "ppc_score", "PPCResult", "posterior_predictive_check"]


def image_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean absolute difference in [0, 1] of uint8 images ``(..., H, W, 3)`` (broadcast); shape ``(...)``."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape[-3:] != b.shape[-3:] or a.shape[-1] != 3:
        raise ValueError(f"images must be (..., H, W, 3) of the same size, got {a.shape} and {b.shape}")
    return np.abs(a.astype(np.float32) - b.astype(np.float32)).mean(axis=(-3, -2, -1)) / 255.0


def ppc_score(d_posterior: np.ndarray, d_prior: np.ndarray) -> float:
    """1 − mean(d_posterior)/mean(d_prior) (see the module docstring)."""
    d_post, d_pri = np.asarray(d_posterior, np.float64), np.asarray(d_prior, np.float64)
    if d_post.size == 0 or d_pri.size == 0:
        raise ValueError("a PPC needs at least one posterior and one prior re-render")
    if d_pri.mean() <= 0:
        raise ValueError("prior re-renders are identical to the observation: the PPC score is undefined")
    return float(1.0 - d_post.mean() / d_pri.mean())


@dataclass(frozen=True)
class PPCResult:
    """Re-renders ``(k, H, W, 3)`` under posterior and prior draws, their distances ``(k,)`` and the score."""

    posterior_renders: np.ndarray
    prior_renders: np.ndarray
    d_posterior: np.ndarray
    d_prior: np.ndarray
    score: float


def _render_all(simulator, thetas: np.ndarray, azimuth: float, scene_seed: int) -> np.ndarray:
    return np.stack([simulator.render(weather.weather_from_theta(t, azimuth), scene_seed) for t in thetas])


def posterior_predictive_check(
    simulator,
    observed: np.ndarray,
    scene_seed: int,
    azimuth: float,
    posterior_theta: np.ndarray,
    prior_theta: np.ndarray,
) -> PPCResult:
    """Re-render scene ``scene_seed`` (azimuth in degrees) under posterior and prior draws θ ``(k, 6)``."""
    if observed.shape != (simulator.height, simulator.width, 3):
        raise ValueError(
            f"observed image {observed.shape} does not match the simulator's {(simulator.height, simulator.width, 3)}"
        )
    for what, draws in (("posterior_theta", posterior_theta), ("prior_theta", prior_theta)):
        if np.ndim(draws) != 2 or np.shape(draws)[0] < 1 or np.shape(draws)[1] != len(weather.PREDICTED):
            raise ValueError(
                f"{what} must be k ≥ 1 draws of θ, shape (k, {len(weather.PREDICTED)}): a PPC needs at "
                f"least one posterior and one prior re-render; got shape {np.shape(draws)}"
            )
    post = _render_all(simulator, np.asarray(posterior_theta), azimuth, scene_seed)
    prior = _render_all(simulator, np.asarray(prior_theta), azimuth, scene_seed)
    d_post, d_prior = image_distance(post, observed), image_distance(prior, observed)
    return PPCResult(post, prior, d_post, d_prior, ppc_score(d_post, d_prior))
