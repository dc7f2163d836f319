"""``cues``: interpretable physical weather cues computed from the pixels (no learning, frozen).

Each of the 377 features is a summary statistic that image-formation physics ties to one or more weather parameters,
computed on the 128×128 sRGB image (other sizes are converted by area interpolation): brightness and its quantiles,
the dark channel (haze), local contrast by image row (a depth proxy), the sky's colour, saturation, edge orientations
(rain streaks), lens-drop blur, the road, colour temperature and lights; regional photometry in linear luminance (a
4×4 grid, row profiles, walls, the sky's distribution); detectors of rain streaks, sunlit against shadowed ground and
puddles; the sky's thumbnail in CIE L*a*b*; and two small frozen networks learned once from the renderer's labels, the
wet road by distance (:mod:`components.features.backbones.wet_road`) and the weather reader with its sun head
(:mod:`components.features.backbones.weather_reader`). It is the interpretable end of the backbone comparison: a flow
on these numbers can use only what physics says is visible. The region split assumes a forward-looking camera with
the horizon near mid-image (true for the simulators' pitch of ±2°). Features are not standardised (downstream code
z-scores them with training-set statistics); the forward pass uses only ONNX-exportable operations.

What each block reads: docs/backbones.md; the versions of the cues and what each added: CHANGELOG.md.

Used by every stage but ``generate``, and by the ``pidc`` CLI.
"""

from __future__ import annotations

import math
import re
from typing import Any, ClassVar

import torch
import torch.nn.functional as F

from components.features.backbones.base import Backbone
from components.features.backbones.tiny import linear_to_lab
from components.features.backbones.weather_reader import FEATURE_NAMES as _READER_NAMES
from components.features.backbones.weather_reader import SUN_FEATURE_NAMES as _SUN_HEAD_NAMES
from components.features.backbones.weather_reader import load_reader, load_sun_head, reader_features
from components.features.backbones.wet_road import FEATURE_NAMES as _WET_ROAD_NAMES
from components.features.backbones.wet_road import load_detector, wet_road_features

__all__ = ["CuesBackbone", "FEATURE_NAMES", "MIRROR", "SPARED"]


_ROAD_Q = (5, 10, 25, 50, 75, 90, 95)
_IMAGE_Q = (1, 5, 10, 25, 50, 75, 90, 95, 99)
_WALL_Q = (10, 50, 90)
_SKY_SAT_Q = (10, 25, 50, 75, 90)
_SKY_B_Q = (10, 50, 90)
_ROWS = 16
_ROW_PROFILES = ("log_y", "bchroma", "dark", "log_fine_energy", "log_streak_ratio")
_LOG_Y_RANGE = (math.log(1e-3), 0.0)  # log of linear luminance + 1e-3, for 0–1 input
_RIDGE_T = ("0.005", "0.01", "0.02", "0.04")  # thresholds of the line response (sRGB luma)
#: line directions (row step, column step): vertical, ╱ and ╲
_RIDGE_DIRECTIONS = {"vertical": (1, 0), "slash": (1, -1), "backslash": (1, 1)}
_RIDGE_LENGTH = 5  # pixels averaged along a line
_PUDDLE_BANDS = ((0.55, 0.70), (0.70, 0.85), (0.85, 1.0))  # road rows (shares of the height): far, mid, near
_SKY_LATTICE = 8  # cells per side of the sky thumbnail's lattice (the tiny backbone's)
_SKY_ROWS = 3  # of its rows, from the top


