"""Camera-like renders: each scene rendered larger than the dataset's images and area-resized to them.

The embedded renderer samples each pixel at its centre; a camera integrates light over the pixel, and an image made
larger and resized does too. Models trained on the renderer's own ``height × width`` images are overconfident on such
images, and models trained on renders of varying size, resized, cover them (docs/studies/other-resolutions.md,
docs/studies/renderer-2-rain.md). ``simulator.render_sizes: [low, high]`` in ``params.yaml`` makes
every stage render so: :func:`components.simulate.base.make_simulator` returns a :class:`ResizedRenders`.

- :func:`render_height`: the render height of a scene, uniform in ``low..high`` pixels, drawn from its scene seed alone
  (so a posterior predictive check re-renders a scene at the size of its training image).
- :func:`area_resize`: the exact area average in integer arithmetic: byte-identical on every machine (OpenCV's
  ``INTER_AREA`` of non-integer ratios sums in float32 with CPU-dispatched kernels), within one level of it.
- :class:`ResizedRenders`: the :class:`~components.simulate.base.Simulator` over a procedural renderer per size.

Used through ``make_simulator`` by the ``generate``, ``evaluate`` (PPCs) and ``task2`` stages, the scheduled monitoring
and :func:`components.simulate.in_memory.render_split`, when ``simulator.render_sizes`` is set; :func:`area_resize` also
by the ``generate`` stage's import of recorded images of another size (:mod:`components.simulate.recorded`).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Mapping

import numpy as np

from components.core import seeding
from components.core.checks import whole_number
from components.core.images import render_shape
from components.simulate.procedural import ProceduralSimulator

__all__ = ["area_weights", "area_resize", "render_height", "ResizedRenders"]

#: renderers kept at once (one per render size; a dataset's consecutive images share a scene, hence a size)
_SIMULATORS = 4


def area_weights(n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The area-average weights of ``n`` input pixels onto ``m ≤ n`` output pixels along one axis.

    Output pixel i covers input coordinates [i n/m, (i+1) n/m); input pixel j covers [j, j+1). In units of 1/m of an
    input pixel their overlap is the integer W_ij = |[i n, (i+1) n) ∩ [j m, (j+1) m)|, with Σ_j W_ij = n.

    Returns:
        ``index (m, K)`` int64 input pixels and ``weight (m, K)`` int64 overlaps W (0 where a row has fewer than
        K = ⌈n/m⌉ + 1 pixels), so that output i = Σ_k weight[i, k] · x[index[i, k]] / n.
    """
    if not 1 <= m <= n:
        raise ValueError(f"area_weights: output size must be within 1..{n} (the input size), got {m}")
    k = -(-n // m) + 1
    out = np.arange(m, dtype=np.int64)[:, None]
    pixels = (out * n) // m + np.arange(k)  # (m, K): from the first input pixel that output i overlaps
    overlap = np.minimum((out + 1) * n, (pixels + 1) * m) - np.maximum(out * n, pixels * m)
    weight = np.where(pixels < n, np.clip(overlap, 0, None), 0)
    return np.minimum(pixels, n - 1), weight


def area_resize(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Shrink a uint8 ``(H, W, C)`` image to ``size = (h, w)`` (h ≤ H, w ≤ W) by the exact area average.

    Each output pixel is the mean of the input over its footprint, rounded half up to uint8, computed in int64: the
    same bytes on every machine. Equal to block means for integer ratios and within one level of OpenCV's
    ``INTER_AREA`` otherwise. The image is returned as it is when it already has the size.
    """
    a = np.asarray(image)
    if a.dtype != np.uint8 or a.ndim != 3:
        raise ValueError(f"area_resize: expected a uint8 (H, W, C) image, got {a.dtype} {a.shape}")
    h, w = int(size[0]), int(size[1])
    if not (1 <= h <= a.shape[0] and 1 <= w <= a.shape[1]):
        raise ValueError(f"area_resize: shrinks only; {a.shape[0]}×{a.shape[1]} cannot become {h}×{w}")
    if (h, w) == a.shape[:2]:
        return a
    rows, row_w = area_weights(a.shape[0], h)
    cols, col_w = area_weights(a.shape[1], w)
    x = a.astype(np.int64)
    across = (x[:, cols, :] * col_w[None, :, :, None]).sum(axis=2)  # (H, w, C), in units of 1/w of a pixel
    total = (across[rows, :, :] * row_w[:, :, None, None]).sum(axis=1)  # (h, w, C), in units of 1/(h w)
    d = a.shape[0] * a.shape[1]  # Σ of the weights: H·W (each axis's sums to its input size)
    return ((2 * total + d) // (2 * d)).astype(np.uint8)


def render_height(scene_seed: int, low: int, high: int) -> int:
    """The render height of scene ``scene_seed``: uniform in ``low..high`` pixels, from the scene seed alone."""
    if not 1 <= low <= high:
        raise ValueError(f"render sizes must satisfy 1 ≤ low ≤ high, got [{low}, {high}]")
    scene_seed = whole_number("scene_seed", scene_seed, low=0)
    return int(seeding.rng(scene_seed, "render_size").integers(low, high + 1))


class ResizedRenders:
    """A :class:`~components.simulate.base.Simulator` of ``height × width`` images: each scene rendered by the
    procedural renderer at :func:`render_height` (``render_sizes = (low, high)``, ``low ≥ height``) and
    :func:`area_resize`-d.

    ``version`` extends the renderer's with the sizes, so datasets, feature caches and models key on them.
    """

    def __init__(self, height: int, width: int, render_sizes: tuple[int, int], *, cache_size: int = 2) -> None:
        low, high = (int(v) for v in render_sizes)
        if not height <= low <= high:
            raise ValueError(
                f"render_sizes [{low}, {high}] must satisfy height ({height}) ≤ low ≤ high: renders are shrunk to the "
                "images' size"
            )
        self.height, self.width = int(height), int(width)
        self.render_sizes = (low, high)
        self._cache_size = int(cache_size)
        self._simulators: OrderedDict[int, ProceduralSimulator] = OrderedDict()
        self._lock = threading.Lock()
        base = self._simulator(low)
        self.version = f"{base.version}+resized-{low}-{high}"

    def __repr__(self) -> str:
        return f"ResizedRenders(height={self.height}, width={self.width}, render_sizes={self.render_sizes})"

    def _simulator(self, render: int) -> ProceduralSimulator:
        with self._lock:
            sim = self._simulators.get(render)
            if sim is None:
                sim = ProceduralSimulator(*render_shape(self.height, self.width, render), cache_size=self._cache_size)
                self._simulators[render] = sim
                while len(self._simulators) > _SIMULATORS:
                    self._simulators.popitem(last=False)
            self._simulators.move_to_end(render)
            return sim

    def render_height(self, scene_seed: int) -> int:
        """The height in pixels at which scene ``scene_seed`` is rendered before it is resized."""
        return render_height(scene_seed, *self.render_sizes)

    def render(self, weather: Mapping[str, float], scene_seed: int) -> np.ndarray:
        """``(height, width, 3)`` uint8: the scene rendered at its :meth:`render_height`, area-resized."""
        image = self._simulator(self.render_height(scene_seed)).render(weather, scene_seed)
        return area_resize(image, (self.height, self.width))
