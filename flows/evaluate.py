"""The ``evaluate`` stage: Task I for every model of the grid on the test split.

``python -m flows.evaluate [--params params.yaml]``. The models are the exported ones of ``registry/``, run on the
torch-free onnxruntime posterior (what a vehicle would run), ``evaluate.runner.workers`` models at a time (one
onnxruntime thread each). Per model (:mod:`components.evaluate.task1`): posterior samples and their log-densities for
``evaluate.images`` test images (``all``: the whole split), HPD credibility of the ground truth, expected coverage,
calibration error beside the band of a perfectly calibrated model on as many images, signed coverage area,
superiority π, test NLL, information gain, a quantitative posterior predictive check, and per parameter
(:mod:`components.evaluate.marginals`) interval widths and coverage, median errors and marginal information gain, for
all, day and night truths. Writes ``reports/task1/``: ``metrics.json`` (model → headline metrics), ``models/<model>.json``
(one flat row per model: the DVC metrics), ``parameters.json`` (model → subset → parameter → figures), ``profiles.json``
(the same by bin of the true value, :mod:`components.evaluate.profile`), ``coverage.json``,
``table.md`` (the README's results table) and PNG plots; logs them to each model's MLflow run; names the champion
(:mod:`components.evaluate.champion`): MLflow aliases ``champion`` and ``challenger`` (the runner-up) and the pointer
``reports/task1/champion.json``.
"""

from __future__ import annotations

import json
import time

import numpy as np
from prefect import flow, task

from components import plots
from components.core import seeding
from components.core.files import atomic_write_bytes
from components.evaluate import marginals, profile, report, task1
from components.evaluate.champion import NoChampionError, champion_pointer, choose_champion
from components.export.lookup import CHAMPION_POINTER
from components.export.runtime import OnnxPosterior
from components.features import cache as features
from components.features.backbones import get_backbone
from components.simulate import dataset
from components.simulate.base import make_simulator
from flows import tracking
from flows.stage import at_most, open_stage, parse_stage_args, share_api_with_workers, task_runner


def _write_json(path, value) -> None:
    atomic_write_bytes(path, json.dumps(value, indent=1).encode())


