"""Input checks shared by the plots: shapes and values of θ samples, log-densities, truths, boxes, levels.

Every check raises a ``ValueError`` (or ``TypeError`` for a wrong kind of object) that names the argument,
the expected shape and what was received, before any plotting library sees the data.

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from components.core.weather import PREDICTED, Box

__all__ = [
    "N_THETA",
    "as_samples",
    "as_log_prob",
    "as_truth",
    "as_box",
    "as_levels",
    "as_images",
    "as_image",
    "as_named_arrays",
]

#: Number of predicted weather parameters (the length of θ).
N_THETA = len(PREDICTED)


def as_samples(samples: object, name: str = "samples") -> np.ndarray:
    """θ samples as float64 of shape ``(n, 6)``, n ≥ 1, all finite (physical units, :data:`PREDICTED` order)."""
    a = np.asarray(samples, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != N_THETA or a.shape[0] == 0:
        raise ValueError(
            f"{name} must have shape (n, {N_THETA}) with n >= 1 (θ in the order {', '.join(PREDICTED)}), got {a.shape}"
        )
    if not np.isfinite(a).all():
        raise ValueError(f"{name} contain non-finite values")
    return a


def as_log_prob(log_prob: object, n: int, name: str = "log_prob") -> np.ndarray:
    """Log-densities of the n samples as float64 of shape ``(n,)``, all finite."""
    a = np.asarray(log_prob, dtype=np.float64)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), one log-density per sample, got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} contains non-finite log-densities (NaN or ±inf)")
    return a


def as_truth(truth: object | None, name: str = "truth") -> np.ndarray | None:
    """The ground-truth θ as float64 of shape ``(6,)``, or None."""
    if truth is None:
        return None
    a = np.asarray(truth, dtype=np.float64)
    if a.shape != (N_THETA,):
        raise ValueError(f"{name} must have shape ({N_THETA},) (θ in the order {', '.join(PREDICTED)}), got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} contains non-finite values")
    return a


def as_box(box: Box | None) -> Box:
    """The plotting box: ``box`` or, when None, the full physical range of every parameter."""
    if box is None:
        return Box.full()
    if not isinstance(box, Box):
        raise TypeError(f"box must be a components.core.weather.Box or None, got {type(box).__name__}")
    return box


def as_levels(levels: object, name: str = "levels") -> np.ndarray:
    """Credible levels as a sorted float64 array, each strictly inside (0, 1)."""
    if np.isscalar(levels):
        levels = [levels]
    a = np.asarray(levels, dtype=np.float64)
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"{name} must be a level or a non-empty 1-D sequence of levels, got shape {a.shape}")
    if not np.isfinite(a).all() or (a <= 0).any() or (a >= 1).any():
        raise ValueError(f"{name} must lie strictly inside (0, 1), got {a.tolist()}")
    return np.sort(a)


def as_image(image: object, name: str = "image") -> np.ndarray:
    """One RGB image: uint8 of shape ``(H, W, 3)``."""
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{name} must have shape (H, W, 3) (RGB), got {a.shape}")
    if a.dtype != np.uint8:
        raise TypeError(f"{name} must be uint8 RGB, got dtype {a.dtype}")
    return a


def as_images(images: object, name: str = "images") -> np.ndarray:
    """A stack of RGB images: uint8 of shape ``(k, H, W, 3)``, k ≥ 1."""
    a = np.asarray(images)
    if a.ndim != 4 or a.shape[0] == 0 or a.shape[3] != 3 or a.shape[1] == 0 or a.shape[2] == 0:
        raise ValueError(f"{name} must have shape (k, H, W, 3) with k >= 1 (RGB), got {a.shape}")
    if a.dtype != np.uint8:
        raise TypeError(f"{name} must be uint8 RGB, got dtype {a.dtype}")
    return a


def as_named_arrays(values: object, name: str, *, allow_nan: bool = False) -> dict[object, np.ndarray]:
    """A non-empty mapping of keys to non-empty 1-D float64 arrays (insertion order kept)."""
    if not isinstance(values, Mapping):
        raise TypeError(f"{name} must be a mapping, got {type(values).__name__}")
    if len(values) == 0:
        raise ValueError(f"{name} is empty")
    out: dict[object, np.ndarray] = {}
    for key, v in values.items():
        try:
            a = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{name}[{key!r}] must be an array of numbers, got {type(v).__name__}") from None
        if a.ndim != 1 or a.size == 0:
            raise ValueError(f"{name}[{key!r}] must be a non-empty 1-D array, got shape {a.shape}")
        bad = np.isinf(a) if allow_nan else ~np.isfinite(a)
        if bad.any():
            raise ValueError(
                f"{name}[{key!r}] contains non-finite values" + (" (only NaN is allowed)" if allow_nan else "")
            )
        if np.isnan(a).all():
            raise ValueError(f"{name}[{key!r}] has no finite value")
        out[key] = a
    return out
