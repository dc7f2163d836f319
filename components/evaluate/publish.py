"""The ``evaluate`` stage's files of the whole grid: the reports of ``reports/task1/`` and the champion's pointer.

* :func:`write_grid_reports`: from every model's Task I result
  (:func:`components.evaluate.evaluation.evaluate_exported`), the cross-model plots (coverage, superiority, parameter heat maps) and the JSON reports
  (``metrics.json``, ``parameters.json``, ``profiles.json``, ``models/<model>.json``, ``coverage.json``).
* :func:`write_table`: the results table ``table.md`` (:func:`components.evaluate.report.results_table`).
* :func:`registered_pointer` and :func:`with_versions`: the pointer ``reports/task1/champion.json``
  (:func:`components.evaluate.champion.champion_pointer`) with the registered model's name, then with the versions
  its MLflow aliases name.

No MLflow here: the stage passes what MLflow returned (``flows/tracking.py``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from components import plots
from components.core.config import Params
from components.core.files import atomic_write_bytes
from components.evaluate import report, task1

__all__ = ["GridReports", "write_json", "write_grid_reports", "write_table", "registered_pointer", "with_versions"]


@dataclass(frozen=True)
class GridReports:
    """What :func:`write_grid_reports` wrote and the stage reads on: ``metrics`` (model → headline metrics),
    ``rows`` (model → flat row, :func:`components.evaluate.report.model_row`) and ``files`` (the cross-model plots
    the grid's MLflow run gets)."""

    metrics: dict[str, dict]
    rows: dict[str, dict]
    files: list[Path]


def write_json(path: Path, value: object) -> None:
    """Write ``value`` as indented JSON (one space) to ``path``, atomically."""
    atomic_write_bytes(path, json.dumps(value, indent=1).encode())


def write_grid_reports(out: Path, results: Sequence[Mapping], params: Params, n: int, band: float) -> GridReports:
    """Write the cross-model reports of ``reports/task1/`` (``out``) from the models' results, in grid order.

    Arguments:
        out: the folder ``reports/task1/``.
        results: one result per model of the grid (``model``, ``metrics``, ``coverage``, ``pi``, ``parameters``,
            ``profiles``, ``local``), in the order of its rows.
        params: the project's settings (``evaluate.band_level``, the prior box).
        n: the number of test images each model was evaluated on.
        band: the calibration band of a perfectly calibrated model on ``n`` images.

    Returns:
        The metrics, rows and plot files written (:class:`GridReports`); a ``models/<model>.json`` of a model no
        longer in ``results`` is removed.
    """
    curves = {r["model"]: (task1.LEVELS, np.array(r["coverage"])) for r in results}
    plots.save_figure(
        plots.coverage_plot(
            curves,
            title=f"Task I: expected coverage on {n} test images",
            band=band,
            band_label=f"{100 * params.evaluate.band_level:g} % band of a calibrated\nmodel on {n} images",
        ),
        out / "plots" / "coverage.png",
    )
    plots.save_figure(
        plots.superiority_boxplot({r["model"]: np.array(r["pi"]) for r in results}), out / "plots" / "superiority.png"
    )
    metrics = {r["model"]: r["metrics"] for r in results}
    parameters = {r["model"]: r["parameters"] for r in results}
    write_json(out / "metrics.json", metrics)
    write_json(out / "parameters.json", parameters)
    write_json(out / "profiles.json", {r["model"]: r["profiles"] for r in results})
    write_json(out / "local.json", {r["model"]: r["local"] for r in results})
    rows = {m: report.model_row(metrics[m], parameters[m]) for m in metrics}
    for m, row in rows.items():
        write_json(out / "models" / f"{m}.json", row)
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
    files = [out / "plots" / f for f in ("coverage.png", "superiority.png", "parameters.png")]
    return GridReports(metrics, rows, files)


def write_table(out: Path, rows: Mapping[str, Mapping], champion: str | None, band_level: float) -> str:
    """Write the results table ``table.md`` into ``out`` and return it.

    Arguments:
        out: the folder ``reports/task1/``.
        rows: model → flat row (:func:`components.evaluate.report.model_row`).
        champion: the champion's id (its line in bold), None when no model qualifies.
        band_level: the level of the calibration band (its column's header).

    Returns:
        The markdown table (:func:`components.evaluate.report.results_table`).
    """
    table = report.results_table(rows, champion, band_level)
    atomic_write_bytes(out / "table.md", table.encode())
    return table


def registered_pointer(pointer: Mapping[str, object], registered_model: str) -> dict:
    """The champion's pointer with the name of the registered model its versions belong to, on the champion and on
    the runner-up (when there is one).

    Arguments:
        pointer: :func:`components.evaluate.champion.champion_pointer`.
        registered_model: the registered model's name (``export.registered_model``).

    Returns:
        A new pointer, keys in the order of ``pointer`` then ``registered_model``.
    """
    named = dict(pointer) | {"registered_model": registered_model}
    if named["runner_up"]:
        named["runner_up"] = dict(named["runner_up"]) | {"registered_model": registered_model}
    return named


def with_versions(
    pointer: Mapping[str, object], aliases: Mapping[str, Mapping[str, str]], champion_alias: str, challenger_alias: str
) -> dict:
    """The pointer with the registered versions the MLflow aliases now name (``version``, ``uri``), on the champion
    and on the runner-up.

    Arguments:
        pointer: :func:`registered_pointer`.
        aliases: alias → ``{"version", "uri"}`` as the Model Registry gave them (an alias not set is absent).
        champion_alias: the champion's alias (``champion``).
        challenger_alias: the runner-up's alias (``challenger``).

    Returns:
        A new pointer.
    """
    versioned = dict(pointer) | dict(aliases.get(champion_alias, {}))
    if versioned["runner_up"]:
        versioned["runner_up"] = dict(versioned["runner_up"]) | dict(aliases.get(challenger_alias, {}))
    return versioned
