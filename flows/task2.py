"""The ``task2`` stage: absolute characterization of a domain from a bag of images (paper, Task II).

``python -m flows.task2 [--params params.yaml]``. Renders the bag (:func:`components.domains.task2.render_bag`: every
parameter fixed but fog density and precipitation, the sun azimuth included), characterizes it with the registry
model ``task2.model`` on onnxruntime (the estimate ``task2.estimate``: the mixture p̂_𝒟(θ) = Σᵢ wᵢ q(θ | xᵢ) or its
deconvolution, :func:`components.domains.task2.characterize`), scores it against the true distribution and the prior
(:func:`components.domains.task2.task2_metrics`; a deconvolved estimate is reported with the mixture's figures beside
it, under ``mixture``) and writes ``reports/task2/metrics.json`` and plots (the true distribution and the estimate
side by side and overlaid, the 1-D marginals of truth, estimate, mixture and prior overlaid, the held-out likelihood
per EM step, the bag); logs the metrics and plots to MLflow.
"""

from __future__ import annotations

import json
import os

import numpy as np
from prefect import flow, task

from components import plots
from components.core.files import atomic_write_bytes
from components.domains import task2 as task2_
from components.domains.absolute import Domain
from components.export.lookup import load_registered, read_champion
from components.simulate.base import make_simulator
from flows import tracking
from flows.stage import open_stage, parse_stage_args


@task(name="task2-render-bag")
def render_bag(params_path: str) -> tuple[np.ndarray, np.ndarray]:
    """The bag: θ ``(n, 6)`` and the images ``(n, H, W, 3)`` rendered under them."""
    params = open_stage(params_path).params
    return task2_.render_bag(params, make_simulator(params.simulator))


def _note(row: dict, floor: float, calibrated: float, interval: dict | None = None) -> str:
    """A parameter's panel title: W₁ estimate→truth against the prior's and their ratio, the ratios of the mixture of
    calibrated posteriors of the same widths (``calibrated``) and of the posteriors moved onto their truths (``floor``;
    :func:`components.domains.task2.width_floor` at s = 1), the marginal HDR; for a varying parameter (``interval``:
    its row of ``width_floor.interval.mixture_minus_calibrated``) the mixture's ratio minus the calibrated one's with its
    95 % interval."""
    unit = "°" if row["unit"] == "deg" else row["unit"]
    return (
        f"W₁ to the truth {row['wasserstein_estimate']:.3g} {unit} (prior {row['wasserstein_prior']:.3g} {unit}): "
        f"ratio {row['wasserstein_ratio']:.2f}\nthese widths, calibrated: {calibrated:.2f}; on the truths: {floor:.2f}\n"
        + (
            ""
            if interval is None
            else "minus the calibrated: {:+.2f}, 95 % [{:+.2f}, {:+.2f}]\n".format(
                interval["difference"], interval["low"], interval["high"]
            )
        )
        + f"HDR {row['hdr_width']:.3g} {unit} wide, holds {100 * row['true_mass_in_hdr']:.0f} % of the truth"
    )


def _description(metrics: dict, model: str) -> str:
    """The Task II run's description: its headline figures."""
    energy = metrics["energy_distance_sq"]["all"]
    return (
        f"Task II with {model}, {metrics['estimate']} estimate: energy distance² estimate→truth "
        f"{energy['estimate_to_truth']:.4f} vs prior→truth "
        f"{energy['prior_to_truth']:.4f} (ratio {energy['ratio']:.3f}); {100 * metrics['true_mass_in_hdr']:.1f} % of "
        "the true mass inside the estimate's HDR. Per parameter: metrics `task2.parameters.<parameter>.*`."
    )


