"""Night lighting of a scene (§2.7), precomputed: lamp and head-light light on surfaces, glow sprites.

Street lamps (points at the lamp heads) light surfaces with E = I·max(0, n·l)/r²; oncoming
vehicles' head lights add a beam towards the camera (cos^k of the off-axis angle). Both vary
smoothly and are evaluated at half resolution. Lamp heads and vehicle lights are drawn as Gaussian
core sprites (emitted radiance), plus wider halo sprites that the renderer scales with the fog
(scattering makes halos). Lit windows emit a warm radiance. Everything here is switched on by the
renderer when the sun is below the horizon (CARLA's night mode).

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .calibration import Calibration
from .geometry import Camera
from .layout import Layout

__all__ = ["night_lights"]

_F32 = np.float32


def _sprites(
    cam: Camera,
    pts: np.ndarray,
    amp: np.ndarray,
    colour: np.ndarray,
    sigma: float,
    depth_map: np.ndarray,
    out: np.ndarray,
) -> None:
    """Add Gaussian sprites (σ px) of amplitude amp·colour (K, 3) at the visible projections of
    pts (K, 3) to ``out`` (3, H·W) channel-planar; an emitter behind a nearer surface is left out."""
    H, W = depth_map.shape
    if len(pts) == 0:
        return
    col, row, z = cam.project(pts)
    dist = np.linalg.norm(pts - cam.origin, axis=1)
    rad = int(math.ceil(3 * sigma))
    ci, ri = np.round(col).astype(np.int64), np.round(row).astype(np.int64)
    on = (ci >= 0) & (ci < W) & (ri >= 0) & (ri < H)
    hidden = np.zeros(len(pts), bool)
    hidden[on] = depth_map[ri[on], ci[on]] < dist[on] - 1.0
    keep = (z > 0.3) & ~hidden & (ci >= -rad) & (ci < W + rad) & (ri >= -rad) & (ri < H + rad)
    if not keep.any():
        return
    off = np.arange(-rad, rad + 1)
    rr = ri[keep][:, None, None] + off[None, :, None]
    cc = ci[keep][:, None, None] + off[None, None, :]
    g = np.exp(-((cc - col[keep][:, None, None]) ** 2 + (rr - row[keep][:, None, None]) ** 2) / (2 * sigma * sigma))
    g = g * amp[keep][:, None, None]
    inside = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
    rr, cc = np.broadcast_to(rr, g.shape), np.broadcast_to(cc, g.shape)
    flat = (rr * W + cc)[inside]
    k = np.broadcast_to(np.arange(int(keep.sum()))[:, None, None], g.shape)[inside]
    w = g[inside]
    cols = colour[keep]
    for c in range(3):
        out[c] += np.bincount(flat, weights=w * cols[k, c], minlength=H * W)


def night_lights(
    lay: Layout,
    cam: Camera,
    pos: np.ndarray,
    normal: np.ndarray,
    albedo: np.ndarray,
    depth: np.ndarray,
    window_lit: np.ndarray,
    cal: Calibration,
) -> tuple[np.ndarray, np.ndarray]:
    """(night radiance (3, N), halo radiance at full fog (3, N)), float32, channel-planar.

    ``pos``/``normal``/``albedo`` (N, 3), ``depth`` (N,) (inf: sky), ``window_lit`` (N,) bool.
    """
    H, W = cam.height, cam.width
    N = H * W
    px = H / 128.0
    o = cam.origin
    lamp_col = np.asarray(cal.lamp_colour)
    solid = np.isfinite(depth)
    ps = pos.reshape(H, W, 3)[::2, ::2].reshape(-1, 3).astype(_F32)
    ns = normal.reshape(H, W, 3)[::2, ::2].reshape(-1, 3).astype(_F32)
    hs, ws = (H + 1) // 2, (W + 1) // 2

    def full(e: np.ndarray) -> np.ndarray:
        return cv2.resize(e.reshape(hs, ws).astype(_F32), (W, H), interpolation=cv2.INTER_LINEAR).ravel() * solid

    acc = np.zeros(len(ps), _F32)
    for lamp in lay.lamps:
        vx, vy, vz = lamp[0] - ps[:, 0], lamp[1] - ps[:, 1], lamp[2] - ps[:, 2]
        r2 = np.maximum(vx * vx + vy * vy + vz * vz, 1.0)
        acc += np.maximum(vx * ns[:, 0] + vy * ns[:, 1] + vz * ns[:, 2], 0.0) / (r2 * np.sqrt(r2))
    e_lamp = cal.lamp_intensity * full(acc)
    acc = np.zeros(len(ps), _F32)
    for light in lay.lights[lay.light_is_head]:
        vx, vy, vz = light[0] - ps[:, 0], light[1] - ps[:, 1], light[2] - ps[:, 2]
        r2 = np.maximum(vx * vx + vy * vy + vz * vz, 1.0)
        r = np.sqrt(r2)
        cone = np.clip(-vz / r, 0, 1) ** cal.headlight_cone_exponent  # beams point towards -z (the camera)
        acc += cone * np.maximum(vx * ns[:, 0] + vy * ns[:, 1] + vz * ns[:, 2], 0.0) / (r2 * r)
    e_head = cal.headlight_intensity * full(acc)
    head_col = np.array([0.95, 0.95, 1.0])
    night = albedo.T.astype(_F32) * (
        (e_lamp[None, :] * lamp_col[:, None] + e_head[None, :] * head_col[:, None]) / math.pi
    ).astype(_F32)
    night[:, window_lit] += (cal.window_emission * np.array([1.0, 0.8, 0.55], _F32))[:, None]
    depth_map = depth.reshape(H, W)
    spr = np.zeros((3, N))
    halo = np.zeros((3, N))
    if len(lay.lamps):
        dist = np.linalg.norm(lay.lamps - o, axis=1)
        near = np.minimum(1.0, cal.lamp_reference_distance / dist)
        cols = np.tile(lamp_col, (len(dist), 1))
        _sprites(cam, lay.lamps, cal.lamp_core * near**2, cols, cal.sprite_px * px, depth_map, spr)
        _sprites(cam, lay.lamps, cal.lamp_halo * near, cols, cal.lamp_halo_px * px, depth_map, halo)
    if len(lay.lights):
        dist = np.linalg.norm(lay.lights - o, axis=1)
        near = np.minimum(1.0, cal.light_reference_distance / dist)
        amp = np.where(lay.light_is_head, cal.headlight_core, cal.taillight_core) * near**2
        cols = np.where(lay.light_is_head[:, None], np.array([1.0, 0.97, 0.9]), np.array([1.0, 0.05, 0.02]))
        _sprites(cam, lay.lights, amp, cols, 0.8 * cal.sprite_px * px, depth_map, spr)
        _sprites(cam, lay.lights, 0.4 * cal.lamp_halo * near, cols, 0.6 * cal.lamp_halo_px * px, depth_map, halo)
    night += spr.astype(_F32)
    return np.ascontiguousarray(night), halo.astype(_F32)
