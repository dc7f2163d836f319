"""The results of the latest run, from ``reports/``, written into the README and the docs' results page.

    python scripts/results_table.py            # rewrite the blocks of README.md and docs/results.md
    python scripts/results_table.py --check    # exit 1 when a block differs from what reports/ says
    python scripts/results_table.py --print    # print the README's block only; write nothing

It reads what the pipeline's stages write (``bash run.sh`` or ``dvc repro`` first):

* ``reports/task1/metrics.json`` (the ``evaluate`` stage: model id → headline metrics of
  :func:`components.evaluate.task1.task1_metrics`, plus ``images`` and ``samples``), in the grid's order;
* ``reports/task1/champion.json`` (the champion's pointer, :func:`components.evaluate.champion.champion_pointer`);
* ``reports/task1/table.md`` (the evaluate stage's full results table, :func:`components.evaluate.report.results_table`);
* ``reports/task2/metrics.json`` (the ``task2`` stage: :func:`components.domains.task2.task2_metrics` and its
  ``estimate``);
* ``reports/task3/metrics.json`` (the ``task3`` stage: :func:`components.domains.task3.task3_metrics`);
* ``reports/task1/parameters.json`` and ``reports/task1/profiles.json`` (the evaluate stage: model → subset →
  parameter → figures, :func:`components.evaluate.marginals.summarize_subsets`, and the same by bin of the true value,
  :func:`components.evaluate.profile.truth_profile`);
* ``reports/task1/local.json`` (the evaluate stage: model → the named weathers and the local test,
  :mod:`components.evaluate.named`).

Each target file holds blocks between markers, ``<!-- NAME:begin -->`` and ``<!-- NAME:end -->``; the script
replaces what lies between them and leaves the rest of the file alone:

* ``results``: one table, a line per model of the grid (backbone, training images, information gain, calibration
  error against its band, test NLL, the champion and runner-up marked), then one line for Task II and one for
  Task III's out-of-ODD decision;
* ``task1-table``: ``reports/task1/table.md`` as the stage wrote it (every headline column);
* ``task1-champion``: the champion, the runner-up and the grid in words, the champion's targets
  (:data:`CHAMPION_TARGETS`) and the grid's (:data:`GRID_CALIBRATION_CEILING`) computed met or not;
* ``champion-parameters``: the champion's daytime median errors against :data:`DAY_TARGETS`, its night coverage
  against :data:`NIGHT_COVERAGE`, and its sun error by bin of the true altitude;
* ``task2``: Task II's figures, with the width floor's comparison and its bootstrap intervals;
* ``named``: the champion at the named weathers (``reports/task1/local.json``): pooled coverage beside the exact
  toy's, the cells outside a correct model's range, the local test, the sun at ClearNoon; a line per model;
* ``task3``: Task III's AUCs by η and kind, the first η meeting :data:`AUC_TARGET` at 95 % confidence, and the
  out-of-ODD decision's false alarms against the range a calibrated decision gives;
* ``targets``: every target the reports can judge (:func:`targets`), met or missed, with its figure.

The targets are the project's; whether a figure meets its target is computed here, never typed.

A file that names no block is an error (the markers were lost in an edit), and so is a missing report.
Standard library only: it runs without the project's virtual environment.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Callable, Mapping
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: the files the script keeps in step, relative to the project root
TARGETS: tuple[str, ...] = ("README.md", "docs/results.md")
#: the reports read, relative to the reports folder
REPORTS: dict[str, str] = {
    "task1": "task1/metrics.json",
    "champion": "task1/champion.json",
    "table": "task1/table.md",
    "task2": "task2/metrics.json",
    "task3": "task3/metrics.json",
    "parameters": "task1/parameters.json",
    "profiles": "task1/profiles.json",
    "local": "task1/local.json",
}
#: a model id of the grid, ``<backbone>-<size>``, or of its variants, ``<backbone>-<size>-<name>``
MODEL_ID = re.compile(r"^(?P<backbone>.+?)-(?P<size>\d+)(?:-(?P<variant>[a-z][a-z0-9_]*))?$")


class ReportsError(RuntimeError):
    """The reports are missing or not what the stages write; the message says which file and what to run."""


def _marker(name: str, end: bool) -> str:
    return f"<!-- {name}:{'end' if end else 'begin'} -->"


def _number(value: object, digits: int) -> str:
    """``value`` with ``digits`` decimals and a true minus sign; ``—`` for a missing or non-finite number."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        return "—"
    return f"{float(value):.{digits}f}".replace("-", "−")


def _thousands(n: int) -> str:
    """``50000`` → ``50 000`` (a thin space would not survive every Markdown renderer; a plain one does)."""
    return f"{n:,}".replace(",", " ")


def read_reports(reports: Path) -> dict[str, object]:
    """The parsed reports of :data:`REPORTS` under ``reports`` (JSON files parsed, ``table.md`` as text).

    Raises:
        ReportsError: the folder or one of the files is missing, or a JSON file does not parse.
    """
    if not reports.is_dir():
        raise ReportsError(f"no reports folder at {reports}: run `bash run.sh` first (it runs the pipeline)")
    out: dict[str, object] = {}
    for key, rel in REPORTS.items():
        path = reports / rel
        if not path.is_file():
            raise ReportsError(f"{path} is missing: run `bash run.sh` first (or `dvc repro` in .venv)")
        text = path.read_text(encoding="utf-8")
        if rel.endswith(".json"):
            try:
                out[key] = json.loads(text)
            except json.JSONDecodeError as err:
                raise ReportsError(f"{path} is not JSON ({err}): re-run its stage (`dvc repro`)") from None
        else:
            out[key] = text
    return out


def _get(report: Mapping, keys: tuple[str, ...], where: str) -> object:
    value: object = report
    for key in keys:
        if not isinstance(value, Mapping) or key not in value:
            raise ReportsError(f"{where} has no {'.'.join(keys)}: re-run its stage (`dvc repro`)")
        value = value[key]
    return value


def _role(model: str, champion: Mapping) -> str:
    if model == champion.get("model"):
        return "**champion**"
    runner_up = champion.get("runner_up")
    if isinstance(runner_up, Mapping) and model == runner_up.get("model"):
        return "runner-up"
    return ""


