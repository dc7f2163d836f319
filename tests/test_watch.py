"""`pidc watch` (components/watch/): the pieces on problems whose answers are known, then the command on small
simulated drives with a champion trained here (:func:`tiny_registry.build_registry`, so that the suite needs no
registry/ of the pipeline's).

The model: an NPE on the ``tiny`` backbone's features (an 8×8 L*a*b* thumbnail and its contrast) of 2 400 renders of
32×32 at weathers uniform in the full box, 40 epochs (about 25 s on one thread; the ``cues`` would cost a minute and a
half per watch, every watch reading its sources' 1 200 frames). The drives (components/simulate/drive.py, 10
frames/s) are rendered at its size, 32×32, so that it reads the images it learned from: two sources, a clear day and
a cloudy one, their weather walking fast (correlation 3 s) so that a minute covers each box; an in-ODD drive walking
inside the clear box; the same drive jumping to dense fog (90 %) at 15 s; and the in-ODD drive as a lossless video
(FFV1).

What the drives' tests prove holds for a model that reads the weather and fails for one that does not: the in-ODD
drive must raise no alarm and the fog drive must (a model blind to the images relates both alike); λ̂ must pick the
clear source over the cloudy one (blind: λ̂ near ½ or arbitrary); the frames' fog medians must follow the truth, within
a few percent in the ODD and near 90 % after the jump (blind: the prior's, tens of percent off). The bounds were
chosen from this model's values over training seeds (in-ODD fog error 2.1–2.6, λ̂ of the clear day 0.96–1.00, fog
median after the jump 85–87), with room for another machine's float rounding.
"""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import stats

from components.cli.main import main
from components.core.weather import Box
from components.domains.difference import parameter_differences
from components.watch.calibration import block_roles
from components.watch.errors import WatchError
from components.watch.frames import open_frames, read_times_csv
from components.watch.relation import marginal_distances
from components.watch.sequential import ConsecutiveRule, garwood_interval, stated_rate
from components.watch.settings import WatchOptions, decay_length
from components.watch.timeline import RecentFrames, WindowShape, domain_summary
from tests import tiny_registry

#: the side of the model's renders and of the drives, pixels
SIZE = 32
CLEAR = {"cloudiness": (0, 30), "fog_density": (0, 10), "sun_altitude_angle": (40, 70), "wind_intensity": (0, 30)}
CLOUDY = {
    "cloudiness": (60, 95),
    "fog_density": (0, 10),
    "sun_altitude_angle": (40, 70),
    "wind_intensity": (0, 30),
    "precipitation": (0, 30),
}
INSIDE = {"cloudiness": (5, 25), "fog_density": (2, 8), "sun_altitude_angle": (45, 65), "wind_intensity": (5, 25)}
#: small settings for drives of tens of seconds (the defaults are for drives of minutes)
SMALL = {
    "--window": "20",
    "--stride": "5",
    "--block": "100",
    "--false-alarm-rate": "0.05",
    "--consecutive": "3",
    "--samples": "100",
    "--draws-per-image": "32",
    "--points": "32",
    "--source-centres": "1024",
    "--batch": "32",
}


def small(**changes: str) -> list[str]:
    """:data:`SMALL` as arguments, with ``changes`` (``window="500"`` for ``--window 500``)."""
    options = SMALL | {f"--{k.replace('_', '-')}": v for k, v in changes.items()}
    return [a for k, v in options.items() for a in (k, v)]


FOG_AT = 15.0


# --- the pieces ---------------------------------------------------------------------------------------------------


def test_consecutive_rule_segments_and_alarms() -> None:
    rule = ConsecutiveRule(2)
    flags = [1, 0, 1, 1, 1, 0, 0, 1, 1]
    assert [(s.first, s.fired, s.last, s.open) for s in rule.segments(flags)] == [(2, 3, 4, False), (7, 8, 8, True)]
    assert rule.alarms(flags).tolist() == [False, False, False, True, True, False, False, False, True]
    assert ConsecutiveRule(1).segments([0, 1, 0, 1]) == ConsecutiveRule(1).segments([0, 1, 0, 1])
    assert len(ConsecutiveRule(1).segments([0, 1, 0, 1])) == 2
    assert ConsecutiveRule(3).segments([1, 1, 0, 1, 1]) == []
    with pytest.raises(ValueError, match="k must be"):
        ConsecutiveRule(0)


