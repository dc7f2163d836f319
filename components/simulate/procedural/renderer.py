"""The embedded procedural weather renderer: pidc's default simulator.

Image formation in linear radiance (relative units), then a camera (:mod:`.camera_response`):

1. sun/sky state from the sun altitude h and the azimuth relative to the car's heading (:mod:`.sky`);
2. cloud layer: static noise quantiles thresholded by cloudiness → sky radiance, sun dimming;
3. fog dims the sun, E_sun × (1 − k_f fog/100);
4. surfaces: L = ρ·(E_sun·max(0, n·s)·V/π + E_amb·a), V the shadow visibility (:mod:`.shadows`);
5. night (h < 0): street lamps, lit windows, vehicle lights and their light on the ground;
6. puddles on the road where the static puddle noise < deposits (soft edge): Fresnel mirror of the
   scene/sky along the reflected ray (ripples when it rains);
7. participating media: t = exp(−(β_haze + β_fog + β_rain)·path), path = depth − fog_distance,
   sky rays the finite height-fog integral; airlight from ambient light + HG sun lobe; lamp halos;
8. rain streaks (occluded by depth, slanted by wind); 9. lens drops; 10. exposure, tonemap, gamma.

The scene (:mod:`.scene`) is built once per scene seed and cached (LRU); a render only thresholds
and scales its fields, so the same (weather, scene_seed) gives a byte-identical image, and the
geometry never changes with the weather.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

import math
import platform
import threading
from collections import OrderedDict
from collections.abc import Mapping

import cv2
import numpy as np

from components import NUMPY_DISPATCH_OFF, numpy_kernels
from components.core.checks import whole_number
from components.core.images import RENDER_SIDES
from components.core.opencv import ipp_off
from components.core.weather import complete_weather

from .calibration import CALIBRATION, Calibration, calibration_hash
from .camera_response import develop
from .rain import add_lens_drops, add_streaks, rain_rate, streak_alpha
from .scene import Scene, build_scene
from .shadows import sun_visibility
from .sky import cloud_coverage, henyey_greenstein, sky_radiance, sun_sky

__all__ = ["ProceduralSimulator", "ALGORITHM_VERSION"]

#: bump when the image-formation algorithm changes (the calibration hash covers the constants)
#: 2: the rain pool and a streak's opacity per solid angle independent of the image size;
#: 3: OpenCV's calls without Intel's IPP, whose kernels differ by CPU (components/core/opencv.py)
ALGORITHM_VERSION = 3

cv2.setNumThreads(1)


def _dot3(v: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``v @ s`` for float32 directions ``v`` (N, 3) and a vector ``s`` (3,), as numpy products and sums, left to right.

    The same bits on every CPU: ``@`` hands the product to numpy's OpenBLAS, whose kernel is chosen by CPU (AVX-512's
    ``SkylakeX`` fuses the multiply-adds, AVX2's ``Haswell`` does not), so its float32 results differ in the last bit
    (docs/studies/openblas-kernels.md). Returns ``(N,)`` float32.
    """
    return v[:, 0] * s[0] + v[:, 1] * s[1] + v[:, 2] * s[2]


def _check_seed(scene_seed: object) -> int:
    return whole_number("scene_seed", scene_seed, low=0)


def _check_numpy_kernels() -> None:
    """Refuse to render with numpy's CPU-dispatched kernels (x86-64): their float32 ``exp`` rounds differently from one
    CPU to another, so the images would not be byte-identical across machines (``components/__init__.py``)."""
    if platform.machine().lower() not in {"x86_64", "amd64"}:
        return
    kernels = numpy_kernels()
    if not kernels.startswith("baseline"):
        raise RuntimeError(
            f"numpy runs its {kernels} kernels in this process, so the rendered images would depend on the CPU: import "
            f"components (or any pidc module) before numpy, or start Python with "
            f"NPY_DISABLE_CPU_FEATURES={NUMPY_DISPATCH_OFF}"
        )