def task1_table(metrics: Mapping[str, Mapping], champion: Mapping) -> list[str]:
    """The Markdown lines of the models' table: one line per model of ``metrics`` (``reports/task1/metrics.json``,
    in its order), the champion's in bold."""
    where = "reports/task1/metrics.json"
    if not metrics:
        raise ReportsError(f"{where} names no model: re-run the evaluate stage (`dvc repro`)")
    lines = [
        "| model | backbone | training images | information gain (nats) | calibration error (band) | "
        "test NLL (nats) | role |",
        "|---|---|---:|---:|---:|---:|---|",
    ]
    for model, m in metrics.items():
        cell = MODEL_ID.match(model)
        if cell is None:
            raise ReportsError(f"{where}: {model!r} is not a model id <backbone>-<size>[-<variant>]")
        backbone = cell["backbone"] + (f" ({cell['variant']})" if cell["variant"] else "")
        gain = _number(_get(m, ("info_gain_nats",), where), 2)
        se = _number(m.get("test_nll_se"), 2)
        within = _get(m, ("within_band",), where)
        error = (
            f"{_number(_get(m, ('calibration_error',), where), 3)} "
            f"({_number(_get(m, ('calibration_band',), where), 3)}) {'within' if within else 'outside'}"
        )
        name = f"**{model}**" if model == champion.get("model") else model
        lines.append(
            f"| {name} | {backbone} | {_thousands(int(cell['size']))} | {gain if se == '—' else f'{gain} ± {se}'} | "
            f"{error} | {_number(_get(m, ('test_nll',), where), 2)} | {_role(model, champion)} |"
        )
    return lines


def task2_line(task2: Mapping) -> str:
    """Task II in one line: the energy distance's ratio to the prior's, the W₁ ratio of each varying parameter, and
    the share of the true mass inside the estimate's HDR."""
    where = "reports/task2/metrics.json"
    parameters = _get(task2, ("parameters",), where)
    varying = [n for n, p in parameters.items() if isinstance(p, Mapping) and p.get("fixed_value") is None]
    ratios = ", ".join(
        f"{n.replace('_', ' ')} {_number(_get(parameters[n], ('wasserstein_ratio',), where), 2)}" for n in varying
    )
    level = _get(task2, ("hdr_level",), where)
    return (
        f"- **Task II** ({_get(task2, ('model',), where)}, {_get(task2, ('images',), where)} images, "
        f"{_get(task2, ('estimate',), where)} estimate): energy distance to the true weather distribution "
        f"{_number(_get(task2, ('energy_distance_sq', 'all', 'ratio'), where), 2)} × the prior's; "
        f"W₁ to the truth over the prior's: {ratios}; "
        f"{100 * float(_get(task2, ('true_mass_in_hdr',), where)):.1f} % of the true mass inside the estimate's "
        f"{100 * float(level):g} % HDR."
    )


def _auc_from(eta: Mapping[str, Mapping], kind: str) -> str:
    """``AUC a [low, high] at η = …`` for the first η > 0 of the sweep, then the lowest AUC from η = 0.3 on with its
    interval."""
    rows = {float(k): v for k, v in eta.items() if isinstance(v, Mapping) and v.get(f"auc_{kind}") is not None}
    if not rows:
        return "no AUC (no η > 0 in the sweep)"

    def text(e: float) -> str:
        r = rows[e]
        return (
            f"{_number(r[f'auc_{kind}'], 2)} [{_number(r.get(f'auc_ci_low_{kind}'), 2)}, "
            f"{_number(r.get(f'auc_ci_high_{kind}'), 2)}] at η = {e:g}"
        )

    first = min(rows)
    later = [e for e in rows if e >= 0.3 and e != first]
    if not later:
        return f"AUC {text(first)}"
    low = min(later, key=lambda e: rows[e][f"auc_{kind}"])
    return f"AUC {text(first)}, at least {text(low).rsplit(' at ', 1)[0]} from η = 0.3 on"


def task3_line(task3: Mapping) -> str:
    """Task III's out-of-ODD decision in one line: the target kind it was calibrated on, α, the threshold, the false
    alarms on in-ODD targets of new seeds with their interval and a calibrated decision's range, the smallest
    out-of-ODD share detected, and the AUCs on that kind."""
    where = "reports/task3/metrics.json"
    odd = _get(task3, ("odd",), where)
    check = _get(odd, ("false_alarms_new_seeds",), where)
    kind = _get(odd, ("calibrated_on",), where)
    floor = odd.get("detects_from_eta")
    detects = "detects no out-of-ODD share" if floor is None else f"flags most targets from η = {float(floor):g} on"
    return (
        f"- **Task III** ({_get(task3, ('model',), where)}, n_W = {_get(task3, ('n_points',), where)}): the out-of-ODD "
        f"decision, calibrated on {kind} targets for α = {float(_get(odd, ('false_alarm_rate',), where)):g} "
        f"(threshold {_number(_get(odd, ('threshold',), where), 4)} on the relative gap), flags "
        f"{_get(check, ('flagged',), where)} of {_get(check, ('n',), where)} in-ODD targets of new seeds "
        f"({_number(check.get('rate'), 3)} [{_number(check.get('ci_low'), 3)}, {_number(check.get('ci_high'), 3)}]; "
        f"a calibrated decision flags {check.get('calibrated_low')}–{check.get('calibrated_high')}); it {detects}; "
        f"{kind} targets' {_auc_from(_get(task3, ('eta',), where), kind)}."
    )


def named_line(reports: Mapping[str, object]) -> str | None:
    """The champion at the named weathers in one line (``reports/task1/local.json``): the pooled 68 % coverage's range
    over the parameters beside the exact toy's, the cells below or above a correct model's range, the joint local
    test on the named images, the sun at ClearNoon; None when they were not evaluated."""
    model, _, _ = _champion_and_metrics(reports)
    where = "reports/task1/local.json"
    local = _local(reports, model)
    if "skipped" in local:
        return None
    rows = _get(local, ("weathers",), where)
    pooled = _get(local, ("pooled", "all", "parameters"), where).values()
    cov = [float(p["coverage68"]) for p in pooled]
    toy = [float(p["toy68"]) for p in pooled]
    cells = [c for r in rows for c in r["parameters"].values()]
    lc = _get(local, ("lc2st",), where)
    joint = _get(lc, ("named", "joint"), where)
    noon = [r for r in rows if r["weather"] == "ClearNoon"]
    sun = (
        f"; it reads the sun at ClearNoon to {_number(float(noon[0]['parameters']['sun_altitude_angle']['median_abs_error']), 2)}°"
        if noon
        else ""
    )
    return (
        f"- **Named weathers** ({model}, {len(rows)} weathers on {sum(int(r['images']) for r in rows)} images of new "
        f"scenes): its 68.27 % HDIs cover the truth {min(cov):.2f}–"
        f"{max(cov):.2f} of the time per parameter, where a correct posterior of the same widths covers "
        f"{min(toy):.2f}–{max(toy):.2f}; {sum(bool(c['below']) for c in cells)} of {len(cells)} weather × parameter "
        f"cells lie below a correct model's range, {sum(bool(c['above']) for c in cells)} above; the local test "
        f"(L-C2ST, level {float(_get(lc, ('level',), where)):g}) rejects {_number(float(joint['rate']), 3)} of the "
        f"named images (p {_number(float(joint['p_value']), 3)}){sun}."
    )


