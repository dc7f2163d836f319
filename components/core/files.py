"""Files written atomically and identified by their SHA-256 (standard library only).

Every atomic write in pidc goes through :func:`atomic_path` (one file) or :func:`atomic_folder` (a whole folder): the
content is written under a temporary name beside the target and renamed over it with ``os.replace`` (atomic on POSIX
and Windows within one file system), so a reader sees either the old or the new content, whole, and an error or a
killed process leaves the target as it was. Temporary names start with ``.<target name>.`` and end with ``.tmp``, so
the clean-ups that remove ``.<stem>…`` leftovers next to their files still find them. With ``fsync=True`` (the
default) the content and the rename are flushed to disk (file(s), then the folder that holds the new name), so a power
loss too leaves the old or the new content.

A killed :func:`atomic_folder` may leave ``.<name>.<8 hex>.tmp`` / ``.<name>.<8 hex>.old`` folders (and, killed between
the two renames of its fallback, the previous folder alone in ``.<name>.<8 hex>.old/<name>``): the next
:func:`atomic_folder` on that target, or :func:`remove_stale_temps` on its folder, puts the previous folder back and
removes the rest.

Used by every stage and the ``pidc`` CLI.
"""

from __future__ import annotations

import ctypes
import errno
import functools
import hashlib
import os
import re
import secrets
import shutil
import stat
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "ATOMIC_TEMP",
    "ATOMIC_FOLDER_LEFTOVER",
    "atomic_path",
    "atomic_folder",
    "atomic_write_bytes",
    "remove_stale_temps",
    "sha256_file",
]

#: The temporary names of :func:`atomic_path`: ``.<target name>.<8 hex>.tmp`` beside the target.
ATOMIC_TEMP = re.compile(r"^\.(?P<name>.+)\.[0-9a-f]{8}\.tmp$")
#: The folders :func:`atomic_folder` makes beside its target: ``.<name>.<8 hex>.tmp`` (the new content) and
#: ``.<name>.<8 hex>.old`` (the previous folder on its way out, as ``.<name>.<8 hex>.old/<name>``). Earlier versions
#: named them with :func:`tempfile.mkdtemp` (8 characters of ``[a-z0-9_]``), which the pattern covers too.
ATOMIC_FOLDER_LEFTOVER = re.compile(r"^\.(?P<name>.+)\.[a-z0-9_]{8}\.(?P<kind>tmp|old)$")

#: Swap folders in one step with Linux's ``renameat2(RENAME_EXCHANGE)`` where the system and file system allow it;
#: False: always the two renames of the fallback (for tests).
USE_RENAME_EXCHANGE = True
_AT_FDCWD = -100
_RENAME_EXCHANGE = 2
#: renameat2 answers these where the kernel, libc or file system cannot exchange: fall back to two renames.
_NO_EXCHANGE = {errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP}


def _fsync_dir(folder: str | os.PathLike[str]) -> None:
    """Flush a folder's entries (a rename into it, a new file) to disk. Windows cannot open a folder to fsync it (its
    file systems journal the rename): nothing there."""
    if os.name == "nt":
        return
    fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_tree(folder: Path) -> None:
    """fsync every regular file below ``folder`` (links not followed), then every folder, ``folder`` itself last."""
    flags = os.O_RDWR if os.name == "nt" else os.O_RDONLY  # Windows' fsync (_commit) needs a writable handle
    for root, _dirs, files in os.walk(folder, topdown=False):
        for name in files:
            path = os.path.join(root, name)
            if not stat.S_ISREG(os.lstat(path).st_mode):
                continue
            fd = os.open(path, flags | getattr(os, "O_BINARY", 0))
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        _fsync_dir(root)