def _names() -> tuple[str, ...]:
    q = ("q02", "q25", "q50", "q75", "q98")
    names = ["v_mean", "v_std", *(f"v_{x}" for x in q), *(f"v_hist{i}" for i in range(8))]
    names += ["dark_mean", *(f"dark_band{i}" for i in range(4)), "airlight", "transmission", "dark_over_v"]
    names += [f"contrast_row{i}" for i in range(8)]
    names += ["sky_r", "sky_g", "sky_b", "sky_v", "sky_std", "sky_bchroma", "sky_sat", "sky_gradient"]
    names += ["horizon_v", "horizon_bchroma"]
    names += ["sat_mean", "sat_std", "sat_upper", "sat_lower"]
    names += [f"edge_hist{i}" for i in range(8)] + ["edge_log_energy"]
    names += [f"fine_edge_hist{i}" for i in range(8)] + ["fine_edge_log_energy"]
    names += ["bandpass_small", "bandpass_large", "bandpass_strong_frac", "bandpass_log_kurtosis", "smooth_block_frac"]
    names += ["road_v", "road_std", "road_q98", "road_brighter_than_sky", "road_sat", "road_bchroma"]
    names += ["chroma_r", "chroma_b", "log_r_over_b", "white_patch_log_r_over_b"]
    names += ["dark_frac", "clipped_frac"]
    # version 2: regional photometry (log linear luminance, chromaticity) and row profiles
    cells = [f"{r}{c}" for r in range(4) for c in range(4)]
    names += [f"grid_log_y{k}" for k in cells] + [f"grid_log_r_over_g{k}" for k in cells]
    names += [f"grid_log_b_over_g{k}" for k in cells]
    names += [f"road_log_y_q{q:02d}" for q in _ROAD_Q] + ["road_lit_over_shadow"]
    names += [f"log_y_q{q:02d}" for q in _IMAGE_Q]
    names += [f"{side}_wall_log_y_q{q:02d}" for side in ("left", "right") for q in _WALL_Q]
    names += [f"row{i:02d}_{what}" for what in _ROW_PROFILES for i in range(_ROWS)]
    names += [f"sky_sat_q{q:02d}" for q in _SKY_SAT_Q] + [f"sky_bchroma_q{q:02d}" for q in _SKY_B_Q]
    names += ["sky_blue_frac", "sky_deep_blue_frac"]
    # version 3: rain streaks, lit and shadowed ground, puddles
    ridge = (*(f"frac{t}" for t in _RIDGE_T), "log_mean", "log_mean_upper")
    names += [f"ridge_{d}_{r}" for d in _RIDGE_DIRECTIONS for r in ridge]
    names += ["ground_lit_frac", "ground_lit_over_shadow", "ground_lit_minus_shadow_log_r_over_b"]
    names += ["ground_lit_log_r_over_b", "ground_shadow_log_r_over_b"]
    names += [
        f"puddle_{b}_{k}" for b in ("far", "mid", "near") for k in ("sky_blue_frac", "bright_frac", "sky_bright_frac")
    ]
    # version 4: the sky's thumbnail
    names += [f"sky_lab_{ch}_{r}{c}" for ch in "Lab" for r in range(_SKY_ROWS) for c in range(_SKY_LATTICE)]
    # version 5: the wet road by distance (a frozen learned detector)
    names += list(_WET_ROAD_NAMES)
    # version 6: the weather reader (a frozen learned network)
    names += list(_READER_NAMES)
    # version 7: the reader's sun head
    names += list(_SUN_HEAD_NAMES)
    return tuple(names)


#: the name of every feature, in output order
FEATURE_NAMES: tuple[str, ...] = _names()


#: the cues the training-input noise spares: the sun head's μ and log σ, an estimate of the sun's altitude whose own σ
#: (1.7° under a clear sky) is finer than the noise at 50 000 images (5.8°). The reader's twelve are estimates too, but
#: spared they let the flow overfit (docs/studies/estimate-noise.md).
SPARED: tuple[int, ...] = tuple(FEATURE_NAMES.index(name) for name in _SUN_HEAD_NAMES)


def _mirror_partner(name: str) -> str:
    """The feature that ``name`` becomes when the image is mirrored left-right: grid column c ↔ 3 − c, sky thumbnail
    column c ↔ 7 − c, left ↔ right wall, edge-orientation bin k ↔ (8 − k) mod 8 (the slant changes sign), ╱ ↔ ╲ ridges;
    itself for every feature of a region symmetric about the vertical midline (rows, bands, the road, the sky,
    whole-image statistics; the wet road's bands, whose detector is mirror-equivariant; the reader's guesses, averaged
    over the image and its mirror)."""
    if m := re.fullmatch(r"(grid_log_\w+?)(\d)(\d)", name):
        return f"{m[1]}{m[2]}{3 - int(m[3])}"
    if m := re.fullmatch(r"(sky_lab_\w_)(\d)(\d)", name):
        return f"{m[1]}{m[2]}{_SKY_LATTICE - 1 - int(m[3])}"
    if m := re.fullmatch(r"(fine_edge_hist|edge_hist)(\d)", name):
        return f"{m[1]}{(8 - int(m[2])) % 8}"
    for a, b in (("left_wall", "right_wall"), ("ridge_slash", "ridge_backslash")):
        if name.startswith(a):
            return b + name[len(a) :]
        if name.startswith(b):
            return a + name[len(b) :]
    return name


