"""Image checks and size conversions shared by every backbone (numpy and OpenCV only, no torch).

Images everywhere in pidc are ``uint8`` arrays of shape ``(n, H, W, 3)`` in RGB order, as rendered by
the simulators. This module validates such batches and converts their size by *area* interpolation
(each output pixel is the mean of the input pixels it covers, i.e. the light a larger camera pixel
would integrate), so that a backbone expecting another resolution sees a physically faithful image.
It is torch-free so that the ONNX runtime can reproduce a backbone's size conversion exactly.

Used by every stage but ``generate``, and by the ``pidc`` CLI.
"""

from __future__ import annotations

import cv2
import numpy as np

from components.core.opencv import ipp_off

__all__ = ["MIN_SIDE", "check_images", "resize_area", "to_unit_chw"]

#: the fewest pixels of an image's height and width that every backbone takes (:func:`check_images`)
MIN_SIDE = 8


def check_images(images: object, *, who: str) -> np.ndarray:
    """Validate a batch of RGB images and return it as a C-contiguous ``(n, H, W, 3)`` uint8 array.

    Accepted: a uint8 array of shape ``(n, H, W, 3)``, or a single image ``(H, W, 3)`` (made a batch of
    one). Anything else raises ``TypeError`` (not an array) or ``ValueError`` naming the expected
    dtype/shape and what was given; ``who`` (the backbone's name) prefixes the message.
    """
    if not isinstance(images, np.ndarray):
        raise TypeError(
            f"{who}: images must be a numpy uint8 array of shape (n, H, W, 3) RGB, got {type(images).__name__}"
        )
    if images.dtype != np.uint8:
        raise ValueError(
            f"{who}: images must have dtype uint8 (0–255 RGB), got dtype {images.dtype}; "
            "convert with np.clip(x * 255, 0, 255).astype(np.uint8) if they are floats in [0, 1]"
        )
    if images.ndim == 3:
        images = images[None]
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(
            f"{who}: images must have shape (n, H, W, 3) with 3 RGB channels last, got shape {images.shape}"
        )
    n, h, w, _ = images.shape
    if n == 0:
        raise ValueError(f"{who}: got an empty batch of images (shape {images.shape})")
    if h < MIN_SIDE or w < MIN_SIDE:
        raise ValueError(f"{who}: images must be at least {MIN_SIDE}×{MIN_SIDE} pixels, got {h}×{w}")
    return np.ascontiguousarray(images)


def resize_area(images: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a ``(n, H, W, 3)`` uint8 batch to ``size = (H', W')`` by area interpolation.

    Down-sampling averages the covered input pixels (``cv2.INTER_AREA``); up-sampling falls back to
    bilinear interpolation, as ``INTER_AREA`` does. Returns uint8 ``(n, H', W', 3)``; the input is returned
    unchanged when it already has the size.
    """
    h, w = size
    if images.shape[1:3] == (h, w):
        return images
    out = np.empty((images.shape[0], h, w, 3), dtype=np.uint8)
    ipp_off()  # the same pixels on every CPU (components/core/opencv.py)
    for i, image in enumerate(images):
        out[i] = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    return out


def to_unit_chw(images: np.ndarray) -> np.ndarray:
    """uint8 ``(n, H, W, 3)`` → float32 ``(n, 3, H, W)`` in [0, 1] (sRGB-encoded values / 255)."""
    return np.ascontiguousarray(images.transpose(0, 3, 1, 2), dtype=np.float32) * np.float32(1.0 / 255.0)
