"""Task II (paper): a bag of images whose weather follows a known distribution → its characterization, scored.

Used by the ``task2`` stage. The domain keeps every predicted parameter fixed but fog density and precipitation,
which follow a mixture of Gaussians (``task2`` in params.yaml, :class:`~components.domains.scenarios.
GaussianMixtureWeather`); the bag's characterization is p̂_𝒟(θ) = Σᵢ wᵢ q(θ | xᵢ) (:class:`~components.domains.
absolute.Domain`), compared with the true distribution P_𝒟(θ).
"""

from __future__ import annotations

import numpy as np
from tqdm.auto import tqdm

from components.core import seeding, weather
from components.core.config import Params
from components.domains.absolute import Domain
from components.domains.scenarios import GaussianMixtureWeather
from components.evaluate import diagnostics

__all__ = ["DISTANCE_DRAWS", "DENSITY_DRAWS", "true_distribution", "render_bag", "task2_metrics"]

#: draws per distribution entering the energy distances (O(n²) pairs)
DISTANCE_DRAWS = 2000
#: draws per distribution whose density under the estimate is evaluated (each costs one flow pass per bag image)
DENSITY_DRAWS = 1000


def true_distribution(params: Params) -> GaussianMixtureWeather:
    """P_𝒟(θ): the fixed parameters and the Gaussian mixture of ``task2``, truncated to the prior box."""
    t = params.task2
    return GaussianMixtureWeather(
        fixed=t.fixed,
        weights=np.array([m.weight for m in t.modes]),
        means=np.array([m.mean for m in t.modes]),
        stds=np.array([m.std for m in t.modes]),
        box=params.box,
    )


def render_bag(params: Params, simulator) -> tuple[np.ndarray, np.ndarray]:
    """The bag: θ ``(n, 6)`` drawn from the true distribution and the images ``(n, H, W, 3)`` uint8 rendered under them
    in fresh scenes (``task2.images_per_scene`` consecutive images share one)."""
    t = params.task2
    theta = true_distribution(params).sample(t.images, seeding.rng(params.seed, "task2", "bag"))
    azimuth = weather.sample_azimuth(seeding.rng(params.seed, "task2", "azimuth"), t.images)
    images = np.empty((t.images, params.simulator.height, params.simulator.width, 3), dtype=np.uint8)
    for i in tqdm(range(t.images), desc="task2: render the bag", unit="image"):
        scene = seeding.derive_seed(params.seed, "scene", "task2", i // t.images_per_scene)
        images[i] = simulator.render(weather.weather_from_theta(theta[i], azimuth[i]), scene)
    return theta, images


def task2_metrics(domain: Domain, params: Params, model_name: str) -> tuple[dict, np.ndarray, np.ndarray]:
    """Score the characterization ``domain`` of the bag against the true distribution.

    Returns ``(metrics, estimate, truth)``: ``task2.samples`` draws of each (physical units) and the metrics — the
    share of the true mass inside the estimate's ``hdr_level`` HDR, the estimate's log-density at each true mode (with
    its typical log-density at its own draws as reference), the energy distances estimate→truth and prior→truth (all
    six parameters scaled by the prior's widths, and the two mixture parameters alone), and the estimate's median
    error on the fixed parameters.
    """
    t = params.task2
    truth_dist = true_distribution(params)
    estimate = domain.sample(t.samples, seeding.derive_seed(params.seed, "task2", "estimate"))
    truth = truth_dist.sample(t.samples, seeding.rng(params.seed, "task2", "truth"))
    k = min(DENSITY_DRAWS, t.samples)
    lp_estimate = domain.log_prob(estimate[:k])
    lp_truth = domain.log_prob(truth[:k])
    lp_modes = domain.log_prob(truth_dist.modes())

    rng = seeding.rng(params.seed, "task2", "distance")
    k = min(DISTANCE_DRAWS, t.samples)
    e_sub = estimate[rng.choice(len(estimate), k, replace=False)]
    t_sub = truth[rng.choice(len(truth), k, replace=False)]
    prior_sub = params.box.sample(rng, k)
    free = [params.box.names.index(n) for n in truth_dist.free]
    width = params.box.width
    fixed_err = {n: float(abs(np.median(estimate[:, params.box.names.index(n)]) - v)) for n, v in t.fixed.items()}
    metrics = {
        "model": model_name,
        "images": t.images,
        "hdr_level": t.hdr_level,
        "true_mass_in_hdr": diagnostics.hdr_mass(lp_estimate, lp_truth, t.hdr_level),
        "log_density_at_modes": [float(v) for v in lp_modes],
        "log_density_median_own_draws": float(np.median(lp_estimate)),
        "mode_density_quantile": [float(np.mean(lp_estimate <= v)) for v in lp_modes],
        "energy_distance": diagnostics.energy_distance(e_sub, t_sub, width),
        "energy_distance_prior": diagnostics.energy_distance(prior_sub, t_sub, width),
        "energy_distance_free": diagnostics.energy_distance(e_sub[:, free], t_sub[:, free], width[free]),
        "energy_distance_free_prior": diagnostics.energy_distance(prior_sub[:, free], t_sub[:, free], width[free]),
        "fixed_median_abs_error": fixed_err,
    }
    return metrics, estimate, truth
