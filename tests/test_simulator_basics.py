"""The procedural simulator's contract: shape, determinism, caching, validation, scenes, sheet."""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from components.core.weather import PREDICTED
from components.simulate.base import Simulator
from components.simulate.contact_sheet import contact_sheet, save_png
from components.simulate.procedural import ProceduralSimulator
from components.simulate.procedural.calibration import CALIBRATION, calibration_hash, calibration_rows

DAY = {
    "cloudiness": 30.0,
    "fog_density": 10.0,
    "precipitation": 40.0,
    "sun_altitude_angle": 35.0,
    "wind_intensity": 50.0,
    "precipitation_deposits": 40.0,
    "sun_azimuth_angle": 200.0,
}


@pytest.fixture(scope="module")
def sim() -> ProceduralSimulator:
    return ProceduralSimulator(64, 64)


def test_render_is_rgb_uint8_of_the_requested_size_and_follows_the_protocol() -> None:
    s = ProceduralSimulator(48, 80)
    img = s.render(DAY, 1)
    assert img.shape == (48, 80, 3) and img.dtype == np.uint8
    assert isinstance(s, Simulator)
    assert s.version.startswith("procedural-") and s.version.endswith(calibration_hash())
    assert 20 < img.mean() < 235 and img.std() > 5


def test_same_weather_and_seed_is_byte_identical_across_fresh_instances(sim: ProceduralSimulator) -> None:
    a = sim.render(DAY, 7)
    b = sim.render(DAY, 7)
    c = ProceduralSimulator(64, 64).render(DAY, 7)
    assert a.tobytes() == b.tobytes() == c.tobytes()
    assert sim.render(DAY, 8).tobytes() != a.tobytes()


def test_rendering_never_changes_the_cached_geometry(sim: ProceduralSimulator) -> None:
    sc = sim.scene(11)
    before = {
        f.name: getattr(sc, f.name).copy()
        for f in dataclasses.fields(sc)
        if isinstance(getattr(sc, f.name), np.ndarray)
    }
    rng = np.random.default_rng(0)
    for _ in range(6):
        w = {n: float(rng.uniform(0, 100)) for n in PREDICTED}
        w["sun_altitude_angle"] = float(rng.uniform(-90, 90))
        w["sun_azimuth_angle"] = float(rng.uniform(0, 360))
        sim.render(w, 11)
    assert sim.scene(11) is sc
    for name, arr in before.items():
        np.testing.assert_array_equal(getattr(sc, name), arr, err_msg=name)
    fresh = ProceduralSimulator(64, 64).scene(11)
    np.testing.assert_array_equal(fresh.depth, sc.depth)
    np.testing.assert_array_equal(fresh.material, sc.material)


def test_scene_cache_is_bounded() -> None:
    s = ProceduralSimulator(32, 32, cache_size=3)
    for seed in range(6):
        s.scene(seed)
    assert len(s._cache) == 3 and list(s._cache) == [3, 4, 5]


@pytest.mark.parametrize(
    "change, match",
    [
        ({"fog_density": 101.0}, "fog_density"),
        ({"sun_altitude_angle": -91.0}, "sun_altitude_angle"),
        ({"cloudiness": math.nan}, "cloudiness"),
        ({"precipitation": "heavy"}, "precipitation"),
        ({"snow": 3.0}, "snow"),
        ({"wetness": 50.0}, "wetness"),
    ],
)
def test_bad_weather_is_a_value_error_naming_the_parameter(sim: ProceduralSimulator, change: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        sim.render({**DAY, **change}, 1)


def test_missing_parameter_and_bad_seed_are_clear_errors(sim: ProceduralSimulator) -> None:
    w = dict(DAY)
    del w["wind_intensity"]
    with pytest.raises(ValueError, match="wind_intensity"):
        sim.render(w, 1)
    for seed in (-1, 1.5, "3", True, None):
        with pytest.raises(ValueError, match="scene_seed"):
            sim.render(DAY, seed)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="scene_seed"):
        sim.scene(-4)


def test_scene_nuisance_varies_across_seeds_like_carla_data() -> None:
    s = ProceduralSimulator(32, 32, cache_size=64)
    layouts = [s.scene(seed).layout for seed in range(40)]
    assert {lay.archetype for lay in layouts} == set(CALIBRATION.archetypes)
    for lay in layouts:
        assert lay.camera[1] == pytest.approx(1.3 * (0.5 + lay.ego_extent_z))
        assert 1.4 < lay.camera[1] < 2.8
        assert CALIBRATION.fov_deg[0] <= lay.fov_deg <= CALIBRATION.fov_deg[1]
    headings = np.array([lay.heading_deg for lay in layouts])
    assert headings.min() < 60 and headings.max() > 300
    n_vehicles = [int((lay.box_material == 7).sum()) for lay in layouts]
    assert len(set(n_vehicles)) > 5


