"""The ``task3`` stage: relative characterization and the out-of-ODD decision swept over the noise level η (Task III).

``python -m flows.task3 [--params params.yaml]``. Bags b0 (out of the ODD) and the sources b1, b2, … of test images
whose weather lies in the sub-boxes of ``task3.bags``; for each η in ``task3.etas``, ``task3.repetitions`` targets
(1 − η)·Σₖ λₖ bₖ + η·b0 related to the sources with n_W = ``task3.n_points`` (:mod:`components.domains.sweep`); the
out-of-ODD decision on the relative gap calibrated on ``task3.calibration_targets`` in-ODD targets for the
false-alarm rate ``task3.false_alarm_rate``. With ``task3.fresh_targets`` (beyond the paper) a second sweep uses
fresh targets — their in-ODD part other test images of the sources' sub-boxes — on which the ODD decision is
calibrated and its ROC curves drawn (the paper's targets reuse the sources' images, so at η = 0 the gap is exactly
zero and detection is trivial). Writes ``reports/task3/metrics.json`` (per η: d_e_median, gap_median,
baseline_gap_median, auc (η > 0), …), ``experiments.json`` and plots (box plots of d_E and δ with the chance
baseline, ROC curves). Also a Prefect deployment on a schedule (prefect.yaml).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE
from tqdm.auto import tqdm

from components.simulate import dataset
from components.features import cache as features
from components import plots
from components.core.config import Params, load_params
from components.core.files import atomic_write_bytes
from components.export.lookup import load_registered
from components.domains.scenarios import in_sub_box
from components.domains.sweep import NoiseSweep, experiments_by_eta, summarize
from flows.export import registry_root
from flows.features import features_root
from flows.generate import data_root
from flows.runtime import params_from_argv


def bag_members(params: Params, theta: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Indices of the test images of each bag (the first ``max_images`` inside its sub-box), and of each source's
    fresh pool (the other test images inside its sub-box)."""
    members, pools = {}, {}
    for name, bag in params.task3.bags.items():
        inside = np.flatnonzero(in_sub_box(theta, bag.box))
        if inside.size == 0:
            raise ValueError(f"task3.bags.{name}: no test image lies in its sub-box {dict(bag.box)}; widen the box or "
                             "grow data.splits.test")
        members[name], pools[name] = inside[: bag.max_images], inside[bag.max_images :]
        if name != "b0" and params.task3.fresh_targets and pools[name].size < members[name].size:
            raise ValueError(f"task3.bags.{name}: {inside.size} test images in its sub-box, too few for a fresh bag of "
                             f"{members[name].size} beside the source bag; lower max_images, grow data.splits.test, "
                             "or set task3.fresh_targets: false")
    return members, pools


def build_sweep(params_file: Path) -> tuple[NoiseSweep, dict[str, np.ndarray], str]:
    """The sweep of ``params_file``'s project: the registry model's contexts of the bags' test images."""
    params = load_params(params_file)
    t = params.task3
    model = load_registered(t.model, registry_root(params_file))  # one thread: many small calls
    test = dataset.open_split(data_root(params, params_file), "test")
    members, pools = bag_members(params, test.theta)
    cached = features.open_features(features_root(params_file), model.backbone.name, test)

    def contexts(idx: np.ndarray) -> np.ndarray:
        return model.posterior.context(features.inputs_from_cached(model.backbone, cached[idx]))

    fresh = [contexts(pools[s]) for s in t.sources] if t.fresh_targets else None
    sweep = NoiseSweep(model.posterior.on_context(), contexts(members["b0"]), [contexts(members[s]) for s in t.sources],
                       t.weights, t.n_points, fresh_pools=fresh)
    return sweep, members, model.name


@task(name="task3-noise-level", cache_policy=NO_CACHE)  # the sweep holds onnxruntime sessions
def run_level(sweep: NoiseSweep, eta: float, repetitions: int, seed: int, fresh: bool = False) -> list:
    return [sweep.run(eta, r, seed, fresh) for r in range(repetitions)]