def results_block(reports: Mapping[str, object]) -> str:
    """The ``results`` block: a sentence on the test split, the models' table, Task II's and Task III's lines, and
    the champion at the named weathers (:func:`named_line`) when they were evaluated."""
    metrics = reports["task1"]
    champion = reports["champion"]
    if not isinstance(metrics, Mapping) or not isinstance(champion, Mapping) or "model" not in champion:
        raise ReportsError("reports/task1/champion.json names no champion: re-run the evaluate stage (`dvc repro`)")
    if champion["model"] not in metrics:
        raise ReportsError(
            f"reports/task1/champion.json names {champion['model']!r}, which reports/task1/metrics.json lacks: "
            "re-run the evaluate stage (`dvc repro`)"
        )
    first = next(iter(metrics.values()))
    images, samples = first.get("images"), first.get("samples")
    split = (
        f" ({_thousands(images)} images, {_thousands(samples)} posterior draws each)"
        if isinstance(images, int) and isinstance(samples, int)
        else ""
    )
    rule = champion.get("rule")
    chosen = RULE_TEXT.get(str(rule), f"rule `{rule}`")
    head = f'Task I on the test split{split}; the champion is {chosen} (`champion.json`: `"rule": "{rule}"`):'
    named = named_line(reports)
    lines = [head, "", *task1_table(metrics, champion), "", task2_line(reports["task2"]), task3_line(reports["task3"])]
    return "\n".join(lines if named is None else [*lines, named])


#: the champion's targets: information gain (nats) at least, test NLL at most, calibration error at most (and within
#: its band)
CHAMPION_TARGETS: dict[str, float] = {"info_gain_nats": 8.0, "test_nll": 20.2, "calibration_error": 0.03}
#: every grid model's calibration error at most
GRID_CALIBRATION_CEILING = 0.10
#: the champion's daytime median |median − truth| at most, in the order the page names them
DAY_TARGETS: dict[str, float] = {
    "cloudiness": 3.0,
    "fog_density": 2.5,
    "precipitation": 4.0,
    "sun_altitude_angle": 3.0,
    "precipitation_deposits": 6.0,
}
#: the champion's median error of the sun at CARLA's ClearNoon (a 45° sun under a clear sky), degrees
CLEAR_NOON_SUN = 5.0
#: the range the champion's central 68 % intervals must cover the truth in at night, every marginal
NIGHT_COVERAGE: tuple[float, float] = (0.63, 0.73)
#: Task III: the AUC a kind of target must reach, at 95 % confidence (its interval's lower end)
AUC_TARGET = 0.95
#: the parameters' names in the page's prose
SHORT: dict[str, str] = {
    "cloudiness": "cloudiness",
    "fog_density": "fog",
    "precipitation": "precipitation",
    "sun_altitude_angle": "sun altitude",
    "wind_intensity": "wind",
    "precipitation_deposits": "deposits",
}


def _short(name: str) -> str:
    return SHORT.get(name, name.replace("_", " "))


def _unit(name: str) -> str:
    return "°" if name == "sun_altitude_angle" else ""


def _pct(value: object, digits: int = 1) -> str:
    """``0.664`` → ``66.4``."""
    return _number(100 * float(value), digits) if isinstance(value, (int, float)) else "—"


def _sci(value: float) -> str:
    """``2.855e-07`` → ``2.9·10⁻⁷``; a number of 0.01 or more with two significant digits."""
    if value == 0 or abs(value) >= 0.01:
        return f"{value:.2g}"
    mantissa, exponent = f"{value:.1e}".split("e")
    sup = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")
    return f"{mantissa}·10{str(int(exponent)).translate(sup)}"


def _count(n: int) -> str:
    """``9`` → ``nine`` up to twelve, the digits above."""
    words = "zero one two three four five six seven eight nine ten eleven twelve".split()
    return words[n] if 0 <= n < len(words) else str(n)


def _join(items: list[str]) -> str:
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} and {items[-1]}"


def _champion_and_metrics(reports: Mapping[str, object]) -> tuple[str, Mapping, Mapping[str, Mapping]]:
    metrics, champion = reports["task1"], reports["champion"]
    if not isinstance(metrics, Mapping) or not isinstance(champion, Mapping) or "model" not in champion:
        raise ReportsError("reports/task1/champion.json names no champion: re-run the evaluate stage (`dvc repro`)")
    model = champion["model"]
    if model not in metrics:
        raise ReportsError(
            f"reports/task1/champion.json names {model!r}, which reports/task1/metrics.json lacks: "
            "re-run the evaluate stage (`dvc repro`)"
        )
    return model, champion, metrics


def _gains(metrics: Mapping[str, Mapping]) -> tuple[dict[str, list[float]], list[str]]:
    """The information gains of each backbone's grid models (no variant) by training size, and the backbones whose
    gain rises with the size."""
    by_backbone: dict[str, list[tuple[int, float]]] = {}
    for n, v in metrics.items():
        cell = MODEL_ID.match(n)
        if cell is not None and cell["variant"] is None:
            gain = float(_get(v, ("info_gain_nats",), "reports/task1/metrics.json"))
            by_backbone.setdefault(cell["backbone"], []).append((int(cell["size"]), gain))
    series = {b: [g for _, g in sorted(rows)] for b, rows in by_backbone.items() if len(rows) > 1}
    rising = [b for b, g in series.items() if all(a < c for a, c in zip(g[:-1], g[1:], strict=True))]
    return series, rising


_CAL = "calibration_error"


