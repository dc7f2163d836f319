"""components.core.files: atomic file and folder replacement, file hashes."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time

import pytest

import components.core.files as files
from components.core.config import PROJECT_ROOT
from components.core.files import (
    ATOMIC_FOLDER_LEFTOVER,
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


@pytest.fixture(params=[True, False], ids=["exchange", "two-renames"])
def exchange(request, monkeypatch):
    """Both ways :func:`atomic_folder` puts a folder in place: Linux's one-step exchange, the two renames elsewhere."""
    monkeypatch.setattr(files, "USE_RENAME_EXCHANGE", request.param)
    return request.param


def test_atomic_folder_swaps_a_whole_folder(tmp_path, exchange):
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


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="renameat2 is Linux's")
def test_exchange_swaps_two_folders_in_one_step_on_linux(tmp_path, monkeypatch):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (a / "x").write_text("a")
    (b / "x").write_text("b")
    if files._renameat2() is None:
        pytest.skip("no renameat2 in this libc")
    if not files._exchange(a, b):
        pytest.skip("this file system cannot exchange")
    assert (a / "x").read_text() == "b" and (b / "x").read_text() == "a"
    with pytest.raises(FileNotFoundError):  # a real failure is an error, not a silent fall back
        files._exchange(a, tmp_path / "missing")
    monkeypatch.setattr(files, "USE_RENAME_EXCHANGE", False)  # the switch the tests of the fallback use
    assert files._exchange(a, b) is False and (a / "x").read_text() == "b"


def _folder(path, **content):
    path.mkdir(parents=True)
    for name, text in content.items():
        (path / name).write_text(text)
    return path


def test_atomic_folder_puts_back_the_folder_a_kill_between_its_two_renames_left(tmp_path, exchange):
    """Killed between ``target → .<name>.<8 hex>.old/<name>`` and ``.tmp → target``: no ``target``; the next start
    puts the previous folder back (old content, whole) and removes the leftovers."""
    target = tmp_path / "model"
    _folder(tmp_path / ".model.abcd1234.old" / "model", **{"card.json": "old"})
    _folder(tmp_path / ".model.0f0f0f0f.tmp", **{"card.json": "new, maybe half"})
    with pytest.raises(_Boom), atomic_folder(target) as tmp:
        assert (target / "card.json").read_text() == "old"  # recovered before the block starts
        assert sorted(os.listdir(tmp_path)) == sorted(["model", tmp.name])
        raise _Boom()
    assert os.listdir(tmp_path) == ["model"] and (target / "card.json").read_text() == "old"

    with atomic_folder(target) as tmp:
        (tmp / "card.json").write_text("new")
    assert os.listdir(tmp_path) == ["model"] and os.listdir(target) == ["card.json"]
    assert (target / "card.json").read_text() == "new"


def test_atomic_folder_removes_its_leftovers_and_nothing_else(tmp_path, exchange):
    """With ``target`` in place, every ``.<name>.<8 hex>.tmp|old`` folder of that target is a leftover (a kill while
    writing, after the swap, during a removal), the previous versions' mkdtemp names included; the rest stays."""
    target = _folder(tmp_path / "model", **{"card.json": "current"})
    leftovers = [
        _folder(tmp_path / ".model.abcd1234.tmp", **{"half.onnx": "x"}),  # killed while writing
        _folder(tmp_path / ".model.1234abcd.tmp", **{"card.json": "older"}),  # killed after the exchange
        _folder(tmp_path / ".model.deadbeef.old" / "model", **{"card.json": "older"}).parent,  # after the renames
        _folder(tmp_path / ".model.ab_cd9yz.old"),  # tempfile.mkdtemp's names (earlier versions), empty
    ]
    keep = [
        _folder(tmp_path / ".other.abcd1234.tmp"),  # another target's
        _folder(tmp_path / ".model.abcd123.tmp"),
        _folder(tmp_path / ".model.ABCD1234.tmp"),
        _folder(tmp_path / ".model.abcd1234.bak"),
        _folder(tmp_path / "model.abcd1234.tmp"),
        _folder(tmp_path / ".model.tmp"),
    ]
    (tmp_path / ".model.cafe0123.tmp").write_text("a file: atomic_path's, not atomic_folder's")
    keep.append(tmp_path / ".model.cafe0123.tmp")
    assert all(ATOMIC_FOLDER_LEFTOVER.match(p.name)["name"] == "model" for p in leftovers)
    with atomic_folder(target) as tmp:
        assert not any(p.exists() for p in leftovers) and all(p.exists() for p in keep)
        assert (target / "card.json").read_text() == "current"
        (tmp / "card.json").write_text("new")
    assert sorted(os.listdir(tmp_path)) == sorted(["model", *(p.name for p in keep)])
    assert (target / "card.json").read_text() == "new"