def test_calibration_table_has_units_and_meanings_and_drives_the_version() -> None:
    rows = calibration_rows()
    assert len(rows) > 40
    for name, _value, unit, meaning in rows:
        assert unit and len(meaning) > 5, name
    other = dataclasses.replace(CALIBRATION, fog_extinction=0.05)
    assert calibration_hash(other) != calibration_hash()
    assert ProceduralSimulator(32, 32, calibration=other).version != ProceduralSimulator(32, 32).version
    a = ProceduralSimulator(32, 32).render({**DAY, "fog_density": 60.0}, 2)
    b = ProceduralSimulator(32, 32, calibration=other).render({**DAY, "fog_density": 60.0}, 2)
    assert a.tobytes() != b.tobytes()


def test_contact_sheet_layout_and_atomic_png(tmp_path) -> None:
    s = ProceduralSimulator(32, 32)
    sheet = contact_sheet(s, [0, 1], steps=3)
    label_w = int(round(32 * 1.1))
    assert sheet.shape == (2 * 6 * 32, label_w + 3 * 32, 3) and sheet.dtype == np.uint8
    assert sheet[:, :label_w].std() > 0  # labels were drawn
    path = tmp_path / "sub" / "sheet.png"
    save_png(path, sheet)
    back = cv2.imread(str(path), cv2.IMREAD_COLOR)[:, :, ::-1]
    np.testing.assert_array_equal(back, sheet)
    assert [p.name for p in path.parent.iterdir()] == ["sheet.png"]
    with pytest.raises(ValueError, match="steps"):
        contact_sheet(s, [0], steps=1)
    with pytest.raises(ValueError, match="uint8"):
        save_png(path, sheet.astype(np.float32))


def test_importing_pidc_first_pins_numpys_simd_kernels_to_the_baseline():
    """Images must not depend on the CPU: numpy's dispatched float32 exp differs between AVX2 and the baseline, so
    every pidc process (stages import flows → components first; the CLI components) uses the baseline kernels (the
    x86-64 feature groups; other architectures keep numpy's choice)."""
    probe = (
        "import {first}, numpy as np; "
        "info = np.lib.introspect.opt_func_info(func_name='exp', signature='float32')['exp']; "
        "print(next(iter(info.values()))['current'])"
    )
    env = {k: v for k, v in os.environ.items() if k != "NPY_DISABLE_CPU_FEATURES"}
    for first in ("components", "flows"):
        out = subprocess.run(
            [sys.executable, "-c", probe.format(first=first)],
            capture_output=True,
            text=True,
            env=env,
            cwd=Path(__file__).resolve().parents[1],
        )
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip().startswith("baseline"), (first, out.stdout)


def test_the_renderer_refuses_numpys_dispatched_kernels():
    """A process that imported numpy before pidc runs the CPU's own kernels (AVX2, AVX-512): the renderer refuses it
    with an error that names the fix, instead of rendering images that differ from another CPU's. On a CPU with no
    dispatch above the baseline there is nothing to refuse."""
    probe = (
        "import numpy, components; print(components.numpy_kernels(), flush=True); "
        "from components.simulate.procedural import ProceduralSimulator; ProceduralSimulator(32, 32)"
    )
    env = {k: v for k, v in os.environ.items() if k != "NPY_DISABLE_CPU_FEATURES"}
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, env=env, cwd=Path(__file__).resolve().parents[1]
    )
    if out.stdout.startswith("baseline"):  # this CPU has no dispatched kernels
        assert out.returncode == 0, out.stderr
    else:
        assert out.returncode != 0
        assert "import components (or any pidc module) before numpy" in out.stderr, out.stderr
        assert "NPY_DISABLE_CPU_FEATURES=X86_V3" in out.stderr


def test_the_renderer_turns_ipp_off_in_every_thread_that_renders():
    """OpenCV keeps Intel's IPP switch per thread and a new thread starts with IPP on; IPP's kernels differ by CPU.
    A render in a fresh thread (as a thread task runner makes them) must run with IPP off, and so must the
    backbones' size conversion."""
    import threading

    import cv2

    from components.features.backbones.imageops import resize_area

    seen: dict[str, object] = {}

    def render() -> None:
        seen["before"] = cv2.ipp.useIPP()
        try:
            weather = {"cloudiness": 40.0, "fog_density": 10.0, "precipitation": 30.0, "sun_altitude_angle": 30.0}
            weather |= {"wind_intensity": 20.0, "precipitation_deposits": 50.0, "sun_azimuth_angle": 90.0}
            ProceduralSimulator(64, 64).render(weather, 3)
        except Exception as e:  # noqa: BLE001  (reported by the assertion below)
            seen["error"] = repr(e)
        seen["render"] = cv2.ipp.useIPP()

    def resize() -> None:
        resize_area(np.zeros((1, 32, 32, 3), np.uint8), (16, 16))
        seen["resize"] = cv2.ipp.useIPP()

    for target in (render, resize):
        t = threading.Thread(target=target)
        t.start()
        t.join()
    if cv2.ipp.getIppVersion() != "disabled" and seen["before"] is not True:
        pytest.fail(f"a new thread should start with IPP on in this OpenCV, so the test would test nothing: {seen}")
    assert "error" not in seen and seen["render"] is False and seen["resize"] is False, seen


