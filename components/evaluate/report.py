"""Task I reports: one flat row of headline metrics per model, and the results table (markdown; shown on docs/results.md).

* :func:`model_row`: what ``reports/task1/models/<model>.json`` holds — :data:`HEADLINE` (the whole-posterior
  metrics of :func:`components.evaluate.task1.task1_metrics` and the stage's counts) and the per-parameter median
  errors of day and night truths (``err_day_cloud`` …, in the parameter's unit; :mod:`components.evaluate.marginals`).
  Every model's file has the same keys, so ``dvc metrics show`` gives one row per model.
* :func:`results_table`: the markdown table of those rows, champion in bold.

Used by the ``evaluate`` stage.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from components.core.weather import PREDICTED, SHORT_NAMES
from components.evaluate.marginals import coverage_interval, flat_errors

__all__ = ["HEADLINE", "model_row", "results_table"]

#: The headline metrics of a model, in the order of its row.
HEADLINE: tuple[str, ...] = (
    "calibration_error",
    "calibration_band",
    "within_band",
    "test_nll",
    "test_nll_se",
    "info_gain_nats",
    "pi_median",
    "coverage_auc_gap",
    "ppc_score",
    "images",
    "samples",
)


def model_row(metrics: Mapping[str, object], parameters: Mapping[str, Mapping[str, Mapping[str, float]]]) -> dict:
    """The flat row of one model: its :data:`HEADLINE` ``metrics``, ``err_<day|night>_<short name>`` from its
    per-parameter report (``subset → parameter → figures``), then the night images' count (``night_images``) and each
    parameter's central-68 % coverage on them (``cov68_night_<short name>``: where the image cannot tell, honest
    intervals cover ~68 %). ``KeyError`` naming a missing headline metric."""
    missing = [k for k in HEADLINE if k not in metrics]
    if missing:
        raise KeyError(f"the Task I metrics lack {', '.join(missing)}")
    errors = flat_errors(parameters, dict(zip(PREDICTED, SHORT_NAMES, strict=True)))
    expected = [f"err_{s}_{short}" for s in ("day", "night") for short in SHORT_NAMES]
    night = parameters.get("night", {})
    coverage = {
        f"cov68_night_{short}": night.get(name, {}).get("coverage68", math.nan)
        for name, short in zip(PREDICTED, SHORT_NAMES, strict=True)
    }
    night_images = night.get(PREDICTED[0], {}).get("images", 0)
    return (
        {k: metrics[k] for k in HEADLINE}
        | {k: errors.get(k, math.nan) for k in expected}
        | {"night_images": night_images}
        | coverage
    )


def _info_gain(row: Mapping[str, object]) -> str:
    """The cell ``<information gain> ± <its standard error over the test images>``."""
    gain, se = _cell(row.get("info_gain_nats"), 2), _cell(row.get("test_nll_se"), 2)
    return gain if se == "—" else f"{gain} ± {se}"


def _lowest_night_coverage(row: Mapping[str, object]) -> str:
    """The cell ``<short name> <coverage %> [<95 % interval>]`` of the parameter whose night coverage is lowest
    (Clopper–Pearson from the count of night images), or ``—``."""
    n = row.get("night_images")
    found = [(float(row[k]), k.removeprefix("cov68_night_")) for k in row if k.startswith("cov68_night_")]
    found = [(c, short) for c, short in found if math.isfinite(c)]
    if not found or not isinstance(n, (int, float)) or n < 1:
        return "—"
    cov, short = min(found)
    low, high = coverage_interval(round(cov * n), int(n))
    return f"{short} {100 * cov:.1f} [{100 * low:.1f}, {100 * high:.1f}]"


def _cell(value: object, digits: int) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float)) and math.isfinite(float(value)):
        return f"{float(value):.{digits}f}".replace("-", "−")
    return "—"


def results_table(
    rows: Mapping[str, Mapping[str, object]], champion: str | None = None, band_level: float = 0.95
) -> str:
    """A markdown table, one line per model of ``rows`` (model id → :func:`model_row`): calibration error and its band
    (at ``band_level``), within band, test NLL, information gain with its standard error, π median, coverage gap, the
    day / night median errors of sun altitude (°), fog and precipitation (%), and the lowest night coverage of a
    central 68 % interval with its parameter and exact binomial interval; the ``champion``'s line in bold. Ends with a
    newline."""
    columns = [
        ("calibration error", "calibration_error", 3),
        (f"band ({100 * band_level:g} %)", "calibration_band", 3),
        ("within band", "within_band", 0),
        ("test NLL (nats)", "test_nll", 2),
        ("info gain (nats) ± s.e.", _info_gain, 2),
        ("π median", "pi_median", 2),
        ("coverage gap", "coverage_auc_gap", 3),
        ("sun err day / night (°)", ("err_day_sun", "err_night_sun"), 1),
        ("fog err day / night (%)", ("err_day_fog", "err_night_fog"), 1),
        ("rain err day / night (%)", ("err_day_rain", "err_night_rain"), 1),
        ("night 68 % coverage, lowest (%) [95 % interval]", _lowest_night_coverage, 1),
    ]
    lines = ["| model | " + " | ".join(c[0] for c in columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for model, row in rows.items():
        cells = []
        for _, key, digits in columns:
            if callable(key):
                cells.append(key(row))
            elif isinstance(key, tuple):
                cells.append(" / ".join(_cell(row.get(k), digits) for k in key))
            else:
                cells.append(_cell(row.get(key), digits))
        name = f"**{model}** (champion)" if model == champion else model
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
