"""The `pidc` command line: renders a PNG, and bad input gets one clear line and exit status 2."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from components.cli.main import PRESETS, main
from components.core import weather


def test_presets_are_valid_weathers():
    for name, w in PRESETS.items():
        weather.complete_weather(w, where=f"preset {name}: ")


def test_render_writes_the_simulators_image(tmp_path):
    out = tmp_path / "fog.png"
    assert (
        main(
            [
                "render",
                "--preset",
                "foggy_morning",
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

    expected = ProceduralSimulator(48, 64).render(PRESETS["foggy_morning"] | {"fog_density": 70}, 3)
    np.testing.assert_array_equal(png, expected)


def test_render_defaults_to_the_default_profiles_image_size(tmp_path):
    """`pidc render` without --height/--width renders the images the default profile's models learned from."""
    from pathlib import Path

    from components.core.config import load_params

    sim = load_params(Path(__file__).resolve().parents[1] / "params.yaml").simulator
    out = tmp_path / "noon.png"
    assert main(["render", "--preset", "clear_noon", "--seed", "1", "-o", str(out)]) == 0
    assert cv2.imread(str(out), cv2.IMREAD_COLOR).shape == (sim.height, sim.width, 3)


@pytest.mark.parametrize(
    "args, message",
    [
        (["render", "--preset", "clear_noon"], "--seed is required"),
        (["render", "--preset", "clear_noon", "--seed", "-2"], "--seed must be a non-negative integer"),
        (
            ["render", "--preset", "clear_noon", "--seed", "1", "--set", "fog_density=140"],
            r"'fog_density' = 140 is outside its range \[0, 100\] %",
        ),
        (["render", "--seed", "1", "--set", "fog_density=10"], "weather is missing 'cloudiness'"),
        (["render", "--preset", "clear_noon", "--seed", "1", "--set", "fog=10"], "unknown weather parameter 'fog'"),
        (["render", "--preset", "clear_noon", "--seed", "1", "--set", "fog_density"], "--set expects NAME=VALUE"),
        (["render", "--preset", "clear_noon", "--seed", "1", "--height", "0"], "--height and --width must be positive"),
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
    assert "sun_altitude_angle" in r.stdout and "[-90, 90] deg" in r.stdout and "clear_noon" in r.stdout