def champion_block(reports: Mapping[str, object]) -> str:
    """The ``task1-champion`` block: the prior's log-volume, then the champion against its targets, the runner-up,
    and the grid: its calibration against the ceiling, the information gain by training size, ``tiny``'s lean."""
    where = "reports/task1/metrics.json"
    model, champion, metrics = _champion_and_metrics(reports)
    m = metrics[model]
    gain, nll = float(_get(m, ("info_gain_nats",), where)), float(_get(m, ("test_nll",), where))
    error, band = float(_get(m, ("calibration_error",), where)), float(_get(m, ("calibration_band",), where))
    within = bool(_get(m, ("within_band",), where))
    images, samples = _get(m, ("images",), where), _get(m, ("samples",), where)
    t = CHAMPION_TARGETS
    missed = [
        text
        for ok, text in (
            (gain >= t["info_gain_nats"], f"the information ({_number(gain, 2)} nats)"),
            (nll <= t["test_nll"], f"the NLL ({_number(nll, 2)})"),
            (within and error <= t["calibration_error"], f"the calibration ({_number(error, 3)})"),
        )
        if not ok
    ]
    verdict = "are met" if not missed else f"are not all met: {_join(missed)} misses"
    se = m.get("test_nll_se")
    lines = [
        f"The prior's log-volume is {_number(gain + nll, 1)} nats; the information gain is the prior's log-volume "
        "minus the test NLL. `reports/task1/parameters.json` gives every parameter, day and night, and "
        "`reports/task1/profiles.json` the same by true value.",
        "",
        f"- **The champion is {model}**: information gain {_number(gain, 2)}"
        f"{'' if _number(se, 2) == '—' else f' ± {_number(se, 2)}'} nats, test NLL {_number(nll, 2)}, calibration error "
        f"{_number(error, 3)}, {'inside' if within else 'outside'} the {_number(band, 3)} band of a perfectly "
        f"calibrated model on {_thousands(int(images))} images × {_thousands(int(samples))} draws. The project's "
        f"targets for it — at least {t['info_gain_nats']:g} nats, an NLL of at most {t['test_nll']:g}, a calibration "
        f"error within the band and at most {t['calibration_error']:g} — {verdict}.",
    ]
    runner_up = champion.get("runner_up")
    others = [n for n, v in metrics.items() if v.get("within_band") and n != model]
    if isinstance(runner_up, Mapping) and runner_up.get("model") in metrics:
        r = runner_up["model"]
        rm = metrics[r]
        rest = [n for n in others if n != r]
        tail = (
            f"; {_join([f'{n} ({_number(metrics[n].get(_CAL), 3)})' for n in rest])} "
            f"{'is' if len(rest) == 1 else 'are'} within {'its band' if len(rest) == 1 else 'their bands'} too"
            if rest
            else ""
        )
        lines.append(
            f"- **The runner-up** (MLflow alias `challenger`) is {r}, "
            f"{'within' if rm.get('within_band') else 'outside'} its band "
            f"({_number(_get(rm, ('info_gain_nats',), where), 2)} nats, "
            f"{_number(_get(rm, ('calibration_error',), where), 3)}){tail}."
        )
    else:
        lines.append("- **No runner-up**: `champion.json` names none.")
    errors = {n: float(_get(v, ("calibration_error",), where)) for n, v in metrics.items()}
    under = [n for n, e in errors.items() if e <= GRID_CALIBRATION_CEILING]
    largest = sorted(errors, key=errors.get, reverse=True)[:2]
    count = (
        f"All {_count(len(errors))} models have"
        if len(under) == len(errors)
        else f"{len(under)} of {len(errors)} models have"
    )
    grid = (
        f"- **{count} a calibration error ≤ {GRID_CALIBRATION_CEILING:.2f}** "
        f"(the largest {_join([f'{n}, {_number(errors[n], 3)}' for n in largest])})."
    )
    series, rising = _gains(metrics)
    if series:
        figures = ", ".join(f"{b} {' / '.join(_number(g, 2) for g in gs)}" for b, gs in series.items())
        if len(rising) == len(series):
            grid += f" Information gain rises with the training size for every backbone: {figures} nats."
        else:
            flat = [b for b in series if b not in rising]
            grid += f" Information gain does not rise with the training size for {_join(flat)}: {figures} nats."
    tiny = [n for n in metrics if n.startswith("tiny-") and isinstance(metrics[n].get("coverage_auc_gap"), float)]
    if tiny:
        gaps = sorted(float(metrics[n]["coverage_auc_gap"]) for n in tiny)
        span = f"coverage gap {_number(gaps[-1], 3)}" + (f" to {_number(gaps[0], 3)}" if len(gaps) > 1 else "")
        lean = "lean overconfident" if gaps[-1] < 0 else "do not all lean overconfident"
        grid += f" The `tiny` models {lean} ({span})."
    lines.append(grid)
    return "\n".join(lines)


def _parameters(reports: Mapping[str, object], model: str, where: str) -> Mapping:
    table = reports["parameters"]
    if not isinstance(table, Mapping) or model not in table:
        raise ReportsError(f"{where} has no {model}: re-run the evaluate stage (`dvc repro`)")
    return table[model]


