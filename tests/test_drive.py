"""Simulated drives (`components.simulate.drive`, `pidc drive`): the walk's box and correlation, the events' ramps,
seeds, the first exit from a box, and the folder and video the command writes."""

from __future__ import annotations

import csv
import json
import math
import re

import cv2
import numpy as np
import pytest
from scipy import stats

from components.cli.main import main
from components.core.seeding import rng
from components.simulate.drive import (
    DEFAULT_HELD,
    DRIVEN,
    Drive,
    Dusk,
    Fog,
    Rain,
    event_from_dict,
    first_exit,
    read_weather_csv,
    uniform_ou,
    write_folder,
)

BOX = {
    "cloudiness": (10.0, 40.0),
    "fog_density": (0.0, 10.0),
    "sun_altitude_angle": (-5.0, 5.0),
    "wind_intensity": (0.0, 100.0),
    "sun_azimuth_angle": (90.0, 90.0),  # a degenerate box holds the parameter
}


def _lag_corr(x: np.ndarray, m: int) -> float:
    x = x - x.mean()
    return float(np.dot(x[m:], x[:-m]) / np.dot(x, x))


def test_the_walk_stays_inside_its_box_at_every_frame_and_the_rest_is_held():
    drive = Drive(seconds=3600, seed=7, box=BOX, held={"precipitation": 30.0}, correlation_s=5.0)
    table = drive.weather_table()
    assert table["time_s"].shape == (36_000,)
    for name, (low, high) in BOX.items():
        assert table[name].min() >= low and table[name].max() <= high, name
    assert np.all(table["sun_azimuth_angle"] == 90.0)
    assert np.all(table["precipitation"] == 30.0)
    assert np.all(table["precipitation_deposits"] == DEFAULT_HELD["precipitation_deposits"])
    # it walks the whole box: within 2 % of each face over an hour of τ = 5 s
    for name in ("cloudiness", "fog_density", "sun_altitude_angle", "wind_intensity"):
        low, high = BOX[name]
        assert table[name].min() < low + 0.02 * (high - low) and table[name].max() > high - 0.02 * (high - low)


@pytest.mark.parametrize("tau", [2.0, 30.0])
def test_lag_one_autocorrelation_is_exp_of_minus_dt_over_tau(tau):
    """θ = low + w Φ(z), z an OU process with ρ = 2 sin(πa/6): corr(θ_k, θ_{k+1}) = a = exp(−Δt/τ); at lag m it is
    (6/π) arcsin(ρ^m/2). Tested on 400 000 frames, within 5 standard errors (AR(1): √((1 − a²)/n))."""
    n, dt = 400_000, 0.1
    a = math.exp(-dt / tau)
    theta = uniform_ou(20.0, 70.0, n, dt, tau, rng(0, "test", "ou", int(tau)).standard_normal(n))
    n_eff = n * (1 - a) / (1 + a)  # independent samples' worth, for the lags' tolerance
    assert abs(_lag_corr(theta, 1) - a) < 5 * math.sqrt((1 - a * a) / n)
    rho = 2 * math.sin(math.pi * a / 6)
    m = int(tau / dt)  # one correlation time: ≈ e⁻¹
    assert abs(_lag_corr(theta, m) - 6 / math.pi * math.asin(rho**m / 2)) < 5 / math.sqrt(n_eff)
    # the marginal is uniform on the box (every 10 τ: nearly independent draws)
    thinned = (theta[:: int(10 * tau / dt)] - 20.0) / 50.0
    assert stats.kstest(thinned, "uniform").pvalue > 1e-3
    # and a wrong τ is told apart: half or twice τ is many standard errors away
    for wrong in (tau / 2, 2 * tau):
        assert abs(_lag_corr(theta, 1) - math.exp(-dt / wrong)) > 10 * math.sqrt((1 - a * a) / n)


