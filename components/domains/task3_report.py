"""The ``task3`` stage's plots, run description and AUC summaries, from the sweep's experiments and metrics
(:func:`components.domains.task3.task3_metrics`).

* :func:`write_plots`: per target kind, box plots of d_E, δ and the relative gap (with the chance baseline and, for
  the kind the ODD decision was calibrated on, its threshold) and the ROC curves.
* :func:`auc_text`, :func:`auc_summary`: the AUCs of a kind of targets with their 95 % intervals, in words.
* :func:`description`: the run's headline figures, in words.

No MLflow here: the stage logs what these return (``flows/tracking.py``).
"""

from __future__ import annotations

from pathlib import Path

from components import plots
from components.domains.relative import OddDetector
from components.domains.sweep import Experiment, experiments_by_eta
from components.evaluate.diagnostics import roc_curve

__all__ = ["TITLES", "write_plots", "auc_text", "auc_summary", "description"]

#: the target kinds, in words
TITLES = {"paper": "the paper's targets", "fresh": "fresh targets"}


def write_plots(
    plot_dir: Path, kind: str, experiments: list[Experiment], detector: OddDetector | None, model: str, per_eta: dict
) -> list[Path]:
    """Write the plots of one target kind into ``plot_dir``.

    Arguments:
        plot_dir: the folder ``reports/task3/plots/``.
        kind: ``paper`` or ``fresh``.
        experiments: the sweep's experiments of that kind.
        detector: the calibrated ODD decision when it was calibrated on this kind (its threshold on the relative gap,
            its operating points on the ROC curves); else None.
        model: the model's id (the titles).
        per_eta: ``metrics["eta"]``: the AUCs' 95 % intervals and the shares flagged, per η.

    Returns:
        The files written: ``d_e-<kind>.png``, ``gap-<kind>.png``, ``relative-gap-<kind>.png``, ``roc-<kind>.png``.
    """
    which = TITLES[kind]
    d_e = experiments_by_eta(experiments, "d_e")
    files = [
        plots.save_figure(
            plots.boxplots_by_level(d_e, ylabel="d_E = ‖λ̂ − λ‖₂", title=f"Task III ({model}, {which}): weights"),
            plot_dir / f"d_e-{kind}.png",
        )
    ]
    gap, base = experiments_by_eta(experiments, "gap"), experiments_by_eta(experiments, "baseline_gap")
    fig = plots.boxplots_by_level(
        gap, baseline=base, ylabel="mean squared gap δ", title=f"Task III ({model}, {which}): gap"
    )
    fig.axes[0].set_yscale("log")
    files.append(plots.save_figure(fig, plot_dir / f"gap-{kind}.png"))
    rel = experiments_by_eta(experiments, "relative_gap")
    fig = plots.boxplots_by_level(
        rel,
        baseline=experiments_by_eta(experiments, "baseline_relative_gap"),
        ylabel="relative gap δ / mean b²",
        title=f"Task III ({model}, {which}): relative gap" + (" and the ODD threshold" if detector is not None else ""),
    )
    fig.axes[0].set_yscale("log")
    if detector is not None:
        fig.axes[0].axhline(detector.threshold, color="tab:red", linestyle="--", linewidth=1)
    files.append(plots.save_figure(fig, plot_dir / f"relative-gap-{kind}.png"))
    files.append(_roc_plot(plot_dir, kind, rel, detector, per_eta))
    return files