def test_garwood_interval_is_the_exact_poisson_interval() -> None:
    # the ends are the rates at which the count's tail probabilities are 2.5 %
    for count in (0, 1, 4, 20):
        low, high = garwood_interval(count, 2.0)
        assert stats.poisson.cdf(count, 2.0 * high) == pytest.approx(0.025, abs=1e-9)
        if count:
            assert stats.poisson.sf(count - 1, 2.0 * low) == pytest.approx(0.025, abs=1e-9)
        else:
            assert low == 0.0
    # it covers the true rate at least 95 % of the time (exact, so conservative for a discrete count)
    r = np.random.default_rng(0)
    rate, hours = 3.0, 1.5
    counts = r.poisson(rate * hours, size=4000)
    covered = [lo <= rate <= hi for lo, hi in (garwood_interval(int(c), hours) for c in counts)]
    assert np.mean(covered) >= 0.95


def test_stated_rate_counts_alarm_segments_over_the_exposure() -> None:
    rule = ConsecutiveRule(2)
    sequences = [np.array([0, 1, 1, 0, 1, 1, 1], bool), np.array([1, 0, 1], bool), np.zeros(10, bool)]
    st = stated_rate(rule, sequences, window_seconds=0.5)
    assert (st.alarms, st.windows, st.flagged, st.sequences) == (2, 20, 7, 3)
    assert st.hours == pytest.approx(20 * 0.5 / 3600)
    assert st.per_hour == pytest.approx(2 / st.hours)
    assert (st.low, st.high) == pytest.approx(garwood_interval(2, st.hours))
    assert st.window_rate == pytest.approx(7 / 20)


def test_window_shapes_weights_and_ends() -> None:
    equal = WindowShape(4, 3)
    assert equal.weights.tolist() == [0.25] * 4
    assert equal.ends(0, 12).tolist() == [3, 6, 9]
    assert equal.ends(10, 13).size == 0
    assert [f for f in range(12) if equal.is_end(f)] == [3, 6, 9]
    decaying = WindowShape(decay_length(0.5, 0.1), 1, decay=0.5)  # ages 3, 2, 1, 0: 0.125 ≥ 0.1 > 0.0625
    assert decaying.length == 4
    assert decaying.weights == pytest.approx(np.array([1, 2, 4, 8]) / 15)


def test_recent_frames_yield_each_window_oldest_first() -> None:
    shape = WindowShape(3, 2)
    recent = RecentFrames(shape, draws=2, dim=1)
    frames = np.arange(9, dtype=float)[:, None, None] * np.ones((1, 2, 1))  # frame k's draws are all k
    out = [(end, w[:, 0, 0].tolist()) for batch in np.array_split(frames, 4) for end, w in recent.push(batch)]
    assert out == [(2, [0, 1, 2]), (4, [2, 3, 4]), (6, [4, 5, 6]), (8, [6, 7, 8])]


def test_domain_summary_of_equal_and_decaying_weights() -> None:
    # two frames whose draws are 0 and 10: equal weights → median 5; weights 1:99 → the mixture is nearly all 10
    draws = np.stack([np.zeros((400, 1)), np.full((400, 1), 10.0)])
    median, low, high = domain_summary(draws, np.array([0.5, 0.5]), seed=0)
    assert median[0] == 5.0 and (low[0], high[0]) in ((0.0, 10.0),)
    median, low, high = domain_summary(draws, np.array([0.01, 0.99]), seed=0)
    assert median[0] == 10.0 and low[0] == high[0] == 10.0


def test_block_roles_cycle_and_leave_no_frame_in_two_roles() -> None:
    roles = block_roles(1000, 30)
    assert roles[:30].tolist() == ["density"] * 30 and roles[30:60].tolist() == ["calibration"] * 30
    assert roles[60:90].tolist() == ["density"] * 30 and roles[90:120].tolist() == ["evaluation"] * 30
    assert np.mean(roles == "density") == pytest.approx(0.5, abs=0.02)


def test_marginal_distances_are_relates_for_equal_weights_and_weight_the_target() -> None:
    box = Box.full()
    r = np.random.default_rng(1)
    target = r.uniform(box.low, box.high, size=(200, 6))
    sources = [r.uniform(box.low, box.high, size=(300, 6)), r.uniform(box.low, box.high, size=(100, 6))]
    lam = np.array([0.3, 0.7])
    expected = [q.wasserstein for q in parameter_differences(target, sources, lam, box)]
    assert marginal_distances(target, None, sources, lam) == pytest.approx(expected, rel=1e-12)
    # weights: a target half of whose weight sits on one draw equals the target with that draw repeated
    two = np.array([[1.0] * 6, [3.0] * 6])
    repeated = np.array([[1.0] * 6] * 3 + [[3.0] * 6])
    got = marginal_distances(two, np.array([0.75, 0.25]), sources, lam)
    assert got == pytest.approx(marginal_distances(repeated, None, sources, lam), rel=1e-12)


