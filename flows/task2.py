"""The ``task2`` stage: absolute characterization of a domain from a bag of images (paper, Task II).

``python -m flows.task2 [--params params.yaml]``. A domain whose weather keeps every predicted parameter fixed but
fog density and precipitation, which follow a mixture of Gaussians (``task2`` in params.yaml); a bag of
``task2.images`` images rendered in fresh scenes under weathers drawn from it; the bag's characterization
p̂_D(θ) = Σᵢ w(iᵢ) q(θ | iᵢ) with the registry model ``task2.model`` on onnxruntime. Writes
``reports/task2/metrics.json`` and plots (the true distribution and the estimate side by side, the bag).

Metrics: the share of the true distribution's mass inside the estimate's ``hdr_level`` HDR, the estimate's
log-density at each true mode (with the estimate's typical log-density at its own draws as reference), the energy
distance between the two (all six parameters, scaled by the prior's widths; and on the two mixture parameters) next
to the prior's distance to the truth (the score of knowing nothing), and the estimate's median error on the fixed
parameters.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from prefect import flow, get_run_logger, task
from tqdm.auto import tqdm

from components.evaluate import diagnostics
from components import plots
from components.core import seeding
from components.core import weather
from components.core.config import Params, load_params
from components.domains.absolute import Domain
from components.core.files import atomic_write_bytes
from components.export.lookup import load_registered
from components.domains.scenarios import GaussianMixtureWeather
from components.simulate.base import make_simulator
from flows.export import registry_root
from flows.runtime import params_from_argv

#: draws per distribution entering the energy distances (O(n²) pairs)
DISTANCE_DRAWS = 2000
#: draws per distribution whose density under the estimate is evaluated (each costs one flow pass per bag image)
DENSITY_DRAWS = 1000


def true_distribution(params: Params) -> GaussianMixtureWeather:
    t = params.task2
    return GaussianMixtureWeather(
        fixed=t.fixed, weights=np.array([m.weight for m in t.modes]), means=np.array([m.mean for m in t.modes]),
        stds=np.array([m.std for m in t.modes]), box=params.box,
    )


@task(name="task2-render-bag")
def render_bag(params_path: str) -> tuple[np.ndarray, np.ndarray]:
    """The bag: θ ``(n, 6)`` drawn from the true distribution and the images ``(n, H, W, 3)`` rendered under them."""
    params = load_params(params_path)
    t = params.task2
    theta = true_distribution(params).sample(t.images, seeding.rng(params.seed, "task2", "bag"))
    azimuth = weather.sample_azimuth(seeding.rng(params.seed, "task2", "azimuth"), t.images)
    sim = make_simulator(params.simulator)
    images = np.empty((t.images, params.simulator.height, params.simulator.width, 3), dtype=np.uint8)
    for i in tqdm(range(t.images), desc="task2: render the bag", unit="image"):
        scene = seeding.derive_seed(params.seed, "scene", "task2", i // t.images_per_scene)
        images[i] = sim.render(weather.weather_from_theta(theta[i], azimuth[i]), scene)
    return theta, images


@flow(name="task2", log_prints=True)
def task2(params_path: str = "params.yaml") -> dict:
    """Characterize the Task II bag and compare with its true weather distribution; write reports/task2/."""
    logger = get_run_logger()
    params_file = Path(params_path)
    params = load_params(params_file)
    t = params.task2
    base = params_file.resolve().parent
    out = base / "reports" / "task2"
    # fails early without a registry model or champion; onnxruntime may use every core (nothing else runs here)
    model = load_registered(t.model, registry_root(params_file), threads=os.cpu_count() or 1)
    truth_dist = true_distribution(params)
    theta_bag, images = render_bag(str(params_file))

    contexts = model.posterior.context(model.inputs(images))  # the embedding runs once per image
    domain = Domain(model.posterior.on_context(), contexts)  # equally weighted bag
    estimate = domain.sample(t.samples, seeding.derive_seed(params.seed, "task2", "estimate"))
    truth = truth_dist.sample(t.samples, seeding.rng(params.seed, "task2", "truth"))
    k = min(DENSITY_DRAWS, t.samples)
    lp_estimate = domain.log_prob(estimate[:k])
    lp_truth = domain.log_prob(truth[:k])
    modes = truth_dist.modes()
    lp_modes = domain.log_prob(modes)

    rng = seeding.rng(params.seed, "task2", "distance")
    k = min(DISTANCE_DRAWS, t.samples)
    e_sub, t_sub = estimate[rng.choice(len(estimate), k, replace=False)], truth[rng.choice(len(truth), k, replace=False)]
    prior_sub = params.box.sample(rng, k)
    free = [params.box.names.index(n) for n in truth_dist.free]
    width = params.box.width
    fixed_err = {n: float(abs(np.median(estimate[:, params.box.names.index(n)]) - v)) for n, v in t.fixed.items()}
    metrics = {
        "model": model.name,
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

    plot_dir = out / "plots"
    plots.save_figure(plots.corner_compare(truth, estimate, labels=("ground truth P_D(W)", "estimate P̂_D(W)"),
                                           box=params.box), plot_dir / "corner-truth-vs-estimate.png")
    plots.save_figure(plots.corner_compare(truth, estimate, labels=("ground truth P_D(W)", "estimate P̂_D(W)"),
                                           box=params.box, overlay=True), plot_dir / "corner-overlay.png")
    shown = min(48, t.images)
    plots.save_figure(plots.image_grid(images[:shown], ncols=8, title=f"Task II bag: {shown} of {t.images} images"),
                      plot_dir / "bag.png")
    atomic_write_bytes(out / "metrics.json", json.dumps(metrics, indent=1).encode())
    logger.info("task2 (%s): %.1f %% of the true mass inside the estimate's %.0f %% HDR; energy distance %.3f "
                "(prior %.3f)", model.name, 100 * metrics["true_mass_in_hdr"], 100 * t.hdr_level,
                metrics["energy_distance"], metrics["energy_distance_prior"])
    return metrics


def main(argv: list[str] | None = None) -> None:
    _, path = params_from_argv("Task II: characterize a bag of images with a known weather distribution.", argv)
    task2(str(path))


if __name__ == "__main__":
    main()
