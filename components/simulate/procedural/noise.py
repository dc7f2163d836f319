"""Static noise fields: periodic fractal (fBm) textures and their sampling.

A texture is a periodic ``N × N`` float32 field with a power-law spectrum (amplitude ∝ f^-(H+1),
the fBm of docs/simulators.md), standardized to zero mean and unit variance. Sampling returns
approximately uniform quantiles (Gaussian CDF of the standardized value), so thresholding a sample
at ``q`` covers a fraction ≈ ``q`` of the area: coverage follows cloudiness/deposits directly.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

import functools
import zlib

import cv2
import numpy as np

__all__ = ["fbm_texture", "static_texture", "scene_texture", "sample_texture", "gaussian_cdf"]


def fbm_texture(rng: np.random.Generator, size: int, hurst: float = 0.6, cutoff: float = 2.0) -> np.ndarray:
    """A periodic fBm texture (size, size), float32, mean 0 and standard deviation 1.

    ``cutoff`` removes wavelengths longer than ``size / cutoff`` texels (the largest features).
    """
    white = rng.standard_normal((size, size))
    f = np.fft.rfft2(white)
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    freq = np.sqrt(fx * fx + fy * fy) * size
    amp = np.where(freq < cutoff, 0.0, 1.0 / np.maximum(freq, 1.0) ** (hurst + 1.0))
    field = np.fft.irfft2(f * amp, s=(size, size))
    field = (field - field.mean()) / max(field.std(), 1e-12)
    return field.astype(np.float32)


@functools.lru_cache(maxsize=16)
def static_texture(name: str, size: int, hurst: float, seed: int) -> np.ndarray:
    """The static (world-wide) fBm texture ``name``: like CARLA's static noise, the same for every
    scene; drawn once from ``SeedSequence([seed, crc32(name)])`` and cached read-only."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([seed, zlib.crc32(name.encode("utf-8"))])))
    tex = fbm_texture(rng, size, hurst=hurst, cutoff=1.0)
    tex.setflags(write=False)
    return tex


def scene_texture(rng: np.random.Generator, name: str, size: int, hurst: float, seed: int) -> np.ndarray:
    """A scene's view of a static texture: periodically shifted by a random offset and turned by one
    of the 8 symmetries of the square, drawn from the scene stream ``rng`` (size × size, float32)."""
    tex = static_texture(name, size, hurst, seed)
    dy, dx, sym = (int(v) for v in rng.integers(0, (size, size, 8)))
    out = np.roll(tex, (dy, dx), axis=(0, 1))
    if sym & 4:
        out = out.T
    if sym & 2:
        out = out[::-1]
    if sym & 1:
        out = out[:, ::-1]
    return np.ascontiguousarray(out)


def gaussian_cdf(x: np.ndarray) -> np.ndarray:
    """Φ(x), the standard normal CDF (tanh approximation, |error| < 2e-4), same shape."""
    x = np.asarray(x, dtype=np.float32)
    return (0.5 * (1.0 + np.tanh(0.7978846 * (x + 0.044715 * x * x * x)))).astype(np.float32)


def sample_texture(texture: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear, periodic samples of ``texture`` at texel coordinates (u column, v row).

    ``u`` and ``v`` are arrays of one shape; returns float32 values of that shape.
    """
    n_rows, n_cols = texture.shape
    shape = np.shape(u)
    mu = np.mod(np.asarray(u, dtype=np.float64), n_cols).astype(np.float32).ravel()
    mv = np.mod(np.asarray(v, dtype=np.float64), n_rows).astype(np.float32).ravel()
    n = mu.size
    if n == 0:
        return np.zeros(shape, np.float32)
    rows = -(-n // 256)  # remap wants maps narrower than 32767: lay the samples out 256 wide
    pad = rows * 256 - n
    mu = np.pad(mu, (0, pad)).reshape(rows, 256)
    mv = np.pad(mv, (0, pad)).reshape(rows, 256)
    out = cv2.remap(texture, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.ravel()[:n].reshape(shape)