#: ``features(mirrored image) = features(image)[MIRROR]`` (to float rounding; ``tests/test_backbones.py``)
MIRROR: tuple[int, ...] = tuple(FEATURE_NAMES.index(_mirror_partner(n)) for n in FEATURE_NAMES)

_EPS = 1e-6


def _srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _box(x: torch.Tensor, k: int) -> torch.Tensor:
    """k×k mean filter of (n, 1, H, W) with replicated borders (separable running sums, O(1) per pixel)."""
    p = k // 2
    h, w = x.shape[-2:]
    c = F.pad(F.pad(x, (p, p, 0, 0), mode="replicate"), (1, 0)).cumsum(-1)
    rows = (c[..., k:] - c[..., :-k])[..., :w] / k
    c = F.pad(F.pad(rows, (0, 0, p, p), mode="replicate"), (0, 0, 1, 0)).cumsum(-2)
    return (c[..., k:, :] - c[..., :-k, :])[..., :h, :] / k


def _min_filter(x: torch.Tensor, k: int) -> torch.Tensor:
    """k×k minimum filter of (n, 1, H, W) with replicated borders (separable, shifted minima)."""
    p = k // 2
    h, w = x.shape[-2:]
    q = F.pad(x, (p, p, 0, 0), mode="replicate")
    rows = q[..., 0:w]
    for i in range(1, k):
        rows = torch.minimum(rows, q[..., i : i + w])
    q = F.pad(rows, (0, 0, p, p), mode="replicate")
    out = q[..., 0:h, :]
    for i in range(1, k):
        out = torch.minimum(out, q[..., i : i + h, :])
    return out


def _histogram(v: torch.Tensor, bins: int) -> torch.Tensor:
    """Counts of the values of each row of (n, m) in ``bins`` equal bins of [0, 1] → (n, bins)."""
    idx = torch.clamp((v * bins).long(), 0, bins - 1)
    return torch.zeros(v.shape[0], bins, dtype=v.dtype, device=v.device).scatter_add_(1, idx, torch.ones_like(v))


def _quantiles(counts: torch.Tensor, qs: tuple[float, ...]) -> torch.Tensor:
    """Quantiles of values in [0, 1] from their (n, bins) histogram (bin centres; 1/bins resolution)."""
    bins = counts.shape[1]
    cdf = counts.cumsum(1) / counts.sum(1, keepdim=True)
    q = torch.tensor(qs, dtype=counts.dtype, device=counts.device)
    idx = (cdf[:, None, :] < q[None, :, None]).sum(2).clamp(max=bins - 1)  # first bin with cdf ≥ q
    return (idx.to(counts.dtype) + 0.5) / bins


def _range_quantiles(v: torch.Tensor, percents: tuple[int, ...], lo: float, hi: float, bins: int = 512) -> torch.Tensor:
    """Quantiles (``percents`` in %) of each row of (n, m) with values in [lo, hi], from a ``bins``-bin histogram."""
    u = ((v - lo) / (hi - lo)).clamp(0.0, 1.0)
    q = _quantiles(_histogram(u, bins), tuple(p / 100.0 for p in percents))
    return lo + q * (hi - lo)


