"""Files written atomically and identified by their SHA-256 (standard library only).

Every atomic write in pidc goes through :func:`atomic_path` (one file) or :func:`atomic_folder` (a whole folder): the
content is written under a temporary name beside the target and renamed over it with ``os.replace`` (atomic on POSIX
and Windows within one file system), so a reader sees either the old or the new content, whole, and an error or a
killed process leaves the target as it was. Temporary names start with ``.<target name>.`` and end with ``.tmp``, so
the clean-ups that remove ``.<stem>…`` leftovers next to their files still find them.

Used by every stage and the ``pidc`` CLI.
"""

from __future__ import annotations

import hashlib
import os
import re
import secrets
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["ATOMIC_TEMP", "atomic_path", "atomic_folder", "atomic_write_bytes", "remove_stale_temps", "sha256_file"]

#: The temporary names of :func:`atomic_path`: ``.<target name>.<8 hex>.tmp`` beside the target.
ATOMIC_TEMP = re.compile(r"^\.(?P<name>.+)\.[0-9a-f]{8}\.tmp$")


@contextmanager
def atomic_path(target: str | os.PathLike[str], *, fsync: bool = True) -> Iterator[Path]:
    """A temporary file path beside ``target`` that replaces ``target`` when the ``with`` block succeeds.

    The parent folder is created if needed. The temporary file exists (empty, with the permissions a plain
    ``open(…, "w")`` would give) when the block starts; write it by name (``open(tmp, "wb")``, ``torch.save``,
    ``savefig``…) and close it inside the block. On success it is flushed to disk (``fsync=True``) and renamed over
    ``target``; on any exception (``KeyboardInterrupt`` included) it is removed and ``target`` is left untouched.

        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = target.with_name(f".{target.name}.{secrets.token_hex(4)}.tmp")
        try:  # O_EXCL: the name is ours alone (mode 0o666 less the umask, as a plain open() would create it)
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            break
        except FileExistsError:
            continue
    try:
        yield tmp
        if fsync:
            with open(tmp, "ab") as f:
                os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_folder(target: str | os.PathLike[str]) -> Iterator[Path]:
    """A fresh temporary folder beside ``target`` that replaces the folder ``target`` when the ``with`` block succeeds.

    On success the temporary folder (mode 0o755) takes ``target``'s place: an existing ``target`` is first moved aside,
    then removed (put back if the final rename fails). On any exception the temporary folder and all it holds are
    removed and ``target`` is left untouched. Two renames, not one: a reader may find no ``target`` for an instant,
    but never a half-written one.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o755)  # mkdtemp makes it private; the folder is meant to be read
        if not target.exists():
            os.replace(tmp, target)
            return
        old = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".old", dir=target.parent))
        os.replace(target, old / target.name)
        try:
            os.replace(tmp, target)
        except BaseException:
            os.replace(old / target.name, target)
            shutil.rmtree(old, ignore_errors=True)
            raise
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def remove_stale_temps(folder: str | os.PathLike[str]) -> list[Path]:
    """Delete the temporary files of :func:`atomic_path` (:data:`ATOMIC_TEMP`) that a killed writer left in
    ``folder`` (not its subfolders), e.g. a checkpoint cut short by a kill; returns them. Call it only where no other
    writer can be at work in the folder (a stage's start): a live writer's temporary file looks the same."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    stale = sorted(f for f in folder.iterdir() if f.is_file() and ATOMIC_TEMP.match(f.name))
    for f in stale:
        f.unlink(missing_ok=True)
    return stale


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (:func:`atomic_path`: temporary file, fsync, rename)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def sha256_file(path: str | Path) -> str:
    """The SHA-256 (hex) of a file's bytes (:func:`hashlib.file_digest`)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()
