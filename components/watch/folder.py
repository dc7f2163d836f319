"""A folder of drives watched on a schedule: the drives in it, what identifies each one's watch, the outputs of a watch,
and the one error of a run whose drives left the sources' ODD.

- A folder's **drives** (:func:`list_drives`) are its sub-folders (folders of frames) and its video files
  (:data:`~components.watch.frames.VIDEO_SUFFIXES`), in natural name order (``drive2`` before ``drive10``). Hidden
  entries (``.name``: a folder still being written, as ``pidc drive`` writes into ``.<name>.<8 hex>.tmp``) and other
  files (a video's ``OUT.weather.csv`` and ``OUT.drive.json``) are not drives. A drive is named by its entry's name (a
  video's with its suffix), unique in the folder; its outputs go to ``<out>/<name>/``.
- A drive's **fingerprint** (:func:`fingerprint`) is the SHA-256 of the name, size (bytes) and modification time (ns) of
  each of its files (a folder's non-hidden files; a video and its sidecars): adding, removing, rewriting or touching a
  frame changes it, reading does not; only ``stat`` is called (an hour of frames at 10 frames/s, 36 000 files, in tens
  of milliseconds).
- A watch's **key** (:func:`watch_key`) is what its result depends on: the drive's fingerprint, the registered model
  version, the sources' names and fingerprints and the settings. ``summary.json`` records it (:func:`watched_summary`,
  under ``watched``), and a drive whose ``<out>/<name>/summary.json`` holds the same key was watched already
  (:func:`already_watched`): a changed drive, a new champion, other sources or settings watch it again.
- :func:`write_tables` writes the frames and windows tables and the timeline figure, as ``pidc watch --out`` does,
  after removing an earlier ``summary.json``: a ``summary.json`` present is always the last file of a finished watch
  of the tables beside it.
- :class:`DrivesLeftOdd` is raised once after the whole folder (:func:`exit_message`: every drive that left the ODD,
  its first alarm's time and cause, and the drives that could not be watched).

Used by the scheduled watch of a folder (``flows/watch.py``); no pipeline stage imports it.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from components.core.files import atomic_write_bytes
from components.watch.errors import WatchError
from components.watch.frames import VIDEO_SUFFIXES

__all__ = [
    "OUTPUT_NAMES",
    "list_drives",
    "drive_name",
    "open_drive",
    "drive_files",
    "fingerprint",
    "source_names",
    "check_layout",
    "watch_key",
    "already_watched",
    "write_tables",
    "watched_summary",
    "write_summary",
    "DriveOutcome",
    "DrivesLeftOdd",
    "exit_message",
]

#: The files of a drive's watch in ``<out>/<name>/`` (CSV tables, as ``pidc watch --out`` writes by default).
OUTPUT_NAMES: dict[str, str] = {
    "timeline": "timeline.png",
    "frames": "frames.csv",
    "windows": "windows.csv",
    "summary": "summary.json",
}


def _natural(name: str) -> list[object]:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def _is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def list_drives(folder: str | Path) -> list[Path]:
    """The drives in ``folder`` (module docstring): its non-hidden sub-folders and video files, in natural name order.

    Raises:
        WatchError: ``folder`` does not exist or is not a folder.
    """
    folder = Path(folder)
    if not folder.exists():
        raise WatchError(f"folder {folder}: no such folder (the folder of drives to watch)")
    if not folder.is_dir():
        raise WatchError(f"folder {folder}: not a folder (give the folder that holds the drives)")
    found = [p for p in folder.iterdir() if not p.name.startswith(".") and (p.is_dir() or _is_video(p))]
    return sorted(found, key=lambda p: _natural(p.name))


def drive_name(path: Path) -> str:
    """A drive's name: its folder's or its video file's name (with the suffix: ``a.mp4`` and ``a/`` may sit side by
    side)."""
    return Path(path).name


def open_drive(path: Path, fps: float | None = None) -> Any:
    """Open a drive (:func:`components.watch.frames.open_frames`): ``fps`` (frames per second) is the rate of a folder
    of frames without ``times.csv`` and is not used otherwise (a video states its rate, ``times.csv`` gives times)."""
    from components.watch.frames import TIMES_CSV, open_frames

    path = Path(path)
    untimed = path.is_dir() and not (path / TIMES_CSV).is_file()
    return open_frames(path, fps if untimed else None)


def drive_files(path: str | Path) -> list[Path]:
    """The files a drive's watch reads: a folder's non-hidden files (frames, ``times.csv``, ``weather.csv``, …), or a
    video and those of its sidecars ``OUT.weather.csv``/``OUT.drive.json`` that exist; in name order."""
    from components.simulate.drive import video_sidecars

    path = Path(path)
    if path.is_dir():
        return sorted((f for f in path.iterdir() if f.is_file() and not f.name.startswith(".")), key=lambda f: f.name)
    return [path, *(s for s in video_sidecars(path) if s.is_file())]


def fingerprint(path: str | Path) -> str:
    """The SHA-256 (hex) of the name, size and modification time (ns) of each of :func:`drive_files`.

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp())
        >>> _ = (d / "000000.png").write_bytes(b"x")
        >>> before = fingerprint(d)
        >>> _ = (d / "000001.png").write_bytes(b"y")
        >>> fingerprint(d) != before
        True
    """
    h = hashlib.sha256()
    for f in drive_files(path):
        st = f.stat()
        h.update(f"{f.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def source_names(paths: Sequence[Path]) -> list[str]:
    """The sources' names, as ``pidc watch`` names them: their folders' names (a video's stem), or their paths where two
    share one."""
    names = [(p.name if p.name not in ("", ".", "..") else p.resolve().name) if p.is_dir() else p.stem for p in paths]
    return names if len(set(names)) == len(names) else [str(p) for p in paths]


def _inside(path: Path, folder: Path) -> bool:
    path, folder = path.resolve(), folder.resolve()
    return path == folder or folder in path.parents


def check_layout(folder: Path, out: Path, sources: Sequence[Path]) -> None:
    """A :class:`WatchError` when the outputs or a source lie in the folder of drives (they would be watched as drives)
    or a source is given twice; nothing when the layout is sound."""
    if _inside(out, folder):
        raise WatchError(f"out {out} lies in the folder of drives {folder}: its outputs would be watched as drives")
    seen: set[Path] = set()
    for s in sources:
        if _inside(s, folder) and s.resolve() != folder.resolve():
            raise WatchError(f"source {s} lies in the folder of drives {folder}: it would be watched as a drive")
        if s.resolve() == folder.resolve():
            raise WatchError(f"source {s} is the folder of drives itself")
        if s.resolve() in seen:
            raise WatchError(f"source {s} is given twice")
        seen.add(s.resolve())


def watch_key(
    drive_fingerprint: str,
    model: Mapping[str, str],
    sources: Mapping[str, str],
    settings: Mapping[str, Any],
) -> dict[str, Any]:
    """What a drive's watch depends on, as JSON: ``fingerprint`` (the drive's), ``model`` (its registered name, version
    and URI), ``sources`` (name → fingerprint) and ``settings`` (``WatchOptions.to_dict()``)."""
    return {
        "fingerprint": drive_fingerprint,
        "model": dict(model),
        "sources": dict(sources),
        "settings": json.loads(json.dumps(dict(settings))),
    }


def _same(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    """Two keys watch the same: the same drive, the same registered model version (not the URI that led to it: the
    alias ``@champion`` and ``/3`` are the same model when they name version 3), sources and settings."""
    model_a, model_b = a.get("model", {}), b.get("model", {})
    return (
        a.get("fingerprint") == b.get("fingerprint")
        and (model_a.get("name"), model_a.get("version")) == (model_b.get("name"), model_b.get("version"))
        and a.get("sources") == b.get("sources")
        and a.get("settings") == b.get("settings")
    )


def already_watched(out: Path, key: Mapping[str, Any]) -> bool:
    """Whether ``out/summary.json`` records a finished watch with ``key`` (:func:`watch_key`). A summary that cannot be
    read (or has no record) is not one: the drive is watched again."""
    path = Path(out) / OUTPUT_NAMES["summary"]
    try:
        record = json.loads(path.read_text()).get("watched")
    except (OSError, ValueError, AttributeError):
        return False
    return isinstance(record, Mapping) and _same(record, key)


def write_tables(out: Path, result: Any) -> dict[str, Path]:
    """Write ``out/frames.csv``, ``out/windows.csv`` and ``out/timeline.png`` of a
    :class:`~components.watch.run.WatchResult` (an earlier ``out/summary.json`` removed first); returns the paths of
    :data:`OUTPUT_NAMES` (``summary`` not yet written: :func:`write_summary`)."""
    from components.plots.canvas import save_figure
    from components.watch.plot import timeline_figure
    from components.watch.report import write_table

    out = Path(out)
    paths = {k: out / v for k, v in OUTPUT_NAMES.items()}
    out.mkdir(parents=True, exist_ok=True)
    paths["summary"].unlink(missing_ok=True)
    write_table(paths["frames"], result.frames, "csv")
    write_table(paths["windows"], result.windows, "csv")
    save_figure(timeline_figure(result), paths["timeline"])
    return paths


def watched_summary(result: Any, record: Mapping[str, Any]) -> dict[str, Any]:
    """``summary.json`` of a watch (:func:`components.watch.report.summary`) with the ``watched`` ``record``: the
    :func:`watch_key` and whatever else the caller adds (the Prefect flow run, the MLflow run)."""
    from components.watch.report import summary

    return summary(result) | {"watched": dict(record)}


def write_summary(path: Path, content: Mapping[str, Any]) -> Path:
    """Write a summary (indented JSON, atomically)."""
    atomic_write_bytes(Path(path), (json.dumps(content, indent=1) + "\n").encode())
    return Path(path)


@dataclass(frozen=True)
class DriveOutcome:
    """What one drive's watch found (or why it could not be watched).

    Attributes:
        name: the drive's name.
        out: its outputs' folder.
        frames: frames watched (0 when not watched).
        alarms: alarm segments.
        first_alarm_s: when the rule first fired, seconds into the drive, or None.
        cause: the first alarm's cause (parameters beyond their in-ODD levels, largest first; empty: none alone).
        error: why it could not be watched (a :class:`WatchError`'s line), or None.
        mlflow_run: the id of its MLflow run, or None.
    """

    name: str
    out: Path
    frames: int = 0
    alarms: int = 0
    first_alarm_s: float | None = None
    cause: list[str] = field(default_factory=list)
    error: str | None = None
    mlflow_run: str | None = None

    @property
    def outside(self) -> bool:
        """Whether the drive left the sources' ODD (the rule raised an alarm)."""
        return self.alarms > 0

    @classmethod
    def of(cls, name: str, out: Path, result: Any, mlflow_run: str | None = None) -> DriveOutcome:
        """The outcome of a :class:`~components.watch.run.WatchResult`."""
        first = result.alarms[0] if result.alarms else None
        return cls(
            name,
            Path(out),
            int(result.frames["frame"].size),
            len(result.alarms),
            None if first is None else float(first.fired_s),
            [] if first is None else list(first.cause),
            None,
            mlflow_run,
        )


class DrivesLeftOdd(RuntimeError):
    """Drives of a watched folder left the sources' ODD, or could not be watched; the message names each one
    (:func:`exit_message`)."""


def exit_message(outcomes: Sequence[DriveOutcome], out: Path) -> str | None:
    """The one line of :class:`DrivesLeftOdd` for the drives watched in a run, or None when every one stayed inside.

    Example:
        >>> o = DriveOutcome("fog", Path("w/fog"), 200, 1, 3.5, ["fog_density"])
        >>> exit_message([DriveOutcome("clear", Path("w/clear"), 200), o], Path("w"))
        '1 of 2 drives left the ODD of the sources: fog at 3.5 s (fog_density) (reports in w)'
    """
    outside = [o for o in outcomes if o.outside]
    broken = [o for o in outcomes if o.error is not None]
    if not outside and not broken:
        return None
    parts = []
    if outside:
        each = ", ".join(
            f"{o.name} at {o.first_alarm_s:.1f} s ({', '.join(o.cause) or 'no single parameter'})" for o in outside
        )
        parts.append(f"{len(outside)} of {len(outcomes)} drives left the ODD of the sources: {each}")
    if broken:
        parts.append(f"{len(broken)} could not be watched: " + "; ".join(f"{o.name}: {o.error}" for o in broken))
    return "; ".join(parts) + f" (reports in {out})"
