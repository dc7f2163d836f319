"""The labels file of a recorded folder: one row per image, its true weather, its drive and optionally its split.

A recorded folder is what the ``generate`` stage imports (``simulator.backend: recorded``,
:mod:`components.simulate.recorded`), what ``pidc record`` writes, and what the scheduled monitoring judges the
models on (``monitor.source: <folder>``, :mod:`components.monitor.recorded`). One format for all three:

    <folder>/labels.csv        (or labels.parquet; another name with ``simulator.recorded.labels``)
        image,cloudiness,fog_density,precipitation,sun_altitude_angle,wind_intensity,precipitation_deposits,sequence
        drive1/frame_0001.png,20,5,0,35.5,10,0,drive1
    <folder>/<image>           the files the ``image`` column names, relative to the folder (PNG, JPEG, … of any
                               size: what components.core.images.read_image reads)

Columns:

- ``image`` and the six predicted parameters (:data:`components.core.weather.PREDICTED`, physical units: % and
  degrees), required; each value inside the prior box (a label outside it cannot be learned or judged: the posterior
  has no mass there).
- ``sun_azimuth_angle`` (the nuisance, degrees in [0, 360]), optional: absent, it is unknown (NaN in the dataset).
- the fixed parameters (``fog_distance`` …, :data:`components.core.weather.FIXED`), optional: when given, each must
  equal its fixed value (the posteriors are defined there only); absent, they take it.
- ``sequence``, optional: the drive (or scene) an image belongs to; frames of one sequence never sit in two splits.
- ``split``, optional: ``train``, ``val`` or ``test``, the split a row must go to (``pidc record`` writes it).
- any other column (notes, timestamps) is ignored.

Every problem is a :class:`RecordedError` of one line naming the file, the row (``line N`` of a CSV file, counting the
header as line 1; ``row N`` of a Parquet file, counting data rows from 1) and the column: a missing folder or labels
file, a missing column, an empty or repeated image name, a value that is not a number, lies outside its range or
differs from a fixed value, an unknown split.

Used by :mod:`components.simulate.recorded` (the ``generate`` stage, ``pidc record``) and
:mod:`components.monitor.recorded` (the scheduled monitoring).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from components.core import weather

__all__ = [
    "LABELS",
    "IMAGE_COLUMN",
    "SEQUENCE_COLUMN",
    "SPLIT_COLUMN",
    "SPLIT_NAMES",
    "RecordedError",
    "Labels",
    "labels_file",
    "read_labels",
    "labels_csv",
]

#: the default labels file of a recorded folder
LABELS = "labels.csv"
#: the column naming each image file (relative to the folder)
IMAGE_COLUMN = "image"
#: the optional column naming each image's sequence (a drive, a scene)
SEQUENCE_COLUMN = "sequence"
#: the optional column naming each image's split
SPLIT_COLUMN = "split"
#: the values of the split column
SPLIT_NAMES = ("train", "val", "test")
_AZIMUTH = weather.NUISANCE[0]


class RecordedError(ValueError):
    """A recorded folder, its labels or one of its images cannot be used; the message is one line naming the file
    (and the row and column)."""


@dataclass(frozen=True)
class Labels:
    """The rows of a labels file, in file order.

    Attributes:
        path: the labels file.
        names: each row's ``image`` entry (relative to the folder).
        weather: ``(n, 13)`` each row's weather in :data:`components.core.weather.ALL_NAMES` order (the azimuth NaN
            when the file has no ``sun_azimuth_angle`` column, fixed parameters at their values when absent).
        sequences: each row's ``sequence`` entry, or None when the file has no such column.
        splits: each row's ``split`` entry, or None when the file has no such column.
        rows: where each row stands, for messages: ``"line 3"`` (CSV) or ``"row 2"`` (Parquet).
    """

    path: Path
    names: list[str]
    weather: np.ndarray
    sequences: list[str] | None
    splits: list[str] | None
    rows: list[str]

    @property
    def theta(self) -> np.ndarray:
        """``(n, 6)`` the true θ, physical units."""
        return weather.theta_from_weather(self.weather)

    def __len__(self) -> int:
        return len(self.names)


def _number(value: object, where: str) -> float:
    if value is None or (isinstance(value, str) and not value.strip()):
        raise RecordedError(f"{where}: empty")
    if isinstance(value, bool):
        raise RecordedError(f"{where}: {value!r} is not a number")
    try:
        number = float(value.strip() if isinstance(value, str) else value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise RecordedError(f"{where}: {value!r} is not a number") from None
    if not math.isfinite(number):
        raise RecordedError(f"{where}: {value!r} is not a finite number")
    return number


def _text(value: object) -> str:
    return "" if value is None else str(value).strip()


def _read_csv(path: Path) -> tuple[list[str], list[tuple[str, dict[str, object]]]]:
    """The header and ``(where, row)`` of every non-blank line below it."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            table = [(reader.line_num, r) for r in reader if any(cell.strip() for cell in r)]  # blank lines skipped
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise RecordedError(f"{path}: unreadable ({e})") from None
    columns = [c.strip() for c in table[0][1]] if table else []
    return columns, [(f"line {line}", dict(zip(columns, r, strict=False))) for line, r in table[1:]]


