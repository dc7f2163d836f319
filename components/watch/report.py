"""What a watch writes: the per-frame and per-window tables (CSV or Parquet), the JSON summary, and the short report.

- ``frames``: one row per frame: ``frame``, ``image`` (its file name, or ``frame <k>`` in a video), ``time_s``, and per
  parameter ``<name>_median``, ``<name>_low``, ``<name>_high`` (the 68.27 % HDI), physical units.
- ``windows``: one row per window: ``window``, ``first_frame``, ``last_frame``, ``start_s``, ``end_s``; per parameter
  the window's domain (Task II) ``<name>_median``/``_low``/``_high``, its ``<name>_w1`` against the fitted mixture and
  ``<name>_beyond`` (W₁ above the parameter's in-ODD level); ``weight_<source>`` (λ̂), ``gap`` (δ, density²),
  ``relative_gap``, ``flagged`` (above the threshold), ``alarm`` (the rule in alarm), ``degenerate``, ``beyond`` (the
  parameters beyond their levels, ``;``-separated).
- ``summary.json``: the drive, model, sources, settings, threshold and levels, the rule with its stated false alarms
  per hour (Garwood interval), the first alarm, every alarm segment with its cause, the record against the known
  weather when there is one, and the timing.

Used by the ``pidc watch`` command.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from components.core.files import atomic_path, atomic_write_bytes

__all__ = ["TABLE_FORMATS", "write_table", "summary", "write_summary", "report_lines"]

#: The table formats and their file suffixes.
TABLE_FORMATS: dict[str, str] = {"csv": ".csv", "parquet": ".parquet"}


def _cell(v: Any) -> str:
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return str(v)


def write_table(path: str | Path, columns: dict[str, np.ndarray], fmt: str) -> Path:
    """Write a column table (name → ``(n,)``) atomically as CSV (``repr`` floats, ``true``/``false``) or Parquet."""
    path = Path(path)
    if fmt == "parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        with atomic_path(path, fsync=False) as tmp:
            pq.write_table(pa.table({k: np.asarray(v) for k, v in columns.items()}), tmp)
        return path
    if fmt != "csv":
        raise ValueError(f"table format must be one of {', '.join(TABLE_FORMATS)}, got {fmt!r}")
    names = list(columns)
    rows = zip(*(np.asarray(columns[n]).tolist() for n in names), strict=True)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(names)
    writer.writerows([_cell(v) for v in row] for row in rows)
    atomic_write_bytes(path, buf.getvalue().encode("utf-8"))
    return path


def _alarm(result: Any, a: Any) -> dict[str, Any]:
    box, levels = result.box, result.calibration.levels
    w1 = {n: result.windows[f"{n}_w1"][a.segment.first : a.segment.last + 1] for n in box.names}
    return {
        "first_flagged_s": a.first_s,
        "fired_s": a.fired_s,
        "end_s": a.end_s,
        "open": a.segment.open,
        "windows": a.segment.last - a.segment.first + 1,
        "cause": a.cause,
        "parameters": {
            n: {
                "share_beyond_level": float(a.share[j]),
                "mean_w1_over_level": float(a.ratio[j]),
                "max_w1": float(w1[n].max()),
                "in_odd_level": float(levels[j]),
            }
            for j, n in enumerate(box.names)
        },
    }


def summary(result: Any) -> dict[str, Any]:
    """The ``summary.json`` of a :class:`~components.watch.run.WatchResult` (see the module docstring)."""
    opts, cal, stated, drive = result.options, result.calibration, result.stated, result.drive
    box = result.box
    return {
        "drive": {
            "path": str(drive.path),
            "kind": drive.kind,
            "frames": int(result.frames["frame"].size),
            "size": [int(drive.size[1]), int(drive.size[0])],
            "frame_seconds": drive.frame_seconds,
            "seconds": result.timing["drive_length_seconds"],
        },
        "model": result.model,
        "sources": [
            {
                "name": n,
                "path": str(f.path),
                "frames": int(f.count),
                "density_frames": int(cal.density_frames[k]),
                "kernel_centres": int(result.densities.draws[k].shape[0]),
            }
            for k, (n, f) in enumerate(zip(result.names, result.sources, strict=True))
        ],
        "settings": opts.to_dict(),
        "bandwidth": dict(zip(box.names, map(float, result.densities.bandwidth), strict=True)),
        "threshold": {
            "relative_gap": float(cal.detector.threshold),
            "false_alarm_rate_per_window": float(opts.false_alarm_rate),
            "calibration_windows": cal.calibration_windows,
            "rank": int(cal.detector.rank),
        },
        "in_odd_levels": {
            n: {"unit": u, "w1": float(v)} for n, u, v in zip(box.names, box.units, cal.levels, strict=True)
        },
        "rule": {
            "kind": "consecutive",
            "consecutive_windows": result.rule.k,
            "window_seconds": result.window_seconds,
            "latency_seconds": (result.rule.k - 1) * result.window_seconds,
            "description": (
                f"alarm after {result.rule.k} consecutive windows of {opts.length} frames (every {opts.stride} frames) "
                f"whose relative gap exceeds {cal.detector.threshold:.4g}"
            ),
            "false_alarms_per_hour": stated.to_dict(),
        },
        "first_alarm_s": result.first_alarm_s,
        "alarms": [_alarm(result, a) for a in result.alarms],
        "windows": {
            "count": int(result.windows["window"].size),
            "flagged": int(np.count_nonzero(result.windows["flagged"])),
            "in_alarm": int(np.count_nonzero(result.windows["alarm"])),
        },
        "truth": result.truth,
        "timing": result.timing,
        "notes": result.notes,
    }


def write_summary(path: str | Path, result: Any) -> Path:
    """``summary.json`` (indented, atomically)."""
    path = Path(path)
    atomic_write_bytes(path, (json.dumps(summary(result), indent=1) + "\n").encode())
    return path


def _rate(stated: Any) -> str:
    return (
        f"{stated.per_hour:.3g} false alarms per hour [{stated.low:.3g}, {stated.high:.3g}] "
        f"({100 * stated.level:g} % Garwood interval; {stated.alarms} in {60 * stated.hours:.3g} min of held-out "
        f"in-ODD windows, {stated.flagged} of {stated.windows} windows flagged)"
    )


def report_lines(result: Any) -> list[str]:
    """The short report on stdout: the drive, the rule and its stated rate, the first alarm, each segment's cause."""
    opts, cal = result.options, result.calibration
    t = result.timing
    lines = [
        f"drive {result.drive.path}: {t['drive_frames']} frames, {t['drive_length_seconds']:.1f} s; model "
        f"{result.model}; sources {', '.join(result.names)}",
        f"windows: {opts.length} frames every {opts.stride} ("
        + ("equal weights" if opts.decay is None else f"weights × {opts.decay:g} per frame of age")
        + f"); threshold {cal.detector.threshold:.4g} on the relative gap (false-alarm rate {opts.false_alarm_rate:g} "
        f"per window, {cal.calibration_windows} held-out calibration windows)",
        f"rule: alarm after {result.rule.k} consecutive flagged windows; stated: {_rate(result.stated)}",
    ]
    if not result.alarms:
        lines.append("no alarm")
    else:
        lines.append(f"first alarm at {result.alarms[0].fired_s:.1f} s; {len(result.alarms)} alarm segment(s):")
        for a in result.alarms:
            cause = ", ".join(a.cause) if a.cause else "no single parameter beyond its in-ODD level"
            end = "end of drive" if a.segment.open else f"{a.end_s:.1f} s"
            lines.append(f"  {a.fired_s:.1f} s – {end} (first flagged {a.first_s:.1f} s): {cause}")
    if result.truth is not None:
        tr = result.truth
        if tr["exit_s"] is None:
            lines.append(f"truth: the drive stays in the sources' range; {tr['false_alarms']} false alarm(s)")
        else:
            delay = "not detected" if tr["delay_s"] is None else f"detected after {tr['delay_s']:.1f} s"
            lines.append(
                f"truth: leaves the sources' range at {tr['exit_s']:.1f} s ({', '.join(tr['exit_parameters'])}); "
                f"{delay}; {tr['false_alarms']} false alarm(s) before"
            )
            for name, p in tr["parameters"].items():
                seen = "no alarm names it" if p["delay_s"] is None else f"named by an alarm after {p['delay_s']:.1f} s"
                lines.append(f"  {name} leaves its range at {p['exit_s']:.1f} s; {seen}")
    lines.append(
        f"watched in {t['drive_seconds']:.1f} s ({t['frames_per_second']:.1f} frames/s, {t['realtime_factor']:.1f}× "
        f"real time) after {t['sources_seconds']:.1f} s on the sources"
    )
    return lines
