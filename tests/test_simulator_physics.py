"""Physical behaviour of the procedural renderer: each test compares renders of one scene.

The thresholds are chosen so that a renderer missing the effect (or wiring it to the wrong
parameter) fails: fog lowers far-field contrast and hides the sky; clouds show only in daylight
without fog; night darkens the image and switches emitters on; rain adds streaks slanted by wind
(and wind alone changes nothing), the same rain at every image size; puddles appear only on the road and mirror the sky; the sun's
azimuth moves shadows, which fade under clouds and fog.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from components.simulate.procedural import ProceduralSimulator
from components.simulate.procedural.layout import ROAD, SKY
from components.simulate.procedural.rain import streak_alpha
from components.simulate.procedural.shadows import sun_visibility
from components.simulate.procedural.sky import sun_sky

BASE = {
    "cloudiness": 0.0,
    "fog_density": 0.0,
    "precipitation": 0.0,
    "sun_altitude_angle": 45.0,
    "wind_intensity": 0.0,
    "precipitation_deposits": 0.0,
    "sun_azimuth_angle": 90.0,
}


@pytest.fixture(scope="module")
def sim() -> ProceduralSimulator:
    return ProceduralSimulator(128, 128, cache_size=64)


def grey(img: np.ndarray) -> np.ndarray:
    return img.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def first_seed(sim: ProceduralSimulator, ok, limit: int = 60) -> int:
    for seed in range(limit):
        if ok(sim.scene(seed)):
            return seed
    raise AssertionError("no scene in the first seeds has the needed layout")


def test_fog_lowers_far_contrast_and_hides_the_sky(sim: ProceduralSimulator) -> None:
    seed = first_seed(sim, lambda s: ((s.depth > 40) & (s.depth < 200)).sum() > 400 and s.sky_mask.mean() > 0.2)
    sc = sim.scene(seed)
    far = ((sc.depth_map > 40) & (sc.depth_map < 200)).ravel()
    sky = sc.sky_mask.ravel()
    contrast, sky_std = [], []
    for fog in (0.0, 30.0, 80.0):
        g = grey(sim.render({**BASE, "cloudiness": 50.0, "fog_density": fog}, seed)).ravel()
        contrast.append(g[far].std())
        sky_std.append(g[sky].std())
    assert contrast[0] > contrast[1] > contrast[2]
    assert contrast[2] < 0.3 * contrast[0]
    assert sky_std[2] < 0.15 * sky_std[0]

    # dense fog: the sky no longer shows the cloud pattern (only the overall light level changes)
    def cloud_pattern(fog: float) -> float:
        a = grey(sim.render({**BASE, "cloudiness": 0.0, "fog_density": fog}, seed)).ravel()
        b = grey(sim.render({**BASE, "cloudiness": 50.0, "fog_density": fog}, seed)).ravel()
        return float((a - b)[sky].std())

    assert cloud_pattern(90.0) < 0.1 * cloud_pattern(0.0)


def test_clouds_show_only_in_daylight_without_fog(sim: ProceduralSimulator) -> None:
    seed = first_seed(sim, lambda s: s.sky_mask.mean() > 0.25)
    sky = sim.scene(seed).sky_mask

    def effect(**kw: float) -> float:
        a = grey(sim.render({**BASE, **kw, "cloudiness": 0.0}, seed))
        b = grey(sim.render({**BASE, **kw, "cloudiness": 70.0}, seed))
        return float(np.abs(a - b)[sky].mean())

    day = effect()
    assert day > 10.0
    assert effect(sun_altitude_angle=-40.0) < 0.15 * day
    assert effect(fog_density=85.0) < 0.15 * day
    # coverage follows cloudiness: the fraction of sky radiance changed by clouds ≈ cloudiness
    a = grey(sim.radiance(BASE, seed))[sky]
    covered = [
        np.mean(np.abs(grey(sim.radiance({**BASE, "cloudiness": c}, seed))[sky] / a - 1) > 0.05) for c in (20, 50, 90)
    ]
    assert covered[0] < covered[1] < covered[2]
    assert 0.05 < covered[0] < 0.5 and covered[2] > 0.8


def test_night_darkens_and_switches_lamps_and_vehicle_lights_on(sim: ProceduralSimulator) -> None:
    seed = first_seed(sim, lambda s: s.night_radiance.max() > 1.0 and len(s.layout.lamps) > 2)
    sc = sim.scene(seed)
    day = grey(sim.render({**BASE, "sun_altitude_angle": 30.0}, seed))
    night = grey(sim.render({**BASE, "sun_altitude_angle": -30.0}, seed))
    assert night.mean() < 0.35 * day.mean()
    dusk = sim.render({**BASE, "sun_altitude_angle": 0.5}, seed).astype(int)
    lit = sim.render({**BASE, "sun_altitude_angle": -0.5}, seed).astype(int)
    jump = (lit - dusk).max(axis=2)
    assert (jump > 60).sum() >= 3  # bright emitters appear when the sun crosses 0°
    # the brightest night pixels are artificial light: emitters (lamps, vehicle lights, windows)
    # or surfaces in their light, and some sit right on projected lamps / vehicle lights
    emitters = np.concatenate([sc.layout.lamps, sc.layout.lights])
    col, row, z = sc.camera.project(emitters)
    ok = (z > 0) & (col > -3) & (col < 131) & (row > -3) & (row < 131)
    bright = np.argwhere(grey(sim.render({**BASE, "sun_altitude_angle": -30.0}, seed)) > 200)
    assert len(bright) >= 2
    dist = np.min(np.hypot(bright[:, :1] - row[ok][None, :], bright[:, 1:] - col[ok][None, :]), axis=1)
    artificial = sc.night_radiance.max(axis=0).reshape(128, 128)[bright[:, 0], bright[:, 1]]
    assert np.all(artificial > 0.05)
    assert (dist < 4.0).sum() >= 2
    # below the twilight band the sun altitude is not identifiable
    deep = [grey(sim.render({**BASE, "sun_altitude_angle": h}, seed)) for h in (-30.0, -80.0)]
    assert np.abs(deep[0] - deep[1]).mean() < 1.0


def _slant_deg(alpha: np.ndarray) -> float:
    """Mean streak slant from vertical (deg) by the structure tensor of the streak layer."""
    gy, gx = np.gradient(alpha)
    jxx, jyy, jxy = (gx * gx).sum(), (gy * gy).sum(), (gx * gy).sum()
    return math.degrees(0.5 * math.atan2(2 * jxy, jxx - jyy))


def test_rain_adds_streaks_whose_slant_grows_with_wind(sim: ProceduralSimulator) -> None:
    seed = first_seed(sim, lambda s: abs(math.sin(math.radians(s.layout.wind_azimuth_deg))) > 0.8)
    sc = sim.scene(seed)
    dry = sim.render(BASE, seed)
    # no rain: wind changes nothing at all
    assert sim.render({**BASE, "wind_intensity": 100.0}, seed).tobytes() == dry.tobytes()
    wet = sim.render({**BASE, "precipitation": 70.0}, seed)
    assert np.abs(wet.astype(int) - dry).max() > 40
    a_light = streak_alpha(sc, 20.0, 0.0)
    a_heavy = streak_alpha(sc, 90.0, 0.0)
    assert (a_heavy > 0.02).sum() > 1.5 * (a_light > 0.02).sum() > 0
    slants = [abs(_slant_deg(streak_alpha(sc, 70.0, w).reshape(128, 128))) for w in (0.0, 50.0, 100.0)]
    assert slants[0] < 5.0
    assert slants[0] + 8 < slants[1] < slants[2] - 5
    assert slants[2] > 25.0
    # rain and wind render differently, and the streaks sit in front of the scene (depth-occluded)
    assert sim.render({**BASE, "precipitation": 70.0, "wind_intensity": 100.0}, seed).tobytes() != wet.tobytes()


def test_the_rain_is_the_same_rain_at_every_image_size() -> None:
    """A scene's drop pool holds the same drops at every image size (positions scaled with the image), and the
    streaks' mean opacity — their opacity per solid angle — stays within 5 % of the 128-pixel render's from 96 to 384
    pixels (it grew with the size, ×1.9 at 256 and ×2.9 at 384, when the pool scaled with the pixel count), and their
    image, area-resized to 128 pixels, keeps the streaks' direction."""
    small = ProceduralSimulator(128, 128, cache_size=4)
    mean = {}
    for size in (96, 128, 192, 256, 384):
        sim = small if size == 128 else ProceduralSimulator(size, size, cache_size=4)
        scenes = [sim.scene(seed) for seed in range(4)]
        for a, b in zip(scenes, (small.scene(seed) for seed in range(4)), strict=True):
            assert np.array_equal(a.rain.z, b.rain.z) and np.array_equal(a.rain.u, b.rain.u)
            np.testing.assert_allclose(a.rain.col * 128 / size, b.rain.col, rtol=1e-5, atol=1e-3)
        mean[size] = np.mean([streak_alpha(sc, p, 60.0).mean() for sc in scenes for p in (20.0, 60.0, 100.0)])
    for size, value in mean.items():
        assert value == pytest.approx(mean[128], rel=0.05), (size, value / mean[128])
    seed = first_seed(small, lambda s: abs(math.sin(math.radians(s.layout.wind_azimuth_deg))) > 0.8)
    big = ProceduralSimulator(256, 256, cache_size=1).scene(seed)
    streaks = streak_alpha(big, 70.0, 100.0).reshape(256, 256)
    resized = streaks.reshape(128, 2, 128, 2).mean(axis=(1, 3))
    assert abs(_slant_deg(resized) - _slant_deg(streak_alpha(small.scene(seed), 70.0, 100.0).reshape(128, 128))) < 5.0


