"""Task II (paper): a bag of images whose weather follows a known distribution → its characterization, scored.

Used by the ``task2`` stage. As in the paper, the domain fixes every weather parameter but fog density and
precipitation — the four other predicted ones (``task2.fixed``) and the sun azimuth (``task2.sun_azimuth_angle``) —
and those two follow a mixture of Gaussians (``task2.modes``,
:class:`~components.domains.scenarios.GaussianMixtureWeather`). The bag's characterization p̂_𝒟(θ) = Σᵢ wᵢ q(θ | xᵢ)
(:class:`~components.domains.absolute.Domain`) is compared with the true distribution P_𝒟(θ), and with the uniform
prior as the no-information reference:

* energy distances (:func:`~components.domains.distances.energy_distance_sq`, unbiased U-statistic of D², prior-width
  units) estimate→truth and prior→truth and their ratio, over the six parameters and over the two free ones, beside
  truth→truth (two independent samples of the truth: D² = 0, so it shows the estimator's noise);
* per parameter, in its physical unit: W₁ estimate→truth and prior→truth (sharpness *and* location: a broad estimate
  scores near the prior), the width of the estimate's marginal ``hdr_level`` HDR and the share of the true mass in it;
* the share of the true mass inside the estimate's joint ``hdr_level`` HDR, and the estimate's density at the true
  modes;
* the width floor (:func:`width_floor`): the W₁ ratios of the mixture whose posteriors are moved onto their images'
  true θ — what the per-image posteriors' widths alone allow, with no bias.

The estimate is ``task2.estimate``: the mixture itself, or its deconvolution (:func:`characterize`,
:mod:`components.domains.deconvolution`: the bag's maximum-likelihood weather distribution, of which the mixture is the
first EM step), scored the same way.

References:
    Halin, Piérard et al., "Physically Interpretable Probabilistic Domain Characterization", Task II (the bag, the
    true distribution of fog density and precipitation, the mixture of posteriors).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from components.core import seeding, weather
from components.core.config import Params
from components.domains.absolute import Domain
from components.domains.deconvolution import deconvolve
from components.domains.distances import (
    energy_distance_sq,
    marginal_hdr,
    resampled_wasserstein_1d,
    wasserstein_1d,
)
from components.domains.scenarios import GaussianMixtureWeather
from components.evaluate import diagnostics

__all__ = [
    "DISTANCE_DRAWS",
    "DENSITY_DRAWS",
    "HDR_BINS",
    "true_distribution",
    "render_bag",
    "characterize",
    "task2_metrics",
    "BagScores",
    "score_bag",
]

#: draws per distribution entering the energy distances (O(n²) pairs)
DISTANCE_DRAWS = 2000
#: draws per distribution whose density under the estimate is evaluated (each costs one flow pass per bag image)
DENSITY_DRAWS = 1000
#: histogram bins over each parameter's prior range for the marginal HDRs (1 % of the range)
HDR_BINS = 100


def true_distribution(params: Params) -> GaussianMixtureWeather:
    """P_𝒟(θ): the fixed parameters and the Gaussian mixture of ``task2``, truncated to the prior box.

    Arguments:
        params: the configuration (``task2.fixed``, ``task2.modes``, the prior box).

    Returns:
        The true weather distribution of the Task II domain: ``sample(n, rng) → (n, 6)``, physical units; its free
            parameters are fog density and precipitation.
    """
    t = params.task2
    return GaussianMixtureWeather(
        fixed=t.fixed,
        weights=np.array([m.weight for m in t.modes]),
        means=np.array([m.mean for m in t.modes]),
        stds=np.array([m.std for m in t.modes]),
        box=params.box,
    )


def render_bag(params: Params, simulator) -> tuple[np.ndarray, np.ndarray]:
    """The bag: θ ``(n, 6)`` drawn from the true distribution and the images ``(n, H, W, 3)`` uint8 rendered under them,
    all with the sun azimuth ``task2.sun_azimuth_angle``, in fresh scenes (``task2.images_per_scene`` consecutive
    images share one)."""
    t = params.task2
    theta = true_distribution(params).sample(t.images, seeding.rng(params.seed, "task2", "bag"))
    images = np.empty((t.images, params.simulator.height, params.simulator.width, 3), dtype=np.uint8)
    for i in tqdm(range(t.images), desc="task2: render the bag", unit="image"):
        scene = seeding.derive_seed(params.seed, "scene", "task2", i // t.images_per_scene)
        images[i] = simulator.render(weather.weather_from_theta(theta[i], t.sun_azimuth_angle), scene)
    return theta, images


def characterize(domain: Domain, params: Params) -> tuple[object, dict]:
    """The estimate ``task2.estimate`` of the bag's weather distribution, and what it took.

    Arguments:
        domain: the bag as the mixture of its posteriors.
        params: the configuration (``task2.estimate``, ``task2.deconvolution``, the seed).

    Returns:
        The estimate (``domain`` itself for ``mixture``, else the deconvolution's kernel density; both with
            ``sample(n, seed)`` and ``log_prob(θ)``) and what it took: empty for the mixture; for ``deconvolved`` the
            EM steps chosen (1 = the mixture), the held-out log likelihood per image gained over the mixture (nats),
            the kernel bandwidth (physical units) and the support's effective size.
    """
    t = params.task2
    if t.estimate == "mixture":
        return domain, {}
    c = t.deconvolution
    dec = deconvolve(domain, c.draws_per_image, c.max_steps, c.folds, seeding.derive_seed(params.seed, "task2"))
    return dec.density, {
        "draws_per_image": c.draws_per_image,
        "max_steps": c.max_steps,
        "folds": c.folds,
        "steps": dec.steps,
        "held_out_gain_per_image": float(dec.held_out[dec.steps] - dec.held_out[1]),
        "held_out_log_likelihood": [float(v) for v in dec.held_out],
        "kernel_scale": dec.kernel_scale,
        "bandwidth": dict(zip(params.box.names, (dec.scott * dec.kernel_scale).tolist(), strict=True)),
        "effective_support": float(1.0 / np.sum(dec.weights**2)),
        "support": int(len(dec.weights)),
    }


def _energy(estimate: np.ndarray, truth: np.ndarray, truth2: np.ndarray, prior: np.ndarray, width: np.ndarray) -> dict:
    est, pri = energy_distance_sq(estimate, truth, width), energy_distance_sq(prior, truth, width)
    return {
        "estimate_to_truth": est,
        "prior_to_truth": pri,
        "ratio": est / pri,
        "truth_to_truth": energy_distance_sq(truth2, truth, width),
    }


def reference_draws(params: Params) -> tuple[np.ndarray, np.ndarray]:
    """``task2.samples`` draws of the true distribution and of the prior ``(S, 6)``, physical units, from their own
    seeded streams: every Task II score compares with these."""
    t = params.task2
    truth = true_distribution(params).sample(t.samples, seeding.rng(params.seed, "task2", "truth"))
    return truth, params.box.sample(seeding.rng(params.seed, "task2", "prior"), t.samples)


def task2_metrics(domain, params: Params, model_name: str) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
    """Score the characterization ``domain`` of the bag against the true distribution (the scores of the module's
    description; the layout of ``reports/task2/metrics.json``: docs/pipeline.md).

    Arguments:
        domain (object): the characterization, anything with ``sample(n, seed) → (n, 6)`` and ``log_prob(θ (m, 6))
            → (m,)`` in physical units (a :class:`~components.domains.absolute.Domain`, the deconvolution's density).
        params: the configuration (``task2``, the prior box, the seed).
        model_name: the model's id, recorded in the metrics.

    Returns:
        ``(metrics, estimate, truth, prior)``: the metrics (a JSON-ready dict), and ``task2.samples`` draws
            ``(S, 6)`` of the estimate, the true distribution and the prior, in physical units.

    Examples:
        The prior itself as the characterization scores as the prior (ratios of 1, no information):

        >>> import numpy as np
        >>> from components.core.config import load_params
        >>> params = load_params("params.yaml")  # the repository's, from its root
        >>> class Prior:
        ...     def sample(self, n, seed):
        ...         return params.box.sample(np.random.default_rng(seed), n)
        ...     def log_prob(self, theta):
        ...         return params.box.log_prob(theta)
        >>> metrics, estimate, truth, prior = task2_metrics(Prior(), params, "prior")
        >>> estimate.shape == truth.shape == (params.task2.samples, 6)
        True
        >>> round(metrics["energy_distance_sq"]["free"]["ratio"], 1)  # estimate→truth over prior→truth
        1.0
    """
    t = params.task2
    box = params.box
    truth_dist = true_distribution(params)
    estimate = domain.sample(t.samples, seeding.derive_seed(params.seed, "task2", "estimate"))
    truth, prior = reference_draws(params)
    k = min(DENSITY_DRAWS, t.samples)
    lp_estimate = domain.log_prob(estimate[:k])
    lp_truth = domain.log_prob(truth[:k])
    lp_modes = domain.log_prob(truth_dist.modes())

    rng = seeding.rng(params.seed, "task2", "distance")
    k = min(DISTANCE_DRAWS, t.samples)
    e_sub = estimate[rng.choice(len(estimate), k, replace=False)]
    t_sub = truth[rng.choice(len(truth), k, replace=False)]
    p_sub = prior[rng.choice(len(prior), k, replace=False)]
    t_two = truth_dist.sample(k, seeding.rng(params.seed, "task2", "truth", "second"))
    free = [box.names.index(n) for n in truth_dist.free]

    metrics = {
        "model": model_name,
        "images": t.images,
        "sun_azimuth_angle": t.sun_azimuth_angle,
        "samples": t.samples,
        "hdr_level": t.hdr_level,
        "true_mass_in_hdr": diagnostics.hdr_mass(lp_estimate, lp_truth, t.hdr_level),
        "log_density_at_modes": [float(v) for v in lp_modes],
        "log_density_median_own_draws": float(np.median(lp_estimate)),
        "mode_density_quantile": [float(np.mean(lp_estimate <= v)) for v in lp_modes],
        "energy_distance_sq": {
            "draws": k,
            "all": _energy(e_sub, t_sub, t_two, p_sub, box.width),
            "free": _energy(e_sub[:, free], t_sub[:, free], t_two[:, free], p_sub[:, free], box.width[free]),
        },
        "parameters": _per_parameter(estimate, truth, prior, params),
    }
    return metrics, estimate, truth, prior


def _per_parameter(estimate: np.ndarray, truth: np.ndarray, prior: np.ndarray, params: Params) -> dict:
    """:func:`task2_metrics`' figures per parameter, in its physical unit.

    Arguments:
        estimate: draws of the estimate, ``(S, 6)`` in physical units.
        truth: as many draws of the true distribution.
        prior: as many draws of the prior.
        params: the configuration (``task2.hdr_level``, ``task2.fixed``, the prior box).

    Returns:
        parameter → its unit, fixed value (None for a free one), the estimate's median and its error from the fixed
        value, W₁ estimate→truth and prior→truth and their ratio, the marginal HDR's width (and share of the prior
        range) and the share of the true mass inside it.
    """
    t, box = params.task2, params.box
    w_est, w_prior = wasserstein_1d(estimate, truth), wasserstein_1d(prior, truth)
    per_parameter = {}
    for i, name in enumerate(box.names):
        hdr = marginal_hdr(estimate[:, i], truth[:, i], box.low[i], box.high[i], t.hdr_level, HDR_BINS)
        fixed = t.fixed.get(name)
        median = float(np.median(estimate[:, i]))
        per_parameter[name] = {
            "unit": box.units[i],
            "fixed_value": fixed,
            "estimate_median": median,
            "median_abs_error": None if fixed is None else abs(median - fixed),
            "wasserstein_estimate": float(w_est[i]),
            "wasserstein_prior": float(w_prior[i]),
            "wasserstein_ratio": float(w_est[i] / w_prior[i]),
            "hdr_width": hdr.width,
            "hdr_width_share": hdr.width_share,
            "true_mass_in_hdr": hdr.mass_inside,
        }
    return per_parameter


def width_floor(posterior, contexts: np.ndarray, theta: np.ndarray, params: Params) -> dict:
    """What the posteriors' widths alone allow: the W₁ ratios (estimate/prior, per parameter) of two mixtures built
    from each image's posterior draws, clipped to the box, for each s of ``task2.width_floor.scales`` (s = 1: the
    posteriors' own widths):

    * ``wasserstein_ratio``: image i contributes θᵢ + s·(draw − median of its draws) — each posterior moved onto its
      truth, its spread scaled by s;
    * ``calibrated``: image i contributes θᵢ − s·(draw′ − median) + s·(draw − median), draw′ an independent draw of
      the same posterior — what a perfectly calibrated posterior of that shape gives: the truth is distributed like a
      draw of it, so its median misses the truth by one of its own deviations, and the mixture of such posteriors is
      the bag's weather blurred twice (the same ratio as the estimate's means the estimate's distance is all width,
      none of it bias);
    * ``mixture``: the posteriors as drawn (θ unused) — the estimate's ratio from these draws;
    * ``interval``, for the parameters that vary in the bag (not in ``task2.fixed``): ``mixture`` minus
      ``calibrated`` at s = 1 with its 95 % percentile-bootstrap interval over the bag's images
      (``task2.width_floor.bootstrap`` replicates resampling the same images for both): an interval that holds 0 says
      the estimate is as far from the truth as calibrated posteriors of its widths would be. The interval is
      conservative: for bags of exact posteriors it holds 0 in ~99 %, not 95 %, of bags (measured on 1 000 bags of
      200 and 400 images: 0.989–0.993; ``tests/test_task2.py``), so an interval that excludes 0 is strong evidence
      and one that holds it is weak. (A single distance gets no such interval: resampling images adds noise of its
      own that shifts its bootstrap distribution up; the paired difference cancels most of it.)

    Arguments:
        posterior (object): anything with ``sample(contexts, n, seed) → (N, n, d)``, draws in physical units (a
            registry model's ``posterior.on_context()``).
        contexts: the bag's ``(N, …)`` contexts.
        theta: their true weather ``(N, d)``, physical units.
        params: the configuration (``task2.width_floor``, the prior box, the seed).

    Returns:
        ``{"draws", "wasserstein_ratio": {f"{s:g}": {parameter: ratio}}, "calibrated": {f"{s:g}": {parameter:
            ratio}}, "mixture": {parameter: ratio}, "interval": {"replicates", "confidence",
            "mixture_minus_calibrated": {parameter: {"difference", "low", "high"}}}, "posterior_sd_median":
            {parameter: the median over images of the posterior standard deviation, physical units}}``; the truth's
            and the prior's draws are :func:`reference_draws`, as for :func:`task2_metrics`, so ``s`` → 0 leaves the
            bag's own sampling distance.
    """
    c, box = params.task2.width_floor, params.box
    theta = np.asarray(theta, dtype=np.float64)
    draws, again = _paired_draws(posterior, contexts, theta, params)
    median = np.median(draws, axis=1, keepdims=True)
    spread = draws - median
    miss = again - median
    truth, prior = reference_draws(params)
    w_prior = wasserstein_1d(prior, truth)

    def ratio(points: np.ndarray) -> dict[str, float]:
        moved = np.clip(points, box.low, box.high).reshape(-1, theta.shape[1])
        return dict(zip(box.names, (wasserstein_1d(moved, truth) / w_prior).tolist(), strict=True))

    ratios = {f"{s:g}": ratio(theta[:, None, :] + s * spread) for s in c.scales}
    calibrated = {f"{s:g}": ratio(theta[:, None, :] - s * miss + s * spread) for s in c.scales}
    mixture = ratio(draws)
    free = [k for k, name in enumerate(box.names) if name not in params.task2.fixed]
    low, high = _difference_interval(draws, theta[:, None, :] - miss + spread, free, truth, prior, params, c.bootstrap)
    sd = np.median(draws.std(axis=1), axis=0)
    return {
        "draws": c.draws,
        "wasserstein_ratio": ratios,
        "calibrated": calibrated,
        "mixture": mixture,
        "interval": {
            "replicates": c.bootstrap,
            "confidence": 0.95,
            "mixture_minus_calibrated": {
                box.names[k]: {
                    "difference": mixture[box.names[k]] - calibrated["1"][box.names[k]],
                    "low": float(low[j]),
                    "high": float(high[j]),
                }
                for j, k in enumerate(free)
            },
        },
        "posterior_sd_median": dict(zip(box.names, sd.tolist(), strict=True)),
    }


def _paired_draws(posterior, contexts: np.ndarray, theta: np.ndarray, params: Params) -> tuple[np.ndarray, np.ndarray]:
    """:func:`width_floor`'s two independent sets of ``task2.width_floor.draws`` draws of every image's posterior,
    each from its own seeded stream (the second: where a calibrated posterior's median would lie).

    Arguments:
        posterior (object): anything with ``sample(contexts, n, seed) → (N, n, d)``, draws in physical units.
        contexts: the bag's ``(N, …)`` contexts.
        theta: their true weather ``(N, d)`` (its shape is checked against the draws').
        params: the configuration (``task2.width_floor.draws``, the seed).

    Returns:
        ``(draws, again)``, each ``(N, n, d)`` in physical units; ``ValueError`` naming a shape that differs.
    """
    n = params.task2.width_floor.draws
    draws = np.asarray(posterior.sample(contexts, n, seeding.derive_seed(params.seed, "task2", "width-floor")))
    if draws.shape != (theta.shape[0], n, theta.shape[1]):
        raise ValueError(f"posterior draws have shape {draws.shape}, expected {(theta.shape[0], n, theta.shape[1])}")
    # independent draws of the same posteriors (their own stream): where a calibrated posterior's median would lie
    again = np.asarray(posterior.sample(contexts, n, seeding.derive_seed(params.seed, "task2", "width-floor", 2)))
    if again.shape != draws.shape:
        raise ValueError(f"posterior draws have shape {again.shape}, expected {draws.shape}")
    return draws, again


def _difference_interval(
    first: np.ndarray,
    second: np.ndarray,
    free: list[int],
    truth: np.ndarray,
    prior: np.ndarray,
    params: Params,
    replicates: int,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`width_floor`'s 95 % percentile-bootstrap interval (conservative: ~99 % for exact posteriors) of the W₁
    ratio (to the truth, over the prior's) of the mixture ``first (N, n, d)`` (image i's n points, clipped to the box)
    minus that of ``second``, per parameter of
    ``free``: ``replicates`` resamplings of the N images, shared by the two mixtures (the truth's draws,
    ``task2.samples`` of a known distribution, are kept) → ``(low, high)``, each ``(len(free),)``."""
    box = params.box
    n = first.shape[0]
    r = seeding.rng(params.seed, "task2", "width-floor", "bootstrap")
    counts = np.stack([np.bincount(r.integers(n, size=n), minlength=n) for _ in range(replicates)])
    w = wasserstein_1d(prior[:, free], truth[:, free])
    reps = np.stack(
        [
            (
                resampled_wasserstein_1d(np.clip(first[..., k], box.low[k], box.high[k]), truth[:, k], counts)
                - resampled_wasserstein_1d(np.clip(second[..., k], box.low[k], box.high[k]), truth[:, k], counts)
            )
            / w[j]
            for j, k in enumerate(free)
        ],
        axis=1,
    )
    low, high = np.quantile(reps, [0.025, 0.975], axis=0)
    return low, high


@dataclass(frozen=True)
class BagScores:
    """The characterization of a bag, scored (:func:`score_bag`).

    Attributes:
        metrics: what ``reports/task2/metrics.json`` holds: ``estimate`` (``task2.estimate``), the scores of
            :func:`task2_metrics`, with a deconvolved estimate ``deconvolution`` (the steps it took) and ``mixture``
            (the mixture's scores), and ``width_floor`` (:func:`width_floor`).
        how: what the estimate took (:func:`characterize`; empty for the mixture).
        estimate: ``task2.samples`` draws of the estimate, ``(S, 6)`` in physical units.
        truth: as many draws of the true distribution.
        prior: as many draws of the prior.
        mixture: with a deconvolved estimate, as many draws of the mixture; else None.
    """

    metrics: dict
    how: dict
    estimate: np.ndarray
    truth: np.ndarray
    prior: np.ndarray
    mixture: np.ndarray | None


def score_bag(posterior, contexts: np.ndarray, theta: np.ndarray, params: Params, model_name: str) -> BagScores:
    """Characterize the equally weighted bag of images whose contexts are ``contexts`` and score the estimate
    ``task2.estimate`` against the true distribution; a deconvolved estimate is scored beside the mixture it starts
    from; the width floor last.

    Arguments:
        posterior (object): the model's posterior, with ``on_context()`` (the posterior of a context,
            :class:`~components.domains.absolute.Domain`).
        contexts: the bag's contexts, one row per image (the embedding's output).
        theta: the bag's true weather, ``(n, 6)`` in physical units.
        params: the project's settings (``task2``, ``seed``, the prior box).
        model_name: the model's id (recorded in the metrics).

    Returns:
        The scores and the draws they compare (:class:`BagScores`).
    """
    domain = Domain(posterior.on_context(), contexts)  # equally weighted bag
    characterization, how = characterize(domain, params)
    scores, estimate, truth, prior = task2_metrics(characterization, params, model_name)
    metrics = {"estimate": params.task2.estimate, **scores}
    mixture = None
    if params.task2.estimate != "mixture":
        metrics["deconvolution"] = how
        metrics["mixture"], mixture, _, _ = task2_metrics(domain, params, model_name)
        del metrics["mixture"]["model"]
    metrics["width_floor"] = width_floor(domain.posterior, contexts, theta, params)
    return BagScores(metrics, how, estimate, truth, prior, mixture)