def test_options_are_checked_naming_the_option() -> None:
    with pytest.raises(WatchError, match="--draws-per-image 300 must not exceed --samples 256"):
        WatchOptions(draws_per_image=300)
    with pytest.raises(WatchError, match="--decay must be in"):
        WatchOptions(decay=1.0)
    with pytest.raises(WatchError, match="--block 20 is shorter"):
        WatchOptions(block=20)
    with pytest.raises(WatchError, match="--batch must be a multiple of 16"):
        WatchOptions(batch=10)
    with pytest.raises(WatchError, match="--false-alarm-rate must be in"):
        WatchOptions(false_alarm_rate=0.0)
    assert WatchOptions(decay=0.9).length == decay_length(0.9, 0.01) == 44
    assert math.ceil((1 - 0.05) / 0.05) == WatchOptions(false_alarm_rate=0.05).calibration_windows_needed


def test_times_csv_errors_name_the_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "times.csv"
    for text, message in [
        ("a,b\n", "expected the header image,time_s"),
        ("image,time_s\na.png,x\n", "line 2: time 'x' is not a number"),
        ("image,time_s\na.png,0\na.png,1\n", "line 3: 'a.png' is listed twice"),
        ("image,time_s\na.png,0\n", "no time for 1 frame"),
        ("image,time_s\na.png,0\nb.png,0.1\nc.png,1\n", "lists 1 frame"),
        ("image,time_s\na.png,1\nb.png,0.5\n", "'b.png' (0.5 s) does not come after 'a.png'"),
    ]:
        path.write_text(text)
        with pytest.raises(WatchError, match=re.escape(message)):
            read_times_csv(path, ["a.png", "b.png"])
    path.write_text("image,time_s\nb.png,0.25\na.png,0\n")
    assert read_times_csv(path, ["a.png", "b.png"]).tolist() == [0.0, 0.25]


# --- the command on simulated drives ------------------------------------------------------------------------------


def _run(args: list[str]) -> tuple[int, str, str]:
    """``pidc`` in-process: (exit status, stdout, stderr)."""
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(args)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict[str, Path]:
    """The model and the drives (module docstring), and the watches of the in-ODD drive, the fog drive and the in-ODD
    video (about 50 s on one thread, a third of it rendering the model's 2 400 images)."""
    from components.simulate.drive import Drive, Fog, write_folder, write_video

    root = tmp_path_factory.mktemp("watch")
    registry = tiny_registry.build_registry(
        root, "watch", n=2400, size=SIZE, backbone="tiny", epochs=40, width=128, batch_size=64, model_id="tiny-watch"
    )
    inside = {"box": INSIDE, "correlation_s": 10.0, "size": SIZE}
    drives = {
        "clear": Drive(seconds=60, seed=11, box=CLEAR, correlation_s=3.0, size=SIZE),
        "cloudy": Drive(seconds=60, seed=12, box=CLOUDY, correlation_s=3.0, size=SIZE),
        "inside": Drive(seconds=40, seed=13, **inside),
        "fog": Drive(seconds=40, seed=13, events=(Fog(start_s=FOG_AT, duration_s=0.1, target=90.0),), **inside),
    }
    paths = {name: write_folder(d, root / name) for name, d in drives.items()}
    paths["video"] = write_video(drives["inside"], root / "inside.mkv")  # FFV1: lossless
    paths["registry"] = registry
    sources = ["--sources", str(paths["clear"]), str(paths["cloudy"])]
    common = [*sources, "--registry", str(registry), *small()]
    for name, extra in [("inside", []), ("fog", []), ("video", ["--batch", "16"])]:
        out = root / f"out-{name}"
        code, stdout, stderr = _run(["watch", str(paths[name]), *common, "--out", str(out), *extra])
        assert code == 0, stderr
        paths[f"out-{name}"] = out
        (out / "stdout.txt").write_text(stdout)
    paths["common"] = common  # type: ignore[assignment]
    return paths


def _table(path: Path) -> dict[str, np.ndarray]:
    import csv

    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([r[k] for r in rows]) for k in rows[0]}


def _summary(world: dict[str, Path], name: str) -> dict:
    return json.loads((world[f"out-{name}"] / "summary.json").read_text())