def test_the_drive_walk_has_the_drives_correlation_time():
    drive = Drive(seconds=20_000, seed=3, fps=5, box={"fog_density": (0, 50)}, correlation_s=4.0)
    fog = drive.weather_table()["fog_density"]
    a = math.exp(-0.2 / 4.0)
    assert abs(_lag_corr(fog, 1) - a) < 5 * math.sqrt((1 - a * a) / fog.size)


def test_events_hold_still_before_start_and_sit_at_their_targets_from_start_plus_duration():
    events = (
        Fog(start_s=30, duration_s=40, target=80),
        Rain(start_s=10, duration_s=20, target=60, lag_s=15, deposits_target=45, cloudiness_target=95),
        Dusk(start_s=50, duration_s=60, target=-10),
    )
    plain = Drive(seconds=150, seed=5, box=BOX).weather_table()
    table = Drive(seconds=150, seed=5, box=BOX, events=events).weather_table()
    t = table["time_s"]
    for name, start, end, target in (
        ("fog_density", 30, 70, 80),
        ("precipitation", 10, 30, 60),
        ("cloudiness", 10, 30, 95),
        ("precipitation_deposits", 25, 45, 45),
        ("sun_altitude_angle", 50, 110, -10),
    ):
        before, after = t <= start, t >= end
        assert np.array_equal(table[name][before], plain[name][before]), name
        assert np.all(table[name][after] == target), name
        inside = (t > start) & (t < end)
        assert np.all(table[name][inside] != plain[name][inside]), name
    # a ramp from a held value is linear: half way at the middle
    held = Drive(seconds=60, seed=0, box={}, held={"fog_density": 10}, events=(Fog(20, 20, 50),)).weather_table()
    assert held["fog_density"][300] == pytest.approx(30.0, abs=1e-12)
    assert np.all(np.diff(held["fog_density"]) >= 0)
    # the other parameters are untouched by an event
    assert np.array_equal(table["wind_intensity"], plain["wind_intensity"])


def test_events_round_trip_through_drive_json_entries():
    for e in (Fog(1, 2, 3), Rain(4, 5, 6), Dusk(7, 8, -9)):
        assert event_from_dict(e.to_dict()) == e
    with pytest.raises(ValueError, match="unknown event kind 'snow'"):
        event_from_dict({"kind": "snow", "start_s": 0, "duration_s": 1, "target": 1})


def _frames(drive: Drive) -> list[tuple[float, dict, bytes]]:
    return [(t, w, img.tobytes()) for t, w, img in drive.frames()]


def test_same_seed_same_frames_and_tables_another_seed_differs():
    kw = dict(seconds=1.2, fps=5, size=32, scene_seconds=0.6, events=(Fog(0.2, 0.6, 60),))
    a, b, c = _frames(Drive(seed=11, **kw)), _frames(Drive(seed=11, **kw)), _frames(Drive(seed=12, **kw))
    assert len(a) == 6 and a == b
    assert all(fa[2] != fc[2] for fa, fc in zip(a, c, strict=True))
    ta, tc = Drive(seed=11, **kw).weather_table(), Drive(seed=12, **kw).weather_table()
    assert np.array_equal(ta["time_s"], tc["time_s"]) and not np.array_equal(ta["cloudiness"], tc["cloudiness"])
    # consecutive frames share a scene (3 frames a scene), so only the weather changes within one
    d = Drive(seed=11, **kw)
    assert [d.scene_index(k) for k in range(6)] == [0, 0, 0, 1, 1, 1]
    assert d.scene_seed(0) == d.scene_seed(2) != d.scene_seed(3)
    # a longer drive of the same seed starts as the shorter one
    longer = Drive(seed=11, **{**kw, "seconds": 30}).weather_table()
    for name in DRIVEN:
        assert np.array_equal(longer[name][:6], ta[name]), name


