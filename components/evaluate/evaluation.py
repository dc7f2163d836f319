"""Task I of one exported model on the test split: its draws, metrics, posterior predictive checks and plots.

What the ``evaluate`` stage runs once per model (:func:`evaluate_exported`), in a worker of its own: the model of
``registry/<model>/`` on the torch-free onnxruntime posterior (one thread: the stage runs models in parallel, not one
model on many threads), its posterior draws for the first ``evaluate.images`` test images
(:mod:`components.evaluate.task1`), the per-parameter scores (:mod:`components.evaluate.marginals`,
:mod:`components.evaluate.profile`), the posterior predictive checks and the model's plots. The stage keeps the result
under a key that covers this module's code (``flows/evaluate.py``, ``EVALUATION_MODULES``).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from components import plots
from components.core import seeding
from components.core.config import Params
from components.core.paths import ProjectPaths
from components.evaluate import marginals, profile, task1
from components.export.runtime import OnnxPosterior
from components.features import cache as features
from components.features.backbones import get_backbone
from components.simulate import dataset
from components.simulate.base import make_simulator

__all__ = ["evaluate_exported"]


def evaluate_exported(
    params: Params, paths: ProjectPaths, model_id: str, band: float, plot_dir: Path, logger: logging.Logger
) -> dict:
    """Task I of the exported model ``model_id`` on the test split, its plots written into ``plot_dir``.

    Arguments:
        params: the project's settings (``evaluate``, ``seed``, ``prior``, ``simulator`` are read).
        paths: the project's folders (``registry/``, ``data/``, ``features/``).
        model_id: the model, a folder of ``registry/``.
        band: the calibration band of a perfectly calibrated model on the stage's number of images.
        plot_dir: where the model's PNG plots go (``ppc.png``, ``profile.png``, ``histograms-<i>.png``,
            ``corner-[zoom-]<i>.png``).
        logger: receives one line of timings (seconds of wall and CPU time per step).

    Returns:
        The JSON-serializable result: ``model``, ``metrics`` (headline metrics, with ``images``, ``samples`` and
        ``ppc_score`` and ``ppc_images``, the images checked: 0 with recorded data), ``coverage`` and ``pi`` (lists of floats), ``parameters`` and ``profiles`` (nested dicts).
    """
    ev = params.evaluate
    start, cpu = time.perf_counter(), time.thread_time()  # one onnxruntime thread: the calling one
    folder = paths.registry / model_id
    posterior = OnnxPosterior.load(folder, intra_op_num_threads=1)  # parallel over models, not inside one
    task1.check_model_matches_data(posterior.box, params, folder / "card.json")
    card = posterior.card
    test = dataset.open_split(paths.data, "test")
    n = task1.images_evaluated(ev.images, len(test))
    backbone = get_backbone(card["backbone"], **card["backbone_options"])
    x = features.inputs_from_cached(backbone, features.open_features(paths.features, card["backbone"], test, stop=n))
    truth = test.theta[:n]
    loaded = time.perf_counter()
    samples, lp, lp_truth = task1.posterior_draws(
        posterior, x, truth, ev.samples, seeding.derive_seed(params.seed, model_id)
    )
    drawn = time.perf_counter()
    metrics, coverage, pi = task1.task1_metrics(lp, lp_truth, params.box.log_volume(), band)
    metrics |= {"images": n, "samples": ev.samples}
    scores = marginals.marginal_scores(samples, truth, params.box)
    parameters = marginals.summarize_subsets(scores, truth, params.box)
    profiles = profile.truth_profile(scores, truth, params.box, ev.profile_bins)
    scored = time.perf_counter()

    metrics["ppc_score"] = _posterior_predictive(params, test, n, samples, model_id, plot_dir)
    metrics["ppc_images"] = 0 if params.simulator.backend == "recorded" else min(ev.ppc_images, n)
    plots.save_figure(
        plots.truth_profile_plot(profiles, title=f"{model_id}: Task I across the true value ({n} test images)"),
        plot_dir / "profile.png",
    )
    _example_plots(params, samples, lp, truth, model_id, plot_dir)
    end = time.perf_counter()
    logger.info(
        "%s: %d images × %d draws in %.1f s, CPU %.1f s (load %.1f s, draws %.1f s, metrics %.1f s, PPC and plots %.1f s)",
        model_id,
        n,
        ev.samples,
        end - start,
        time.thread_time() - cpu,
        loaded - start,
        drawn - loaded,
        scored - drawn,
        end - scored,
    )
    return {
        "model": model_id,
        "metrics": metrics,
        "coverage": coverage.tolist(),
        "pi": pi.tolist(),
        "parameters": parameters,
        "profiles": profiles,
    }


def _posterior_predictive(
    params: Params, test: dataset.Split, n: int, samples: np.ndarray, model_id: str, plot_dir: Path
) -> float:
    """The posterior predictive checks of the first ``evaluate.ppc_images`` test images: each scene re-rendered under
    posterior and prior draws (``samples``: ``(n, draws, 6)``), the sheet of the first written to ``ppc.png``.

    Arguments:
        params: the project's settings (``evaluate``, ``seed``, ``prior``, ``simulator``).
        test: the test split.
        n: the number of test images evaluated.
        samples: the posterior draws, ``(n, draws, 6)`` in physical units.
        model_id: the model (its random stream and the sheet's title).
        plot_dir: the folder of ``ppc.png``.

    Returns:
        The median PPC score over the checked images, NaN when none is checked: always with recorded data
        (``simulator.backend: recorded``), whose scenes no simulator can render again (``ppc_images`` 0 in the
        metrics).
    """
    ev = params.evaluate
    if params.simulator.backend == "recorded":
        return float("nan")
    n_ppc = min(ev.ppc_images, n)
    ppc_images = test.images(stop=n_ppc)
    checks = task1.posterior_predictive_checks(
        make_simulator(params.simulator),
        ppc_images,
        test.scene_seed[:n_ppc],
        test.weather[:n_ppc, 6],
        samples,
        params.box,
        ev.ppc_renders,
        seeding.rng(params.seed, "ppc", model_id),
    )
    score = float(np.median([c.score for c in checks])) if checks else float("nan")
    if checks:
        c = checks[0]
        plots.save_figure(
            plots.ppc_sheet(
                ppc_images[0],
                c.posterior_renders,
                c.prior_renders,
                {"posterior": c.d_posterior, "prior": c.d_prior},
                title=f"{model_id}: posterior predictive check (score {c.score:.2f})",
            ),
            plot_dir / "ppc.png",
        )
    return score


def _example_plots(
    params: Params, samples: np.ndarray, lp: np.ndarray, truth: np.ndarray, model_id: str, plot_dir: Path
) -> None:
    """The marginal histograms and the corner plots (whole prior box and zoomed) of the first
    ``evaluate.example_images`` test images.

    Arguments:
        params: the project's settings (``evaluate.example_images``, ``prior``).
        samples: the posterior draws, ``(n, draws, 6)`` in physical units.
        lp: their log-densities, ``(n, draws)`` (nats).
        truth: the true weather of the images, ``(n, 6)``.
        model_id: the model (the plots' titles).
        plot_dir: the folder of ``histograms-<i>.png``, ``corner-<i>.png`` and ``corner-zoom-<i>.png``.
    """
    for i in range(min(params.evaluate.example_images, len(truth))):
        plots.save_figure(
            plots.marginal_histograms(samples[i], lp[i], truth[i], box=params.box), plot_dir / f"histograms-{i}.png"
        )
        for zoom in (False, True):
            plots.save_figure(
                plots.corner_plot(
                    samples[i],
                    lp[i],
                    truth[i],
                    box=params.box,
                    zoom=zoom,
                    title=f"{model_id}, test image {i}" + (" (zoomed)" if zoom else ""),
                ),
                plot_dir / f"corner-{'zoom-' if zoom else ''}{i}.png",
            )
