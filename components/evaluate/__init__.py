"""evaluate — the ``evaluate`` stage (Task I): how good is a posterior on labelled test images.

- :mod:`~components.evaluate.diagnostics`: HPD credibility, expected coverage, calibration error and the band of a
  perfectly calibrated model, superiority π, energy distance, HDR mass, ROC curves.
- :mod:`~components.evaluate.ppc`: the quantitative posterior predictive check.
- :mod:`~components.evaluate.task1`: per-model draws, metrics and PPCs of the stage.
- :mod:`~components.evaluate.marginals`: per-parameter interval widths and coverage, median errors and marginal
  information gain (reflected KDE), for all, day and night truths.
- :mod:`~components.evaluate.report`: one flat metrics row per model and the results table (markdown).
- :mod:`~components.evaluate.champion`: the rule that names the champion and the runner-up.
- :mod:`~components.evaluate.evaluation`: one exported model's evaluation (draws, metrics, PPC, plots).
- :mod:`~components.evaluate.publish`: the cross-model reports, ``table.md`` and ``champion.json``.
- :mod:`~components.evaluate.summary`: per-parameter medians and highest-density intervals of draws (the CLI).

Used by the ``evaluate`` stage; ``diagnostics`` also by the ``train``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI (through the plots and the sweep), ``summary`` by the CLI only.
"""

__all__ = ["diagnostics", "ppc", "task1", "marginals", "report", "champion", "evaluation", "publish", "summary"]
