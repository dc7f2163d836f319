"""Output files of the ``pidc`` commands, checked before any work: writable, not a folder, not one of the inputs; and
the one-line messages of the errors that reach :func:`components.cli.main.main` (a failed write, memory).

Used by the ``pidc`` CLI only.
"""

from __future__ import annotations

import argparse
import os
import re
import tempfile
from collections.abc import Iterable
from pathlib import Path

from components.cli.errors import CLIError
from components.core.files import ATOMIC_TEMP

__all__ = [
    "check_output",
    "check_outputs",
    "check_not_input",
    "os_error_line",
    "memory_error_line",
    "OUTPUT_OPTIONS",
    "SIZE_OPTIONS",
]

#: The commands' output options (argparse destinations → how the user wrote them), to name them in errors.
OUTPUT_OPTIONS: dict[str, str] = {
    "json": "--json",
    "corner": "--corner",
    "plot": "--plot",
    "samples_out": "--samples-out",
    "out": "-o",
    "write": "--write",
}
#: The options that size the arrays a command allocates (named when memory runs out).
SIZE_OPTIONS: dict[str, str] = {"samples": "--samples", "points": "--points", "draws_per_image": "--draws-per-image"}


def _existing_folder(path: Path) -> Path:
    """The nearest ancestor of ``path`` that exists (the folder a write would create the missing ones in)."""
    p = path.parent
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_output(path: Path | None, option: str) -> None:
    """A one-line :class:`CLIError` naming ``option`` and ``path`` unless a file can be written at ``path``: not a
    folder, below a folder (missing folders are made by the write), where a file can be created (a probe file named as
    :func:`components.core.files.atomic_path`'s temporary files, removed at once); then removes the temporary files
    a killed earlier write of ``path`` left (:func:`check_outputs`). Nothing when ``path`` is None."""
    check_outputs([(option, path)])


def check_outputs(outputs: Iterable[tuple[str, Path | None]]) -> list[Path]:
    """:func:`check_output` of each ``(option, path)`` pair, probing each folder once (e.g. one corner plot per
    image, all in one folder); then removes the temporary files an earlier run writing the same outputs left when it
    was killed (``.<name>.<8 hex>.tmp`` beside each output, :data:`components.core.files.ATOMIC_TEMP`; a
    ``--samples-out`` table may be large); other files are left alone. Another ``pidc`` writing the same output at
    the same time would lose its temporary file too (and fail, naming the file). Returns the files removed."""
    probed: set[Path] = set()
    named: list[Path] = []
    for option, path in outputs:
        if path is None:
            continue
        named.append(path)
        if path.is_dir():
            raise CLIError(f"{option} {path}: is a folder; give a file name")
        folder = _existing_folder(path)
        if not folder.is_dir():
            raise CLIError(f"{option} {path}: {folder} is a file, not a folder")
        if folder in probed:
            continue
        try:
            fd, probe = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
        except OSError as e:
            raise CLIError(f"{option} {path}: cannot write there ({e.strerror or e})") from None
        os.close(fd)
        os.unlink(probe)
        probed.add(folder)
    return _remove_stale_temps(named)


def _remove_stale_temps(paths: Iterable[Path]) -> list[Path]:
    """Delete the :data:`~components.core.files.ATOMIC_TEMP` files of ``paths`` (``.<name>.<8 hex>.tmp`` beside
    each, not links' targets nor folders) that can be deleted; the ones deleted."""
    by_folder: dict[Path, set[str]] = {}
    for path in paths:
        by_folder.setdefault(path.parent, set()).add(path.name)
    removed: list[Path] = []
    for folder, names in by_folder.items():
        try:
            with os.scandir(folder) as entries:
                stale = [
                    Path(e.path)
                    for e in entries
                    if (m := ATOMIC_TEMP.match(e.name)) and m["name"] in names and e.is_file(follow_symlinks=False)
                ]
        except OSError:  # a folder the write will create
            continue
        for f in sorted(stale):
            try:
                f.unlink()
            except OSError:  # gone meanwhile, or not ours to delete (a shared folder): the write does not need it
                continue
            removed.append(f)
    return removed


def check_not_input(outputs: Iterable[tuple[str, Path | None]], inputs: Iterable[Path]) -> None:
    """A :class:`CLIError` when an output path (``(option, path)`` pairs; None skipped) is one of the ``inputs`` (after
    resolving links and ``..``): writing it would replace the user's image."""
    given = {p.resolve() for p in inputs}
    for option, path in outputs:
        if path is not None and path.resolve() in given:
            raise CLIError(f"{option} {path} is one of the input images; choose another file name")


def _user_path(name: str | os.PathLike[str]) -> Path:
    """The file the user named behind ``name``: the target of an :func:`atomic_path` temporary name, else ``name``."""
    path = Path(name)
    m = ATOMIC_TEMP.match(path.name)
    return path.with_name(m["name"]) if m else path


def os_error_line(args: argparse.Namespace, error: OSError) -> str:
    """One line for an ``OSError`` that reached ``main``: the user's path (not a temporary name), the option that named
    it when one did, and the reason."""
    reason = error.strerror or str(error) or type(error).__name__
    name = error.filename2 or error.filename  # os.replace(temporary, target) names the target second
    if name is None:
        return reason
    path = _user_path(os.fsdecode(name) if isinstance(name, bytes) else name)
    for dest, option in OUTPUT_OPTIONS.items():
        value = getattr(args, dest, None)
        if value is not None and Path(value).absolute() == path.absolute():
            return f"{option} {value}: cannot write there ({reason})"
    return f"{path}: {reason}"


def memory_error_line(args: argparse.Namespace, error: MemoryError) -> str:
    """One line for a ``MemoryError``: how much numpy asked for (when it says) and the size options given."""
    m = re.search(r"allocate (\S+ \S+)", str(error))
    need = f" (could not allocate {m[1]})" if m else ""
    sizes = [f"{option} {getattr(args, dest)}" for dest, option in SIZE_OPTIONS.items() if hasattr(args, dest)]
    return f"out of memory{need}" + (f"; use smaller sizes: {', '.join(sizes)}" if sizes else "")