def champion_parameters_block(reports: Mapping[str, object]) -> str:
    """The ``champion-parameters`` block: the champion's daytime median errors against :data:`DAY_TARGETS`, its
    night coverage against :data:`NIGHT_COVERAGE`, and its daytime sun error by bin of the true altitude."""
    where = "reports/task1/parameters.json"
    model, _, _ = _champion_and_metrics(reports)
    p = _parameters(reports, model, where)
    day = {n: _get(p, ("day", n), where) for n in DAY_TARGETS}
    errors = {n: float(_get(v, ("median_abs_error",), where)) for n, v in day.items()}
    parts = []
    for n, e in errors.items():
        text = f"{_short(n)} {_number(e, 2)}{_unit(n)}"
        if n == "sun_altitude_angle":
            low, high = day[n].get("median_abs_error_low"), day[n].get("median_abs_error_high")
            text += f" (95 % interval {_number(low, 2)}–{_number(high, 2)}°)"
        parts.append(text)
    targets = " / ".join(f"{t:g}{_unit(n)}" for n, t in DAY_TARGETS.items())
    missed = [n for n, e in errors.items() if e > DAY_TARGETS[n]]
    sun = "sun_altitude_angle"
    if not missed:
        verdict = "all are met on the test split"
        if sun in errors:
            verdict += f", the sun's by {_number(DAY_TARGETS[sun] - errors[sun], 2)}°"
    else:
        verdict = "not met on the test split: " + ", ".join(
            f"{_short(n)} ({_number(errors[n], 2)}{_unit(n)} against {DAY_TARGETS[n]:g}{_unit(n)})" for n in missed
        )
    lines = [
        f"- **Daytime median errors**: {', '.join(parts)}. The targets are {targets}: {verdict} "
        "(but see the limitations below)."
    ]
    night = _get(p, ("night",), where)
    cover = {n: float(_get(v, ("coverage68",), where)) for n, v in night.items()}
    order = sorted(cover, key=cover.get)
    low, high = NIGHT_COVERAGE
    outside = [n for n in order if not low <= cover[n] <= high]
    lowest = night[order[0]]
    listed = ", ".join(
        f"{_short(n)} {_pct(cover[n])} %"
        + (
            f" (95 % interval {_pct(lowest.get('coverage68_low'))}–{_pct(lowest.get('coverage68_high'))} %)"
            if i == 0
            else ""
        )
        for i, n in enumerate(order)
    )
    where_range = (
        f"inside the target range of {100 * low:g}–{100 * high:g} % for every marginal"
        if not outside
        else f"outside the target range of {100 * low:g}–{100 * high:g} % for {_join([_short(n) for n in outside])}"
    )
    wind = p.get("all", {}).get("wind_intensity") if isinstance(p.get("all"), Mapping) else None
    wind_all = (
        f" Over all images, day and night, wind's cover {_pct(wind['coverage68'])} %."
        if isinstance(wind, Mapping) and "coverage68" in wind
        else ""
    )
    lines.append(
        f"- **At night** its central 68 % intervals cover the truth {_pct(cover[order[0]])}–{_pct(cover[order[-1]])} % "
        f"of the time, {where_range}: {listed}.{wind_all}"
    )
    profiles = reports["profiles"]
    wp = "reports/task1/profiles.json"
    if not isinstance(profiles, Mapping) or model not in profiles:
        raise ReportsError(f"{wp} has no {model}: re-run the evaluate stage (`dvc repro`)")
    s = _get(profiles[model], ("day", sun), wp)
    edges, counts, errs = (_get(s, (k,), wp) for k in ("edges", "images", "median_abs_error"))
    bins = [(edges[b], edges[b + 1], errs[b]) for b in range(len(counts)) if counts[b] and errs[b] is not None]
    if not bins:
        raise ReportsError(f"{wp}: {model}'s daytime sun profile has no image: re-run the evaluate stage")
    said = []
    for i, (a, b, e) in enumerate(bins):
        digits = 2 if e < 1 else 1
        if i == 0 and len(bins) > 1:
            said.append(f"{_number(e, digits)}° below {b:g}° of altitude")
        elif i == len(bins) - 1 and len(bins) > 1:
            said.append(f"and {_number(e, digits)}° above {a:g}°")
        else:
            said.append(f"{_number(e, digits)}° at {a:g}–{b:g}°")
    lines.append(
        f"- **Where it is sharp, by true value** (`reports/task1/profiles.json`, {len(counts)} bins of each range). The "
        f"daytime medians above average over very different weathers. The sun's error is {', '.join(said)}, where the "
        "camera's auto-exposure evens out the brightness. Wind is seen only through the rain, and its posterior stays "
        "wide. Calibration promises 68 % coverage on average, not in each bin; each bin's coverage is in the JSON, "
        "with its interval."
    )
    return "\n".join(lines)


#: Task II's bag in the paper's setting: fog and precipitation free, the other parameters fixed
PAPER_SETTING = ", the paper's setting"


def task2_block(reports: Mapping[str, object]) -> str:
    """The ``task2`` block: the estimate's energy distance and W₁ ratios, the true mass in its HDR, and the width
    floor: the W₁ ratio calibrated posteriors of the same widths give and the one posteriors moved onto their truths
    give, with the bootstrap intervals of the estimate minus the calibrated mixture."""
    where = "reports/task2/metrics.json"
    t = reports["task2"]
    model = _get(t, ("model",), where)
    champion = reports["champion"]
    who = "The champion" if isinstance(champion, Mapping) and champion.get("model") == model else str(model)
    parameters = _get(t, ("parameters",), where)
    varying = [n for n, p in parameters.items() if isinstance(p, Mapping) and p.get("fixed_value") is None]
    fixed = [n for n in parameters if n not in varying]

    def ratios(names: list[str]) -> str:
        return ", ".join(f"{_short(n)} {_number(_get(parameters[n], ('wasserstein_ratio',), where), 2)}" for n in names)

    level = float(_get(t, ("hdr_level",), where))
    masses = {n: float(_get(parameters[n], ("true_mass_in_hdr",), where)) for n in parameters}
    below = sorted((n for n, v in masses.items() if v < 1), key=masses.get)
    per = (
        f"per parameter ≥ {_number(masses[below[0]], 3)}: "
        + ", ".join(f"{_short(n)} {_number(masses[n], 3)}" for n in below)
        + ", the others 1.0"
        if below
        else "1.0 for every parameter"
    )
    lines = [
        f"{who}, {_thousands(int(_get(t, ('images',), where)))} images"
        f"{PAPER_SETTING if sorted(varying) == ['fog_density', 'precipitation'] else ''}, "
        f"the {_get(t, ('estimate',), where)} of posteriors:",
        "",
        f"- energy distance ratio estimate / prior {_number(_get(t, ('energy_distance_sq', 'all', 'ratio'), where), 2)};",
        f"- W₁ estimate / prior: {ratios(varying)}"
        + (f" (of the parameters held fixed: {ratios(fixed)})" if fixed else "")
        + ";",
        f"- true mass in the {100 * level:g} % HDR {_number(_get(t, ('true_mass_in_hdr',), where), 3)} ({per});",
    ]
    floor = _get(t, ("width_floor",), where)
    focus = "precipitation"
    calibrated = _get(floor, ("calibrated", "1", focus), where)
    moved = _get(floor, ("wasserstein_ratio", "1", focus), where)
    mixture = _get(floor, ("mixture", focus), where)
    interval = _get(floor, ("interval", "mixture_minus_calibrated"), where)
    confidence = float(_get(floor, ("interval", "confidence"), where))
    diffs = []
    biased = []
    for n, d in interval.items():
        low, high = float(_get(d, ("low",), where)), float(_get(d, ("high",), where))
        sign = "+" if float(d["difference"]) >= 0 else ""
        diffs.append(
            f"{_short(n)} {sign}{_number(d['difference'], 3)} [{'+' if low >= 0 else ''}{_number(low, 3)}, "
            f"{'+' if high >= 0 else ''}{_number(high, 3)}]"
        )
        if not low <= 0 <= high:
            biased.append(_short(n))
    sd = _get(floor, ("posterior_sd_median",), where)
    bias = "no bias to find" if not biased else f"a bias in {_join(biased)}"
    opening = (
        f"- the mixture's {focus} distance is what its posteriors' widths make it, with nothing left for bias"
        if not biased
        else f"- the mixture's {focus} distance is more than its posteriors' widths make it"
    )
    lines.append(
        f"{opening}: the mixture calibrated posteriors of the same widths would give has a W₁ ratio of "
        f"{_number(calibrated, 2)}, the estimate's {_number(mixture, 2)}; each posterior moved onto its truth, "
        f"{_number(moved, 2)} — which no calibrated posterior can do. Estimate minus calibrated, with its "
        f"{100 * confidence:g} % bootstrap interval over the bag's images: {', '.join(diffs)}: {bias}. The posteriors' "
        f"median standard deviation on this bag is {_number(_get(sd, (focus,), where), 1)} units for {focus}, "
        f"{_number(_get(sd, ('fog_density',), where), 1)} for fog ([study](studies/task2-width-floor.md))."
    )
    return "\n".join(lines)