def _roc_plot(
    plot_dir: Path, kind: str, rel: dict[float, list[float]], detector: OddDetector | None, per_eta: dict
) -> Path:
    """The ROC curves of the relative gap at each η > 0 against η = 0, with their AUCs' intervals and, with
    ``detector``, the point where its threshold puts each curve; written to ``roc-<kind>.png``.

    Arguments:
        plot_dir: the folder ``reports/task3/plots/``.
        kind: ``paper`` or ``fresh``.
        rel: η → the relative gaps of that kind's targets.
        detector: the calibrated ODD decision, or None.
        per_eta: ``metrics["eta"]``.

    Returns:
        The file written.
    """
    curves = {eta: roc_curve(rel[0.0], scores) for eta, scores in rel.items() if eta > 0}
    points = None
    if detector is not None:  # the alarm as deployed: the shares of the η = 0 and of the η targets it flags
        flagged = {float(k): row[f"flagged_rate_{kind}"] for k, row in per_eta.items()}
        points = {eta: (flagged[0.0], flagged[eta]) for eta in curves}
    return plots.save_figure(
        plots.roc_curves(
            curves,
            score_name="δ / mean b²",
            title=f"Out-of-ODD detection ({TITLES[kind]})",
            intervals={
                eta: (per_eta[f"{eta:g}"][f"auc_ci_low_{kind}"], per_eta[f"{eta:g}"][f"auc_ci_high_{kind}"])
                for eta in curves
            },
            operating_points=points,
            alpha=None if detector is None else detector.false_alarm_rate,
        ),
        plot_dir / f"roc-{kind}.png",
    )


def auc_text(row: dict, kind: str) -> str:
    """A per-η row's AUC of ``kind`` targets with its 95 % interval.

    Arguments:
        row: a row of ``metrics["eta"]``.
        kind: ``paper`` or ``fresh``.

    Returns:
        E.g. ``"0.82 [0.69, 0.90]"``; ``"n/a"`` without an AUC.
    """
    if row.get(f"auc_{kind}") is None:
        return "n/a"
    return f"{row[f'auc_{kind}']:.2f} [{row[f'auc_ci_low_{kind}']:.2f}, {row[f'auc_ci_high_{kind}']:.2f}]"


def auc_summary(eta: dict, kind: str, from_eta: float = 0.3) -> str:
    """The AUCs of ``kind`` targets below η = ``from_eta`` one by one, then the lowest from it on (the target:
    ≥ 0.95 at every η ≥ 0.3).

    Arguments:
        eta: ``metrics["eta"]``: η (text) → its row.
        kind: ``paper`` or ``fresh``.
        from_eta: the η from which on only the lowest AUC is named.

    Returns:
        E.g. ``"η=0.1 0.80 [0.70, 0.87], η=0.2 0.99 [0.94, 1.00], lowest at η ≥ 0.3 1.00 [0.96, 1.00] (η=0.3)"``;
        ``"n/a"`` without any AUC.
    """
    rows = {float(k): v for k, v in eta.items() if v.get(f"auc_{kind}") is not None}
    parts = [f"η={k:g} {auc_text(v, kind)}" for k, v in sorted(rows.items()) if k < from_eta]
    later = {k: v for k, v in rows.items() if k >= from_eta}
    if later:
        k = min(later, key=lambda e: (later[e][f"auc_{kind}"], e))
        parts.append(f"lowest at η ≥ {from_eta:g} {auc_text(later[k], kind)} (η={k:g})")
    return ", ".join(parts) or "n/a"


def description(metrics: dict, kind: str) -> str:
    """The Task III run's description: its headline figures.

    Arguments:
        metrics: :func:`components.domains.task3.task3_metrics`.
        kind: the target kind the ODD decision was calibrated on.

    Returns:
        One paragraph of markdown.
    """
    odd, eta = metrics["odd"]["false_alarms_new_seeds"], metrics["eta"]
    aucs = ", ".join(f"η={k}: {auc_text(v, kind)}" for k, v in eta.items() if v.get(f"auc_{kind}") is not None)
    return (
        f"Task III with {metrics['model']}: out-of-ODD detection AUC ({kind} targets; 95 % intervals) {aucs}. "
        f"Median d_E at η=0: "
        f"{eta['0'][f'd_e_median_{kind}']:.3f} ({kind}), {eta['0']['d_e_median_paper']:.3f} (paper). False alarms on new "
        f"in-ODD targets: {odd['flagged']} of {odd['n']} ({odd['rate']:.3f}, 95 % interval [{odd['ci_low']:.3f}, "
        f"{odd['ci_high']:.3f}]; a calibrated decision flags {odd['calibrated_low']}–{odd['calibrated_high']})."
    )