def test_a_folder_is_byte_identical_for_the_same_seed(tmp_path):
    kw = dict(seconds=1, fps=4, size=24)
    write_folder(Drive(seed=2, **kw), tmp_path / "a")
    write_folder(Drive(seed=2, **kw), tmp_path / "b")
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == ["000000.png", "000001.png", "000002.png", "000003.png", "drive.json", "times.csv", "weather.csv"]
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name


def test_first_exit_finds_the_crossing_of_a_scripted_fog_ramp():
    """fog 5 → 65 over [10, 30] s crosses 30 at t* = 10 + 20·25/60 = 18.33 s: the first frame outside is within one."""
    for fps in (10.0, 3.0, 25.0):
        drive = Drive(seconds=60, seed=1, fps=fps, held={"fog_density": 5.0}, events=(Fog(10, 20, 65),))
        table = drive.weather_table()
        e = first_exit(table, {"fog_density": (0, 30), "cloudiness": (0, 100)})
        assert e is not None and e.parameters == ("fog_density",)
        assert 0 < e.time_s - (10 + 20 * 25 / 60) <= 1 / fps
        assert e.time_s == table["time_s"][e.frame]
    assert first_exit(table, {"fog_density": (0, 65)}) is None
    # the drive's own box and held values: fog leaves its held 5 at the ramp's first frame after 10 s
    assert drive.to_dict()["exits"] == {"fog_density": table["time_s"][table["time_s"] > 10][0]}


