"""Contact sheet: one row per predicted weather parameter swept from its low to its high value.

The other parameters stay at a pleasant base weather; the block of six rows repeats for every scene
seed. Each row starts with a label panel naming the parameter (``cv2.putText``) and each tile is
captioned with the swept value, so a person can check at a glance that fog, rain, puddles, night,
cloud cover and low sun look like what they are.

With recorded data (no simulator to sweep), :func:`recorded_sheet` picks recorded images along each parameter instead.

Used by the ``generate`` stage and the ``pidc`` CLI (``render`` writes its PNG).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from components.core.checks import whole_number
from components.core.files import atomic_path
from components.core.weather import PARAMETERS, PREDICTED

from .base import Simulator

__all__ = ["BASE_WEATHER", "contact_sheet", "recorded_sheet", "save_png"]

#: a pleasant day: some clouds, no fog or rain, sun at 45°, mild wind, dry road
BASE_WEATHER: dict[str, float] = {
    "cloudiness": 15.0,
    "fog_density": 0.0,
    "precipitation": 0.0,
    "sun_altitude_angle": 45.0,
    "wind_intensity": 20.0,
    "precipitation_deposits": 0.0,
    "sun_azimuth_angle": 135.0,
}

_SWEEP_OVERRIDES: dict[str, dict[str, float]] = {
    # wind is only visible through rain: sweep it in rain
    "wind_intensity": {"precipitation": 80.0},
}


def _label(text: str, height: int, width: int, scale: float) -> np.ndarray:
    panel = np.full((height, width, 3), 24, np.uint8)
    cv2.putText(
        panel,
        text,
        (4, height // 2 + int(5 * scale)),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.45 * scale,
        (235, 235, 235),
        1,
        cv2.LINE_AA,
    )
    return panel


def contact_sheet(
    simulator: Simulator, scene_seeds: Sequence[int], steps: int, base_weather: Mapping[str, float] | None = None
) -> np.ndarray:
    """A uint8 RGB sheet: for each scene seed, one row per predicted parameter, ``steps`` tiles from
    the parameter's low to its high value (other parameters at ``base_weather``).

    Shape: (len(scene_seeds)·6·H, W_label + steps·W, 3) with H×W the simulator's image size.
    """
    whole_number("contact sheet steps", steps, low=2)
    seeds = list(scene_seeds)
    if not seeds:
        raise ValueError("contact sheet needs at least one scene seed")
    base = dict(BASE_WEATHER if base_weather is None else base_weather)
    H, W = simulator.height, simulator.width
    scale = max(H / 128.0, 0.75)
    label_w = int(round(W * 1.1))
    rows = []
    for seed in seeds:
        for name in PREDICTED:
            p = PARAMETERS[name]
            tiles = [_label(f"{p.short} {seed}" if len(seeds) > 1 else p.short, H, label_w, scale)]
            for v in np.linspace(p.low, p.high, steps):
                w = {**base, **_SWEEP_OVERRIDES.get(name, {}), name: float(v)}
                img = np.ascontiguousarray(simulator.render(w, seed))
                cv2.putText(
                    img, f"{v:.0f}", (3, H - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.35 * scale, (0, 0, 0), 2, cv2.LINE_AA
                )
                cv2.putText(
                    img, f"{v:.0f}", (3, H - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.35 * scale, (255, 255, 255), 1, cv2.LINE_AA
                )
                tiles.append(img)
            rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(rows, axis=0)


def recorded_sheet(images: np.ndarray, theta: np.ndarray, steps: int) -> np.ndarray:
    """The contact sheet of recorded images, which no simulator can sweep: one row per predicted parameter, the
    ``steps`` images (of ``images (n, H, W, 3)`` uint8, true weather ``theta (n, 6)``) whose value of it lies nearest to
    ``steps`` evenly spaced values from its low to its high end, each captioned with its own value: a look tells whether
    the labels say what the images show.

    Shape: (6·H, W_label + steps·W, 3)."""
    whole_number("contact sheet steps", steps, low=2)
    images, theta = np.asarray(images), np.asarray(theta, dtype=np.float64)
    if len(images) == 0 or len(images) != len(theta):
        raise ValueError(f"a recorded contact sheet needs images and one θ each, got {len(images)} and {len(theta)}")
    H, W = images.shape[1:3]
    scale = max(H / 128.0, 0.75)
    rows = []
    for k, name in enumerate(PREDICTED):
        p = PARAMETERS[name]
        tiles = [_label(f"{p.short} (recorded)", H, int(round(W * 1.1)), scale)]
        for v in np.linspace(p.low, p.high, steps):
            i = int(np.argmin(np.abs(theta[:, k] - v)))
            img = np.array(images[i], copy=True, order="C")
            for colour, thickness in (((0, 0, 0), 2), ((255, 255, 255), 1)):
                cv2.putText(
                    img, f"{theta[i, k]:.0f}", (3, H - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.35 * scale, colour, thickness
                )
            tiles.append(img)
        rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(rows, axis=0)


def save_png(path: str | os.PathLike[str], image: np.ndarray) -> None:
    """Write an RGB uint8 image (H, W, 3) as PNG atomically (:func:`components.core.files.atomic_path`)."""
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"save_png needs an (H, W, 3) uint8 RGB image, got {img.dtype} {img.shape}")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[:, :, ::-1]))
    if not ok:
        raise ValueError(f"could not encode a PNG for {os.fspath(path)}")
    with atomic_path(path, fsync=False) as tmp:
        tmp.write_bytes(buf.tobytes())