@task(name="evaluate-model")
def evaluate_model(model_id: str, params_path: str, band: float) -> dict:
    """Task I of one exported model (``band``: the calibration band of the stage's number of images)."""
    stage = open_stage(params_path)
    params, paths, ev = stage.params, stage.paths, stage.params.evaluate
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
    plots.save_figure(
        plots.truth_profile_plot(profiles, title=f"{model_id}: Task I across the true value ({n} test images)"),
        plot_dir / "profile.png",
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
    end = time.perf_counter()
    stage.logger.info(
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


@flow(name="evaluate", log_prints=True)
def evaluate(params_path: str) -> dict:
    """Evaluate every model of the grid; write reports/task1/, log to MLflow and name the champion."""
    stage = open_stage(params_path)
    params, paths, logger, ev = stage.params, stage.paths, stage.logger, stage.params.evaluate
    out = paths.reports("task1")
    ids = params.model_ids()
    missing = [m for m in ids if not (paths.registry / m / "card.json").is_file()]
    if missing:
        raise FileNotFoundError(f"no exported model in registry/ for {', '.join(missing)}: run `dvc repro export`")
    test = dataset.open_split(paths.data, "test")  # a missing test split fails here, before any work
    n = task1.images_evaluated(ev.images, len(test))
    band = task1.calibration_band(n, ev.samples, ev.band_level, ev.band_replicates, params.seed)
    cards = {m: json.loads((paths.registry / m / "card.json").read_text()) for m in ids}
    share_api_with_workers()
    done = at_most(
        ev.runner.workers,
        task1.evaluation_order(ids, cards),
        lambda m: evaluate_model.submit(m, str(stage.params_file), band),
        "evaluate models",
    )
    results = [done[m] for m in ids]

    levels = task1.LEVELS
    curves = {r["model"]: (levels, np.array(r["coverage"])) for r in results}
    plots.save_figure(
        plots.coverage_plot(
            curves,
            title=f"Task I: expected coverage on {n} test images",
            band=band,
            band_label=f"{100 * ev.band_level:g} % band of a calibrated\nmodel on {n} images",
        ),
        out / "plots" / "coverage.png",
    )
    plots.save_figure(
        plots.superiority_boxplot({r["model"]: np.array(r["pi"]) for r in results}), out / "plots" / "superiority.png"
    )
    metrics = {r["model"]: r["metrics"] for r in results}
    parameters = {r["model"]: r["parameters"] for r in results}
    _write_json(out / "metrics.json", metrics)
    _write_json(out / "parameters.json", parameters)
    _write_json(out / "profiles.json", {r["model"]: r["profiles"] for r in results})
    rows = {m: report.model_row(metrics[m], parameters[m]) for m in ids}
    for m, row in rows.items():
        _write_json(out / "models" / f"{m}.json", row)
    for stale in (out / "models").glob("*.json"):
        if stale.stem not in rows:
            stale.unlink()  # a model no longer in the grid
    plots.save_figure(plots.parameter_heatmaps(parameters, box=params.box), out / "plots" / "parameters.png")
    coverage_rows = [
        {"model": m, "level": float(lv), "coverage": float(c)}
        for m, (ls, cs) in curves.items()
        for lv, c in zip(ls, cs, strict=True)
    ]
    atomic_write_bytes(out / "coverage.json", json.dumps(coverage_rows).encode())
    tracking.log_task1(paths.root, params.train.experiment, results, out / "plots")
    grid_files = [out / "plots" / f for f in ("coverage.png", "superiority.png", "parameters.png")]
    for m, v in metrics.items():
        logger.info(
            "%s: calibration error %.3f (band %.3f: %s), coverage gap %+.3f, π median %.2f, NLL %.2f (information "
            "gain %.2f nats), PPC %.2f",
            m,
            v["calibration_error"],
            v["calibration_band"],
            "within" if v["within_band"] else "outside",
            v["coverage_auc_gap"],
            v["pi_median"],
            v["test_nll"],
            v["info_gain_nats"],
            v["ppc_score"],
        )

    try:
        champion, runner_up = choose_champion(metrics, params.export.champion_max_calibration_error)
    except NoChampionError:
        (paths.root / CHAMPION_POINTER).unlink(missing_ok=True)  # no stale pick for task2, task3 and the CLI
        tracking.clear_champion_aliases(paths.root, params)  # nor for models:/pidc@champion (the monitoring)
        table = report.results_table(rows, None, ev.band_level)
        atomic_write_bytes(out / "table.md", table.encode())
        tracking.describe_grid(paths.root, params, test.content_hash, metrics, None, table, grid_files)
        raise
    table = report.results_table(rows, champion.model, ev.band_level)
    atomic_write_bytes(out / "table.md", table.encode())
    grid_files.append(out / "table.md")
    pointer = champion_pointer(metrics, champion, runner_up)
    aliases = tracking.set_champion_alias(
        paths.root, params, metrics, champion.model, runner_up.model if runner_up else None
    )
    pointer |= {"registered_model": tracking.registered_model(params)}
    pointer |= aliases.get(tracking.CHAMPION_ALIAS, {})
    if runner_up:
        pointer["runner_up"] |= {"registered_model": tracking.registered_model(params)}
        pointer["runner_up"] |= aliases.get(tracking.CHALLENGER_ALIAS, {})
    _write_json(paths.root / CHAMPION_POINTER, pointer)
    tracking.describe_grid(paths.root, params, test.content_hash, metrics, pointer, table, grid_files)
    logger.info(
        "champion: %s (%s: %s), %s",
        champion.model,
        champion.rule,
        champion.reason,
        pointer.get("uri", "not in the MLflow Model Registry"),
    )
    if runner_up:
        logger.info("runner-up (challenger): %s (%s)", runner_up.model, runner_up.rule)
    return metrics


def main(argv: list[str] | None = None) -> None:
    args, params = parse_stage_args("Task I evaluation of the grid (the evaluate stage).", argv)
    evaluate.with_options(task_runner=task_runner(params.evaluate.runner))(str(args.params))


if __name__ == "__main__":
    main()