def test_puddles_appear_only_on_the_road_and_mirror_the_sky(sim: ProceduralSimulator) -> None:
    seed = first_seed(sim, lambda s: s.road_mask.mean() > 0.2)
    sc = sim.scene(seed)
    road = sc.road_mask
    dry = sim.render(BASE, seed).astype(int)
    dry_l = sim.radiance(BASE, seed)
    changed = []
    for dep in (20.0, 60.0, 100.0):
        diff_l = np.abs(sim.radiance({**BASE, "precipitation_deposits": dep}, seed) - dry_l).max(axis=2)
        assert diff_l[~road].max() == 0.0  # nowhere else (in radiance; the auto-exposure may shift the image)
        changed.append((diff_l[road] > 0.02 * dry_l.max(axis=2)[road]).mean())
    assert changed[0] < changed[1] < changed[2]
    assert changed[2] > 0.8
    # the flooded road takes the (blue) colour of the clear sky it mirrors, far more than the dry road
    far_road = road & (sc.depth_map > 12)
    wet = sim.render({**BASE, "precipitation_deposits": 100.0}, seed).astype(int)
    blue_dry = (dry[..., 2] - dry[..., 0])[far_road].mean()
    blue_wet = (wet[..., 2] - wet[..., 0])[far_road].mean()
    assert blue_wet > blue_dry + 5
    # in the image the road changes far more than the rest (which only follows the auto-exposure)
    diff = np.abs(wet - dry).max(axis=2)
    assert diff[road].mean() > 4 * max(diff[~road].mean(), 0.5)


