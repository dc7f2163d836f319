"""The ``evaluate`` stage: Task I for every model of the grid on the test split.

``python -m flows.evaluate [--params params.yaml]``. The models are the exported ones of ``registry/``, run on the
torch-free onnxruntime posterior (what a vehicle would run). Per model: posterior samples and their
log-densities for the first ``evaluate.images`` test images, HPD credibility of the ground truth,
expected coverage, calibration error, signed coverage area, superiority π, test NLL, information gain
and a quantitative posterior predictive check. Writes ``reports/task1/metrics.json`` and PNG plots,
and logs the metrics and plots to each model's MLflow run. Finally the best-calibrated model gets the MLflow alias
``champion`` and the pointer ``reports/task1/champion.json`` (:func:`flows.export.set_champion`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import mlflow
import numpy as np
from prefect import flow, get_run_logger, task
from tqdm.auto import tqdm

from components.simulate import dataset
from components.evaluate import diagnostics
from components.features import cache as features
from components import plots
from components.evaluate import ppc
from components.core import seeding
from components.core import weather
from components.features.backbones import get_backbone
from components.core.config import PROJECT_ROOT, Params, load_params
from components.core.files import atomic_write_bytes
from components.export.runtime import OnnxPosterior
from components.simulate.base import make_simulator
from flows.export import newest_model_run, registry_root, set_champion
from flows.features import features_root
from flows.generate import data_root
from flows.train import tracking_uri

LEVELS = diagnostics.DEFAULT_LEVELS


def model_ids(params: Params) -> list[str]:
    """The grid's models, then the calibrated variants."""
    grid = [f"{b}-{s}" for b in params.backbones.names for s in params.train.sizes]
    return grid + [f"{v.backbone}-{v.size}-{name}" for name, v in params.train.variants.items()]


def check_model_matches_data(box: weather.Box, params: Params, path: Path) -> None:
    """The model's θ order, units and prior box must be the dataset's."""
    box = {"names": list(box.names), "units": list(box.units), "low": box.low, "high": box.high}
    if tuple(box["names"]) != weather.PREDICTED:
        raise ValueError(f"{path}: the model's θ order {box['names']} differs from the dataset's {list(weather.PREDICTED)}")
    units = tuple(weather.PARAMETERS[n].unit for n in weather.PREDICTED)
    if tuple(box["units"]) != units:
        raise ValueError(f"{path}: the model's θ units {box['units']} differ from the dataset's {list(units)}")
    if not (np.allclose(box["low"], params.box.low) and np.allclose(box["high"], params.box.high)):
        raise ValueError(f"{path}: the model's prior box differs from params.yaml's prior")


def posterior_draws(posterior: OnnxPosterior, x: np.ndarray, theta: np.ndarray, n: int, seed: int, chunk: int = 25):
    """Samples ``(N, n, 6)``, their log-densities ``(N, n)`` and the truth's ``(N,)`` for N inputs ``x``."""
    out_s, out_lp, out_lt = [], [], []
    for s in range(0, len(x), chunk):
        xs = x[s : s + chunk]
        th, lp = posterior.sample_and_log_prob(xs, n, seed=seeding.derive_seed(seed, "evaluate", s))
        out_s.append(th)
        out_lp.append(lp)
        out_lt.append(posterior.log_prob(theta[s : s + chunk], xs))
    return np.concatenate(out_s), np.concatenate(out_lp), np.concatenate(out_lt)


