"""A table of posterior draws on disk, written image by image: columns ``image, draw, <θ names…>``.

One row per draw: ``image`` (a label, e.g. the file path), ``draw`` (0-based index within that image), then the d
parameters in physical units. ``.csv`` is written with the standard library; ``.parquet`` needs pyarrow (checked when
the writer is created, before any work). The file appears only on :meth:`DrawsWriter.close` (temporary file + atomic
rename, :func:`components.core.files.atomic_path`), so an interrupted run leaves no partial table.

Used by the ``pidc`` CLI only (``characterize --samples-out``).
"""

from __future__ import annotations

import contextlib
import csv
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType

import numpy as np

from components.core.files import atomic_path

__all__ = ["DRAWS_FORMATS", "check_draws_path", "DrawsWriter"]

#: Supported suffixes → format.
DRAWS_FORMATS: dict[str, str] = {".csv": "csv", ".parquet": "parquet", ".pq": "parquet"}


def check_draws_path(path: str | Path) -> str:
    """The format (``"csv"``/``"parquet"``) of a draws file ``path``; ``ValueError`` for an unknown suffix,
    ``ImportError`` for Parquet without pyarrow (both naming the file). Cheap: call it before any work."""
    path = Path(path)
    fmt = DRAWS_FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: unknown draws file type {path.suffix!r}; use .csv or .parquet")
    if fmt == "parquet":
        try:
            import pyarrow  # noqa: F401
            import pyarrow.parquet  # noqa: F401
        except ImportError:
            raise ImportError(
                f"{path}: writing Parquet needs pyarrow (pip install pyarrow); or write a .csv file"
            ) from None
    return fmt


class _Discarded(Exception):
    """Raised into the writer's :func:`atomic_path` to drop the temporary file."""


class DrawsWriter:
    """Write draws ``(m, d)`` per image to ``path`` (``.csv`` or ``.parquet``); use as a context manager.

    Arguments:
        path: the output file; its suffix picks the format.
        names: the d parameter names (column names after ``image`` and ``draw``).

    Raises ``ValueError`` (unknown suffix) or ``ImportError`` (Parquet without pyarrow), naming the file.
    """

    def __init__(self, path: str | Path, names: Sequence[str]) -> None:
        self.path = Path(path)
        self.names = tuple(names)
        self.rows = 0
        self.format = check_draws_path(self.path)
        self._atomic = contextlib.ExitStack()  # holds the atomic_path: closing it puts the file in place
        self._tmp = self._atomic.enter_context(atomic_path(self.path))
        self._file = None
        self._csv = None
        self._parquet = None
        if self.format == "csv":
            self._file = open(self._tmp, "w", newline="", encoding="utf-8")
            self._csv = csv.writer(self._file)
            self._csv.writerow(["image", "draw", *self.names])

    def write(self, image: str, draws: np.ndarray) -> None:
        """Append the ``(m, d)`` draws of one image (physical units)."""
        a = np.asarray(draws, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != len(self.names):
            raise ValueError(f"draws must have shape (m, {len(self.names)}), got shape {a.shape}")
        if self.format == "csv":
            assert self._csv is not None
            self._csv.writerows([image, i, *(repr(float(v)) for v in row)] for i, row in enumerate(a))
        else:
            import pyarrow as pa
            import pyarrow.parquet as pq

            columns = {
                "image": pa.array([image] * a.shape[0], pa.string()),
                "draw": pa.array(np.arange(a.shape[0], dtype=np.int64)),
            }
            columns.update({name: pa.array(a[:, j]) for j, name in enumerate(self.names)})
            table = pa.table(columns)
            if self._parquet is None:
                self._parquet = pq.ParquetWriter(self._tmp, table.schema)
            self._parquet.write_table(table)
        self.rows += a.shape[0]

    def close(self) -> None:
        """Finish the file and move it into place (an empty table still gets its header/schema)."""
        try:
            if self.format == "csv":
                assert self._file is not None
                self._file.close()
            else:
                import pyarrow as pa
                import pyarrow.parquet as pq

                if self._parquet is None:
                    fields = [pa.field("image", pa.string()), pa.field("draw", pa.int64())]
                    fields += [pa.field(n, pa.float64()) for n in self.names]
                    self._parquet = pq.ParquetWriter(self._tmp, pa.schema(fields))
                self._parquet.close()
        except BaseException:
            self.discard()
            raise
        self._atomic.close()  # fsync + os.replace (the temporary file is removed if that fails)

    def discard(self) -> None:
        """Drop the temporary file (after an error); the destination is left untouched."""
        for handle in (self._file, self._parquet):
            if handle is not None:
                with contextlib.suppress(Exception):  # closing a half-written file after another error
                    handle.close()
        with contextlib.suppress(_Discarded), self._atomic:
            raise _Discarded  # leaving atomic_path with an error removes the temporary file

    def __enter__(self) -> DrawsWriter:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None, tb: TracebackType | None) -> None:
        if kind is None:
            self.close()
        else:
            self.discard()