def _read_parquet(path: Path) -> tuple[list[str], list[tuple[str, dict[str, object]]]]:
    """The columns and ``(where, row)`` of every row (numbered from 1)."""
    try:
        import pyarrow.parquet as pq

        table = pq.read_table(path)
    except ImportError:
        raise RecordedError(f"{path}: reading Parquet labels needs pyarrow (pip install pyarrow)") from None
    except Exception as e:  # pyarrow raises ArrowInvalid, OSError, … for a damaged file
        raise RecordedError(f"{path}: unreadable Parquet file ({type(e).__name__}: {e})") from None
    columns = [str(c).strip() for c in table.column_names]
    rows = table.to_pylist()
    return columns, [(f"row {i}", {str(k).strip(): v for k, v in r.items()}) for i, r in enumerate(rows, start=1)]


def _required() -> tuple[str, ...]:
    return (IMAGE_COLUMN, *weather.PREDICTED)


def _weather_row(row: dict[str, object], where: str, box: weather.Box, has: set[str]) -> np.ndarray:
    """One row's 13 weather values, validated (``where``: ``"<file>, line N"``)."""
    out = np.empty(len(weather.ALL_NAMES))
    for j, name in enumerate(weather.ALL_NAMES):
        p = weather.PARAMETERS[name]
        at = f"{where}, column {name}"
        if name not in has:
            out[j] = p.fixed if p.role == "fixed" else np.nan  # an absent azimuth is unknown
            continue
        value = _number(row.get(name), at)
        if p.role == "predicted":
            i = box.names.index(name)
            low, high = box.low[i], box.high[i]
            if not low <= value <= high:
                raise RecordedError(
                    f"{at}: {value:g} lies outside [{low:g}, {high:g}] {box.units[i]} (the prior box of the models)"
                )
        elif not p.low <= value <= p.high:
            raise RecordedError(f"{at}: {value:g} lies outside its range {p.describe_range()}")
        elif p.role == "fixed" and not math.isclose(value, p.fixed, rel_tol=1e-9, abs_tol=1e-12):  # type: ignore[arg-type]
            raise RecordedError(
                f"{at}: {value:g}, but pidc fixes {name} to {p.fixed:g} (the models are defined there only; drop the "
                "column or record with the fixed value)"
            )
        out[j] = value
    return out