def _beta_binomial_above(n: int, a: int, b: int, k: int) -> float:
    """P(X > k) for X ~ BB(n, a, b)."""

    def log_pmf(x: int) -> float:
        return (
            math.lgamma(n + 1)
            - math.lgamma(x + 1)
            - math.lgamma(n - x + 1)
            + math.lgamma(x + a)
            + math.lgamma(n - x + b)
            - math.lgamma(n + a + b)
            + math.lgamma(a + b)
            - math.lgamma(a)
            - math.lgamma(b)
        )

    return sum(math.exp(log_pmf(x)) for x in range(k + 1, n + 1))


def _auc_text(row: Mapping, kind: str) -> str:
    return (
        f"{_number(row[f'auc_{kind}'], 2)} [{_number(row.get(f'auc_ci_low_{kind}'), 2)}, "
        f"{_number(row.get(f'auc_ci_high_{kind}'), 2)}]"
    )


def _aucs(eta: Mapping[float, Mapping], kind: str) -> str:
    """The AUCs of a kind by η > 0: each η's own until the rest of the sweep gives one figure, then ``at every η ≥``."""
    rows = sorted(e for e, r in eta.items() if r.get(f"auc_{kind}") is not None)
    if not rows:
        return "no AUC (no η > 0 in the sweep)"
    texts = [_auc_text(eta[e], kind) for e in rows]
    start = len(rows) - 1
    while start > 0 and texts[start - 1] == texts[-1]:
        start -= 1
    said = [f"{texts[i]} at η = {rows[i]:g}" for i in range(start)]
    said.append(
        f"{texts[-1]} at η = {rows[-1]:g}" if start == len(rows) - 1 else f"{texts[-1]} at every η ≥ {rows[start]:g}"
    )
    return "AUC " + ", ".join(said)


def _holds_from(eta: Mapping[float, Mapping], kind: str) -> float | None:
    """The first η from which the AUC's 95 % interval lies above :data:`AUC_TARGET` at every η of the sweep."""
    rows = sorted(e for e, r in eta.items() if r.get(f"auc_{kind}") is not None)
    first = None
    for e in reversed(rows):
        low = eta[e].get(f"auc_ci_low_{kind}")
        if not isinstance(low, (int, float)) or low < AUC_TARGET:
            break
        first = e
    return first


def task3_block(reports: Mapping[str, object]) -> str:
    """The ``task3`` block: each kind's AUCs by η and its median d_E at η = 0, the first η meeting
    :data:`AUC_TARGET` at 95 % confidence, and the out-of-ODD decision's false alarms."""
    where = "reports/task3/metrics.json"
    t = reports["task3"]
    eta = {float(k): v for k, v in _get(t, ("eta",), where).items() if isinstance(v, Mapping)}
    if 0.0 not in eta:
        raise ReportsError(f"{where} has no eta.0 (the sweep's η = 0): re-run the task3 stage (`dvc repro`)")
    kinds = [k for k in ("paper", "fresh") if f"d_e_median_{k}" in eta[0.0]]
    repetitions = _get(eta[0.0], ("repetitions",), where)
    lines = [
        f"n_W = {_get(t, ('n_points',), where)}, kernel characterization, {repetitions} targets per η and kind; AUCs "
        "with their 95 % intervals (Newcombe):",
        "",
    ]
    names = {"paper": "paper-style targets", "fresh": "**fresh targets**"}
    for kind in kinds:
        holds = _holds_from(eta, kind)
        verdict = (
            f"the target AUC ≥ {AUC_TARGET:g} holds at 95 % confidence from η = {holds:g}"
            if holds is not None
            else f"the target AUC ≥ {AUC_TARGET:g} does not hold at 95 % confidence at the sweep's last η"
        )
        lines.append(
            f"- {names[kind]}: median d_E {_sci(float(eta[0.0][f'd_e_median_{kind}']))} at η = 0, "
            f"{_aucs(eta, kind)}: {verdict};"
        )
    odd = _get(t, ("odd",), where)
    check = _get(odd, ("false_alarms_new_seeds",), where)
    alpha = float(_get(odd, ("false_alarm_rate",), where))
    m, rank = int(_get(odd, ("calibration_targets",), where)), int(_get(odd, ("rank",), where))
    n, flagged = int(_get(check, ("n",), where)), int(_get(check, ("flagged",), where))
    low, high = float(_get(check, ("ci_low",), where)), float(_get(check, ("ci_high",), where))
    lo, hi = int(_get(check, ("calibrated_low",), where)), int(_get(check, ("calibrated_high",), where))
    statistic = str(_get(odd, ("statistic",), where)).replace("_", " ")
    lines.append(
        f"- the decision is calibrated on {m} {_get(odd, ('calibrated_on',), where)} in-ODD targets for α = {alpha:g} "
        f"(threshold {_number(_get(odd, ('threshold',), where), 4)} on the {statistic}). It flags {flagged} of {n} "
        f"in-ODD targets of new seeds: {_number(_get(check, ('rate',), where), 3)}, 95 % CI {_number(low, 3)}–"
        f"{_number(high, 3)}, α {'inside' if low <= alpha <= high else 'outside'};"
    )
    exceeds = bool(_get(check, ("exceeds_alpha",), where))
    above = _beta_binomial_above(n, m + 1 - rank, rank, hi)
    lines.append(
        "- the Clopper–Pearson interval is the decision's own rate; whether a count breaks the promise is judged "
        "against the range a perfectly calibrated decision gives on as many targets, which holds the spread of a "
        f"threshold estimated from m targets: the beta-binomial BB(n, m + 1 − r, r), [{lo}, {hi}] of {n} at 95 % for "
        f"m = {m} (`calibrated_low`/`calibrated_high`; `exceeds_alpha` when the count is above it, in "
        f"{_pct(above)} % of a calibrated decision's runs); this run's {flagged} is "
        f"{'above it' if exceeds else 'not above it'}."
    )
    return "\n".join(lines)


#: Task II: the estimate's energy-distance ratio to the prior's and each free parameter's W₁ ratio at most, and the
#: share of the true mass inside the estimate's HDR at least
TASK2_TARGETS: dict[str, float] = {"energy_ratio": 0.3, "wasserstein_ratio": 0.3, "true_mass_in_hdr": 0.95}
#: Task III: the η from which each kind of target must reach :data:`AUC_TARGET` at 95 % confidence
AUC_FROM_ETA = 0.3


