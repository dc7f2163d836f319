"""A folder of recorded images with their weather labels: what scheduled monitoring judges the models on instead of
new simulated images (``monitor.source: <folder>``).

The format:

    <folder>/labels.csv      one row per image, a header row first:
                             image,cloudiness,fog_density,precipitation,sun_altitude_angle,wind_intensity,precipitation_deposits
                             drive1/frame_0001.png,20,5,0,35.5,10,0
    <folder>/<image>         the image files the ``image`` column names, relative to the folder (PNG, JPEG, … of any
                             size: what components.core.images.read_image reads)

The six parameters are the true weather of each image in physical units (% and degrees, :mod:`components.core.weather`),
inside the prior box the models were trained on (a label outside it cannot be judged: the posterior has no mass there).
Other columns (e.g. ``sun_azimuth_angle``, notes) are ignored. Rows are used in file order. Every problem is a
:class:`RecordedError` naming the file, the line and the column: a missing folder or ``labels.csv``, a missing column,
an empty or repeated image name, a value that is not a number or lies outside its range, an image that is missing or
cannot be read.

Used by the scheduled monitoring (``flows/monitor.py``).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from components.core import weather
from components.core.images import ImageError, read_image

__all__ = ["LABELS", "IMAGE_COLUMN", "RecordedError", "Labels", "Recorded", "read_labels", "read_recorded"]

#: the labels file of a recorded folder
LABELS = "labels.csv"
#: the column naming each image file (relative to the folder)
IMAGE_COLUMN = "image"


class RecordedError(ValueError):
    """A recorded folder, its labels or one of its images cannot be used; the message names the file (and line and
    column)."""


@dataclass(frozen=True)
class Recorded:
    """Labelled recorded images.

    Attributes:
        folder: the recorded folder.
        names: the ``image`` entry of each row used, in file order.
        theta: ``(n, 6)`` true weather, :data:`components.core.weather.PREDICTED` order, physical units.
        images: the ``n`` images, uint8 ``(H, W, 3)`` RGB each (sizes may differ).
    """

    folder: Path
    names: list[str]
    theta: np.ndarray
    images: list[np.ndarray]


def _number(text: str | None, where: str) -> float:
    if text is None or not text.strip():
        raise RecordedError(f"{where}: empty")
    try:
        value = float(str(text).strip())
    except ValueError:
        raise RecordedError(f"{where}: {text!r} is not a number") from None
    if not np.isfinite(value):
        raise RecordedError(f"{where}: {text!r} is not a finite number")
    return value


@dataclass(frozen=True)
class Labels:
    """The rows of a ``labels.csv``: ``names[i]`` (the ``image`` entry), ``theta[i]`` (physical units) and the file's
    line ``lines[i]`` they stand on."""

    path: Path
    names: list[str]
    theta: np.ndarray
    lines: list[int]


def read_labels(folder: str | Path, box: weather.Box, limit: int | None = None) -> Labels:
    """The rows of ``folder``'s ``labels.csv`` (its first ``limit`` rows when given), validated against the prior
    ``box``; :class:`RecordedError` naming file, line and column otherwise."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RecordedError(f"{folder}: no such folder (a recorded folder holds its images and {LABELS})")
    path = folder / LABELS
    if not path.is_file():
        raise RecordedError(
            f"{path}: missing; a recorded folder holds {LABELS} with the columns {IMAGE_COLUMN}, "
            f"{', '.join(weather.PREDICTED)} (physical units) and the images it names"
        )
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            table = [(reader.line_num, r) for r in reader if any(cell.strip() for cell in r)]  # blank lines skipped
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise RecordedError(f"{path}: unreadable ({e})") from None
    columns = [c.strip() for c in table[0][1]] if table else []
    missing = [c for c in (IMAGE_COLUMN, *weather.PREDICTED) if c not in columns]
    if missing:
        raise RecordedError(
            f"{path}: missing column(s) {', '.join(missing)}; the header must name {IMAGE_COLUMN} and "
            f"{', '.join(weather.PREDICTED)} (found: {', '.join(columns) or 'no header'})"
        )
    rows = [(line, dict(zip(columns, r, strict=False))) for line, r in table[1:]]
    if limit is not None:
        rows = rows[: int(limit)]
    if not rows:
        raise RecordedError(f"{path}: no rows below the header: no labelled image")
    names: list[str] = []
    first_line: dict[str, int] = {}
    theta = np.empty((len(rows), len(weather.PREDICTED)))
    for i, (line, row) in enumerate(rows):
        name = (row.get(IMAGE_COLUMN) or "").strip()
        if not name:
            raise RecordedError(f"{path}, line {line}, column {IMAGE_COLUMN}: empty")
        if name in first_line:
            raise RecordedError(
                f"{path}, line {line}, column {IMAGE_COLUMN}: {name!r} is listed twice (lines {first_line[name]} "
                f"and {line})"
            )
        first_line[name] = line
        names.append(name)
        for j, param in enumerate(weather.PREDICTED):
            where = f"{path}, line {line}, column {param}"
            value = _number(row.get(param), where)
            low, high = box.low[j], box.high[j]
            if not low <= value <= high:
                raise RecordedError(
                    f"{where}: {value:g} lies outside [{low:g}, {high:g}] {box.units[j]} (the prior box of the models)"
                )
            theta[i, j] = value
    return Labels(path, names, theta, [line for line, _ in rows])


def read_recorded(folder: str | Path, box: weather.Box, limit: int | None = None) -> Recorded:
    """The labelled images of ``folder`` (:func:`read_labels`, then every image it names, read as RGB);
    :class:`RecordedError` naming the file for an image that is missing, outside the folder or unreadable."""
    folder = Path(folder)
    labels = read_labels(folder, box, limit)
    root = folder.resolve()
    images = []
    for name, line in zip(labels.names, labels.lines, strict=True):
        path = folder / name
        if root not in path.resolve().parents:
            raise RecordedError(f"{labels.path}, line {line}, column {IMAGE_COLUMN}: {name!r} lies outside {folder}")
        try:
            image, _ = read_image(path)
        except ImageError as e:
            raise RecordedError(f"{e} (named on line {line} of {labels.path})") from None
        images.append(image)
    return Recorded(folder, labels.names, labels.theta, images)
