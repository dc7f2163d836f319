"""A folder of recorded images with their weather labels: what scheduled monitoring judges the models on instead of
new simulated images (``monitor.source: <folder>``).

The format is the recorded folders' of the ``generate`` stage and ``pidc record`` (:mod:`components.simulate.labels`:
``labels.csv`` with an ``image`` column and the six parameters in physical units, inside the prior box; optional
azimuth, fixed parameters, ``sequence`` and ``split`` columns, ignored here; the images of any size). Rows are used in
file order. Every problem is a :class:`RecordedError` naming the file, the line and the column: a missing folder or
``labels.csv``, a missing column, an empty or repeated image name, a value that is not a number or lies outside its
range, an image that is missing or cannot be read.

Used by the scheduled monitoring (``flows/monitor.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from components.core import weather
from components.core.images import ImageError, read_image
from components.simulate.labels import IMAGE_COLUMN, LABELS, Labels, RecordedError, read_labels

__all__ = ["LABELS", "IMAGE_COLUMN", "RecordedError", "Labels", "Recorded", "read_labels", "read_recorded"]


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


def read_recorded(folder: str | Path, box: weather.Box, limit: int | None = None) -> Recorded:
    """The labelled images of ``folder`` (:func:`~components.simulate.labels.read_labels` of its ``labels.csv``, its
    first ``limit`` rows when given, then every image it names, read as RGB); :class:`RecordedError` naming the file
    for an image that is missing, outside the folder or unreadable."""
    folder = Path(folder)
    labels = read_labels(folder, box, limit)
    root = folder.resolve()
    images = []
    for name, at in zip(labels.names, labels.rows, strict=True):
        path = folder / name
        if root not in path.resolve().parents:
            raise RecordedError(f"{labels.path}, {at}, column {IMAGE_COLUMN}: {name!r} lies outside {folder}")
        try:
            image, _ = read_image(path)
        except ImageError as e:
            raise RecordedError(f"{e} (named on {at} of {labels.path})") from None
        images.append(image)
    return Recorded(folder, labels.names, labels.theta, images)
