"""The camera (§2.8): limited auto-exposure, filmic tonemap and display gamma.

Exposure follows UE/CARLA's EV100 window: EV = clip(log2(L̄·100/12.5), EV_min, EV_max) with L̄ the
mean luminance (cd/m², bright sources clipped out of the metering), exposure = 2^{comp}/(1.2·2^EV);
with only a 2-EV window, night and overcast stay dark as in CARLA. The tonemap is the ACES filmic
fit (Narkowicz 2015); tonemap and gamma 2.2 are folded into one lookup table indexed by
u = √(x/(1+x)) (fine steps in the shadows, bounded for any x ≥ 0). Glow around
bright sources is part of the scene's emitter sprites (:mod:`.scene`), so there is no bloom pass.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .calibration import CALIBRATION, Calibration

__all__ = ["exposure_scale", "develop"]

_LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)
_LUT_SIZE = 4096


def _aces(x: np.ndarray) -> np.ndarray:
    """ACES filmic fit (Narkowicz 2015): scene-referred x ≥ 0 → display-referred [0, 1]."""
    return np.clip(x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)


def _display_lut(gamma: float) -> np.ndarray:
    """uint8 output for u = √(x/(1+x)) on a grid of _LUT_SIZE: tonemap and gamma folded together."""
    u = np.linspace(0.0, 1.0, _LUT_SIZE)
    u2 = np.minimum(u * u, 1.0 - 1e-9)
    x = u2 / (1.0 - u2)
    return np.round(255.0 * _aces(x) ** (1.0 / gamma)).astype(np.uint8)


_LUTS: dict[float, np.ndarray] = {}


def exposure_scale(radiance: np.ndarray, cal: Calibration = CALIBRATION) -> float:
    """Exposure multiplier for channel-planar radiance (3, N) in relative units."""
    sub = radiance[:, ::3]
    # written out, not ``_LUMA @ sub``: numpy's BLAS rounds by CPU (docs/studies/openblas-kernels.md)
    lum = np.minimum(_LUMA[0] * sub[0] + _LUMA[1] * sub[1] + _LUMA[2] * sub[2], cal.luminance_clip)
    mean = float(lum.mean()) * cal.radiance_to_luminance
    ev = math.log2(max(mean, 1e-9) * 100.0 / 12.5)
    ev = min(max(ev, cal.exposure_window[0]), cal.exposure_window[1])
    return 2.0**cal.exposure_compensation / (1.2 * 2.0**ev) * cal.radiance_to_luminance


def develop(radiance: np.ndarray, height: int, width: int, cal: Calibration = CALIBRATION) -> np.ndarray:
    """Channel-planar radiance (3, N) float32 → uint8 RGB image (height, width, 3)."""
    x = radiance * np.float32(exposure_scale(radiance, cal))
    np.maximum(x, 0.0, out=x)
    u = np.sqrt(x / (x + 1.0))
    lut = _LUTS.get(cal.gamma)
    if lut is None:
        lut = _LUTS.setdefault(cal.gamma, _display_lut(cal.gamma))
    planes = lut[(u * (_LUT_SIZE - 1) + 0.5).astype(np.int32)].reshape(3, height, width)
    return cv2.merge([planes[0], planes[1], planes[2]])