def test_a_drive_in_the_sources_weather_raises_no_alarm(world) -> None:
    s = _summary(world, "inside")
    assert s["alarms"] == [] and s["first_alarm_s"] is None
    assert "no alarm" in (world["out-inside"] / "stdout.txt").read_text()
    assert s["truth"]["exit_s"] is None and s["truth"]["false_alarms"] == 0
    frames = _table(world["out-inside"] / "frames.csv")
    assert frames["frame"].astype(int).tolist() == list(range(400))  # one row per frame
    assert frames["image"][0] == "000000.png" and float(frames["time_s"][-1]) == pytest.approx(39.9)
    windows = _table(world["out-inside"] / "windows.csv")
    assert windows["last_frame"].astype(int).tolist() == list(range(19, 400, 5))  # L − 1, then every stride
    lam = np.stack([windows["weight_clear"], windows["weight_cloudy"]]).astype(float)
    assert np.allclose(lam.sum(axis=0), 1.0) and np.median(lam[0]) > 0.9  # the clear day explains it
    # the frames' posterior medians follow the known weather (fog 2–8 %; the prior's median is 50 %)
    truth = _table(world["inside"] / "weather.csv")
    fog_error = np.abs(frames["fog_density_median"].astype(float) - truth["fog_density"].astype(float))
    assert np.median(fog_error) < 5.0
    assert (world["out-inside"] / "timeline.png").stat().st_size > 10_000


def test_a_jump_to_dense_fog_alarms_within_a_window_naming_fog(world) -> None:
    s = _summary(world, "fog")
    truth = s["truth"]
    assert truth["exit_s"] == pytest.approx(FOG_AT + 0.1) and truth["exit_parameters"] == ["fog_density"]
    assert len(s["alarms"]) == 1 and s["alarms"][0]["open"]
    alarm = s["alarms"][0]
    # not before the jump; by the time a whole window is in the fog and the rule's k − 1 more strides have passed
    settings = s["settings"]
    latest = FOG_AT + 0.1 + (settings["length"] + (settings["consecutive"] - 1) * settings["stride"]) * 0.1
    assert FOG_AT < alarm["fired_s"] <= latest
    assert s["first_alarm_s"] == alarm["fired_s"]
    assert alarm["cause"][0] == "fog_density"
    assert alarm["parameters"]["fog_density"]["share_beyond_level"] == 1.0
    assert truth["parameters"]["fog_density"]["delay_s"] == pytest.approx(alarm["fired_s"] - (FOG_AT + 0.1))
    stdout = (world["out-fog"] / "stdout.txt").read_text()
    assert f"first alarm at {alarm['fired_s']:.1f} s" in stdout and "fog_density" in stdout
    # the rule and its measured rate are stated
    rate = s["rule"]["false_alarms_per_hour"]
    assert rate["low"] <= rate["per_hour"] <= rate["high"] and rate["windows"] > 0
    assert "false alarms per hour" in stdout
    # the frames' fog medians follow the truth into the fog: near 90 % after the jump (before it, the frames are the
    # in-ODD drive's, whose medians the test above checks)
    frames, known = _table(world["out-fog"] / "frames.csv"), _table(world["fog"] / "weather.csv")
    error = np.abs(frames["fog_density_median"].astype(float) - known["fog_density"].astype(float))
    after = known["time_s"].astype(float) >= FOG_AT + 0.1
    assert np.median(error[after]) < 15.0


def test_the_video_and_the_folder_of_the_same_frames_give_the_same_tables(world) -> None:
    # the video was watched with --batch 16, the folder with 32: the same numbers, to the last bit
    for name in ("frames.csv", "windows.csv"):
        folder, video = _table(world["out-inside"] / name), _table(world["out-video"] / name)
        assert folder.keys() == video.keys()
        for key in folder:
            if key != "image":
                assert folder[key].tolist() == video[key].tolist(), key
    assert _table(world["out-video"] / "frames.csv")["image"][3] == "frame 3"


def test_draws_do_not_depend_on_the_batch(world) -> None:
    from components.export.lookup import load_registered
    from components.watch.run import read_source

    model = load_registered("champion", world["registry"])
    frames = open_frames(world["fog"], timed=False)
    small = read_source(model, frames, 0, WatchOptions(batch=16, samples=100, draws_per_image=32), [])
    large = read_source(model, frames, 0, WatchOptions(batch=96, samples=100, draws_per_image=32), [])
    assert small.shape == (400, 32, 6) and np.array_equal(small, large)