def _read_csv(path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_cli_writes_a_drive_folder_with_its_truth(tmp_path, capsys):
    out = tmp_path / "drive"
    args = ["drive", "-o", str(out), "--seconds", "3", "--fps", "4", "--seed", "9", "--size", "32"]
    args += ["--box", "fog_density=0:20", "--set", "cloudiness=50", "--event", "rain:start=1,over=1,to=70,lag=0.5"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert f"wrote 12 frames (3 s at 4 frames/s, 32×32, seed 9) to {out}" in printed
    assert "precipitation at 1.25 s" in printed
    times = _read_csv(out / "times.csv")
    assert [r["image"] for r in times] == [f"{k:06d}.png" for k in range(12)]
    assert [float(r["time_s"]) for r in times] == [k / 4 for k in range(12)]
    weather = read_weather_csv(out / "weather.csv")
    drive = Drive(
        seconds=3,
        seed=9,
        fps=4,
        size=32,
        box={"fog_density": (0, 20), "sun_altitude_angle": (30, 60), "wind_intensity": (0, 30)},
        held={"cloudiness": 50},
        events=(Rain(1, 1, 70, lag_s=0.5),),
    )
    truth = drive.weather_table()
    for name in ("time_s", *DRIVEN):
        assert np.array_equal(weather[name], truth[name]), name  # written to the last bit
    info = json.loads((out / "drive.json").read_text())
    assert info["fps"] == 4 and info["seed"] == 9 and info["size"] == [32, 32] and info["frames"] == 12
    assert info["box"]["fog_density"] == [0, 20] and "cloudiness" not in info["box"]
    assert info["correlation_seconds"] == 30 and info["events"][0]["kind"] == "rain"
    first = cv2.imread(str(out / "000000.png"))[:, :, ::-1]
    assert np.array_equal(first, next(drive.frames()).image)


@pytest.mark.parametrize("suffix", [".avi", ".mp4", ".mkv"])
def test_cli_writes_a_video_that_opencv_reads_back(tmp_path, suffix):
    video = tmp_path / f"drive{suffix}"
    assert main(["drive", "-o", str(video), "--seconds", "2.5", "--fps", "6", "--seed", "4", "--size", "32"]) == 0
    cap = cv2.VideoCapture(str(video))
    assert cap.isOpened()
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame[:, :, ::-1])
    cap.release()
    assert len(frames) == 15 and frames[0].shape == (32, 32, 3)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary file left
    weather = read_weather_csv(tmp_path / "drive.weather.csv")
    assert weather["frame"].tolist() == list(range(15))
    assert json.loads((tmp_path / "drive.drive.json").read_text())["frames"] == 15
    if suffix == ".mkv":  # FFV1 is lossless: the frames themselves
        drive = Drive(seconds=2.5, fps=6, seed=4, size=32)
        assert all(np.array_equal(a, f.image) for a, f in zip(frames, drive.frames(), strict=True))


_GOOD = ["--seconds", "2", "--fps", "2", "--seed", "1", "--size", "16"]


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--box", "fog_density=0:140"], r"--box fog_density = 140 is outside its range \[0, 100\] %"),
        (["--box", "sun_altitude_angle=-100:10"], r"--box sun_altitude_angle = -100 is outside its range \[-90, 90\]"),
        (["--box", "fog_density=30:10"], "--box fog_density: low 30 > high 10"),
        (["--box", "fog=0:10"], "--box: unknown parameter 'fog'; known: cloudiness"),
        (["--box", "fog_density=0-10"], "--box expects NAME=LOW:HIGH"),
        (["--box", "fog_density=a:10"], "--box fog_density: 'a' is not a number"),
        (["--set", "wetness=10"], "--set: unknown parameter 'wetness'"),
        (["--set", "precipitation=120"], r"--set precipitation = 120 is outside its range \[0, 100\] %"),
        (
            ["--box", "fog_density=0:20", "--set", "fog_density=5"],
            "--set fog_density: it is walked by --box fog_density=…; hold it or walk it",
        ),
        (["--event", "snow:start=1,over=1,to=5"], "--event snow:start=1,over=1,to=5: unknown event 'snow'"),
        (["--event", "fog:start=1,over=0,to=50"], "fog event: duration must be > 0 s, got 0"),
        (["--event", "dusk:start=1,over=-2,to=-5"], "dusk event: duration must be > 0 s, got -2"),
        (["--event", "fog:start=1,over=1,to=150"], r"fog event: target fog_density = 150 is outside its range"),
        (["--event", "fog:start=1,over=1"], "--event fog:start=1,over=1: missing to"),
        (["--event", "fog:start=1,over=1,to=5,lag=2"], "unknown key 'lag'; fog takes start, over, to"),
        (["--event", "fog:start=9,over=1,to=5"], "--event: fog event: start 9 s is not within the drive's 2 s"),
        (["--seconds", "0"], "--seconds must be a positive, finite number of s, got 0"),
        (["--fps", "-1"], "--fps must be a positive, finite number of frames/s, got -1"),
        (["--correlation-seconds", "0"], "--correlation-seconds must be a positive"),
        (["--scene-seconds", "-0.5"], "--scene-seconds must be a positive"),
        (["--size", "8"], "--size must be within 16..2048 pixels"),
        (["--seed", "-3"], "--seed must be a non-negative integer"),
    ],
)
def test_bad_input_is_one_line(extra, message, tmp_path, capsys):
    out = tmp_path / "drive"
    assert main(["drive", "-o", str(out), *_GOOD, *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("pidc drive: error: ") and re.search(message, err), err
    assert not out.exists()


def test_a_missing_seed_a_bad_extension_and_a_full_folder_are_one_line(tmp_path, capsys):
    full = tmp_path / "full"
    full.mkdir()
    (full / "x.txt").write_text("x")
    for out, args, message in (
        (tmp_path / "d", ["--seconds", "1"], "--seed is required"),
        (
            tmp_path / "d.png",
            _GOOD,
            r"-o .*d\.png: a drive is a folder .* or a video \(\.avi, \.mp4, \.mkv\), got '\.png'",
        ),
        (full, _GOOD, "the folder is not empty"),
        (tmp_path / "x.txt", _GOOD, "a drive is a folder"),
    ):
        assert main(["drive", "-o", str(out), *args]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and re.search(message, err), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full"] and [p.name for p in full.iterdir()] == ["x.txt"]
    # an empty folder is fine
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["drive", "-o", str(empty), *_GOOD]) == 0
    assert len(list(empty.glob("*.png"))) == 4