class ProceduralSimulator:
    """Renders ``height × width`` RGB front-camera images of procedural scenes under CARLA weathers.

    Implements :class:`components.simulate.base.Simulator`. ``cache_size`` scenes are kept
    (least recently used evicted); :meth:`scene` exposes a scene's cached geometry and masks. ``version`` = ``"procedural-<algorithm>+<calibration hash>"``.
    """

    def __init__(
        self, height: int = 128, width: int = 128, *, cache_size: int = 16, calibration: Calibration = CALIBRATION
    ) -> None:
        for name, v in (("height", height), ("width", width), ("cache_size", cache_size)):
            whole_number(name, v, error=TypeError)
        low, high = RENDER_SIDES
        if not (low <= height <= high and low <= width <= high):
            raise ValueError(f"image size must be within {low}..{high} pixels, got {height}×{width}")
        if cache_size < 1:
            raise ValueError(f"cache_size must be >= 1, got {cache_size}")
        _check_numpy_kernels()
        self.height = int(height)
        self.width = int(width)
        self.calibration = calibration
        self.version = f"procedural-{ALGORITHM_VERSION}+{calibration_hash(calibration)}"
        self._cache_size = int(cache_size)
        self._cache: OrderedDict[int, Scene] = OrderedDict()
        self._lock = threading.Lock()  # the cache may be shared by a thread task runner

    def __repr__(self) -> str:
        return f"ProceduralSimulator(height={self.height}, width={self.width}, version={self.version!r})"

    def scene(self, scene_seed: int) -> Scene:
        """The cached weather-independent scene (geometry, masks, fields) of ``scene_seed``."""
        seed = _check_seed(scene_seed)
        ipp_off()  # in the calling thread: the same pixels on every CPU (components/core/opencv.py)
        with self._lock:
            sc = self._cache.get(seed)
            if sc is not None:
                self._cache.move_to_end(seed)
                return sc
        sc = build_scene(seed, self.height, self.width, self.calibration)
        with self._lock:
            self._cache[seed] = sc
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return sc

    def render(self, weather: Mapping[str, float], scene_seed: int) -> np.ndarray:
        """An (height, width, 3) uint8 RGB image of scene ``scene_seed`` under ``weather``."""
        w = complete_weather(weather)
        seed = _check_seed(scene_seed)
        return self._render(w, self.scene(seed))

    def radiance(self, weather: Mapping[str, float], scene_seed: int) -> np.ndarray:
        """The linear radiance (H, W, 3) float32 before the camera (for diagnostics and tests)."""
        w = complete_weather(weather)
        sc = self.scene(_check_seed(scene_seed))
        return self._radiance(w, sc).reshape(3, sc.height, sc.width).transpose(1, 2, 0)

    def _render(self, w: dict[str, float], sc: Scene) -> np.ndarray:
        return develop(self._radiance(w, sc), sc.height, sc.width, self.calibration)

    def _radiance(self, w: dict[str, float], sc: Scene) -> np.ndarray:
        """Channel-planar linear radiance (3, N) float32 of scene ``sc`` under the complete weather ``w``."""
        ipp_off()  # in the calling thread: the same pixels on every CPU (components/core/opencv.py)
        cal = self.calibration
        cloud, fog, precip = w["cloudiness"], w["fog_density"], w["precipitation"]
        alt, wind, deposits = w["sun_altitude_angle"], w["wind_intensity"], w["precipitation_deposits"]
        st = sun_sky(alt, w["sun_azimuth_angle"] - sc.layout.heading_deg, cloud, fog, cal)
        s = st.sun_dir.astype(np.float32)
        n0 = len(sc.sky_pixels)
        # 1-2: sky (direct and reflected rays) with clouds
        alpha = cloud_coverage(sc.sky_quantile, cloud, cal)
        sky = sky_radiance(st, sc.sky_dirs[:, 1], _dot3(sc.sky_dirs, s), alpha, cloud, cal)
        # 3-4: surfaces
        vis = sun_visibility(sc.shadow, sc.height * sc.width, st.sun_dir, cal)
        direct = np.maximum(_dot3(sc.normal, s), 0.0) * vis
        sun = (st.sun / math.pi).astype(np.float32)[:, None]
        amb = st.ambient.astype(np.float32)[:, None]
        L = sc.albedo * (direct[None, :] * sun + sc.ambient_factor[None, :] * amb)
        # 5: night emitters
        if st.night > 0:
            L += sc.night_radiance
        L[:, sc.sky_pixels] = sky[:, :n0]
        # 7 (extinction coefficient, needed by the reflected rays too)
        beta = cal.base_extinction + cal.fog_extinction * fog / 100.0
        if precip > 0:
            beta += cal.rain_extinction * rain_rate(precip, cal) ** 0.67
        # 6: puddles
        edge = cal.puddle_edge
        q = deposits / 100.0 * (1.0 + edge)
        k = int(np.searchsorted(sc.reflections.quantile, q, side="left"))
        if k > 0:
            ext = np.concatenate([L, sky[:, n0:]], axis=1)
            refl = ext[:, sc.reflections.source[:k]]
            if precip > 0:
                rw = np.float32(min(1.0, precip / cal.ripple_saturation))
                refl += rw * (ext[:, sc.reflections.source_ripple[:k]] - refl)
            F = sc.reflections.fresnel[:k]
            a = np.clip((q - sc.reflections.quantile[:k]) * (1.0 / edge), 0.0, 1.0)
            refl *= (F * np.exp(-beta * sc.reflections.path[:k]))[None, :]
            px = sc.reflections.pixels[:k]
            under = L[:, px]
            puddle = ((1.0 - F) * np.float32(cal.puddle_darkening))[None, :] * under + refl
            L[:, px] = under + a[None, :] * (puddle - under)
        # 7: fog, haze, rain extinction and airlight
        t = np.exp(-beta * sc.fog_path)
        cos_g = _dot3(sc.dirs, s)
        air_amb = (st.ambient * cal.airlight_ambient).astype(np.float32)[:, None]
        air_sun = (st.sun * cal.airlight_sun * w["scattering_intensity"]).astype(np.float32)[:, None]
        airlight = air_amb + henyey_greenstein(cos_g, cal.airlight_g)[None, :] * air_sun
        L = airlight + t[None, :] * (L - airlight)
        if st.night > 0:
            L += sc.halo * np.float32(1.0 - math.exp(-beta * cal.lamp_halo_path) + cal.lamp_halo_haze)
        # 8: rain streaks
        if precip > 0:
            a = streak_alpha(sc, precip, wind, cal)
            add_streaks(L, a, L.mean(axis=1) * cal.streak_brightness)
            # 9: lens drops
            add_lens_drops(sc, L, precip, cal)
        return L
