"""Results kept between runs (components.core.kept): written whole or not at all, read back only when whole and under
their key, restored byte for byte, pruned to the current keys."""

from __future__ import annotations

import json

import pytest

from components.core import kept


def _make(files):
    (files / "a.png").write_bytes(b"\x89PNG a")
    (files / "b.txt").write_text("b")
    return {"x": 1.5, "nan": float("nan"), "list": [1, 2]}


def test_keep_read_restore(tmp_path):
    folder = tmp_path / "model"
    path = kept.keep(folder, "k1", _make, {"seed": 1})
    assert path == folder / "k1"
    entry = kept.read(folder, "k1")
    assert entry["parts"] == {"seed": 1} and entry["result"]["x"] == 1.5 and entry["result"]["nan"] != 0
    assert kept.read(folder, "k2") is None, "another key: nothing kept"
    dest = tmp_path / "reports" / "plots"
    assert kept.restore(folder, "k1", entry, dest)["list"] == [1, 2]
    assert {f.name: f.read_bytes() for f in dest.iterdir()} == {"a.png": b"\x89PNG a", "b.txt": b"b"}
    # a new key replaces the model's other keys
    kept.keep(folder, "k2", _make, {"seed": 2})
    assert [p.name for p in folder.iterdir()] == ["k2"]


def test_a_failed_make_keeps_nothing(tmp_path):
    def broken(files):
        (files / "half.png").write_bytes(b"half")
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError):
        kept.keep(tmp_path / "m", "k", broken, {})
    assert kept.read(tmp_path / "m", "k") is None and list((tmp_path / "m").iterdir()) == []


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda e: (e / "entry.json").write_text('{"format": 1, "ke'), "entry.json does not parse"),
        (lambda e: (e / "entry.json").unlink(), "no readable entry.json"),
        (lambda e: (e / "files" / "a.png").write_bytes(b"other"), "file 'a.png' is missing or differs"),
        (lambda e: (e / "files" / "b.txt").unlink(), "file 'b.txt' is missing or differs"),
        (
            lambda e: (e / "entry.json").write_text(
                json.dumps(json.loads((e / "entry.json").read_text()) | {"key": "x"})
            ),
            "not an entry of format 1 under this key",
        ),
        (
            lambda e: (e / "entry.json").write_text(
                json.dumps(json.loads((e / "entry.json").read_text()) | {"format": 0})
            ),
            "not an entry of format 1 under this key",
        ),
    ],
)
def test_a_damaged_entry_is_refused_with_what_is_wrong(tmp_path, damage, message):
    entry = kept.keep(tmp_path / "m", "k", _make, {})
    damage(entry)
    with pytest.raises(kept.KeptError, match=message):
        kept.read(tmp_path / "m", "k")


def test_prune_keeps_the_current_keys_only(tmp_path):
    root = tmp_path / "task1"
    kept.keep(root / "a", "ka", _make, {})
    kept.keep(root / "b", "kb", _make, {})
    (root / "a" / "old-key").mkdir()
    removed = kept.prune(root, {"a": "ka"})
    assert sorted(p.relative_to(root).as_posix() for p in removed) == ["a/old-key", "b"]
    assert [p.name for p in root.iterdir()] == ["a"] and [p.name for p in (root / "a").iterdir()] == ["ka"]
    assert kept.prune(tmp_path / "none", {}) == []
