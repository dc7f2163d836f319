"""components.core.files: atomic file and folder replacement, file hashes."""

from __future__ import annotations

import hashlib
import os

import pytest

from components.core.files import (
    ATOMIC_TEMP,
    atomic_folder,
    atomic_path,
    atomic_write_bytes,
    remove_stale_temps,
    sha256_file,
)


class _Boom(Exception):
    pass


def test_atomic_path_replaces_the_target_only_at_the_end(tmp_path):
    target = tmp_path / "sub" / "out.bin"  # the folder is created
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent and tmp.name.startswith(".out.bin.") and tmp.exists()
        tmp.write_bytes(b"new")
        assert not target.exists()  # nothing visible before the block ends
    assert target.read_bytes() == b"new"
    assert os.listdir(target.parent) == ["out.bin"]
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask  # as a plain open() would make it

    with atomic_path(target) as tmp:  # over an existing file
        tmp.write_bytes(b"newer")
    assert target.read_bytes() == b"newer"
    assert os.listdir(target.parent) == ["out.bin"]


@pytest.mark.parametrize("error", [_Boom, KeyboardInterrupt])
def test_atomic_path_leaves_the_old_target_and_no_temporary_file_on_error(tmp_path, error):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(error):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise error()
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["out.bin"]


def test_atomic_write_bytes_writes_exactly_the_bytes(tmp_path):
    data = bytes(range(256)) * 1000
    atomic_write_bytes(tmp_path / "a" / "b.bin", data)
    assert (tmp_path / "a" / "b.bin").read_bytes() == data
    atomic_write_bytes(tmp_path / "a" / "b.bin", b"")
    assert (tmp_path / "a" / "b.bin").read_bytes() == b""
    assert os.listdir(tmp_path / "a") == ["b.bin"]


def test_atomic_folder_swaps_a_whole_folder(tmp_path):
    target = tmp_path / "model"
    with atomic_folder(target) as tmp:
        (tmp / "a.txt").write_text("1")
        assert not target.exists()
    assert sorted(os.listdir(target)) == ["a.txt"] and target.stat().st_mode & 0o777 == 0o755

    with atomic_folder(target) as tmp:  # an existing folder is replaced as a whole: a.txt does not survive
        (tmp / "b.txt").write_text("2")
    assert sorted(os.listdir(target)) == ["b.txt"]
    assert os.listdir(tmp_path) == ["model"]

    with pytest.raises(_Boom):
        with atomic_folder(target) as tmp:
            (tmp / "c.txt").write_text("3")
            raise _Boom()
    assert sorted(os.listdir(target)) == ["b.txt"]
    assert os.listdir(tmp_path) == ["model"]


@pytest.mark.parametrize("size", [0, 1, (1 << 20) + 17])
def test_sha256_file_matches_hashlib(tmp_path, size):
    data = os.urandom(size)
    path = tmp_path / "f.bin"
    path.write_bytes(data)
    assert sha256_file(path) == hashlib.sha256(data).hexdigest()
    assert sha256_file(str(path)) == hashlib.sha256(data).hexdigest()


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_draws_writer_appears_on_close_and_leaves_nothing_on_discard(tmp_path, suffix):
    import numpy as np

    from components.cli.drawsfile import DrawsWriter

    target = tmp_path / f"draws{suffix}"
    target.write_bytes(b"old")
    writer = DrawsWriter(target, ["a", "b"])
    writer.write("img", np.zeros((3, 2)))
    writer.discard()
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == [target.name]

    with pytest.raises(_Boom), DrawsWriter(target, ["a", "b"]) as writer:
        writer.write("img", np.zeros((3, 2)))
        raise _Boom()
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == [target.name]

    with DrawsWriter(target, ["a", "b"]) as writer:
        writer.write("img", np.ones((3, 2)))
    assert target.read_bytes() != b"old" and writer.rows == 3 and os.listdir(tmp_path) == [target.name]
    if suffix == ".csv":
        assert target.read_text().splitlines() == ["image,draw,a,b"] + [f"img,{i},1.0,1.0" for i in range(3)]


def test_remove_stale_temps_takes_only_the_temporary_files_a_killed_writer_leaves(tmp_path):
    """A write killed inside :func:`atomic_path` leaves its ``.<name>.<8 hex>.tmp``; the clean-up at a stage's start
    removes those (and only those: targets, other dotfiles, subfolders and look-alikes stay)."""
    with pytest.raises(KeyboardInterrupt), atomic_path(tmp_path / "model.pt") as tmp:
        tmp.write_bytes(b"half")
        left = tmp.with_name(tmp.name + ".copy")  # what a SIGKILL would leave: the temporary file itself
        left.write_bytes(b"half")
        raise KeyboardInterrupt
    stale = tmp_path / left.name.removesuffix(".copy")
    left.rename(stale)
    assert ATOMIC_TEMP.match(stale.name)["name"] == "model.pt"
    keep = [tmp_path / n for n in ("model.pt", ".hidden", ".model.pt.tmp", ".x.0123456.tmp", "a.0123abcd.tmp")]
    for f in keep:
        f.write_bytes(b"keep")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / ".y.0123abcd.tmp").write_bytes(b"not this folder")
    assert remove_stale_temps(tmp_path) == [stale]
    assert all(f.exists() for f in keep) and (tmp_path / "sub" / ".y.0123abcd.tmp").exists() and not stale.exists()
    assert remove_stale_temps(tmp_path / "missing") == []