@flow(name="task2", log_prints=True)
def task2(params_path: str = "params.yaml") -> dict:
    """Characterize the Task II bag and compare with its true weather distribution; write reports/task2/."""
    stage = open_stage(params_path)
    params, paths, t = stage.params, stage.paths, stage.params.task2
    out = paths.reports("task2")
    # fails early without a registry model or champion; onnxruntime may use every core (nothing else runs here)
    pointer = read_champion(paths.registry) if t.model in tracking.ALIASES else None
    folder = tracking.registered_folder(paths.root, params, t.model, pointer)  # models:/pidc@champion
    model = load_registered(folder or t.model, paths.registry, threads=os.cpu_count() or 1)
    theta, images = render_bag(str(stage.params_file))
    contexts = model.posterior.context(model.inputs(images))  # the embedding runs once per image
    domain = Domain(model.posterior.on_context(), contexts)  # equally weighted bag
    characterization, how = task2_.characterize(domain, params)
    metrics, estimate, truth, prior = task2_.task2_metrics(characterization, params, model.name)
    metrics = {"estimate": t.estimate, **metrics}
    mixture = None
    if t.estimate != "mixture":
        metrics["deconvolution"] = how
        metrics["mixture"], mixture, _, _ = task2_.task2_metrics(domain, params, model.name)
        del metrics["mixture"]["model"]
    metrics["width_floor"] = floor = task2_.width_floor(domain.posterior, contexts, theta, params)

    labels = ("ground truth P_D(W)", f"estimate P̂_D(W), {t.estimate}")
    figures = [
        plots.save_figure(
            plots.corner_compare(truth, estimate, labels=labels, box=params.box),
            out / "plots" / "corner-truth-vs-estimate.png",
        ),
        plots.save_figure(
            plots.corner_compare(truth, estimate, labels=labels, box=params.box, overlay=True),
            out / "plots" / "corner-overlay.png",
        ),
        plots.save_figure(
            plots.marginals_overlay(
                truth,
                estimate,
                prior,
                box=params.box,
                notes=[
                    _note(
                        r,
                        floor["wasserstein_ratio"]["1"][n],
                        floor["calibrated"]["1"][n],
                        floor["interval"]["mixture_minus_calibrated"].get(n),
                    )
                    for n, r in metrics["parameters"].items()
                ],
                title=f"Task II ({model.name}): marginals of the truth, the {t.estimate} estimate and the prior "
                f"({100 * t.hdr_level:.0f} % HDR)",
                reference=mixture,
            ),
            out / "plots" / "marginals.png",
        ),
    ]
    if t.estimate != "mixture":
        figures.append(
            plots.save_figure(
                plots.held_out_curve(
                    np.asarray(how["held_out_log_likelihood"]),
                    how["steps"],
                    title=f"Task II ({model.name}): how far to deconvolve ({t.deconvolution.folds}-fold cross-validation)",
                ),
                out / "plots" / "deconvolution.png",
            )
        )
    shown = min(48, t.images)
    figures.append(
        plots.save_figure(
            plots.image_grid(images[:shown], ncols=8, title=f"Task II bag: {shown} of {t.images} images"),
            out / "plots" / "bag.png",
        )
    )
    atomic_write_bytes(out / "metrics.json", json.dumps(metrics, indent=1).encode())
    # MLflow: the held-out curve as one metric over the EM steps, not one metric per step
    flat, series = metrics, {}
    if t.estimate != "mixture":
        curve = how["held_out_log_likelihood"]
        flat = {**metrics, "deconvolution": {k: v for k, v in how.items() if k != "held_out_log_likelihood"}}
        series = {"task2.deconvolution.held_out_log_likelihood": dict(enumerate(curve))}
    tracking.log_domain_task(
        paths.root,
        params.train.experiment,
        "task2",
        model.name,
        tracking.flatten_numbers(flat, "task2"),
        series,
        [out / "metrics.json", *figures],
        {"pidc.model_source": tracking.model_source(params, t.model)},
        _description(metrics, model.name),
    )
    energy = metrics["energy_distance_sq"]["all"]
    varying = [n for n in metrics["parameters"] if n not in t.fixed]
    stage.logger.info(
        "task2 (%s, %s estimate): %.1f %% of the true mass inside the estimate's %.0f %% HDR; energy distance² (U) "
        "%.4f, prior %.4f, ratio %.3f (truth vs truth %.4f); W₁ to the truth over the prior's: %s",
        model.name,
        t.estimate,
        100 * metrics["true_mass_in_hdr"],
        100 * t.hdr_level,
        energy["estimate_to_truth"],
        energy["prior_to_truth"],
        energy["ratio"],
        energy["truth_to_truth"],
        ", ".join(
            f"{n} {metrics['parameters'][n]['wasserstein_ratio']:.3f} (calibrated posteriors of its widths "
            f"{floor['calibrated']['1'][n]:.3f})"
            for n in varying
        ),
    )
    return metrics


def main(argv: list[str] | None = None) -> None:
    args, _ = parse_stage_args("Task II: characterize a bag of images with a known weather distribution.", argv)
    task2(str(args.params))


if __name__ == "__main__":
    main()
