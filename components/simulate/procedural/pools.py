"""Pre-drawn pools of a scene: rain drops (camera frame) and lens drops (per-pixel lookup).

Weather only selects a prefix of each pool (common random numbers): the first drops of the rain
pool, the lens drops whose priority is below a threshold. Rain drops fill the camera frustum
uniformly in volume (p(Z) ∝ Z² between ``rain_near`` and ``rain_far``), at uniform image
positions (with a margin so that slanted streaks enter from outside); each carries a diameter
quantile u. Lens drops are discs; every pixel stores the covering drop with the lowest priority
(the first to appear as precipitation grows), the pixel it refracts (a flipped, shifted view) and
a rim shading.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .calibration import Calibration
from .geometry import nearest_per_pixel, rect_pixels

__all__ = ["RainPool", "LensPool", "rain_pool", "lens_pool"]

_F32 = np.float32


@dataclass(frozen=True)
class RainPool:
    """``col``, ``row`` (px), ``z`` (m, camera depth), ``u`` (diameter quantile), all (n,) float32."""

    col: np.ndarray
    row: np.ndarray
    z: np.ndarray
    u: np.ndarray


@dataclass(frozen=True)
class LensPool:
    """Pixels under a lens drop sorted by the drop's ``priority`` (n,); ``source`` (n,) pixel seen
    through the drop; ``shade`` (n,) rim darkening."""

    pixels: np.ndarray
    priority: np.ndarray
    source: np.ndarray
    shade: np.ndarray


def rain_pool(rng: np.random.Generator, height: int, width: int, cal: Calibration) -> RainPool:
    """The scene's rain-drop pool: ``rain_drop_pool`` drops at every image size, the same drops (their positions
    scale with the image; a pool scaled with the pixel count drew 4× the drops at 256 × 256, so the rain's look and
    what it tells depended on the render size: docs/studies/renderer-2-rain.md)."""
    n = int(cal.rain_drop_pool)
    margin = cal.streak_max_px * height / 128.0
    col = rng.uniform(-margin, width + margin, n)
    row = rng.uniform(-margin, height + margin, n)
    a3, b3 = cal.rain_near**3, cal.rain_far**3
    z = np.cbrt(a3 + rng.random(n) * (b3 - a3))
    u = rng.random(n)
    return RainPool(col.astype(_F32), row.astype(_F32), z.astype(_F32), u.astype(_F32))


def lens_pool(rng: np.random.Generator, height: int, width: int, cal: Calibration) -> LensPool:
    """The scene's lens drops as a per-pixel lookup sorted by priority."""
    H, W = height, width
    n = cal.lens_drop_pool
    lc = rng.uniform(0, W, n)
    lr = rng.uniform(0, H, n)
    lrad = rng.uniform(*cal.lens_drop_radius, n) * W
    lpri = rng.random(n)
    m = cal.lens_drop_magnification
    rects = [
        (
            max(int(lr[k] - lrad[k]) - 1, 0),
            min(int(lr[k] + lrad[k]) + 2, H),
            max(int(lc[k] - lrad[k]) - 1, 0),
            min(int(lc[k] + lrad[k]) + 2, W),
        )
        for k in range(n)
    ]
    pix, drop = rect_pixels(rects, W)
    dx, dy = pix % W - lc[drop], pix // W - lr[drop]
    rho2 = (dx * dx + dy * dy) / lrad[drop] ** 2
    inside = rho2 < 1.0
    px, pri, k = nearest_per_pixel(pix[inside], lpri[drop[inside]], np.flatnonzero(inside), H * W)
    kd = drop[k]
    sc = np.clip(np.round(lc[kd] + m * dx[k] - 0.35 * lrad[kd]), 0, W - 1).astype(np.int64)
    sr = np.clip(np.round(lr[kd] + m * dy[k] - 0.5 * lrad[kd]), 0, H - 1).astype(np.int64)
    shade = 1.05 - 0.3 * rho2[k] ** 2
    order = np.argsort(pri, kind="stable")
    return LensPool(px[order], pri[order].astype(_F32), (sr * W + sc)[order], shade[order].astype(_F32))
