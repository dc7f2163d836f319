"""The cached, weather-independent part of a scene: geometry buffers, static fields, pools.

:func:`build_scene` draws a layout from the scene seed, casts the camera rays once and precomputes
everything a render needs that does not depend on the weather: per-pixel depth, normals, materials,
albedo (:mod:`.surfaces`), the road's mirror reflections (:mod:`.reflections`), the sky rays (direct
and reflected) with their cloud-noise quantiles and fog path lengths, shadow receivers and occluders
(:mod:`.shadows`), night lighting (:mod:`.lights`) and the rain- and lens-drop pools (:mod:`.pools`).

Random streams: ``np.random.SeedSequence(scene_seed).spawn(7)`` → layout, surface texture, clouds,
puddles, rain drops, lens drops, windows. The three noise fields are the scene's views (random
shift and symmetry) of static world textures (:func:`.noise.scene_texture`), as CARLA's puddles
come from static noise. Weather only thresholds or scales these fields later (common random
numbers), so a scene re-renders identically under any weather.

Per-pixel arrays are flattened in row-major order (``N = H·W``); float arrays are float32.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from components.core.weather import FIXED

from .calibration import CALIBRATION, Calibration
from .geometry import Camera, cast_objects, make_camera
from .layout import MARKING, ROAD, SKY, Layout, sample_layout
from .lights import night_lights
from .noise import gaussian_cdf, sample_texture, scene_texture
from .pools import LensPool, RainPool, lens_pool, rain_pool
from .reflections import RoadReflections, road_reflections, sky_fog_path
from .shadows import ShadowGeometry, shadow_geometry
from .surfaces import surfaces

__all__ = ["Scene", "build_scene", "N_STREAMS"]

N_STREAMS = 7
_F32 = np.float32


@dataclass(frozen=True)
class Scene:
    """Precomputed buffers of one scene at one resolution (see the module docstring).

    Image-sized: ``dirs`` (N, 3) ray directions, ``material`` (N,) int8 ids of
    :mod:`components.simulate.procedural.layout`, ``depth`` (N,) metres (inf for sky), ``fog_path`` (N,) metres
    of fog along the ray (sky: finite height-fog integral), ``albedo`` (3, N) channel-planar,
    ``normal`` (N, 3), ``ambient_factor`` (N,), ``night_radiance`` (3, N) lamp/window/vehicle-light
    radiance when lamps are on, ``halo`` (3, N) lamp halo radiance at full fog.
    Sky rays: ``sky_pixels`` (S₀,) pixel indices; ``sky_dirs`` (S, 3) with the first S₀ the sky
    pixels and the rest the reflected sky rays of road pixels; ``sky_quantile`` (S,) cloud-noise
    quantiles; ``sky_path`` (S,) fog path lengths. ``reflections``, ``shadow``, ``rain`` and ``lens``
    hold the puddle lookups, shadow geometry and drop pools.
    """

    seed: int
    height: int
    width: int
    layout: Layout
    camera: Camera
    dirs: np.ndarray
    material: np.ndarray
    depth: np.ndarray
    fog_path: np.ndarray
    albedo: np.ndarray
    normal: np.ndarray
    ambient_factor: np.ndarray
    night_radiance: np.ndarray
    halo: np.ndarray
    sky_pixels: np.ndarray
    sky_dirs: np.ndarray
    sky_quantile: np.ndarray
    sky_path: np.ndarray
    reflections: RoadReflections
    shadow: ShadowGeometry
    rain: RainPool
    lens: LensPool

    def mask(self, *materials: int) -> np.ndarray:
        """Boolean (H, W) mask of the pixels whose material is one of ``materials``."""
        return np.isin(self.material, materials).reshape(self.height, self.width)

    @property
    def depth_map(self) -> np.ndarray:
        """Distance along the ray (m), (H, W); inf for sky."""
        return self.depth.reshape(self.height, self.width)

    @property
    def road_mask(self) -> np.ndarray:
        """(H, W) bool: road surface incl. markings (where puddles can be)."""
        return self.mask(ROAD, MARKING)

    @property
    def sky_mask(self) -> np.ndarray:
        return self.mask(SKY)


def build_scene(scene_seed: int, height: int, width: int, cal: Calibration = CALIBRATION) -> Scene:
    """Build the cached part of scene ``scene_seed`` at ``height × width`` pixels."""
    streams = [np.random.Generator(np.random.PCG64(s)) for s in np.random.SeedSequence(scene_seed).spawn(N_STREAMS)]
    r_layout, r_tex, r_cloud, r_puddle, r_rain, r_lens, r_window = streams
    lay = sample_layout(r_layout, cal)
    H, W = height, width
    cam = make_camera(lay.camera, lay.fov_deg, lay.pitch_deg, lay.yaw_deg, H, W)
    dirs = cam.rays()
    o = cam.origin
    dy = dirs[..., 1]
    with np.errstate(divide="ignore"):
        t_ground = np.where(dy < -1e-6, o[1] / np.maximum(-dy, 1e-12), np.inf)
    hits = cast_objects(
        cam, dirs, lay.box_lo, lay.box_hi, lay.sphere_center, lay.sphere_radius, np.full((H, W), 0.05), t_ground
    )
    d = dirs.reshape(-1, 3)
    surf = surfaces(
        lay, o, d, hits, t_ground.ravel(), scene_texture(r_tex, "surface", 64, 0.5, cal.texture_seed), r_window, cal
    )
    sky = surf.material == SKY
    depth = np.where(sky, np.inf, surf.t)
    fog_path = np.maximum(np.where(sky, 0.0, depth) - FIXED["fog_distance"], 0.0).astype(_F32)
    fog_path[sky] = sky_fog_path(d[sky, 1], cal)
    ambient_factor = (cal.ambient_vertical + (1 - cal.ambient_vertical) * np.clip(surf.normal[:, 1], 0, 1)).astype(_F32)
    refl = road_reflections(lay, cam, d, surf.pos, np.isin(surf.material, (ROAD, MARKING)), r_puddle, cal)
    # sky rays: direct, then reflected; clouds on a plane at cloud_height (foreshortened to the horizon)
    sky_pixels = np.flatnonzero(sky)
    sky_dirs = np.concatenate([d[sky_pixels], refl.sky_dirs]).astype(_F32)
    ctex = scene_texture(r_cloud, "cloud", 128, 0.55, cal.texture_seed)
    sdy = np.maximum(sky_dirs[:, 1].astype(np.float64), 0.02)
    k = cal.cloud_height / sdy * (128 / cal.cloud_scale)
    sky_quantile = gaussian_cdf(sample_texture(ctex, sky_dirs[:, 0] * k, sky_dirs[:, 2] * k))
    night, halo = night_lights(lay, cam, surf.pos, surf.normal, surf.albedo, depth, surf.window_lit, cal)
    return Scene(
        seed=int(scene_seed),
        height=H,
        width=W,
        layout=lay,
        camera=cam,
        dirs=d.astype(_F32),
        material=surf.material,
        depth=depth.astype(_F32),
        fog_path=fog_path,
        albedo=np.ascontiguousarray(surf.albedo.T, _F32),
        normal=surf.normal.astype(_F32),
        ambient_factor=ambient_factor,
        night_radiance=night,
        halo=halo,
        sky_pixels=sky_pixels,
        sky_dirs=sky_dirs,
        sky_quantile=sky_quantile.astype(_F32),
        sky_path=sky_fog_path(sky_dirs[:, 1], cal),
        reflections=refl,
        shadow=shadow_geometry(lay, surf.material, surf.normal, surf.pos, surf.ground, cal),
        rain=rain_pool(r_rain, H, W, cal),
        lens=lens_pool(r_lens, H, W, cal),
    )
