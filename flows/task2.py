"""The ``task2`` stage: absolute characterization of a domain from a bag of images (paper, Task II).

``python -m flows.task2 [--params params.yaml]``. Renders the bag (:func:`components.domains.task2.render_bag`: every
parameter fixed but fog density and precipitation, the sun azimuth included), characterizes it with the registry
model ``task2.model`` on onnxruntime (the estimate ``task2.estimate``: the mixture p̂_𝒟(θ) = Σᵢ wᵢ q(θ | xᵢ) or its
deconvolution, :func:`components.domains.task2.characterize`), scores it against the true distribution and the prior
(:func:`components.domains.task2.task2_metrics`; a deconvolved estimate is reported with the mixture's figures beside
it, under ``mixture``) and writes ``reports/task2/metrics.json`` and plots (the true distribution and the estimate
side by side and overlaid, the 1-D marginals of truth, estimate, mixture and prior overlaid, the held-out likelihood
per EM step, the bag); logs the metrics and plots to MLflow. ``bag_renderer`` in the metrics names the simulator that
rendered the bag. With recorded data (``simulator.backend: recorded``) the bag is rendered by
``simulator.recorded.renderer`` and the metrics say so (``bag_note``); when it names none, no simulator can render the
bag: the stage writes ``{"skipped": <why>}`` as its metrics and logs nothing to MLflow.
"""

from __future__ import annotations

import json

import numpy as np
from prefect import flow, task

from components.core.files import atomic_write_bytes
from components.core.hardware import usable_cores
from components.domains import task2 as task2_
from components.domains import task2_report
from components.export.lookup import load_registered, read_champion
from components.simulate.base import new_scene_simulator
from flows import tracking
from flows.stage import open_stage, parse_stage_args

#: the metrics' ``skipped`` entry when no simulator can render the bag (recorded data without a renderer)
NO_RENDERER = (
    "no simulator renders the bag: the data are recorded (simulator.backend: recorded) and "
    "simulator.recorded.renderer is null; set it to procedural or carla to run Task II"
)


@task(name="task2-render-bag")
def render_bag(params_path: str) -> tuple[np.ndarray, np.ndarray, str]:
    """The bag: θ ``(n, 6)``, the images ``(n, H, W, 3)`` rendered under them, and the renderer's version."""
    params = open_stage(params_path).params
    simulator = new_scene_simulator(params.simulator)
    return (*task2_.render_bag(params, simulator), simulator.version)


def _bag_note(params) -> dict:
    """What the metrics say of the bag's renderer when the models learned recorded images."""
    if params.simulator.backend != "recorded":
        return {}
    return {
        "bag_note": f"the models learned recorded images; the bag is rendered by simulator.recorded.renderer "
        f"({params.simulator.recorded.renderer}) in new scenes: the figures hold for that renderer's images"
    }


def _log_summary(logger, metrics: dict, params, model_name: str) -> None:
    """The stage's last log line: the HDR mass, the energy distances and the varying parameters' W₁ ratios."""
    t = params.task2
    energy, floor = metrics["energy_distance_sq"]["all"], metrics["width_floor"]
    varying = [n for n in metrics["parameters"] if n not in t.fixed]
    logger.info(
        "task2 (%s, %s estimate): %.1f %% of the true mass inside the estimate's %.0f %% HDR; energy distance² (U) "
        "%.4f, prior %.4f, ratio %.3f (truth vs truth %.4f); W₁ to the truth over the prior's: %s",
        model_name,
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


@flow(name="task2", log_prints=True)
def task2(params_path: str = "params.yaml") -> dict:
    """Characterize the Task II bag and compare with its true weather distribution; write reports/task2/."""
    stage = open_stage(params_path)
    params, paths, t = stage.params, stage.paths, stage.params.task2
    out = paths.reports("task2")
    if params.simulator.backend == "recorded" and params.simulator.recorded.renderer is None:
        (out / "plots").mkdir(parents=True, exist_ok=True)
        skipped = {"skipped": NO_RENDERER}
        atomic_write_bytes(out / "metrics.json", json.dumps(skipped, indent=1).encode())
        stage.logger.warning("task2 skipped: %s", NO_RENDERER)
        return skipped
    # fails early without a registry model or champion; onnxruntime may use every core (nothing else runs here)
    pointer = read_champion(paths.registry) if t.model in tracking.ALIASES else None
    folder = tracking.registered_folder(paths.root, params, t.model, pointer)  # models:/pidc@champion
    model = load_registered(folder or t.model, paths.registry, threads=usable_cores())
    theta, images, renderer = render_bag(str(stage.params_file))
    contexts = model.posterior.context(model.inputs(images))  # the embedding runs once per image
    bag = task2_.score_bag(model.posterior, contexts, theta, params, model.name)
    bag.metrics.update({"bag_renderer": renderer, **_bag_note(params)})
    figures = task2_report.write_plots(out / "plots", bag, images, params, model.name)
    atomic_write_bytes(out / "metrics.json", json.dumps(bag.metrics, indent=1).encode())
    # MLflow: the held-out curve as one metric over the EM steps, not one metric per step
    flat, series = task2_report.mlflow_values(bag, t.estimate)
    tracking.log_domain_task(
        paths.root,
        params.train.experiment,
        "task2",
        model.name,
        tracking.flatten_numbers(flat, "task2"),
        series,
        [out / "metrics.json", *figures],
        {"pidc.model_source": tracking.model_source(params, t.model)},
        task2_report.description(bag.metrics, model.name),
    )
    _log_summary(stage.logger, bag.metrics, params, model.name)
    return bag.metrics


def main(argv: list[str] | None = None) -> None:
    args, _ = parse_stage_args("Task II: characterize a bag of images with a known weather distribution.", argv)
    task2(str(args.params))


if __name__ == "__main__":
    main()