def _local(reports: Mapping[str, object], model: str) -> Mapping:
    where = "reports/task1/local.json"
    return _get(reports["local"], (model,), where)


def _set_test(t: Mapping, where: str) -> str:
    lo, hi = _get(t, ("null_range",), where)
    rate, p = float(_get(t, ("rate",), where)), float(_get(t, ("p_value",), where))
    return f"{_number(rate, 3)} (the null's 95 % range {_number(lo, 3)}–{_number(hi, 3)}, p {_number(p, 3)})"


def named_block(reports: Mapping[str, object]) -> str:
    """The ``named`` block: the champion at the named weathers (``reports/task1/local.json``) — the pooled 68 %
    coverage per parameter beside the exact toy's, the cells outside a correct model's range, the joint L-C2ST on
    the named images and on test images, the sun at ClearNoon — then one line per model."""
    model, _, metrics = _champion_and_metrics(reports)
    where = "reports/task1/local.json"
    local = _local(reports, model)
    if "skipped" in local:
        return f"The named weathers were not evaluated: {local['skipped']}."
    rows = _get(local, ("weathers",), where)
    pooled = _get(local, ("pooled", "all", "parameters"), where)
    lc = _get(local, ("lc2st",), where)
    level = float(_get(lc, ("level",), where))
    images = sum(int(r["images"]) for r in rows)
    cells = [c for r in rows for c in r["parameters"].values()]
    below, above = sum(bool(c["below"]) for c in cells), sum(bool(c["above"]) for c in cells)
    cov = ", ".join(
        f"{_short(n)} {_number(v['coverage68'], 2)} [{_number(v['ci68'][0], 2)}, {_number(v['ci68'][1], 2)}] "
        f"(toy {_number(v['toy68'], 2)})"
        for n, v in pooled.items()
    )
    lines = [
        f"The champion ({model}) at {len(rows)} named weathers ({images} images of new scenes, "
        "[how to read it](named-weathers.md)): its 68.27 % HDIs cover the truth, pooled, "
        f"{cov}: an exact posterior on a toy with the same faces and widths in parentheses. "
        f"{below} of {len(cells)} weather × parameter cells lie below the 95 % range of a correct model's coverage, "
        f"{above} above (a correct model: about {round(0.05 * len(cells))} in all).",
        f"The local test (L-C2ST, joint, level {level:g}) rejects {_set_test(_get(lc, ('named', 'joint'), where), where)}"
        f" of the named images and {_set_test(_get(lc, ('test', 'joint'), where), where)} of "
        f"{_get(lc, ('test_images',), where)} test images.",
    ]
    noon = [r for r in rows if r["weather"] == "ClearNoon"]
    if noon:
        e = float(noon[0]["parameters"]["sun_altitude_angle"]["median_abs_error"])
        lines[-1] += f" At ClearNoon (a 45° sun under a clear sky) it reads the sun to {_number(e, 2)}°."
    table = ["", "| model | pooled 68 % coverage (mean) | cells below · above | L-C2ST named (p) | L-C2ST test (p) |"]
    table.append("|---|---:|---:|---:|---:|")
    for m in metrics:
        v = metrics[m]
        if "named_weathers" not in v or v["named_weathers"] != v["named_weathers"]:  # NaN: skipped
            continue
        table.append(
            f"| {m} | {_number(v['named_coverage68'], 3)} | {int(v['named_cells_below'])} · "
            f"{int(v['named_cells_above'])} | {_number(v['lc2st_named_rate'], 3)} ({_number(v['lc2st_named_p'], 3)}) "
            f"| {_number(v['lc2st_test_rate'], 3)} ({_number(v['lc2st_test_p'], 3)}) |"
        )
    return "\n".join([" ".join(lines), *table])


