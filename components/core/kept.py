"""Results kept between runs, keyed by what made them (standard library only).

A stage whose outputs DVC removes when it starts (a non-persist out) loses every finished part of its work when it is
killed. Such a stage keeps each part — a result (JSON) and the files it made — in a folder of its own outside its
outputs, ``<folder>/<key>/``, where ``key`` is a hash of everything the part depends on (its inputs, settings and code:
:func:`components.core.code.code_fingerprint`); a later run with the same key reads it back instead of redoing it. A
kept entry is written atomically (:func:`components.core.files.atomic_folder`: a kill leaves none, never half of one)
and checked whole when read (its format, its key, every file's SHA-256): an entry that fails is an error the caller
reports and redoes, never trusted.

Layout: ``<folder>/<key>/entry.json`` (``format``, ``key``, ``parts``: what the key hashes, for a reader; ``files``:
name → SHA-256; ``result``) and ``<folder>/<key>/files/<name>``.

Used by the ``evaluate`` stage (``.cache/task1/<model>/<key>/``: a model's Task I result and plots).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from components.core.files import atomic_folder, atomic_write_bytes, sha256_file

__all__ = ["FORMAT", "KeptError", "keep", "read", "restore", "prune"]

#: The layout of an entry (checked when read: another layout is never read as this one).
FORMAT = 1
ENTRY, FILES = "entry.json", "files"


class KeptError(ValueError):
    """A kept entry that is incomplete, unreadable, or not the one its folder names: never trusted."""


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def keep(folder: Path, key: str, make: Callable[[Path], Any], parts: Mapping[str, Any]) -> Path:
    """Run ``make(files)`` — the work, writing its files into the folder ``files`` and returning its result (JSON:
    NaN and infinities as Python's json writes them) — inside a temporary folder that becomes ``<folder>/<key>/``
    once it is complete, with ``entry.json`` (``parts``: what ``key`` hashes); then remove ``folder``'s entries of
    other keys and what killed writes left. Returns ``<folder>/<key>``."""
    with atomic_folder(folder / key) as tmp:
        (tmp / FILES).mkdir()
        result = make(tmp / FILES)
        files = {f.name: sha256_file(f) for f in sorted((tmp / FILES).iterdir()) if f.is_file()}
        entry = {"format": FORMAT, "key": key, "parts": dict(parts), "files": files, "result": result}
        atomic_write_bytes(tmp / ENTRY, json.dumps(entry, indent=1).encode())
    for other in folder.iterdir():
        if other.name != key:
            _remove(other)
    return folder / key


def read(folder: Path, key: str) -> dict[str, Any] | None:
    """The entry kept in ``<folder>/<key>/`` (its ``entry.json`` as a dict: ``result``, ``files``, ``parts``), checked
    whole, or None when there is none. :class:`KeptError` naming what is wrong when it is incomplete or unreadable,
    of another format or key, or a file is missing or differs from its SHA-256."""
    entry_folder = folder / key
    if not entry_folder.is_dir():
        return None
    try:
        entry = json.loads((entry_folder / ENTRY).read_text())
    except OSError as e:
        raise KeptError(f"{entry_folder}: no readable {ENTRY} ({e.strerror or e})") from None
    except ValueError as e:
        raise KeptError(f"{entry_folder}: {ENTRY} does not parse ({e})") from None
    if not isinstance(entry, dict) or (entry.get("format"), entry.get("key")) != (FORMAT, key):
        raise KeptError(f"{entry_folder}: {ENTRY} is not an entry of format {FORMAT} under this key")
    files = entry.get("files")
    if "result" not in entry or not isinstance(files, dict):
        raise KeptError(f"{entry_folder}: {ENTRY} holds no result or no list of files")
    for name, digest in files.items():
        path = entry_folder / FILES / name
        if Path(name).name != name or not path.is_file() or sha256_file(path) != digest:
            raise KeptError(f"{entry_folder}: file {name!r} is missing or differs from its sha256")
    return entry


def restore(folder: Path, key: str, entry: Mapping[str, Any], dest: Path, mode: int = 0o644) -> Any:
    """Copy the files of ``entry`` (:func:`read` of ``<folder>/<key>``) byte for byte into the folder ``dest``, which
    they replace whole, atomically (each file with ``mode``); returns the entry's result."""
    with atomic_folder(dest) as tmp:
        for name in sorted(entry["files"]):
            shutil.copyfile(folder / key / FILES / name, tmp / name)
            os.chmod(tmp / name, mode)
    return entry["result"]


def prune(root: Path, keys: Mapping[str, str]) -> list[Path]:
    """In ``root`` (one folder per item, e.g. per model), remove the folders of items not in ``keys`` (item → its
    current key) and, in the others, the entries of other keys and what killed writes left; returns what was removed.
    Call it at the end of a successful run only (a running one may still write)."""
    if not root.is_dir():
        return []
    removed = []
    for item in sorted(root.iterdir()):
        if item.name not in keys or not item.is_dir() or item.is_symlink():
            stale = [item]
        else:
            stale = [f for f in sorted(item.iterdir()) if f.name != keys[item.name]]
        for f in stale:
            _remove(f)
            removed.append(f)
    return removed
