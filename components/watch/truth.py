"""The known weather of a simulated drive, and what the rule did against it: its false alarms and its detection delay,
measured on the drive.

A drive made by ``pidc drive`` (:mod:`components.simulate.drive`) carries its truth θ(t): ``weather.csv`` in a folder,
``OUT.weather.csv`` beside a video ``OUT.avi``. When the drive and every source carry one, the sources' *range* is the
box of each parameter's lowest to highest true value over all the sources' frames, the drive *leaves* it at the first
frame outside that box (:func:`components.simulate.drive.first_exit`), and

- every alarm fired before that time is a false alarm (in-ODD driving), counted over the hours before it;
- the detection delay is the time from leaving to the first alarm fired at or after it.

Used by :mod:`components.watch.run`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from components.core.weather import PREDICTED
from components.watch.errors import WatchError

__all__ = ["truth_path", "read_truth", "sources_range", "against_truth"]


def truth_path(frames: Any) -> Path:
    """Where a drive's truth would be: ``weather.csv`` in its folder, or the video's ``OUT.weather.csv``."""
    from components.simulate.drive import video_sidecars

    path = Path(frames.path)
    return path / "weather.csv" if frames.kind == "folder" else video_sidecars(path)[0]


def read_truth(frames: Any) -> dict[str, np.ndarray] | None:
    """The truth table of a drive or source (:func:`components.simulate.drive.read_weather_csv`), None when it has none;
    a :class:`WatchError` naming the file when it does not hold one row per frame and the six parameters."""
    from components.simulate.drive import read_weather_csv

    path = truth_path(frames)
    if not path.is_file():
        return None
    try:
        table = read_weather_csv(path)
    except (ValueError, IndexError, OSError) as e:
        raise WatchError(f"{path}: not a drive's weather table ({e})") from None
    missing = [n for n in PREDICTED if n not in table]
    if missing:
        raise WatchError(f"{path}: no column {missing[0]!r} (a drive's weather table has the six parameters)")
    rows = len(table["time_s"])
    if rows != frames.count:
        raise WatchError(f"{path}: {rows} rows for the {frames.count} frames of {frames.path}")
    return table


def sources_range(tables: Sequence[dict[str, np.ndarray]]) -> dict[str, tuple[float, float]]:
    """Each parameter's lowest and highest true value over all the sources' frames."""
    return {n: (float(min(t[n].min() for t in tables)), float(max(t[n].max() for t in tables))) for n in PREDICTED}


def against_truth(
    table: dict[str, np.ndarray],
    box: dict[str, tuple[float, float]],
    alarms: Sequence[tuple[float, Sequence[str]]],
    seconds: float,
) -> dict[str, Any]:
    """The rule's record on a drive of known weather.

    Arguments:
        table: the drive's truth (``time_s`` and the parameters).
        box: the sources' range (:func:`sources_range`).
        alarms: per alarm, in order, the time the rule fired (seconds) and its cause (parameter names).
        seconds: the drive's length, seconds (the in-ODD time when it never leaves the range).

    Returns:
        ``exit_s`` (the first frame outside the range; None when the drive stays in it), ``exit_parameters``,
        ``in_odd_hours`` (before the exit), ``false_alarms`` (fired before it) and ``false_alarms_per_hour``,
        ``detected_s`` (the first alarm at or after the exit, None if none) and ``delay_s``; and ``parameters``: per
        parameter that leaves its range, its own ``exit_s``, the first alarm at or after it that names it
        (``detected_s``) and ``delay_s``.
    """
    from components.simulate.drive import exits, first_exit

    exit_ = first_exit(table, box)
    exit_s = None if exit_ is None else exit_.time_s
    in_odd = seconds if exit_s is None else exit_s
    fired = [float(t) for t, _ in alarms]
    false = [t for t in fired if exit_s is None or t < exit_s]
    after = [t for t in fired if exit_s is not None and t >= exit_s]
    hours = in_odd / 3600.0
    per: dict[str, Any] = {}
    for name, t in exits(table, box).items():
        named = [float(a) for a, cause in alarms if a >= t and name in cause]
        per[name] = {"exit_s": t, "detected_s": named[0] if named else None, "delay_s": named[0] - t if named else None}
    return {
        "sources_range": {n: list(v) for n, v in box.items()},
        "exit_s": exit_s,
        "exit_parameters": [] if exit_ is None else list(exit_.parameters),
        "in_odd_hours": hours,
        "false_alarms": len(false),
        "false_alarms_per_hour": len(false) / hours if hours > 0 else None,
        "detected_s": after[0] if after else None,
        "delay_s": (after[0] - exit_s) if after and exit_s is not None else None,
        "parameters": per,
    }