def _bad_inputs(world: dict[str, Path], root: Path) -> dict[str, tuple[list[str], str]]:
    """Per case: (the command line, the message its one-line error must hold)."""
    sources = world["common"][:3]
    junk = root / "junk.avi"
    junk.write_bytes(b"not a video at all")
    data = world["video"].read_bytes()
    cut = root / "cut.mkv"
    cut.write_bytes(data[: len(data) // 2])
    empty = root / "empty"
    empty.mkdir()
    mixed = root / "mixed"
    mixed.mkdir()
    for k in range(30):
        shutil.copy(world["inside"] / f"{k:06d}.png", mixed / f"{k:06d}.png")
    cv2.imwrite(str(mixed / "000030.png"), np.zeros((64, 96, 3), np.uint8))
    short = root / "short"
    short.mkdir()
    for k in range(30):
        shutil.copy(world["clear"] / f"{k:06d}.png", short / f"{k:06d}.png")
    untimed = root / "untimed"
    shutil.copytree(world["inside"], untimed)
    (untimed / "times.csv").unlink()
    drive = str(world["inside"])
    return {
        "unreadable video": ([str(junk), *sources], f"{junk}: OpenCV cannot open this video"),
        "truncated video": ([str(cut), *sources], f"{cut}: truncated video"),
        "no images": ([str(empty), *sources], f"{empty}: no image files in this folder"),
        "mixed sizes": ([str(mixed), *sources], f"{mixed / '000030.png'}: a frame of 96×64 pixels"),
        "window longer than the drive": (
            [drive, *sources, *small(window="500", block="1000")],
            "--window 500: a window of 500 frames is longer than the drive",
        ),
        "source too short": (
            [drive, "--sources", str(short), str(world["cloudy"])],
            "source short: 30 frames are too few to calibrate: in blocks of --block 100",
        ),
        "no times": ([str(untimed), *sources], "without times.csv; give --fps"),
        "drive is a source": ([drive, "--sources", drive], "is also given as a source"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "unreadable video",
        "truncated video",
        "no images",
        "mixed sizes",
        "window longer than the drive",
        "source too short",
        "no times",
        "drive is a source",
    ],
)
def test_bad_input_is_one_line_naming_the_file_or_option(world, tmp_path, case) -> None:
    args, message = _bad_inputs(world, tmp_path)[case]
    code, stdout, stderr = _run(
        ["watch", *small(), *args, "--registry", str(world["registry"]), "--out", str(tmp_path / "o")]
    )
    errors = [line for line in stderr.splitlines() if "error" in line]
    assert code == 2 and len(errors) == 1, stderr
    assert errors[0].startswith("pidc watch: error: ") and message in errors[0], errors[0]
    assert "Traceback" not in stderr


def test_decaying_windows_weigh_recent_frames_and_still_name_the_fog(world, tmp_path) -> None:
    out = tmp_path / "decay"
    with pytest.raises(SystemExit):  # --window or --decay, not both (argparse's usage error)
        _run(["watch", str(world["fog"]), *world["common"], "--out", str(out), "--decay", "0.85"])
    i = world["common"].index("--window")
    args = world["common"][:i] + world["common"][i + 2 :]
    code, _, stderr = _run(["watch", str(world["fog"]), *args, "--out", str(out), "--decay", "0.85"])
    assert code == 0, stderr
    s = json.loads((out / "summary.json").read_text())
    length = decay_length(0.85, 0.01)
    assert s["settings"]["length"] == length == 29
    windows = _table(out / "windows.csv")
    assert (windows["last_frame"].astype(int) - windows["first_frame"].astype(int) + 1 == length).all()
    alarm = s["alarms"][0]
    assert FOG_AT < alarm["fired_s"] <= FOG_AT + 0.1 + (length + 2 * 5) * 0.1 and alarm["cause"][0] == "fog_density"


def test_tables_round_trip_as_csv_and_parquet(tmp_path) -> None:
    import pyarrow.parquet as pq

    from components.watch.report import write_table

    columns = {"frame": np.arange(3), "x": np.array([0.1, 1 / 3, 2.5e-300]), "ok": np.array([True, False, True])}
    write_table(tmp_path / "t.csv", columns, "csv")
    back = _table(tmp_path / "t.csv")
    assert back["x"].astype(float).tolist() == columns["x"].tolist()  # floats written exactly
    assert back["ok"].tolist() == ["true", "false", "true"]
    write_table(tmp_path / "t.parquet", columns, "parquet")
    table = pq.read_table(tmp_path / "t.parquet").to_pydict()
    assert table == {k: v.tolist() for k, v in columns.items()}