def targets(reports: Mapping[str, object]) -> list[tuple[str, bool, str]]:
    """Every target the reports can judge, as ``(what, met, the figure against the target)``, in the page's order."""
    model, _, metrics = _champion_and_metrics(reports)
    w1, w2, w3 = "reports/task1/metrics.json", "reports/task1/parameters.json", "reports/task2/metrics.json"
    m = metrics[model]
    gain, nll = float(_get(m, ("info_gain_nats",), w1)), float(_get(m, ("test_nll",), w1))
    error, within = float(_get(m, ("calibration_error",), w1)), bool(_get(m, ("within_band",), w1))
    t = CHAMPION_TARGETS
    out = [
        (
            "the champion's information",
            gain >= t["info_gain_nats"],
            f"{_number(gain, 2)} nats, target ≥ {t['info_gain_nats']:g}",
        ),
        ("its NLL", nll <= t["test_nll"], f"{_number(nll, 2)}, target ≤ {t['test_nll']:g}"),
        (
            "its calibration",
            within and error <= t["calibration_error"],
            f"{_number(error, 3)}, {'within' if within else 'outside'} its band; target within it and ≤ {t['calibration_error']:g}",
        ),
    ]
    p = _parameters(reports, model, w2)
    for n, target in DAY_TARGETS.items():
        e = float(_get(p, ("day", n, "median_abs_error"), w2))
        out.append(
            (f"its daytime {_short(n)}", e <= target, f"{_number(e, 2)}{_unit(n)}, target ≤ {target:g}{_unit(n)}")
        )
    low, high = NIGHT_COVERAGE
    span = f"{100 * low:g}–{100 * high:g} %"
    for n in _get(p, ("night",), w2):
        c = float(_get(p, ("night", n, "coverage68"), w2))
        out.append((f"the night coverage of {_short(n)}", low <= c <= high, f"{_pct(c)} %, target {span}"))
    local = _local(reports, model)
    if "skipped" not in local:
        w5 = "reports/task1/local.json"
        lc = _get(local, ("lc2st",), w5)
        level, t = float(_get(lc, ("level",), w5)), _get(lc, ("named", "joint"), w5)
        p_named = float(_get(t, ("p_value",), w5))
        out.append(
            (
                "the local test at the named weathers",
                p_named > level,
                f"rate {_number(float(t['rate']), 3)}, set p {_number(p_named, 3)}; target p > {level:g}",
            )
        )
        noon = [r for r in _get(local, ("weathers",), w5) if r["weather"] == "ClearNoon"]
        if noon:
            e = float(noon[0]["parameters"]["sun_altitude_angle"]["median_abs_error"])
            out.append(("the sun at ClearNoon", e <= CLEAR_NOON_SUN, f"{_number(e, 2)}°, target ≤ {CLEAR_NOON_SUN:g}°"))
    wind = float(_get(p, ("all", "wind_intensity", "coverage68"), w2))
    out.append(("wind's over all images", low <= wind <= high, f"{_pct(wind)} %, target {span}"))
    worst = max(metrics, key=lambda n: float(_get(metrics[n], ("calibration_error",), w1)))
    worst_error = float(metrics[worst]["calibration_error"])
    out.append(
        (
            "every grid model's calibration",
            worst_error <= GRID_CALIBRATION_CEILING,
            f"{worst} {_number(worst_error, 3)}, target ≤ {GRID_CALIBRATION_CEILING:.2f}",
        )
    )
    series, rising = _gains(metrics)
    flat = [b for b in series if b not in rising]
    out.append(
        (
            "the grid's gain with size",
            bool(series) and not flat,
            f"it does not rise for {_join(flat)}" if flat else "it rises for every backbone",
        )
    )
    t2 = reports["task2"]
    energy = float(_get(t2, ("energy_distance_sq", "all", "ratio"), w3))
    out.append(
        (
            "the Task II energy ratio",
            energy <= TASK2_TARGETS["energy_ratio"],
            f"{_number(energy, 2)}, target ≤ {TASK2_TARGETS['energy_ratio']:g}",
        )
    )
    parameters = _get(t2, ("parameters",), w3)
    for n, v in parameters.items():
        if isinstance(v, Mapping) and v.get("fixed_value") is None:
            r = float(_get(v, ("wasserstein_ratio",), w3))
            target = TASK2_TARGETS["wasserstein_ratio"]
            out.append((f"{_short(n)}'s W₁", r <= target, f"{_number(r, 2)} × the prior's, target ≤ {target:g}"))
    mass = float(_get(t2, ("true_mass_in_hdr",), w3))
    target = TASK2_TARGETS["true_mass_in_hdr"]
    out.append(("the HDR mass", mass >= target, f"{_number(mass, 3)}, target ≥ {target:g}"))
    w4 = "reports/task3/metrics.json"
    t3 = reports["task3"]
    eta = {float(k): v for k, v in _get(t3, ("eta",), w4).items() if isinstance(v, Mapping)}
    for kind in ("paper", "fresh"):
        if not any(f"auc_{kind}" in r for r in eta.values()):
            continue
        holds = _holds_from(eta, kind)
        out.append(
            (
                f"Task III's {kind} AUC",
                holds is not None and holds <= AUC_FROM_ETA,
                f"≥ {AUC_TARGET:g} at 95 % confidence "
                + (f"from η = {holds:g}" if holds is not None else "at no η")
                + f", target from η = {AUC_FROM_ETA:g}",
            )
        )
    check = _get(t3, ("odd", "false_alarms_new_seeds"), w4)
    out.append(
        (
            "Task III's false alarms",
            not bool(_get(check, ("exceeds_alpha",), w4)),
            f"{_get(check, ('flagged',), w4)} of {_get(check, ('n',), w4)}, target at most "
            f"{_get(check, ('calibrated_high',), w4)}",
        )
    )
    return out


def targets_block(reports: Mapping[str, object]) -> str:
    """The ``targets`` block: which of the project's targets the latest run meets and which it misses, by figure."""
    judged = targets(reports)
    met = [what for what, ok, _ in judged if ok]
    missed = [f"{what} ({figure})" for what, ok, figure in judged if not ok]
    lines = [f"The latest run meets {len(met)} of the {len(judged)} targets the reports can judge: {_join(met)}."]
    lines.append(f"It misses {_join(missed)}." if missed else "It misses none of them.")
    return " ".join(lines)


#: the champion rule's branches (:data:`components.evaluate.champion.RULES`) in words
RULE_TEXT: dict[str, str] = {
    "within_band": "the lowest test NLL among the models calibrated within their band",
    "ceiling": "the lowest test NLL under the calibration-error ceiling: no model is calibrated within its band",
}

#: block name → how its content is made from the reports
BLOCKS: dict[str, Callable[[Mapping[str, object]], str]] = {
    "results": results_block,
    "task1-table": lambda r: str(r["table"]).strip(),
    "task1-champion": champion_block,
    "champion-parameters": champion_parameters_block,
    "task2": task2_block,
    "task3": task3_block,
    "named": named_block,
    "targets": targets_block,
}


def fill(text: str, reports: Mapping[str, object], where: str = "the file") -> str:
    """``text`` with the content between each pair of markers of :data:`BLOCKS` replaced by what ``reports`` say.

    Raises:
        ReportsError: no block in ``text``, a begin marker without its end (or the reverse), or one twice.
    """
    found = 0
    for name, make in BLOCKS.items():
        begin, end = _marker(name, False), _marker(name, True)
        counts = (text.count(begin), text.count(end))
        if counts == (0, 0):
            continue
        if counts != (1, 1) or text.index(begin) > text.index(end):
            raise ReportsError(f"{where}: the markers {begin} … {end} must appear once each, in that order")
        head, rest = text.split(begin)
        _, tail = rest.split(end)
        text = f"{head}{begin}\n{make(reports)}\n{end}{tail}"
        found += 1
    if not found:
        raise ReportsError(f"{where} holds no block ({', '.join(_marker(n, False) for n in BLOCKS)})")
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reports", type=Path, default=ROOT / "reports", help="the reports folder (default reports/)")
    parser.add_argument(
        "--files",
        type=Path,
        nargs="+",
        default=[ROOT / t for t in TARGETS],
        help="the files whose blocks are kept in step (default README.md docs/results.md)",
    )
    what = parser.add_mutually_exclusive_group()
    what.add_argument("--check", action="store_true", help="exit 1 when a file's block differs from the reports")
    what.add_argument("--print", action="store_true", help="print the results block only; write nothing")
    args = parser.parse_args(argv)
    try:
        reports = read_reports(args.reports)
        if args.print:
            print(results_block(reports))
            return 0
        stale = []
        for path in args.files:
            if not path.is_file():
                raise ReportsError(f"{path} does not exist")
            old = path.read_text(encoding="utf-8")
            new = fill(old, reports, str(path))
            if new != old:
                stale.append(path)
                if not args.check:
                    path.write_text(new, encoding="utf-8")
    except ReportsError as err:
        print(f"results_table: {err}", file=sys.stderr)
        return 2
    for path in stale:
        print(f"{path}: {'stale (run python scripts/results_table.py)' if args.check else 'updated'}", file=sys.stderr)
    return 1 if args.check and stale else 0


if __name__ == "__main__":
    sys.exit(main())
