"""Mirror reflections of the road (puddles, §2.5), precomputed per scene.

A ray reflected at a flat road point continues along (d_x, −d_y, d_z); equivalently the camera
ray continues into the scene mirrored below the ground, which is what is cast (at half resolution:
ripples blur the reflection anyway). A reflected ray that hits an object takes the radiance of the
pixel where the camera sees that object (screen-space lookup); one that escapes takes the sky
radiance along the reflected direction, evaluated by the renderer with the direct sky rays.
Per road pixel this module stores the source index, the source of a jittered neighbour (rain
ripples), the reflected path length (for fog), the Schlick Fresnel reflectance and the static
puddle-noise quantile, sorted by that quantile so deposits select a prefix.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .calibration import Calibration
from .geometry import Camera, cast_objects, make_camera
from .layout import Layout
from .noise import gaussian_cdf, sample_texture, scene_texture

__all__ = ["RoadReflections", "road_reflections"]

_F32 = np.float32


@dataclass(frozen=True)
class RoadReflections:
    """Road pixels sorted by puddle quantile: ``pixels``, ``quantile``, ``fresnel``, ``source`` and
    ``source_ripple`` (indices into [pixel radiance (N) ; reflected sky radiance]), ``path`` (m);
    ``sky_dirs`` (S', 3) the escaping reflected directions, in the order of their sources."""

    pixels: np.ndarray
    quantile: np.ndarray
    fresnel: np.ndarray
    source: np.ndarray
    source_ripple: np.ndarray
    path: np.ndarray
    sky_dirs: np.ndarray


def sky_fog_path(dir_y: np.ndarray, cal: Calibration) -> np.ndarray:
    """Equivalent homogeneous path (m) of the height fog to infinity: H_s / sin e, capped."""
    return np.minimum(cal.fog_scale_height / np.maximum(dir_y, 1e-6), cal.sky_max_path).astype(_F32)


def road_reflections(
    lay: Layout,
    cam: Camera,
    dirs: np.ndarray,
    pos: np.ndarray,
    road: np.ndarray,
    rng: np.random.Generator,
    cal: Calibration,
) -> RoadReflections:
    """Reflection lookups of the ``road`` pixels (N,) bool; ``dirs``/``pos`` (N, 3); ``rng`` is the
    scene's puddle stream (noise texture and ripple jitter)."""
    H, W = cam.height, cam.width
    N = H * W
    o = cam.origin
    mirror_lo, mirror_hi = lay.box_lo.copy(), lay.box_hi.copy()
    mirror_lo[:, 1], mirror_hi[:, 1] = -lay.box_hi[:, 1], -lay.box_lo[:, 1]
    mc = lay.sphere_center.copy()
    mc[:, 1] *= -1
    h2, w2 = (H + 1) // 2, (W + 1) // 2
    cam2 = make_camera(lay.camera, lay.fov_deg, lay.pitch_deg, lay.yaw_deg, h2, w2)
    dirs2 = cam2.rays()
    with np.errstate(divide="ignore"):
        tg2 = np.where(dirs2[..., 1] < -1e-6, o[1] / np.maximum(-dirs2[..., 1], 1e-12), np.inf)
    road_rows = np.flatnonzero(road.reshape(H, W).any(axis=1))
    rows = (int(road_rows[0]) // 2, (int(road_rows[-1]) + 2) // 2) if len(road_rows) else (0, 0)
    mh = cast_objects(cam2, dirs2, mirror_lo, mirror_hi, mc, lay.sphere_radius, tg2, np.full((h2, w2), np.inf), rows)
    px = np.flatnonzero(road)
    half = (px // W // 2) * w2 + (px % W) // 2
    m_t = mh.t.ravel()[half]
    refl_dir = dirs[px] * (1.0, -1.0, 1.0)
    geo = np.isfinite(m_t)
    hit_mirrored = o + np.where(geo, m_t, 0.0)[:, None] * dirs2.reshape(-1, 3)[half]
    q = np.where(geo[:, None], hit_mirrored * (1.0, -1.0, 1.0), pos[px])
    qc, qr, _ = cam.project(q)
    src_geo = np.clip(np.round(qr).astype(np.int64), 0, H - 1) * W + np.clip(np.round(qc).astype(np.int64), 0, W - 1)
    sky_dirs = refl_dir[~geo]
    source = np.where(geo, src_geo, 0)
    source[~geo] = N + np.arange(int((~geo).sum()))
    path = np.linalg.norm(q - pos[px], axis=1).astype(_F32)
    path[~geo] = sky_fog_path(sky_dirs[:, 1], cal)
    # ripples: the source of a jittered neighbouring road pixel
    jr = rng.normal(0.0, cal.ripple_px * H / 128.0, (len(px), 2))
    rr = np.clip(px // W + np.round(jr[:, 0]).astype(np.int64), 0, H - 1)
    rc = np.clip(px % W + np.round(jr[:, 1]).astype(np.int64), 0, W - 1)
    lookup = np.full(N, -1, np.int64)
    lookup[px] = np.arange(len(px))
    nb = lookup[rr * W + rc]
    ripple = np.where(nb >= 0, source[np.maximum(nb, 0)], source)
    cos_i = np.clip(-dirs[px, 1], 0.0, 1.0)
    fresnel = np.maximum(cal.water_f0 + (1 - cal.water_f0) * (1 - cos_i) ** 5, cal.puddle_min_reflectance)
    tex = scene_texture(rng, "puddle", 64, 0.4, cal.texture_seed)
    k = 64 / cal.puddle_scale
    quant = gaussian_cdf(sample_texture(tex, pos[px, 0] * k, pos[px, 2] * k))
    order = np.argsort(quant, kind="stable")
    return RoadReflections(
        px[order],
        quant[order].astype(_F32),
        fresnel[order].astype(_F32),
        source[order],
        ripple[order],
        path[order],
        sky_dirs.astype(_F32),
    )
