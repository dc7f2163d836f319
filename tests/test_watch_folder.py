"""components/watch/folder.py, the pieces of the scheduled watch of a folder of drives (flows/watch.py), on folders
whose answers are known; the flow itself runs as a deployment in tests/test_deployments.py."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from components.watch import folder
from components.watch.errors import WatchError


def _drive(path: Path, frames: int = 3) -> Path:
    path.mkdir(parents=True)
    for k in range(frames):
        (path / f"{k:06d}.png").write_bytes(b"png" * (k + 1))
    (path / "times.csv").write_text("image,time_s\n")
    return path


def test_the_drives_of_a_folder_are_its_folders_and_videos_in_natural_name_order(tmp_path) -> None:
    for name in ("drive10", "drive2", ".drive3.0123abcd.tmp"):  # the last: a drive still being written
        _drive(tmp_path / name)
    (tmp_path / "today.MKV").write_bytes(b"video")
    (tmp_path / "today.weather.csv").write_text("image,time_s\n")  # a video's truth: not a drive
    (tmp_path / "notes.txt").write_text("not a drive")
    assert [p.name for p in folder.list_drives(tmp_path)] == ["drive2", "drive10", "today.MKV"]
    with pytest.raises(WatchError, match="no such folder"):
        folder.list_drives(tmp_path / "missing")
    with pytest.raises(WatchError, match="not a folder"):
        folder.list_drives(tmp_path / "notes.txt")


def test_the_fingerprint_changes_with_the_files_not_with_reading_them(tmp_path) -> None:
    drive = _drive(tmp_path / "d")
    before = folder.fingerprint(drive)
    for f in drive.iterdir():
        f.read_bytes()
    assert folder.fingerprint(drive) == before
    frame = drive / "000001.png"
    st = frame.stat()
    os.utime(frame, ns=(st.st_atime_ns, st.st_mtime_ns + 1))  # touched: rewritten with the same bytes
    touched = folder.fingerprint(drive)
    assert touched != before
    (drive / "000003.png").write_bytes(b"new")
    grown = folder.fingerprint(drive)
    assert grown not in (before, touched)
    (drive / ".hidden").write_bytes(b"x")  # hidden files are not the drive's
    assert folder.fingerprint(drive) == grown
    # a video's sidecars are part of it
    video = tmp_path / "v.avi"
    video.write_bytes(b"video")
    alone = folder.fingerprint(video)
    (tmp_path / "v.weather.csv").write_text("image,time_s\n")
    assert folder.drive_files(video) == [video, tmp_path / "v.weather.csv"]
    assert folder.fingerprint(video) != alone


def test_a_watch_is_found_by_its_key_whatever_uri_named_the_version(tmp_path) -> None:
    model = {"uri": "models:/pidc@champion", "name": "pidc", "version": "3", "id": "cues-2000"}
    key = folder.watch_key("abc", model, {"clear": "s1"}, {"window": 10, "decay": None})
    out = tmp_path / "out" / "d"
    assert not folder.already_watched(out, key)  # no summary
    out.mkdir(parents=True)
    (out / "summary.json").write_text("{not json")
    assert not folder.already_watched(out, key)  # unreadable: watched again
    folder.write_summary(out / "summary.json", {"drive": {}, "watched": key | {"mlflow_run": "r1"}})
    assert folder.already_watched(out, key)
    assert folder.already_watched(out, key | {"model": model | {"uri": "models:/pidc/3"}})  # the same version
    for changed in (
        {"fingerprint": "abd"},
        {"model": model | {"version": "4"}},
        {"sources": {"clear": "s2"}},
        {"settings": {"window": 20, "decay": None}},
    ):
        assert not folder.already_watched(out, key | changed), changed
    assert json.loads((out / "summary.json").read_text())["watched"]["mlflow_run"] == "r1"


def test_outputs_and_sources_must_lie_outside_the_folder_of_drives(tmp_path) -> None:
    drives, sources = tmp_path / "drives", tmp_path / "sources"
    folder.check_layout(drives, tmp_path / "reports", [sources / "a", sources / "b"])
    with pytest.raises(WatchError, match="out .* lies in the folder of drives"):
        folder.check_layout(drives, drives / "reports", [sources / "a"])
    with pytest.raises(WatchError, match="source .* lies in the folder of drives"):
        folder.check_layout(drives, tmp_path / "reports", [drives / "a"])
    with pytest.raises(WatchError, match="given twice"):
        folder.check_layout(drives, tmp_path / "reports", [sources / "a", sources / "a"])
    assert folder.source_names([sources / "a", tmp_path / "v.mkv"]) == ["a", "v"]
    assert folder.source_names([sources / "a", tmp_path / "a.mkv"]) == [str(sources / "a"), str(tmp_path / "a.mkv")]


def test_the_message_names_every_drive_that_left_or_could_not_be_watched() -> None:
    out = Path("reports/watch")
    inside = folder.DriveOutcome("inside", out / "inside", 200)
    fog = folder.DriveOutcome("fog", out / "fog", 200, 2, 1.7, ["fog_density", "cloudiness"])
    dusk = folder.DriveOutcome("dusk", out / "dusk", 300, 1, 12.0, [])
    broken = folder.DriveOutcome("cut.mkv", out / "cut.mkv", error="cut.mkv: truncated video")
    assert folder.exit_message([inside], out) is None
    assert not inside.outside and fog.outside
    assert folder.exit_message([inside, fog, dusk, broken], out) == (
        "2 of 4 drives left the ODD of the sources: fog at 1.7 s (fog_density, cloudiness), dusk at 12.0 s (no single "
        "parameter); 1 could not be watched: cut.mkv: cut.mkv: truncated video (reports in reports/watch)"
    )
