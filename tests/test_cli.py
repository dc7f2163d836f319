"""The `pidc` command line: renders a PNG, and bad input gets one clear line and exit status 2."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from components.cli.main import main
from components.core import presets


def test_render_takes_carlas_preset_names_and_values(tmp_path):
    """`--preset ClearNoon` is CARLA's ClearNoon (sun 45°, fog 2 %), at pidc's documented azimuth unless --set."""
    from components.simulate.procedural import ProceduralSimulator

    out = tmp_path / "noon.png"
    assert (
        main(["render", "--preset", "ClearNoon", "--seed", "2", "--height", "48", "--width", "64", "-o", str(out)]) == 0
    )
    png = cv2.cvtColor(cv2.imread(str(out), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    carla_noon = {"cloudiness": 5, "fog_density": 2, "precipitation": 0, "sun_altitude_angle": 45}
    carla_noon |= {"wind_intensity": 10, "precipitation_deposits": 0, "sun_azimuth_angle": presets.PRESET_SUN_AZIMUTH}
    np.testing.assert_array_equal(png, ProceduralSimulator(48, 64).render(carla_noon, 2))
    # --set overrides the preset's azimuth (the sun moves in the image)
    args = ["render", "--preset", "ClearNoon", "--set", "sun_azimuth_angle=180", "--seed", "2"]
    assert main([*args, "--height", "48", "--width", "64", "-o", str(out)]) == 0
    moved = cv2.cvtColor(cv2.imread(str(out), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(moved, ProceduralSimulator(48, 64).render(carla_noon | {"sun_azimuth_angle": 180}, 2))
    assert not np.array_equal(moved, png)


@pytest.mark.parametrize(
    "name, reason",
    [
        ("ClearNight", "fog_distance 75 vs pidc's fixed 0.75, fog_falloff 1 vs pidc's fixed 0.1"),
        ("HardRainNight", "wetness 100 vs pidc's fixed 0"),
        ("DustStorm", r"dust_storm 100 vs 0 \(pidc does not model it\)"),
    ],
)
def test_a_refused_preset_is_one_line_naming_the_parameter(name, reason, capsys, tmp_path):
    assert main(["render", "--preset", name, "--seed", "1", "-o", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert re.search(rf"^pidc render: error: --preset {name}: {reason} ", err), err
    assert not (tmp_path / "x.png").exists()


def test_pidc_own_preset_names_are_gone(capsys, tmp_path):
    with pytest.raises(SystemExit) as info:
        main(["render", "--preset", "clear_noon", "--seed", "1", "-o", str(tmp_path / "x.png")])
    assert info.value.code == 2
    assert "invalid choice: 'clear_noon'" in capsys.readouterr().err


def test_render_writes_the_simulators_image(tmp_path):
    out = tmp_path / "fog.png"
    assert (
        main(
            [
                "render",
                "--preset",
                "CloudySunset",
                "--set",
                "fog_density=70",
                "--seed",
                "3",
                "--height",
                "48",
                "--width",
                "64",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    png = cv2.cvtColor(cv2.imread(str(out), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    from components.simulate.procedural import ProceduralSimulator

    expected = ProceduralSimulator(48, 64).render(presets.preset_weather("CloudySunset") | {"fog_density": 70}, 3)
    np.testing.assert_array_equal(png, expected)


def test_render_defaults_to_the_default_profiles_image_size(tmp_path):
    """`pidc render` without --height/--width renders the images the default profile's models learned from."""
    from pathlib import Path

    from components.core.config import load_params

    sim = load_params(Path(__file__).resolve().parents[1] / "params.yaml").simulator
    out = tmp_path / "noon.png"
    assert main(["render", "--preset", "ClearNoon", "--seed", "1", "-o", str(out)]) == 0
    assert cv2.imread(str(out), cv2.IMREAD_COLOR).shape == (sim.height, sim.width, 3)