@flow(name="task3", log_prints=True)
def task3(params_path: str = "params.yaml") -> dict:
    """Run the Task III sweep; write reports/task3/."""
    logger = get_run_logger()
    params_file = Path(params_path)
    params = load_params(params_file)
    t = params.task3
    out = params_file.resolve().parent / "reports" / "task3"
    sweep, members, model_name = build_sweep(params_file)
    logger.info("task3 with %s: bags %s", model_name, {n: int(i.size) for n, i in members.items()})

    t0 = time.perf_counter()
    experiments = []
    for eta in tqdm(t.etas, desc="task3: noise levels η (the paper's targets)", unit="level"):
        experiments += run_level(sweep, eta, t.repetitions, params.seed)
    seconds = time.perf_counter() - t0
    fresh = t.fresh_targets
    detector, calibration = sweep.calibrate(t.calibration_targets, t.false_alarm_rate, params.seed, fresh=fresh)
    fresh_experiments = []
    if fresh:
        for eta in tqdm(t.etas, desc="task3: noise levels η (fresh targets)", unit="level"):
            fresh_experiments += run_level(sweep, eta, t.repetitions, params.seed, fresh=True)
    decided = fresh_experiments if fresh else experiments

    paper, judged = summarize(experiments, detector), summarize(decided, detector)
    per_eta = {}
    for key, row in paper.items():
        per_eta[key] = {**{k: row[k] for k in ("d_e_median", "gap_median", "baseline_gap_median",
                                               "relative_gap_median", "baseline_relative_gap_median")},
                        **({"auc": judged[key]["auc"], "auc_same_images": row["auc"]} if "auc" in row else {}),
                        "flagged_rate": judged[key]["flagged_rate"]}
        if fresh:
            per_eta[key]["fresh"] = {k: judged[key][k] for k in ("d_e_median", "gap_median", "relative_gap_median")}
    metrics = {
        "model": model_name,
        "bags": {n: int(i.size) for n, i in members.items()},
        "n_points": t.n_points,
        "odd": {"statistic": "relative_gap", "targets": "fresh" if fresh else "paper",
                "threshold": detector.threshold, "false_alarm_rate": t.false_alarm_rate,
                "calibration_targets": detector.n_calibration,
                "observed_false_alarm_rate": per_eta["0"]["flagged_rate"]},
        "experiments": len(experiments) + len(fresh_experiments),
        "sweep_seconds": seconds,
        "eta": per_eta,
    }
    atomic_write_bytes(out / "metrics.json", json.dumps(metrics, indent=1).encode())
    rows = [e.to_dict() | {"targets": "paper"} for e in experiments] + [e.to_dict() | {"targets": "fresh"}
                                                                        for e in fresh_experiments]
    atomic_write_bytes(out / "experiments.json", json.dumps(rows).encode())

    plot_dir = out / "plots"
    d_e = experiments_by_eta(experiments, "d_e")
    plots.save_figure(plots.boxplots_by_level(d_e, ylabel="d_E = ‖λ̂ − λ‖₂", title=f"Task III ({model_name}): weights"),
                      plot_dir / "d_e.png")
    gap, base = experiments_by_eta(experiments, "gap"), experiments_by_eta(experiments, "baseline_gap")
    fig = plots.boxplots_by_level(gap, baseline=base, ylabel="mean squared gap δ", title=f"Task III ({model_name}): gap")
    fig.axes[0].set_yscale("log")
    plots.save_figure(fig, plot_dir / "gap.png")
    which = "fresh targets" if fresh else "the paper's targets"
    rel = experiments_by_eta(decided, "relative_gap")
    fig = plots.boxplots_by_level(rel, baseline=experiments_by_eta(decided, "baseline_relative_gap"),
                                  ylabel="relative gap δ / mean b²",
                                  title=f"Task III ({model_name}, {which}): relative gap and the ODD threshold")
    fig.axes[0].set_yscale("log")
    fig.axes[0].axhline(detector.threshold, color="tab:red", linestyle="--", linewidth=1)
    plots.save_figure(fig, plot_dir / "relative-gap.png")
    plots.save_figure(plots.roc_curves(rel[0.0], {k: v for k, v in rel.items() if k > 0}, score_name="δ / mean b²",
                                       title=f"Out-of-ODD detection ({which})"), plot_dir / "roc.png")
    if fresh:
        plots.save_figure(plots.boxplots_by_level(experiments_by_eta(fresh_experiments, "d_e"),
                                                  ylabel="d_E = ‖λ̂ − λ‖₂",
                                                  title=f"Task III ({model_name}, fresh targets): weights"),
                          plot_dir / "d_e-fresh.png")
    logger.info("task3: %d paper experiments in %.1f s; d_E median at η=0: %.3g; AUC (%s) at η=0.1: %s; "
                "threshold %.3g (α = %.2f, observed %.2f)", len(experiments), seconds, per_eta["0"]["d_e_median"],
                which, per_eta.get("0.1", {}).get("auc"), detector.threshold, t.false_alarm_rate,
                per_eta["0"]["flagged_rate"])
    return metrics


def main(argv: list[str] | None = None) -> None:
    _, path = params_from_argv("Task III: relative characterization and the out-of-ODD decision over η.", argv)
    task3(str(path))


if __name__ == "__main__":
    main()