def labels_file(folder: str | Path, name: str = LABELS) -> Path:
    """The labels file ``name`` of ``folder``; :class:`RecordedError` naming what is missing."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RecordedError(f"{folder}: no such folder (a recorded folder holds its images and {name})")
    path = folder / name
    if not path.is_file():
        raise RecordedError(
            f"{path}: missing; a recorded folder holds {name} with the columns {IMAGE_COLUMN}, "
            f"{', '.join(weather.PREDICTED)} (physical units) and the images it names"
        )
    return path


def read_labels(folder: str | Path, box: weather.Box, limit: int | None = None, name: str = LABELS) -> Labels:
    """The rows of ``folder``'s labels file ``name`` (``.csv`` or ``.parquet``; its first ``limit`` rows when given),
    validated against the prior ``box``.

    Raises:
        RecordedError: one line naming the file, the row and the column (the module's description lists the checks).
    """
    path = labels_file(folder, name)
    columns, rows = _read_parquet(path) if path.suffix.lower() == ".parquet" else _read_csv(path)
    missing = [c for c in _required() if c not in columns]
    if missing:
        raise RecordedError(
            f"{path}: missing column(s) {', '.join(missing)}; the header must name {IMAGE_COLUMN} and "
            f"{', '.join(weather.PREDICTED)} (found: {', '.join(columns) or 'no header'})"
        )
    if limit is not None:
        rows = rows[: int(limit)]
    if not rows:
        raise RecordedError(f"{path}: no rows below the header: no labelled image")
    has = set(columns)
    names: list[str] = []
    first: dict[str, str] = {}
    table = np.empty((len(rows), len(weather.ALL_NAMES)))
    sequences = [] if SEQUENCE_COLUMN in has else None
    splits = [] if SPLIT_COLUMN in has else None
    for i, (at, row) in enumerate(rows):
        where = f"{path}, {at}"
        image = _text(row.get(IMAGE_COLUMN))
        if not image:
            raise RecordedError(f"{where}, column {IMAGE_COLUMN}: empty")
        if image in first:
            kind, before = first[image].split()
            raise RecordedError(
                f"{where}, column {IMAGE_COLUMN}: {image!r} is listed twice ({kind}s {before} and {at.split()[1]})"
            )
        first[image] = at
        names.append(image)
        table[i] = _weather_row(row, where, box, has)
        if sequences is not None:
            sequence = _text(row.get(SEQUENCE_COLUMN))
            if not sequence:
                raise RecordedError(f"{where}, column {SEQUENCE_COLUMN}: empty (every row of the column needs one)")
            sequences.append(sequence)
        if splits is not None:
            split = _text(row.get(SPLIT_COLUMN))
            if split not in SPLIT_NAMES:
                raise RecordedError(f"{where}, column {SPLIT_COLUMN}: {split!r} is not one of {', '.join(SPLIT_NAMES)}")
            splits.append(split)
    return Labels(path, names, table, sequences, splits, [at for at, _ in rows])


def labels_csv(
    names: Sequence[str], rows: np.ndarray, sequences: Sequence[str], splits: Sequence[str] | None = None
) -> bytes:
    """The labels CSV of ``names`` with their 13 weather values ``rows (n, 13)`` (:data:`weather.ALL_NAMES` order, all
    finite), ``sequences`` and optionally ``splits``; each value written as Python's ``repr`` of the float, so
    :func:`read_labels` reads back the same float64 bits. Used by ``pidc record``."""
    rows = np.asarray(rows, dtype=np.float64)
    if rows.shape != (len(names), len(weather.ALL_NAMES)) or len(sequences) != len(names):
        raise ValueError(f"{len(names)} names need weather rows ({len(names)}, 13) and as many sequences")
    if not np.all(np.isfinite(rows)):
        raise ValueError("labels_csv writes finite weather values only (an unknown azimuth: leave the column out)")
    header = [IMAGE_COLUMN, *weather.ALL_NAMES, SEQUENCE_COLUMN] + ([SPLIT_COLUMN] if splits is not None else [])
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    for i, name in enumerate(names):
        extra = [splits[i]] if splits is not None else []
        writer.writerow([name, *(repr(float(v)) for v in rows[i]), sequences[i], *extra])
    return buf.getvalue().encode()