def test_sun_azimuth_moves_shadows_which_fade_under_clouds_and_fog(sim: ProceduralSimulator) -> None:
    seed = first_seed(sim, lambda s: s.layout.archetype == "urban_canyon" and s.road_mask.mean() > 0.15)
    sc = sim.scene(seed)
    head = sc.layout.heading_deg
    # sun from the right side of the road (relative azimuth 90°), then from the left
    w = {**BASE, "sun_altitude_angle": 55.0, "sun_azimuth_angle": (head + 90.0) % 360}
    vis_a = sun_visibility(sc.shadow, sc.height * sc.width, sun_sky(55.0, 90.0, 0.0, 0.0).sun_dir)
    vis_b = sun_visibility(sc.shadow, sc.height * sc.width, sun_sky(55.0, 270.0, 0.0, 0.0).sun_dir)
    ground = sc.shadow.ground_pixels
    assert np.mean(vis_a[ground] != vis_b[ground]) > 0.05
    img_a = sim.render(w, seed)
    img_b = sim.render({**w, "sun_azimuth_angle": (head + 270.0) % 360}, seed)
    assert np.abs(img_a.astype(int) - img_b).max(axis=2)[sc.road_mask].mean() > 5
    road = np.isin(sc.material, (ROAD,))
    shade, lit = road & (vis_a == 0), road & (vis_a == 1)
    assert shade.sum() > 30 and lit.sum() > 30

    def contrast(**kw: float) -> float:
        g = grey(sim.radiance({**w, **kw}, seed)).ravel()
        return float(g[lit].mean() / g[shade].mean())

    assert contrast() > 2.0
    assert contrast(cloudiness=100.0) < 1.25
    assert contrast(fog_density=100.0) < 1.25
    # longer shadows at low sun
    low = sun_visibility(sc.shadow, sc.height * sc.width, sun_sky(20.0, 90.0, 0.0, 0.0).sun_dir)
    assert (low[ground] == 0).mean() > (vis_a[ground] == 0).mean()
    assert not np.isin(sc.material[ground], (SKY,)).any()