@task(name="evaluate-model")
def evaluate_model(model_id: str, params_path: str, out: str) -> dict:
    params_file = Path(params_path)
    params = load_params(params_file)
    ev = params.evaluate
    base = params_file.resolve().parent
    folder = registry_root(params_file) / model_id
    posterior = OnnxPosterior.load(folder)
    check_model_matches_data(posterior.box, params, folder / "card.json")
    card = posterior.card
    test = dataset.open_split(data_root(params, params_file), "test")
    n = min(ev.images, len(test))
    backbone = get_backbone(card["backbone"], **card["backbone_options"])
    cached = features.open_features(features_root(params_file), card["backbone"], test, stop=n)
    x = features.inputs_from_cached(backbone, cached)
    truth = test.theta[:n]
    samples, lp, lp_truth = posterior_draws(posterior, x, truth, ev.samples, seeding.derive_seed(params.seed, model_id))

    cred = diagnostics.hpd_credibility(lp, lp_truth)
    coverage = diagnostics.expected_coverage(cred, LEVELS)
    pi = diagnostics.superiority(lp, lp_truth)
    test_nll = float(-lp_truth.mean())
    metrics = {
        "calibration_error": diagnostics.calibration_error(cred, LEVELS),
        # signed area between the coverage curve and the diagonal: < 0 overconfident, > 0 conservative
        "coverage_auc_gap": float(np.trapezoid(coverage - LEVELS, LEVELS)),
        "pi_median": float(np.median(pi)),
        "test_nll": test_nll,
        "info_gain_nats": -test_nll + params.box.log_volume(),
        "images": n,
        "samples": ev.samples,
    }

    # posterior predictive checks: the same scene re-rendered under posterior and prior draws
    folder = Path(out) / "plots" / model_id
    sim = make_simulator(params.simulator)
    rng = seeding.rng(params.seed, "ppc", model_id)
    scores = []
    n_ppc = min(ev.ppc_images, n)
    ppc_images = test.images(stop=n_ppc)
    for i in range(n_ppc):
        post = samples[i, rng.choice(ev.samples, ev.ppc_renders, replace=False)]
        prior = params.box.sample(rng, ev.ppc_renders)
        image = ppc_images[i]
        result = ppc.posterior_predictive_check(sim, image, int(test.scene_seed[i]), float(test.weather[i, 6]), post, prior)
        scores.append(result.score)
        if i == 0:
            plots.save_figure(plots.ppc_sheet(image, result.posterior_renders, result.prior_renders,
                                              {"posterior": result.d_posterior, "prior": result.d_prior},
                                              title=f"{model_id}: posterior predictive check (score {result.score:.2f})"),
                              folder / "ppc.png")
    metrics["ppc_score"] = float(np.median(scores)) if scores else float("nan")

    for i in range(min(ev.example_images, n)):
        plots.save_figure(plots.marginal_histograms(samples[i], lp[i], truth[i], box=params.box), folder / f"histograms-{i}.png")
        plots.save_figure(plots.corner_plot(samples[i], lp[i], truth[i], box=params.box, title=f"{model_id}, test image {i}"),
                          folder / f"corner-{i}.png")
        plots.save_figure(plots.corner_plot(samples[i], lp[i], truth[i], box=params.box, zoom=True,
                                            title=f"{model_id}, test image {i} (zoomed)"), folder / f"corner-zoom-{i}.png")
    return {"model": model_id, "metrics": metrics, "coverage": coverage.tolist(), "pi": pi.tolist()}


def log_to_mlflow(base: Path, experiment: str, results: list[dict], out: Path) -> None:
    """Log each model's metrics and plots to its newest MLflow run (by tag ``pidc.model``)."""
    mlflow.set_tracking_uri(tracking_uri(base))
    client = mlflow.MlflowClient()
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return
    for r in results:
        run_id = newest_model_run(client, exp.experiment_id, r["model"])
        if run_id is None:
            continue
        for k, v in r["metrics"].items():
            client.log_metric(run_id, f"task1.{k}", float(v))
        for f in sorted((out / "plots" / r["model"]).glob("*.png")):
            client.log_artifact(run_id, str(f), artifact_path="task1")


@flow(name="evaluate", log_prints=True)
def evaluate(params_path: str) -> dict:
    """Evaluate every model of the grid; write reports/task1/ and log to MLflow."""
    logger = get_run_logger()
    params_file = Path(params_path)
    params = load_params(params_file)
    base = params_file.resolve().parent
    out = base / "reports" / "task1"
    ids = model_ids(params)
    missing = [m for m in ids if not (registry_root(params_file) / m / "card.json").is_file()]
    if missing:
        raise FileNotFoundError(f"no exported model in registry/ for {', '.join(missing)}: run `dvc repro export`")
    dataset.open_split(data_root(params, params_file), "test")  # a missing test split fails here, before any work
    results = [evaluate_model(m, str(params_file), str(out)) for m in tqdm(ids, desc="evaluate models", unit="model")]

    curves = {r["model"]: (LEVELS, np.array(r["coverage"])) for r in results}
    plots.save_figure(plots.coverage_plot(curves, title="Task I: expected coverage on the test split"), out / "plots" / "coverage.png")
    plots.save_figure(plots.superiority_boxplot({r["model"]: np.array(r["pi"]) for r in results}), out / "plots" / "superiority.png")
    metrics = {r["model"]: r["metrics"] for r in results}
    atomic_write_bytes(out / "metrics.json", json.dumps(metrics, indent=1).encode())
    rows = [{"model": m, "level": float(l), "coverage": float(c)} for m, (ls, cs) in curves.items() for l, c in zip(ls, cs)]
    atomic_write_bytes(out / "coverage.json", json.dumps(rows).encode())
    log_to_mlflow(base, params.train.experiment, results, out)
    champion = set_champion(params, base, metrics)
    logger.info("champion (lowest %s): %s = %.3f, %s", champion["metric"], champion["model"], champion["value"],
                champion.get("uri", "not in the MLflow Model Registry"))
    for m, v in metrics.items():
        logger.info("%s: calibration error %.3f, coverage gap %+.3f, π median %.2f, NLL %.2f, PPC %.2f", m,
                    v["calibration_error"], v["coverage_auc_gap"], v["pi_median"], v["test_nll"], v["ppc_score"])
    return metrics


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Task I evaluation of the grid (the evaluate stage).")
    parser.add_argument("--params", type=Path, default=PROJECT_ROOT / "params.yaml")
    args = parser.parse_args(argv)
    evaluate(str(args.params))


if __name__ == "__main__":
    main()
