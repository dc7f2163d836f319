"""Rain streaks and lens drops (§2.4), drawn from a scene's pre-drawn pools.

Rain rate R = R_max (p/100)^γ (mm/h). The first ``pool·(R/R_max)^k`` drops of the scene's pool are
drawn (common random numbers: more rain only adds drops). A drop's diameter is its stored quantile
u mapped through the Marshall–Palmer exponential, D = −ln(1−u)/Λ with Λ = 4.1 R^−0.21 mm⁻¹; its
fall speed v(D) = 9.65 − 10.3 e^{−0.6 D} m/s (Atlas 1973). The lateral wind u_x = k_w (wind/100)
sin(α_w) (α_w the scene's wind azimuth relative to the camera) slants the streak by atan(u_x/v);
its image length is f·|(u_x, v)|·T_eff/Z pixels, its width one pixel at 128 × 128 (px = H/128 pixels at
H × W, its opacity per pixel × px/⌈px⌉, so that a streak's opacity per solid angle does not depend on the image
size). Streaks are scattered with ``np.bincount`` over sample points along every segment (⌈px⌉ lines
across; no Python loop over drops), occluded by the depth map, and composited with the mean scene radiance
(a drop refracts a wide field of view). The pool holds the same drops at every image size.
Lens drops: pixels covered by an active drop (priority < fraction·p/100) show a blurred, flipped
view of the scene through the drop.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .calibration import CALIBRATION, Calibration
from .scene import Scene

__all__ = ["rain_rate", "streak_alpha", "add_streaks", "add_lens_drops"]


def rain_rate(precipitation: float, cal: Calibration = CALIBRATION) -> float:
    """Rain rate R (mm/h) at ``precipitation`` (%)."""
    return cal.rain_rate_max * (precipitation / 100.0) ** cal.rain_rate_exponent


def streak_alpha(scene: Scene, precipitation: float, wind: float, cal: Calibration = CALIBRATION) -> np.ndarray:
    """Streak opacity per pixel (N,) float32 in [0, 0.9]; all zeros when ``precipitation`` is 0."""
    N = scene.height * scene.width
    if precipitation <= 0.0:
        return np.zeros(N, np.float32)
    R = rain_rate(precipitation, cal)
    n = int(round(len(scene.rain.z) * (R / cal.rain_rate_max) ** cal.rain_count_exponent))
    if n == 0:
        return np.zeros(N, np.float32)
    px = scene.height / 128.0
    z = scene.rain.z[:n]
    lam = 4.1 * max(R, 1e-3) ** -0.21
    diam = np.clip(-np.log1p(-scene.rain.u[:n] * 0.999) / lam, 0.3, 6.0)
    v = np.maximum(9.65 - 10.3 * np.exp(-0.6 * diam), 1.0)
    ux = cal.wind_speed_max * (wind / 100.0) * math.sin(math.radians(scene.layout.wind_azimuth_deg))
    speed = np.sqrt(v * v + ux * ux)
    length = np.minimum(scene.camera.focal * speed * cal.streak_exposure / z, cal.streak_max_px * px).astype(np.float32)
    ex, ey = (ux / speed).astype(np.float32), (v / speed).astype(np.float32)
    k = int(math.ceil(float(length.max()))) + 1
    s = np.linspace(-0.5, 0.5, k, dtype=np.float32)[None, :]
    cols = scene.rain.col[:n, None] + (s * length[:, None]) * ex[:, None]
    rows = scene.rain.row[:n, None] + (s * length[:, None]) * ey[:, None]
    m = max(1, math.ceil(px - 1e-6))  # sample lines across a streak px pixels wide (one at 128 pixels and below)
    if m > 1:
        across = (((np.arange(m, dtype=np.float32) + 0.5) / m - 0.5) * px)[None, None, :]
        cols = (cols[:, :, None] - across * ey[:, None, None]).reshape(n, k * m)
        rows = (rows[:, :, None] + across * ex[:, None, None]).reshape(n, k * m)
    ci = cols.astype(np.int32)
    ri = rows.astype(np.int32)
    inside = (cols >= 0) & (ci < scene.width) & (rows >= 0) & (ri < scene.height)
    pix = (ri * scene.width + ci)[inside]
    a = (
        cal.streak_alpha
        * (precipitation / 100.0) ** cal.streak_alpha_exponent
        * np.clip(cal.streak_near_depth / z, cal.streak_far_alpha, 1.0)
    )
    per_sample = a * np.minimum(length / (k - 1), 1.0)
    if px != m:  # a streak's opacity spread over its width: the same per 128-pixel area at every size
        per_sample = per_sample * np.float32(px / m)
    w = np.broadcast_to(per_sample[:, None], cols.shape)[inside]
    zz = np.broadcast_to(z[:, None], cols.shape)[inside]
    w = np.where(scene.depth[pix] > zz, w, 0.0)
    acc = np.bincount(pix, weights=w, minlength=N)
    return np.minimum(acc, cal.streak_alpha_cap).astype(np.float32)


def add_streaks(radiance: np.ndarray, alpha: np.ndarray, streak_radiance: np.ndarray) -> None:
    """In place: L ← L + α (L_streak − L) for radiance (3, N), α (N,), L_streak (3,)."""
    hit = np.flatnonzero(alpha)
    if len(hit):
        a = alpha[hit][None, :]
        radiance[:, hit] += a * (streak_radiance.astype(np.float32)[:, None] - radiance[:, hit])


def add_lens_drops(scene: Scene, radiance: np.ndarray, precipitation: float, cal: Calibration = CALIBRATION) -> None:
    """In place on radiance (3, N): pixels under active lens drops show a blurred, flipped view."""
    thr = cal.lens_drop_fraction * precipitation / 100.0
    k = int(np.searchsorted(scene.lens.priority, thr, side="left"))
    if k == 0:
        return
    ks = max(int(round(cal.lens_blur_px * scene.height / 128.0)) | 1, 1)
    px = scene.lens.pixels[:k]
    src = scene.lens.source[:k]
    shade = scene.lens.shade[:k]
    for c in range(3):
        blurred = cv2.blur(radiance[c].reshape(scene.height, scene.width), (ks, ks)).ravel()
        radiance[c, px] = blurred[src] * shade