def test_the_renders_do_not_depend_on_opencvs_simd_kernels():
    """With IPP off the images are the same whichever of OpenCV's own kernels run: renders (each in a fresh
    process, scenes built and rendered) with every dispatched feature this CPU has turned off
    (``OPENCV_CPU_DISABLE``, down to OpenCV's SSE3 baseline) equal the default process's to the byte. OpenCV names
    a feature it turned off with a ``?`` in its feature line; the test checks that the switch took effect."""
    probe = (
        "import components, hashlib, cv2, numpy as np; "
        "from components.simulate.procedural import ProceduralSimulator; "
        "s = ProceduralSimulator(96, 96); "
        "ims = [s.render({'cloudiness': c, 'fog_density': f, 'precipitation': p, 'sun_altitude_angle': a, "
        "'precipitation_deposits': d, 'wind_intensity': 30.0, 'sun_azimuth_angle': 40.0 * k}, k) for k, (c, f, p, a, d) in enumerate("
        "[(10, 5, 80, 30, 60), (70, 40, 20, -20, 90), (30, 0, 50, 60, 40), (90, 70, 0, 5, 0), (0, 20, 95, 80, 100)])]; "
        "print(cv2.getCPUFeaturesLine()); print(hashlib.sha256(np.stack(ims).tobytes()).hexdigest())"
    )
    root = Path(__file__).resolve().parents[1]

    def run(env_extra: dict[str, str]) -> tuple[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_")} | env_extra
        out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, cwd=root)
        assert out.returncode == 0, out.stderr
        features, digest = out.stdout.strip().rsplit("\n", 1)
        return features, digest

    features, default = run({})
    dispatched = [f.lstrip("*") for f in features.split() if f.startswith("*") and not f.endswith("?")]
    if not dispatched:
        pytest.fail(f"OpenCV dispatches no kernel above its baseline on this CPU ({features!r}): nothing to compare")
    features_off, limited = run({"OPENCV_CPU_DISABLE": ",".join(dispatched)})
    assert all(f"*{f}?" in features_off.split() for f in dispatched), features_off
    assert limited == default, (features, features_off)


def test_the_renders_do_not_depend_on_the_blas_kernels():
    """The renders are the same whichever kernels numpy's OpenBLAS picks for this CPU: the linear radiance (float32,
    far more sensitive than the uint8 images) of scenes rendered in a fresh process under OpenBLAS's SSE3 kernels
    (``OPENBLAS_CORETYPE=Prescott``, which every x86-64 CPU runs) equals the default process's to the byte. Before
    the renderer's products were written out (docs/studies/openblas-kernels.md), AVX-512's fused multiply-adds made
    them differ on every scene."""
    if platform.machine().lower() not in {"x86_64", "amd64"}:
        pytest.fail(f"OpenBLAS's x86-64 kernel names do not apply on {platform.machine()}: this test needs x86-64")
    probe = (
        "import components, hashlib, numpy as np; "
        "from components.simulate.procedural import ProceduralSimulator; "
        "s = ProceduralSimulator(96, 96); "
        "rs = [s.radiance({'cloudiness': c, 'fog_density': f, 'precipitation': p, 'sun_altitude_angle': a, "
        "'precipitation_deposits': d, 'wind_intensity': 30.0, 'sun_azimuth_angle': 40.0 * k}, k) for k, (c, f, p, a, d) in enumerate("
        "[(10, 5, 80, 30, 60), (70, 40, 20, -20, 90), (30, 0, 50, 60, 40)])]; "
        "print(hashlib.sha256(np.stack(rs).tobytes()).hexdigest())"
    )
    root = Path(__file__).resolve().parents[1]

    def run(coretype: str | None) -> str:
        env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
        if coretype is not None:
            env["OPENBLAS_CORETYPE"] = coretype
        out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, cwd=root)
        assert out.returncode == 0, out.stderr
        return out.stdout.strip().splitlines()[-1]

    assert run("Prescott") == run(None)
