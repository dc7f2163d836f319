"""The ``evaluate`` stage: Task I for every model of the grid on the test split.

``python -m flows.evaluate [--params params.yaml]``. The models are the exported ones of ``registry/``, run on the
torch-free onnxruntime posterior (what a vehicle would run). Per model (:mod:`components.evaluate.task1`): posterior
samples and their log-densities for the first ``evaluate.images`` test images, HPD credibility of the ground truth,
expected coverage, calibration error, signed coverage area, superiority π, test NLL, information gain and a
quantitative posterior predictive check. Writes ``reports/task1/metrics.json``, ``coverage.json`` and PNG plots, logs
them to each model's MLflow run, and gives the champion (:mod:`components.evaluate.champion`) the MLflow alias
``champion`` and the pointer ``reports/task1/champion.json``.
"""

from __future__ import annotations

import json

import numpy as np
from prefect import flow, task
from tqdm.auto import tqdm

from components import plots
from components.core import seeding
from components.core.files import atomic_write_bytes
from components.evaluate import task1
from components.evaluate.champion import choose_champion
from components.export.lookup import CHAMPION_POINTER
from components.export.runtime import OnnxPosterior
from components.features import cache as features
from components.features.backbones import get_backbone
from components.simulate import dataset
from components.simulate.base import make_simulator
from flows import tracking
from flows.stage import open_stage, parse_stage_args


@task(name="evaluate-model")
def evaluate_model(model_id: str, params_path: str) -> dict:
    stage = open_stage(params_path)
    params, paths, ev = stage.params, stage.paths, stage.params.evaluate
    folder = paths.registry / model_id
    posterior = OnnxPosterior.load(folder)
    task1.check_model_matches_data(posterior.box, params, folder / "card.json")
    card = posterior.card
    test = dataset.open_split(paths.data, "test")
    n = min(ev.images, len(test))
    backbone = get_backbone(card["backbone"], **card["backbone_options"])
    x = features.inputs_from_cached(backbone, features.open_features(paths.features, card["backbone"], test, stop=n))
    truth = test.theta[:n]
    samples, lp, lp_truth = task1.posterior_draws(
        posterior, x, truth, ev.samples, seeding.derive_seed(params.seed, model_id)
    )
    metrics, coverage, pi = task1.task1_metrics(lp, lp_truth, params.box.log_volume())
    metrics |= {"images": n, "samples": ev.samples}

    # posterior predictive checks: the same scene re-rendered under posterior and prior draws
    plot_dir = paths.reports("task1", "plots", model_id)
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
    metrics["ppc_score"] = float(np.median([c.score for c in checks])) if checks else float("nan")
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
    for i in range(min(ev.example_images, n)):
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
    return {"model": model_id, "metrics": metrics, "coverage": coverage.tolist(), "pi": pi.tolist()}


@flow(name="evaluate", log_prints=True)
def evaluate(params_path: str) -> dict:
    """Evaluate every model of the grid; write reports/task1/, log to MLflow and name the champion."""
    stage = open_stage(params_path)
    params, paths, logger = stage.params, stage.paths, stage.logger
    out = paths.reports("task1")
    ids = task1.model_ids(params)
    missing = [m for m in ids if not (paths.registry / m / "card.json").is_file()]
    if missing:
        raise FileNotFoundError(f"no exported model in registry/ for {', '.join(missing)}: run `dvc repro export`")
    dataset.open_split(paths.data, "test")  # a missing test split fails here, before any work
    results = [evaluate_model(m, str(stage.params_file)) for m in tqdm(ids, desc="evaluate models", unit="model")]

    levels = task1.LEVELS
    curves = {r["model"]: (levels, np.array(r["coverage"])) for r in results}
    plots.save_figure(
        plots.coverage_plot(curves, title="Task I: expected coverage on the test split"), out / "plots" / "coverage.png"
    )
    plots.save_figure(
        plots.superiority_boxplot({r["model"]: np.array(r["pi"]) for r in results}), out / "plots" / "superiority.png"
    )
    metrics = {r["model"]: r["metrics"] for r in results}
    atomic_write_bytes(out / "metrics.json", json.dumps(metrics, indent=1).encode())
    rows = [
        {"model": m, "level": float(lv), "coverage": float(c)}
        for m, (ls, cs) in curves.items()
        for lv, c in zip(ls, cs, strict=True)
    ]
    atomic_write_bytes(out / "coverage.json", json.dumps(rows).encode())
    tracking.log_task1(paths.root, params.train.experiment, results, out / "plots")

    metric = params.export.champion_metric
    best, value = choose_champion(metrics, metric)
    pointer = {
        "model": best,
        "metric": metric,
        "value": value,
        "registered_model": tracking.registered_name(params, best),
    }
    pointer |= tracking.set_champion_alias(paths.root, params, metrics, best)
    atomic_write_bytes(paths.root / CHAMPION_POINTER, json.dumps(pointer, indent=1).encode())
    logger.info(
        "champion (lowest %s): %s = %.3f, %s",
        metric,
        best,
        value,
        pointer.get("uri", "not in the MLflow Model Registry"),
    )
    for m, v in metrics.items():
        logger.info(
            "%s: calibration error %.3f, coverage gap %+.3f, π median %.2f, NLL %.2f, PPC %.2f",
            m,
            v["calibration_error"],
            v["coverage_auc_gap"],
            v["pi_median"],
            v["test_nll"],
            v["ppc_score"],
        )
    return metrics


def main(argv: list[str] | None = None) -> None:
    args, _ = parse_stage_args("Task I evaluation of the grid (the evaluate stage).", argv)
    evaluate(str(args.params))


if __name__ == "__main__":
    main()