@pytest.mark.parametrize(
    "args, message",
    [
        (["render", "--preset", "ClearNoon"], "--seed is required"),
        (["render", "--preset", "ClearNoon", "--seed", "-2"], "--seed must be a non-negative integer"),
        (
            ["render", "--preset", "ClearNoon", "--seed", "1", "--set", "fog_density=140"],
            r"'fog_density' = 140 is outside its range \[0, 100\] %",
        ),
        (["render", "--seed", "1", "--set", "fog_density=10"], "weather is missing 'cloudiness'"),
        (["render", "--preset", "ClearNoon", "--seed", "1", "--set", "fog=10"], "unknown weather parameter 'fog'"),
        (["render", "--preset", "ClearNoon", "--seed", "1", "--set", "fog_density"], "--set expects NAME=VALUE"),
        (
            ["render", "--preset", "ClearNoon", "--seed", "1", "--height", "0"],
            "--height and --width must be within 16..2048",
        ),
    ],
)
def test_bad_input_is_one_clear_line(args, message, capsys, tmp_path):
    assert main([*args, "-o", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    import re

    assert re.search(message, err), err
    assert not (tmp_path / "x.png").exists()


def test_console_script_lists_weather():
    r = subprocess.run(
        [sys.executable, "-m", "components.cli.main", "weather"], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0
    assert "sun_altitude_angle" in r.stdout and "[-90, 90] deg" in r.stdout
    # the usable presets with CARLA's values (cloud, fog, rain, sun, wind, deposit, then pidc's azimuth)
    rows = {line.split()[0]: line.split()[1:] for line in r.stdout.splitlines() if line.split()[:1] == ["HardRainNoon"]}
    assert rows["HardRainNoon"] == ["100", "7", "100", "45", "100", "90", "0"]
    assert all(re.search(rf"^{n} +[0-9]", r.stdout, re.M) for n in presets.USABLE)
    # the refused ones with the parameter that differs
    assert "  ClearNight: fog_distance 75 vs pidc's fixed 0.75, fog_falloff 1 vs pidc's fixed 0.1\n" in r.stdout
    assert "  DustStorm: dust_storm 100 vs 0 (pidc does not model it)\n" in r.stdout
    assert not re.search(r"^ClearNight +[0-9]", r.stdout, re.M)


@pytest.mark.parametrize(
    "size, message",
    [
        (
            ["--height", "1", "--width", "1"],
            r"--height and --width must be within 16\.\.2048 pixels \(the renderer's sizes\), got --height 1 --width 1",
        ),
        (
            ["--height", "5000"],
            r"must be within 16\.\.2048 pixels \(the renderer's sizes\), got --height 5000 --width 128",
        ),
    ],
)
def test_render_sizes_outside_the_renderers_bounds(size, message, capsys, tmp_path):
    assert main(["render", "--preset", "ClearNoon", "--seed", "1", *size, "-o", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and re.search(message, err), err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "name, message",
    [
        ("r.jpg", r"-o .*r\.jpg: pidc render writes PNG; use a \.png file name"),
        ("r", r"-o .*/r: pidc render writes PNG; use a \.png file name"),
        ("a.png/r.png", r"-o .*a\.png/r\.png: .*a\.png is a file, not a folder"),
        ("isdir.png", r"-o .*isdir\.png: is a folder; give a file name"),
    ],
)
def test_render_output_that_cannot_be_a_png_file(name, message, capsys, tmp_path):
    (tmp_path / "a.png").write_bytes(b"")
    (tmp_path / "isdir.png").mkdir()
    assert main(["render", "--preset", "ClearNoon", "--seed", "1", "-o", str(tmp_path / name)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("pidc render: error: ") and re.search(message, err), err
    assert (
        sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "isdir.png"]
        and (tmp_path / "a.png").stat().st_size == 0
    )


def test_config_check_write_to_a_folder_is_one_line(capsys, tmp_path):
    params = Path(__file__).resolve().parents[1] / "params.yaml"
    (tmp_path / "out.yaml").mkdir()
    assert main(["config", "check", "--params", str(params), "--write", str(tmp_path / "out.yaml")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"pidc config: error: --write {tmp_path / 'out.yaml'}: is a folder; give a file name"


def test_a_failed_write_names_the_users_file_not_a_temporary_one(capsys, tmp_path, monkeypatch):
    """An OSError no early check foresaw (here raised by the PNG writer as os.replace would) is one line naming the
    option and the user's file, not a traceback with the temporary name."""
    import components.simulate.contact_sheet as sheet

    target = tmp_path / "r.png"

    def fail(path, image):
        raise IsADirectoryError(21, "Is a directory", str(tmp_path / ".r.png.1fa1588e.tmp"), None, str(target))

    monkeypatch.setattr(sheet, "save_png", fail)
    assert main(["render", "--preset", "ClearNoon", "--seed", "1", "-o", str(target)]) == 2
    assert capsys.readouterr().err.strip() == f"pidc render: error: -o {target}: cannot write there (Is a directory)"

    def fail_temporary(path, image):  # the temporary file alone (os.open of it failed)
        raise FileNotFoundError(2, "No such file or directory", str(tmp_path / ".r.png.1fa1588e.tmp"))

    monkeypatch.setattr(sheet, "save_png", fail_temporary)
    assert main(["render", "--preset", "ClearNoon", "--seed", "1", "-o", str(target)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"pidc render: error: -o {target}: cannot write there (No such file or directory)"


def test_check_outputs_removes_what_a_killed_write_of_the_same_outputs_left(tmp_path):
    """A ``pidc`` killed while writing (SIGKILL: no clean-up) leaves ``.<name>.<8 hex>.tmp`` beside the file it was
    writing; the next run's output check removes those of the outputs it was given, and nothing else."""
    from components.cli.outputs import check_outputs

    draws, corner = tmp_path / "d.csv", tmp_path / "sub" / "c.png"
    corner.parent.mkdir()
    stale = [tmp_path / ".d.csv.0123abcd.tmp", corner.parent / ".c.png.fedcba98.tmp"]
    keep = [
        tmp_path / ".hidden",
        tmp_path / ".d.csv.tmp",
        tmp_path / ".d.csv.0123abc.tmp",
        tmp_path / ".d.csv.0123ABCD.tmp",
        tmp_path / ".d.csv.0123abcd.tmp.bak",
        tmp_path / ".other.csv.0123abcd.tmp",  # not an output of this run
        corner.parent / ".d.csv.0123abcd.tmp",  # d.csv's name, another folder
    ]
    for f in stale + keep:
        f.write_bytes(b"x" * 1000)
    (tmp_path / ".d.csv.aaaa0000.tmp").mkdir()  # a folder: not a temporary file of a write
    keep.append(tmp_path / ".d.csv.aaaa0000.tmp")
    removed = check_outputs([("--samples-out", draws), ("--json", None), ("--corner", corner)])
    assert sorted(removed) == sorted(stale) and not any(f.exists() for f in stale) and all(f.exists() for f in keep)
    assert check_outputs([("--samples-out", tmp_path / "new" / "d.csv")]) == []  # a folder the write will make


def test_render_removes_the_temporary_file_a_killed_render_left(tmp_path):
    out, stale, other = tmp_path / "r.png", tmp_path / ".r.png.1fa1588e.tmp", tmp_path / ".r.png.notes"
    stale.write_bytes(b"half a png")
    other.write_bytes(b"the user's")
    args = ["render", "--preset", "ClearNoon", "--seed", "1", "--height", "48", "--width", "64", "-o", str(out)]
    assert main(args) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, other.name])


def test_out_of_memory_names_the_size_options(capsys, monkeypatch):
    import components.cli.models as models

    def huge(args):
        raise MemoryError("Unable to allocate 22.4 GiB for an array with shape (1, 500000000, 6) and data type float64")

    monkeypatch.setattr(models, "cmd_characterize", huge)
    monkeypatch.setattr(models, "cmd_relate", huge)
    assert main(["characterize", "a.png", "--samples", "500000000"]) == 2
    assert capsys.readouterr().err.strip() == (
        "pidc characterize: error: out of memory (could not allocate 22.4 GiB); use smaller sizes: --samples 500000000"
    )
    assert main(["relate", "t", "s", "--points", "200000000"]) == 2
    assert capsys.readouterr().err.strip() == (
        "pidc relate: error: out of memory (could not allocate 22.4 GiB); use smaller sizes: --points 200000000, "
        "--draws-per-image 64"
    )


def test_config_check_prints_the_plan_on_this_machine(capsys):
    """After the resolved config, one comment line per stage with a runner: its kind, workers (``auto``: the usable
    cores), threads per worker and device; the GPU profile is valid here, its torch stages named as unable to run
    on a machine where torch sees no CUDA (with the key and what was found), and the command still exits 0."""
    import torch

    from components.core.hardware import usable_cores

    params = Path(__file__).resolve().parents[1] / "params.yaml"
    cores = usable_cores()
    device = "cuda" if torch.cuda.is_available() else "cpu"
    assert main(["config", "check", "--params", str(params)]) == 0
    out = capsys.readouterr().out.splitlines()
    gpus = torch.cuda.device_count() if torch.cuda.is_available() else 0
    head = f"# the plan on this machine ({cores} usable core{'s' if cores != 1 else ''}, {gpus} CUDA device(s)):"
    plan = out[out.index(head) + 1 :]
    workers = f"{cores} worker{'s' if cores != 1 else ''}"
    assert [re.sub(r"\s+", " ", line) for line in plan] == [
        f"# generate processes, {workers} × 1 thread, device —",
        f"# features processes, {workers} × 1 thread, device {device}",
        f"# train processes, {workers} × 1 thread, device {device}",
        f"# export processes, {workers} × 1 thread, device —",
        f"# evaluate processes, {workers} × 1 thread, device —",
    ]
    assert main(["config", "check", "--params", str(params), "--profile", "gpu"]) == 0
    out = capsys.readouterr().out
    if not torch.cuda.is_available():
        assert re.search(r"^#   train +cannot run here: train\.device: cuda, but torch sees no CUDA device", out, re.M)
        assert re.search(r"^#   features +cannot run here: backbones\.device: cuda, but torch sees no CUDA", out, re.M)
