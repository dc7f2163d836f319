"""The ``task2`` stage's plots, MLflow values and run description, from a scored bag
(:class:`components.domains.task2.BagScores`).

* :func:`write_plots`: the true distribution and the estimate side by side and overlaid, the 1-D marginals of truth,
  estimate, mixture and prior overlaid (each panel titled by :func:`panel_note`), the held-out likelihood per EM step
  of a deconvolved estimate, and the bag.
* :func:`mlflow_values`: the metrics as MLflow takes them (the held-out curve as one series over the EM steps).
* :func:`description`: the run's headline figures, in words.

No MLflow here: the stage logs what these return (``flows/tracking.py``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from components import plots
from components.core.config import Params
from components.domains.task2 import BagScores

__all__ = ["panel_note", "write_plots", "mlflow_values", "description"]

#: the most images of the bag shown in ``bag.png``
SHOWN_IMAGES = 48


def panel_note(row: dict, floor: float, calibrated: float, interval: dict | None = None) -> str:
    """A parameter's panel title in ``marginals.png``.

    Arguments:
        row: the parameter's row of ``metrics["parameters"]`` (W₁ estimate→truth and prior→truth in its ``unit``,
            their ratio, the marginal HDR's width and the share of the truth in it).
        floor: the W₁ ratio of the posteriors moved onto their truths (:func:`components.domains.task2.width_floor`
            at s = 1).
        calibrated: the ratio of the mixture of calibrated posteriors of the same widths.
        interval: for a varying parameter, its row of ``width_floor.interval.mixture_minus_calibrated`` (the
            mixture's ratio minus the calibrated one's and its 95 % interval); None for a fixed one.

    Returns:
        The title, three or four lines.
    """
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


def write_plots(plot_dir: Path, bag: BagScores, images: np.ndarray, params: Params, model_name: str) -> list[Path]:
    """Write the Task II plots into ``plot_dir``.

    Arguments:
        plot_dir: the folder ``reports/task2/plots/``.
        bag: the scored bag.
        images: the bag's images, ``(n, H, W, 3)`` uint8.
        params: the project's settings (``task2``, the prior box).
        model_name: the model's id (the titles).

    Returns:
        The files written: ``corner-truth-vs-estimate.png``, ``corner-overlay.png``, ``marginals.png``,
        ``deconvolution.png`` (a deconvolved estimate only) and ``bag.png``.
    """
    t, metrics = params.task2, bag.metrics
    floor = metrics["width_floor"]
    labels = ("ground truth P_D(W)", f"estimate P̂_D(W), {t.estimate}")
    notes = [
        panel_note(
            r,
            floor["wasserstein_ratio"]["1"][n],
            floor["calibrated"]["1"][n],
            floor["interval"]["mixture_minus_calibrated"].get(n),
        )
        for n, r in metrics["parameters"].items()
    ]
    figures = [
        plots.save_figure(
            plots.corner_compare(bag.truth, bag.estimate, labels=labels, box=params.box),
            plot_dir / "corner-truth-vs-estimate.png",
        ),
        plots.save_figure(
            plots.corner_compare(bag.truth, bag.estimate, labels=labels, box=params.box, overlay=True),
            plot_dir / "corner-overlay.png",
        ),
        plots.save_figure(
            plots.marginals_overlay(
                bag.truth,
                bag.estimate,
                bag.prior,
                box=params.box,
                notes=notes,
                title=f"Task II ({model_name}): marginals of the truth, the {t.estimate} estimate and the prior "
                f"({100 * t.hdr_level:.0f} % HDR)",
                reference=bag.mixture,
            ),
            plot_dir / "marginals.png",
        ),
    ]
    if t.estimate != "mixture":
        figures.append(
            plots.save_figure(
                plots.held_out_curve(
                    np.asarray(bag.how["held_out_log_likelihood"]),
                    bag.how["steps"],
                    title=f"Task II ({model_name}): how far to deconvolve ({t.deconvolution.folds}-fold cross-validation)",
                ),
                plot_dir / "deconvolution.png",
            )
        )
    shown = min(SHOWN_IMAGES, t.images)
    figures.append(
        plots.save_figure(
            plots.image_grid(images[:shown], ncols=8, title=f"Task II bag: {shown} of {t.images} images"),
            plot_dir / "bag.png",
        )
    )
    return figures


def mlflow_values(bag: BagScores, estimate: str) -> tuple[dict, dict[str, dict[int, float]]]:
    """The metrics to flatten into MLflow metrics and the series to log step by step.

    Arguments:
        bag: the scored bag.
        estimate: ``task2.estimate``.

    Returns:
        ``(values, series)``: the metrics, a deconvolved estimate's held-out curve left out of its ``deconvolution``;
        that curve as ``{"task2.deconvolution.held_out_log_likelihood": {step: value}}`` (empty for the mixture).
    """
    if estimate == "mixture":
        return bag.metrics, {}
    curve = bag.how["held_out_log_likelihood"]
    flat = {**bag.metrics, "deconvolution": {k: v for k, v in bag.how.items() if k != "held_out_log_likelihood"}}
    return flat, {"task2.deconvolution.held_out_log_likelihood": dict(enumerate(curve))}


def description(metrics: dict, model: str) -> str:
    """The Task II run's description: its headline figures.

    Arguments:
        metrics: :attr:`BagScores.metrics`.
        model: the model's id.

    Returns:
        One paragraph of markdown.
    """
    energy = metrics["energy_distance_sq"]["all"]
    return (
        f"Task II with {model}, {metrics['estimate']} estimate: energy distance² estimate→truth "
        f"{energy['estimate_to_truth']:.4f} vs prior→truth "
        f"{energy['prior_to_truth']:.4f} (ratio {energy['ratio']:.3f}); {100 * metrics['true_mass_in_hdr']:.1f} % of "
        "the true mass inside the estimate's HDR. Per parameter: metrics `task2.parameters.<parameter>.*`."
    )
