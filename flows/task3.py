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

from prefect import flow, task
from prefect.cache_policies import NO_CACHE
from tqdm.auto import tqdm

from components import plots
from components.core.files import atomic_write_bytes
from components.domains.sweep import NoiseSweep, experiments_by_eta
from components.domains.task3 import build_sweep, task3_metrics
from components.evaluate.diagnostics import roc_curve
from flows.stage import open_stage, parse_stage_args


@task(name="task3-noise-level", cache_policy=NO_CACHE)  # the sweep holds onnxruntime sessions
def run_level(sweep: NoiseSweep, eta: float, repetitions: int, seed: int, fresh: bool = False) -> list:
    return [sweep.run(eta, r, seed, fresh) for r in range(repetitions)]


@flow(name="task3", log_prints=True)
def task3(params_path: str = "params.yaml") -> dict:
    """Run the Task III sweep; write reports/task3/."""
    stage = open_stage(params_path)
    params, logger, t = stage.params, stage.logger, stage.params.task3
    out = stage.paths.reports("task3")
    sweep, members, model_name = build_sweep(params, stage.paths)
    logger.info("task3 with %s: bags %s", model_name, {n: int(i.size) for n, i in members.items()})

    t0 = time.perf_counter()
    experiments = []
    for eta in tqdm(t.etas, desc="task3: noise levels η (the paper's targets)", unit="level"):
        experiments += run_level(sweep, eta, t.repetitions, params.seed)
    seconds = time.perf_counter() - t0
    fresh = t.fresh_targets
    detector, _ = sweep.calibrate(t.calibration_targets, t.false_alarm_rate, params.seed, fresh=fresh)
    fresh_experiments = []
    if fresh:
        for eta in tqdm(t.etas, desc="task3: noise levels η (fresh targets)", unit="level"):
            fresh_experiments += run_level(sweep, eta, t.repetitions, params.seed, fresh=True)
    decided = fresh_experiments if fresh else experiments
    metrics = task3_metrics(params, model_name, members, experiments, fresh_experiments, detector, seconds)
    per_eta = metrics["eta"]
    atomic_write_bytes(out / "metrics.json", json.dumps(metrics, indent=1).encode())
    rows = [e.to_dict() | {"targets": "paper"} for e in experiments] + [
        e.to_dict() | {"targets": "fresh"} for e in fresh_experiments
    ]
    atomic_write_bytes(out / "experiments.json", json.dumps(rows).encode())

    plot_dir = out / "plots"
    d_e = experiments_by_eta(experiments, "d_e")
    plots.save_figure(
        plots.boxplots_by_level(d_e, ylabel="d_E = ‖λ̂ − λ‖₂", title=f"Task III ({model_name}): weights"),
        plot_dir / "d_e.png",
    )
    gap, base = experiments_by_eta(experiments, "gap"), experiments_by_eta(experiments, "baseline_gap")
    fig = plots.boxplots_by_level(
        gap, baseline=base, ylabel="mean squared gap δ", title=f"Task III ({model_name}): gap"
    )
    fig.axes[0].set_yscale("log")
    plots.save_figure(fig, plot_dir / "gap.png")
    which = "fresh targets" if fresh else "the paper's targets"
    rel = experiments_by_eta(decided, "relative_gap")
    fig = plots.boxplots_by_level(
        rel,
        baseline=experiments_by_eta(decided, "baseline_relative_gap"),
        ylabel="relative gap δ / mean b²",
        title=f"Task III ({model_name}, {which}): relative gap and the ODD threshold",
    )
    fig.axes[0].set_yscale("log")
    fig.axes[0].axhline(detector.threshold, color="tab:red", linestyle="--", linewidth=1)
    plots.save_figure(fig, plot_dir / "relative-gap.png")
    plots.save_figure(
        plots.roc_curves(
            {eta: roc_curve(rel[0.0], scores) for eta, scores in rel.items() if eta > 0},
            score_name="δ / mean b²",
            title=f"Out-of-ODD detection ({which})",
        ),
        plot_dir / "roc.png",
    )
    if fresh:
        plots.save_figure(
            plots.boxplots_by_level(
                experiments_by_eta(fresh_experiments, "d_e"),
                ylabel="d_E = ‖λ̂ − λ‖₂",
                title=f"Task III ({model_name}, fresh targets): weights",
            ),
            plot_dir / "d_e-fresh.png",
        )
    logger.info(
        "task3: %d paper experiments in %.1f s; d_E median at η=0: %.3g; AUC (%s) at η=0.1: %s; "
        "threshold %.3g (α = %.2f, observed %.2f)",
        len(experiments),
        seconds,
        per_eta["0"]["d_e_median"],
        which,
        per_eta.get("0.1", {}).get("auc"),
        detector.threshold,
        t.false_alarm_rate,
        per_eta["0"]["flagged_rate"],
    )
    return metrics


def main(argv: list[str] | None = None) -> None:
    args, _ = parse_stage_args("Task III: relative characterization and the out-of-ODD decision over η.", argv)
    task3(str(args.params))


if __name__ == "__main__":
    main()