@functools.cache
def _renameat2() -> Callable[..., int] | None:
    """libc's ``renameat2`` (Linux, glibc ≥ 2.28 or musl ≥ 1.2.5), or None where there is none."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


def _exchange(a: Path, b: Path) -> bool:
    """Swap the names ``a`` and ``b`` (both existing) in one atomic step; False, with nothing done, where that is not
    available (not Linux, no ``renameat2``, a file system without ``RENAME_EXCHANGE``, :data:`USE_RENAME_EXCHANGE`
    off); ``OSError`` on any other failure."""
    fn = _renameat2() if USE_RENAME_EXCHANGE else None
    if fn is None:
        return False
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in _NO_EXCHANGE:
        return False
    raise OSError(err, os.strerror(err), str(a), None, str(b))


def _leftovers(folder: Path) -> dict[str, list[Path]]:
    """The :data:`ATOMIC_FOLDER_LEFTOVER` folders (not links) directly in ``folder``, by target name."""
    out: dict[str, list[Path]] = {}
    with os.scandir(folder) as entries:
        for e in entries:
            m = ATOMIC_FOLDER_LEFTOVER.match(e.name)
            if m and e.is_dir(follow_symlinks=False):
                out.setdefault(m["name"], []).append(Path(e.path))
    return {name: sorted(paths) for name, paths in out.items()}


def _recover_folder(target: Path, leftovers: list[Path], *, fsync: bool = True) -> list[Path]:
    """Undo what a killed :func:`atomic_folder` on ``target`` left (``leftovers``: its ``.tmp``/``.old`` folders): with
    no ``target`` and one ``.old`` holding the previous folder, that folder goes back to ``target``; then the
    leftovers are removed (when ``target`` is missing and several ``.old`` hold a previous folder, which one is the
    latest is unknown: those are kept). Returns the leftovers removed."""
    olds = [p for p in leftovers if p.name.endswith(".old") and os.path.lexists(p / target.name)]
    keep: set[Path] = set()
    if not os.path.lexists(target):
        if len(olds) == 1:
            os.replace(olds[0] / target.name, target)
            if fsync:
                _fsync_dir(target.parent)
        else:
            keep.update(olds)
    removed = [p for p in leftovers if p not in keep]
    for p in removed:
        shutil.rmtree(p, ignore_errors=True)
    return removed


def _new_sibling(target: Path, suffix: str) -> Path:
    """A new empty private folder ``.<target name>.<8 hex><suffix>`` beside ``target`` (a name no one else has)."""
    while True:
        path = target.with_name(f".{target.name}.{secrets.token_hex(4)}{suffix}")
        try:
            os.mkdir(path, 0o700)
            return path
        except FileExistsError:
            continue


@contextmanager
def atomic_path(target: str | os.PathLike[str], *, fsync: bool = True) -> Iterator[Path]:
    """A temporary file path beside ``target`` that replaces ``target`` when the ``with`` block succeeds.

    The parent folder is created if needed. The temporary file exists (empty, with the permissions a plain
    ``open(…, "w")`` would give) when the block starts; write it by name (``open(tmp, "wb")``, ``torch.save``,
    ``savefig``…) and close it inside the block. On success it is flushed to disk (``fsync=True``), renamed over
    ``target``, and the rename flushed too (an fsync of the parent folder; not on Windows, which cannot open a
    folder); on any exception (``KeyboardInterrupt`` included) it is removed and ``target`` is left untouched.

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
        if fsync:  # by name, never created anew: a temporary file someone removed meanwhile is an error, not b""
            fd = os.open(tmp, os.O_WRONLY | os.O_APPEND | getattr(os, "O_BINARY", 0))
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        os.replace(tmp, target)
        if fsync:
            _fsync_dir(target.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_folder(target: str | os.PathLike[str], *, fsync: bool = True) -> Iterator[Path]:
    """A fresh temporary folder beside ``target`` that replaces the folder ``target`` when the ``with`` block succeeds.

    One writer per ``target`` at a time: it starts by undoing what a killed writer of ``target`` left (its previous
    folder put back when only that is left; its ``.<name>.<8 hex>.tmp``/``.old`` folders removed, see
    :data:`ATOMIC_FOLDER_LEFTOVER`), which would remove a live writer's folder too.

    On success every file and folder in the temporary folder is flushed to disk (``fsync=True``), the folder (mode
    0o755) takes ``target``'s place and the parent folder is flushed. An existing ``target`` is swapped with it in one
    step where Linux's ``renameat2(RENAME_EXCHANGE)`` works, so a reader always finds a whole ``target``, old or new;
    elsewhere it is first moved aside into ``.<name>.<8 hex>.old/`` (put back if the second rename fails), so a reader
    may find no ``target`` for an instant, and a kill between the renames leaves the previous folder there, put back
    by the next start. The previous folder is then removed. On any exception the temporary folder and all it holds
    are removed and ``target`` is left untouched.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    _recover_folder(target, _leftovers(target.parent).get(target.name, []), fsync=fsync)
    tmp = _new_sibling(target, ".tmp")
    try:
        yield tmp
        os.chmod(tmp, 0o755)  # private while written; the folder is meant to be read
        if fsync:
            _fsync_tree(tmp)
        previous: Path | None = None  # what holds the previous folder once the new one is in place
        if not os.path.lexists(target):
            os.replace(tmp, target)
        elif _exchange(tmp, target):
            previous = tmp
        else:
            previous = _new_sibling(target, ".old")
            try:
                os.replace(target, previous / target.name)
                try:
                    os.replace(tmp, target)
                except BaseException:
                    os.replace(previous / target.name, target)
                    raise
            except BaseException:
                shutil.rmtree(previous, ignore_errors=True)
                raise
        if fsync:
            _fsync_dir(target.parent)
        if previous is not None:
            shutil.rmtree(previous, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def remove_stale_temps(folder: str | os.PathLike[str]) -> list[Path]:
    """Delete what killed writers left directly in ``folder`` (not its subfolders), e.g. a checkpoint cut short by a
    kill; returns the paths removed. The temporary files of :func:`atomic_path` (:data:`ATOMIC_TEMP`) are removed;
    the leftover folders of :func:`atomic_folder` (:data:`ATOMIC_FOLDER_LEFTOVER`) are cleaned as its next start
    would (a previous folder left alone in ``.<name>.<8 hex>.old/`` is put back first). Call it only where no other
    writer can be at work in the folder (a stage's start): a live writer's temporary file or folder looks the same."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    stale = sorted(f for f in folder.iterdir() if ATOMIC_TEMP.match(f.name) and f.is_file())
    for f in stale:
        f.unlink(missing_ok=True)
    for name, leftovers in _leftovers(folder).items():
        stale += _recover_folder(folder / name, leftovers)
    return stale


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (:func:`atomic_path`: temporary file, fsync, rename)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def sha256_file(path: str | Path) -> str:
    """The SHA-256 (hex) of a file's bytes (:func:`hashlib.file_digest`)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()