def _regional(x: torch.Tensor, lin: torch.Tensor) -> torch.Tensor:
    """Version-2 cues of sRGB images ``x (n, 3, H, W)`` in [0, 1], ``lin`` their linear RGB → ``(n, 161)`` (what each
    block reads: docs/backbones.md)."""
    n, _, h, w = x.shape
    y = 0.2126 * lin[:, 0] + 0.7152 * lin[:, 1] + 0.0722 * lin[:, 2]  # (n, H, W) linear luminance
    log_y = torch.log(y + 1e-3)
    lo, hi = _LOG_Y_RANGE
    out: list[torch.Tensor] = []
    # 4×4 grid of mean linear radiance: log luminance and log chromaticity ratios
    g = F.adaptive_avg_pool2d(lin, 4)
    gy = 0.2126 * g[:, 0] + 0.7152 * g[:, 1] + 0.0722 * g[:, 2]
    out += [torch.log(gy + 1e-3).flatten(1), torch.log((g[:, 0] + 1e-3) / (g[:, 1] + 1e-3)).flatten(1)]
    out.append(torch.log((g[:, 2] + 1e-3) / (g[:, 1] + 1e-3)).flatten(1))
    # road (lower 35 %, central 60 %): sunlit vs shadowed ground
    r0, c0 = int(0.65 * h), round(0.2 * w)
    c1 = w - c0  # left-right symmetric regions
    road = _range_quantiles(log_y[:, r0:, c0:c1].flatten(1), _ROAD_Q, lo, hi)
    out += [road, road[:, 5:6] - road[:, 1:2]]
    out.append(_range_quantiles(log_y.flatten(1), _IMAGE_Q, lo, hi))
    # side walls (rows 30–65 %, outer 20 % of columns): vertical surfaces, lit as cos h where the road is lit as sin h
    rows = slice(int(0.3 * h), int(0.65 * h))
    out.append(_range_quantiles(log_y[:, rows, :c0].flatten(1), _WALL_Q, lo, hi))
    out.append(_range_quantiles(log_y[:, rows, c1:].flatten(1), _WALL_Q, lo, hi))
    # row profiles (depth proxy): luminance, blue chromaticity, dark channel, fine-detail energy, streak ratio
    v = 0.2126 * x[:, 0] + 0.7152 * x[:, 1] + 0.0722 * x[:, 2]
    fine = v - _box(v[:, None], 3)[:, 0]
    pv = F.pad(v[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    gx = pv[:, 1:-1, 2:] - pv[:, 1:-1, :-2]  # horizontal gradient: vertical streaks
    gy_ = pv[:, 2:, 1:-1] - pv[:, :-2, 1:-1]
    profiles = (
        log_y,
        x[:, 2] / (x.sum(1) + _EPS),
        x.amin(1),
        torch.log(fine * fine + 1e-6),
        torch.log(gx * gx + 1e-6) - torch.log(gy_ * gy_ + 1e-6),
    )
    for f in profiles:
        out.append(F.adaptive_avg_pool1d(f.mean(2)[:, None], _ROWS)[:, 0])
    # sky (top 30 %): saturation and blue chromaticity distributions, share of clear blue sky
    sky = x[:, :, : int(0.3 * h)].flatten(2)
    smax = sky.amax(1)
    sat = (smax - sky.amin(1)) / (smax + _EPS)
    out.append(_range_quantiles(sat, _SKY_SAT_Q, 0.0, 1.0))
    out.append(_range_quantiles(sky[:, 2] / (sky.sum(1) + _EPS), _SKY_B_Q, 0.0, 1.0))
    out += [(sat > 0.15).to(x.dtype).mean(1, keepdim=True), (sat > 0.3).to(x.dtype).mean(1, keepdim=True)]
    return torch.cat(out, dim=1)


def _shift(x: torch.Tensor, dy: int, dx: int) -> torch.Tensor:
    """``x (n, H, W)`` read at (row + dy, column + dx), borders replicated (|dy|, |dx| ≤ 2)."""
    h, w = x.shape[-2:]
    p = F.pad(x[:, None], (2, 2, 2, 2), mode="replicate")[:, 0]
    return p[:, 2 + dy : 2 + dy + h, 2 + dx : 2 + dx + w]


def _ridges(v: torch.Tensor) -> torch.Tensor:
    """Thin bright lines of sRGB luma ``v (n, H, W)`` → ``(n, 18)``: per direction of :data:`_RIDGE_DIRECTIONS`, the
    response ``v − (v₋ + v₊)/2`` across the line averaged over :data:`_RIDGE_LENGTH` pixels along it; the shares of
    pixels above each threshold of :data:`_RIDGE_T`, log(mean positive response + 1e-5) over the image and its upper
    half."""
    out: list[torch.Tensor] = []
    thresholds = [float(t) for t in _RIDGE_T]
    half = v.shape[1] // 2
    for dy, dx in _RIDGE_DIRECTIONS.values():
        ay, ax = dx, -dy  # across the line: perpendicular to (dy, dx)
        r = v - 0.5 * (_shift(v, -ay, -ax) + _shift(v, ay, ax))
        k = _RIDGE_LENGTH // 2
        line = sum(_shift(r, i * dy, i * dx) for i in range(-k, k + 1)) / _RIDGE_LENGTH
        out += [(line > t).to(v.dtype).mean((1, 2))[:, None] for t in thresholds]
        pos = line.clamp_min(0.0)
        out += [torch.log(pos.mean((1, 2)) + 1e-5)[:, None], torch.log(pos[:, :half].mean((1, 2)) + 1e-5)[:, None]]
    return torch.cat(out, dim=1)


def _otsu(u: torch.Tensor, bins: int = 64) -> torch.Tensor:
    """Otsu's threshold of each row of ``u (n, m)`` (values in [0, 1]) from a ``bins``-bin histogram → ``(n, 1)``."""
    p = _histogram(u, bins)
    p = p / p.sum(1, keepdim=True)
    centre = (torch.arange(bins, dtype=u.dtype, device=u.device) + 0.5) / bins
    w0, mu = p.cumsum(1), (p * centre).cumsum(1)
    between = (mu[:, -1:] * w0 - mu) ** 2 / (w0 * (1.0 - w0) + 1e-9)  # between-class variance per split
    return (between.argmax(1, keepdim=True).to(u.dtype) + 1.0) / bins


def _ground(lin: torch.Tensor) -> torch.Tensor:
    """Lit and shadowed ground of linear RGB ``lin (n, 3, H, W)`` (lower 40 % of rows) → ``(n, 5)``: the lit share, the
    lit-minus-shadowed log ``Y`` and log(R/B), log(R/B) of the lit and of the shadowed pixels."""
    h = lin.shape[2]
    g = lin[:, :, int(0.6 * h) :].flatten(2)
    log_y = torch.log(0.2126 * g[:, 0] + 0.7152 * g[:, 1] + 0.0722 * g[:, 2] + 1e-3)
    log_rb = torch.log((g[:, 0] + 1e-3) / (g[:, 2] + 1e-3))
    lo, hi = log_y.amin(1, keepdim=True), log_y.amax(1, keepdim=True)
    lit = (log_y >= lo + _otsu((log_y - lo) / (hi - lo + 1e-6)) * (hi - lo)).to(lin.dtype)

    def mean(v: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        return (v * w).sum(1, keepdim=True) / w.sum(1, keepdim=True).clamp_min(1.0)

    y_lit, y_shadow = mean(log_y, lit), mean(log_y, 1.0 - lit)
    rb_lit, rb_shadow = mean(log_rb, lit), mean(log_rb, 1.0 - lit)
    return torch.cat([lit.mean(1, keepdim=True), y_lit - y_shadow, rb_lit - rb_shadow, rb_lit, rb_shadow], dim=1)


def _puddles(x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Puddles in three road bands of sRGB ``x (n, 3, H, W)`` with luma ``v (n, H, W)`` → ``(n, 9)``: per band of
    :data:`_PUDDLE_BANDS`, the shares of pixels bluer than the sky (top 30 %) less 0.02, brighter than 1.5 × the band's
    median and brighter than 0.6 × the sky's mean luma."""
    n, _, h, w = x.shape
    bchroma = x[:, 2] / (x.sum(1) + _EPS)
    s = int(0.3 * h)
    sky_b, sky_v = bchroma[:, :s].mean((1, 2))[:, None], v[:, :s].mean((1, 2))[:, None]
    c0, c1 = round(0.2 * w), w - round(0.2 * w)
    out: list[torch.Tensor] = []
    for a, b in _PUDDLE_BANDS:
        rows = slice(int(a * h), int(b * h))
        band_v, band_b = v[:, rows, c0:c1].flatten(1), bchroma[:, rows, c0:c1].flatten(1)
        median = _quantiles(_histogram(band_v, 256), (0.5,))
        out.append((band_b > sky_b - 0.02).to(x.dtype).mean(1, keepdim=True))
        out.append((band_v > 1.5 * median).to(x.dtype).mean(1, keepdim=True))
        out.append((band_v > 0.6 * sky_v).to(x.dtype).mean(1, keepdim=True))
    return torch.cat(out, dim=1)


def _orientation_histogram(v: torch.Tensor, bins: int = 8) -> torch.Tensor:
    """Energy-weighted histogram of edge orientation of (n, 1, H, W) → (n, bins + 1).

    Orientation is that of the Sobel gradient modulo 180°, binned through the doubled angle
    ``atan2(2 gx gy, gx² − gy²)``; bin ``k`` is centred on ``k·180°/bins``, so vertical structures
    (rain streaks without wind; horizontal gradient) fall in bin 0 and slanted streaks in bins 1 and
    ``bins − 1`` by sign of the slant. The histogram sums to 1; the last column is
    ``log(mean squared gradient magnitude + 1e-6)``.
    """
    p = F.pad(v, (1, 1, 1, 1), mode="replicate")[:, 0]
    dx = p[:, :, 2:] - p[:, :, :-2]  # (n, H+2, W) central differences
    dy = p[:, 2:, :] - p[:, :-2, :]  # (n, H, W+2)
    gx = ((dx[:, :-2] + 2 * dx[:, 1:-1] + dx[:, 2:]) * 0.125).flatten(1)  # Sobel
    gy = ((dy[:, :, :-2] + 2 * dy[:, :, 1:-1] + dy[:, :, 2:]) * 0.125).flatten(1)
    gxx, gyy = gx * gx, gy * gy
    energy = gxx + gyy
    doubled = torch.atan2(2.0 * gx * gy, gxx - gyy)  # (-π, π]
    idx = (doubled * (bins / (2 * torch.pi)) + (bins + 0.5)).long()  # in [bins/2, 3·bins/2]
    idx = torch.where(idx >= bins, idx - bins, idx)
    hist = torch.zeros(energy.shape[0], bins, dtype=energy.dtype, device=energy.device).scatter_add_(1, idx, energy)
    total = energy.sum(1, keepdim=True)
    return torch.cat([hist / (total + _EPS), torch.log(energy.mean(1, keepdim=True) + _EPS)], dim=1)


class CuesBackbone(Backbone):
    """Physical weather cues (377 features); frozen: no trained weights but the wet-road detector's, the reader's and its sun head's. See the module
    docstring."""

    name: ClassVar[str] = "cues"
    # 4.1: the sky's lattice converted to L*a*b* whole, as the tiny backbone converts it (version 4 sliced its rows
    # first: the same features but 1 ULP apart from the tiny's on some CPUs); cached features of "4" are recomputed.
    # 5: the wet road by distance (the detector's weights are in the fingerprint too)
    # 6: the weather reader, and the wet-road detector retrained on 100 000 images
    # 7: the reader's sun head (a second head on its convolutions, for the sun's altitude)
    # 8: the sun head retrained with 60 000 more images of the clear-sky face (docs/studies/sun-head-faces.md)
    version: ClassVar[str] = "8"
    dim: int = len(FEATURE_NAMES)
    trainable: bool = False
    input_size: tuple[int, int] = (128, 128)
    feature_names: tuple[str, ...] = FEATURE_NAMES
    cpu_chunk: ClassVar[int | None] = 16  # 0.6–0.7× the time of batches of 256 (docs/studies/cache-sized-pieces.md)

    def __init__(self) -> None:
        super().__init__()
        self.wet_road = load_detector()  # frozen, in eval mode; its weights checked against their card
        self.reader = load_reader()  # likewise
        self.sun_head = load_sun_head()  # likewise, and checked against the reader it reads

    def train(self, mode: bool = True) -> CuesBackbone:
        """Modules' training mode; the wet-road detector stays in eval mode (its batch norm is frozen)."""
        super().train(mode)
        self.wet_road.eval()
        self.reader.eval()
        self.sun_head.eval()
        return self

    def config(self) -> dict[str, Any]:
        return {"input_size": list(self.input_size)}

    def mirror_index(self) -> tuple[int, ...]:
        """:data:`MIRROR`: every region of the cues is symmetric about the vertical midline or has its mirror twin."""
        return MIRROR

    def spared_index(self) -> tuple[int, ...]:
        """:data:`SPARED`: the sun head's mean and log σ (the last two cues)."""
        return SPARED

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """sRGB images ``(n, 3, 128, 128)`` in [0, 1] → cues ``(n, 377)`` float32 (:data:`FEATURE_NAMES`).

        Region and colour statistics use the 2×2 area-averaged 64×64 image (4× cheaper, same means);
        contrast, edges and the clipped/dark fractions use full resolution (thin streaks, lamps).

        One method on purpose (over 80 lines): it reads as the table of cue blocks (docs/backbones.md), block after
        block in the order of :data:`FEATURE_NAMES`, sharing the intermediate images every block needs.
        """
        if x.ndim != 4 or x.shape[1] != 3 or x.shape[2] < 16 or x.shape[3] < 16:
            raise ValueError(f"cues: expected a tensor (n, 3, H, W) with H, W ≥ 16, got shape {tuple(x.shape)}")
        x = x.float().clamp(0.0, 1.0)
        n = x.shape[0]
        v_full = 0.2126 * x[:, 0:1] + 0.7152 * x[:, 1:2] + 0.0722 * x[:, 2:3]  # (n,1,H,W) sRGB luma
        xs = F.avg_pool2d(x, 2)  # (n,3,H/2,W/2)
        h, w = xs.shape[-2:]
        v = 0.2126 * xs[:, 0:1] + 0.7152 * xs[:, 1:2] + 0.0722 * xs[:, 2:3]
        vf = v.flatten(1)
        mx, mn = xs.amax(1, keepdim=True), xs.amin(1, keepdim=True)
        sat = (mx - mn) / (mx + _EPS)
        bchroma = xs[:, 2:3] / (xs.sum(1, keepdim=True) + _EPS)
        feats: list[torch.Tensor] = []

        # brightness
        counts = _histogram(vf, 256)
        feats += [vf.mean(1, keepdim=True), vf.std(1, keepdim=True), _quantiles(counts, (0.02, 0.25, 0.5, 0.75, 0.98))]
        feats.append(counts.view(n, 8, 32).sum(2) / vf.shape[1])

        # haze: dark channel (3×3 minimum at half resolution ≈ 6×6 pixels of the input)
        dark = _min_filter(mn, 3)
        df = dark.flatten(1)
        bands = torch.stack([dark[:, 0, i * h // 4 : (i + 1) * h // 4].mean((1, 2)) for i in range(4)], dim=1)
        airlight = _quantiles(_histogram(df, 256), (0.995,))
        transmission = (1.0 - 0.95 * df / (airlight + 1e-3)).clamp(0.0, 1.0).mean(1, keepdim=True)
        feats += [df.mean(1, keepdim=True), bands, airlight, transmission]
        feats.append(df.mean(1, keepdim=True) / (vf.mean(1, keepdim=True) + 1e-3))

        # contrast as a function of image row (depth proxy), 8×8 blocks at full resolution
        m1 = F.avg_pool2d(v_full, 8)
        m2 = F.avg_pool2d(v_full * v_full, 8)
        local = torch.sqrt((m2 - m1 * m1).clamp_min(0.0)) / (m1 + 0.05)  # (n,1,H/8,W/8)
        rows = local.shape[2]
        feats.append(torch.stack([local[:, 0, i * rows // 8 : (i + 1) * rows // 8].mean((1, 2)) for i in range(8)], 1))

        # sky band (top 30 %) and horizon band (30–55 %)
        s0, s1, s2 = round(0.3 * h), round(0.55 * h), max(1, round(0.1 * h))
        sky_v = v[:, :, :s0].flatten(1)
        feats += [xs[:, :, :s0].mean((2, 3)), sky_v.mean(1, keepdim=True), sky_v.std(1, keepdim=True)]
        feats += [bchroma[:, :, :s0].mean((1, 2, 3))[:, None], sat[:, :, :s0].mean((1, 2, 3))[:, None]]
        feats.append((v[:, :, :s2].mean((1, 2, 3)) - v[:, :, s0 - s2 : s0].mean((1, 2, 3)))[:, None])
        feats += [v[:, :, s0:s1].mean((1, 2, 3))[:, None], bchroma[:, :, s0:s1].mean((1, 2, 3))[:, None]]

        # saturation
        sf = sat.flatten(1)
        feats += [sf.mean(1, keepdim=True), sf.std(1, keepdim=True)]
        feats += [sat[:, :, : h // 2].mean((1, 2, 3))[:, None], sat[:, :, h // 2 :].mean((1, 2, 3))[:, None]]

        # oriented edge energy, full and fine scale (full resolution)
        fine = v_full - _box(v_full, 3)
        feats.append(_orientation_histogram(v_full))
        feats.append(_orientation_histogram(fine))

        # lens blobs: band-pass energies (half resolution) and smooth blocks (full resolution)
        blur3, blur7 = _box(v, 3), _box(v, 7)
        dog_small, dog_large = (v - blur3).flatten(1), (blur3 - blur7).flatten(1)
        e2 = (dog_large**2).mean(1, keepdim=True)
        kurt = (dog_large**4).mean(1, keepdim=True) / (e2 * e2 + 1e-12)
        block = F.avg_pool2d(fine * fine, 8).flatten(1)
        median = torch.sort(block, dim=1).values[:, block.shape[1] // 2 : block.shape[1] // 2 + 1]
        feats += [dog_small.abs().mean(1, keepdim=True), dog_large.abs().mean(1, keepdim=True)]
        feats += [(dog_large.abs() > 0.02).float().mean(1, keepdim=True), torch.log(kurt + 1.0)]
        feats.append((block < 0.1 * median + 1e-9).float().mean(1, keepdim=True))

        # road region: lower 35 %, central 60 % of columns
        r0, c0, c1 = round(0.65 * h), round(0.2 * w), round(0.8 * w)
        road_v = v[:, 0, r0:, c0:c1].flatten(1)
        feats += [
            road_v.mean(1, keepdim=True),
            road_v.std(1, keepdim=True),
            _quantiles(_histogram(road_v, 256), (0.98,)),
        ]
        feats.append((road_v > sky_v.mean(1, keepdim=True)).float().mean(1, keepdim=True))
        feats += [sat[:, 0, r0:, c0:c1].mean((1, 2))[:, None], bchroma[:, 0, r0:, c0:c1].mean((1, 2))[:, None]]

        # colour temperature
        lin = _srgb_to_linear(xs).flatten(2)  # (n,3,hw)
        lin_mean = lin.mean(2)
        chroma = xs.mean((2, 3)) / (xs.mean((2, 3)).sum(1, keepdim=True) + _EPS)
        feats += [chroma[:, 0:1], chroma[:, 2:3]]
        feats.append(torch.log((lin_mean[:, 0:1] + 1e-4) / (lin_mean[:, 2:3] + 1e-4)))
        bright = (vf >= _quantiles(counts, (0.98,)) - 0.5 / 256).to(lin.dtype)[:, None]  # (n,1,hw)
        white = (lin * bright).sum(2) / bright.sum(2).clamp_min(1.0)
        feats.append(torch.log((white[:, 0:1] + 1e-4) / (white[:, 2:3] + 1e-4)))

        # light sources and night (full resolution)
        vff = v_full.flatten(1)
        feats += [(vff < 0.05).float().mean(1, keepdim=True), (vff > 0.95).float().mean(1, keepdim=True)]

        lin_full = _srgb_to_linear(x)
        feats.append(_regional(x, lin_full))
        feats += [_ridges(v_full[:, 0]), _ground(lin_full), _puddles(x, v_full[:, 0])]
        # the tiny's cells (n, 3, lattice, lattice), converted whole as the tiny converts them: a slice of rows would
        # vectorize differently and round 1 ULP apart on some CPUs (AVX-512); then the upper rows
        lab = linear_to_lab(F.adaptive_avg_pool2d(lin_full, _SKY_LATTICE))
        feats.append(lab[:, :, :_SKY_ROWS].flatten(1) / 100.0)
        # the detector reads 128×128 rows (the image converted by area interpolation when of another size)
        x128 = x if tuple(x.shape[-2:]) == (128, 128) else F.interpolate(x, size=(128, 128), mode="area")
        feats.append(wet_road_features(self.wet_road, x128))
        feats.append(reader_features(self.reader, x128, self.sun_head))
        out = torch.cat(feats, dim=1)
        if out.shape[1] != self.dim:  # internal consistency of FEATURE_NAMES and the code above
            raise RuntimeError(f"cues: computed {out.shape[1]} features, FEATURE_NAMES has {self.dim}")
        return out
