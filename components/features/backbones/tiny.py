"""``tiny``: "tiny images" (Torralba, Fergus & Freeman, PAMI 2008) — a thumbnail plus local contrast.

What it sees. The 128×128 sRGB image (other sizes are converted by area interpolation) is
linearised, averaged over a ``grid × grid`` lattice of cells (area integration of light, as a coarse
camera would), and each cell's mean colour is expressed in CIE L*a*b* (D65), a perceptual colour
space in which Euclidean distances track perceived differences. Each cell also reports its local
contrast, the standard deviation of per-pixel L* inside the cell, which the thumbnail alone would
average away (fog, rain and lens drops change texture more than mean colour). Output, flattened in
this order: L*/100, a*/100, b*/100 (each ``grid²``, row-major cells), then std(L*)/100 (``grid²``):
``dim = 4·grid²`` (256 for the default 8×8).

Why. It is the baseline between the two other embedded backbones: unlike ``cues`` it encodes no
physics (just raw spatial appearance), unlike ``cnn`` it learns nothing and is frozen (features
cached). Torralba et al. showed that 32×32 colour thumbnails keep most scene-level information;
weather is a scene-level property, so an 8×8 lattice already carries sky colour, horizon haze,
overall brightness and where it changes.

Used by every stage but ``generate``, and by the ``pidc`` CLI.
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
import torch.nn.functional as F

from components.core.checks import whole_number
from components.features.backbones.base import Backbone

__all__ = ["TinyImagesBackbone", "srgb_to_lab"]

# linear sRGB → XYZ (D65), and the D65 white point
_RGB_TO_XYZ = torch.tensor(
    [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]]
)
_WHITE = torch.tensor([0.95047, 1.0, 1.08883])


def _lab_f(t: torch.Tensor) -> torch.Tensor:
    d = 6.0 / 29.0
    return torch.where(t > d**3, t.clamp_min(1e-12) ** (1.0 / 3.0), t / (3 * d * d) + 4.0 / 29.0)


def linear_to_lab(lin: torch.Tensor) -> torch.Tensor:
    """Linear sRGB ``(n, 3, ...)`` in [0, 1] → CIE L*a*b* ``(n, 3, ...)`` (L* in [0, 100])."""
    m = _RGB_TO_XYZ.to(lin.device, lin.dtype)
    xyz = torch.einsum("ij,nj...->ni...", m, lin)
    white = _WHITE.to(lin.device, lin.dtype).view(1, 3, *([1] * (lin.ndim - 2)))
    fx, fy, fz = _lab_f(xyz / white).unbind(1)
    return torch.stack([116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)], dim=1)


def srgb_to_lab(srgb: torch.Tensor) -> torch.Tensor:
    """sRGB-encoded ``(n, 3, ...)`` in [0, 1] → CIE L*a*b* ``(n, 3, ...)``."""
    lin = torch.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    return linear_to_lab(lin)


class TinyImagesBackbone(Backbone):
    """A ``grid × grid`` L*a*b* thumbnail plus per-cell L* contrast; frozen, no weights."""

    name: ClassVar[str] = "tiny"
    version: ClassVar[str] = "1"
    trainable: bool = False
    input_size: tuple[int, int] = (128, 128)
    cpu_chunk: ClassVar[int | None] = 16  # 0.5–0.7× the time of batches of 256 (docs/studies/cache-sized-pieces.md)

    def __init__(self, grid: int = 8) -> None:
        super().__init__()
        whole_number("tiny: grid", grid, low=2, high=32, hint=" (cells per side)")
        self.grid = grid
        self.dim = 4 * grid * grid

    def config(self) -> dict[str, Any]:
        return {"grid": self.grid, "input_size": list(self.input_size)}

    def mirror_index(self) -> tuple[int, ...]:
        """A left-right mirror of the image mirrors each lattice row: cell (row, column) ↔ (row, grid − 1 − column),
        in each of the four blocks."""
        g = self.grid
        return tuple(c * g * g + r * g + (g - 1 - k) for c in range(4) for r in range(g) for k in range(g))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """sRGB images ``(n, 3, H, W)`` in [0, 1] → ``(n, 4·grid²)`` float32 (see module docstring)."""
        if x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"tiny: expected a tensor (n, 3, H, W), got shape {tuple(x.shape)}")
        x = x.float().clamp(0.0, 1.0)
        lin = torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
        lab = linear_to_lab(F.adaptive_avg_pool2d(lin, self.grid))  # (n, 3, g, g)
        luminance = torch.einsum("j,njhw->nhw", _RGB_TO_XYZ[1].to(lin.device), lin)[:, None]
        lightness = 116.0 * _lab_f(luminance) - 16.0  # per-pixel L* (white Y = 1)
        m1 = F.adaptive_avg_pool2d(lightness, self.grid)
        m2 = F.adaptive_avg_pool2d(lightness * lightness, self.grid)
        contrast = torch.sqrt((m2 - m1 * m1).clamp_min(0.0))
        return torch.cat([lab, contrast], dim=1).flatten(1) / 100.0