def test_atomic_folder_keeps_previous_folders_it_cannot_order(tmp_path):
    """No ``target`` and two ``.old`` holding one: which is the latest is unknown, so neither is put back or
    removed (one writer per target makes this impossible; a person decides)."""
    target = tmp_path / "model"
    olds = [
        _folder(tmp_path / f".model.{h}.old" / "model", **{"card.json": h}).parent for h in ("aaaa1111", "bbbb2222")
    ]
    with pytest.raises(_Boom), atomic_folder(target):
        raise _Boom()
    assert not target.exists() and all((p / "model" / "card.json").exists() for p in olds)


def test_atomic_folder_survives_a_sigkill_inside_the_block(tmp_path, exchange):
    """A real kill: the writer is SIGKILLed while its new folder is half written. The target keeps the old content,
    whole; the next writer removes the leftover folder and puts its own in place."""
    folder = tmp_path / "registry"
    target = _folder(folder / "model", **{"card.json": "old"})
    marker = tmp_path / "marker"
    code = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "import components.core.files as files\n"
        "files.USE_RENAME_EXCHANGE = sys.argv[3] == '1'\n"
        "with files.atomic_folder(sys.argv[1]) as tmp:\n"
        "    (tmp / 'card.json').write_text('new, half')\n"
        "    Path(sys.argv[2]).write_text(tmp.name)\n"
        "    time.sleep(120)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(PROJECT_ROOT)}
    args = [sys.executable, "-c", code, str(target), str(marker), "1" if exchange else "0"]
    proc = subprocess.Popen(args, cwd=PROJECT_ROOT, env=env)
    try:
        deadline = time.monotonic() + 60
        while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert marker.exists(), f"the writer did not reach its block (exit status {proc.poll()})"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    left = marker.read_text()
    assert sorted(os.listdir(folder)) == sorted(["model", left]) and ATOMIC_TEMP.match(left)
    assert (target / "card.json").read_text() == "old"

    with atomic_folder(target) as tmp:
        assert sorted(os.listdir(folder)) == sorted(["model", tmp.name])  # the killed writer's folder is gone
        (tmp / "card.json").write_text("new")
    assert os.listdir(folder) == ["model"] and (target / "card.json").read_text() == "new"


@pytest.mark.parametrize("fsync", [True, False])
def test_atomic_folder_flushes_a_nested_folder_and_leaves_it_whole(tmp_path, exchange, fsync):
    """With fsync every file and folder is flushed before the swap (links are not followed): the content is exact."""
    target = tmp_path / "model"
    data = {f"g{i}.onnx": os.urandom(1000 * i + 1) for i in range(3)}
    for _ in range(2):  # a new target, then over it
        with atomic_folder(target, fsync=fsync) as tmp:
            for name, b in data.items():
                (tmp / name).write_bytes(b)
            (tmp / "sub" / "deeper").mkdir(parents=True)
            (tmp / "sub" / "deeper" / "x.bin").write_bytes(b"x" * 5)
            (tmp / "link").symlink_to(tmp_path / "nowhere")  # a dangling link: not opened
        assert {n: (target / n).read_bytes() for n in data} == data
        assert (target / "sub" / "deeper" / "x.bin").read_bytes() == b"xxxxx" and (target / "link").is_symlink()
        assert os.listdir(tmp_path) == ["model"]


def test_atomic_path_never_makes_an_empty_file_of_a_temporary_file_removed_meanwhile(tmp_path):
    """The fsync opens the temporary file by name without creating it: if a clean-up removed it during the block,
    the write fails and the target keeps its content (not an empty file in its place)."""
    target = tmp_path / "draws.csv"
    target.write_text("old")
    with pytest.raises(FileNotFoundError), atomic_path(target) as tmp:
        tmp.write_text("new")
        tmp.unlink()
    assert target.read_text() == "old" and os.listdir(tmp_path) == ["draws.csv"]


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


def test_remove_stale_temps_cleans_the_folders_a_killed_atomic_folder_leaves(tmp_path):
    """A stage's clean-up handles :func:`atomic_folder`'s leftovers as its next start would: a previous folder left
    alone in ``.old`` goes back in place, the other leftover folders are removed, anything else stays."""
    _folder(tmp_path / ".a.abcd1234.old" / "a", **{"card.json": "a"})  # a: killed between the renames
    _folder(tmp_path / ".a.0123abcd.tmp", **{"card.json": "a, new"})
    _folder(tmp_path / "b", **{"card.json": "b"})  # b: killed while writing
    _folder(tmp_path / ".b.fedc9876.tmp")
    keep = [_folder(tmp_path / ".c.abcd1234.bak"), _folder(tmp_path / "sub" / ".d.abcd1234.tmp").parent]
    removed = remove_stale_temps(tmp_path)
    assert sorted(p.name for p in removed) == [".a.0123abcd.tmp", ".a.abcd1234.old", ".b.fedc9876.tmp"]
    assert (tmp_path / "a" / "card.json").read_text() == "a" and (tmp_path / "b" / "card.json").read_text() == "b"
    assert sorted(os.listdir(tmp_path)) == sorted(["a", "b", *(p.name for p in keep)])
    assert (tmp_path / "sub" / ".d.abcd1234.tmp").is_dir()
