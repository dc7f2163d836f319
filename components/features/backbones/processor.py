"""A pretrained model's image preprocessing (resize, centre crop, rescale, normalise), batched in torch.

The recipe is read from the model's own image processor (``preprocessor_config.json`` saved with
the weights, parsed by ``transformers.AutoImageProcessor`` with its portable PIL backend, which also
normalises legacy formats such as ``"size": 224``) and then executed on whole batches in torch:

- ``size = {"shortest_edge": s}``: the shorter side becomes ``s``, the longer ``int(s·long/short)``;
  ``{"height": h, "width": w}``: resize to ``h × w``;
- ConvNeXT-style processors (used by ResNet-50) with ``s < 384``: resize the shorter side to
  ``int(s / crop_pct)`` and centre-crop ``s × s``; with ``s ≥ 384``: resize to ``s × s``;
- ``do_center_crop``: crop ``crop_size`` at offset ``((H − h)//2, (W − w)//2)``, zero-padding if smaller;
- rescale (``× rescale_factor``, usually 1/255) and normalise ``(x − mean) / std`` per channel.

Resampling uses torch's anti-aliased kernels, which are PIL's (bicubic with a = −0.5), and rounds
the resized image to 8 bits as PIL does, so the tensors match the reference processor to within
one grey level before normalisation (checked in ``tests/test_pretrained.py``).

Used by every stage but ``generate``, and by the ``pidc`` CLI.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch
import torch.nn.functional as F

__all__ = ["ImageTransform"]

# PIL resampling codes → torch interpolate modes (LANCZOS and HAMMING have no torch kernel: nearest
# anti-aliased kernels are used and the mode is recorded in the transform, hence in the fingerprint)
_MODES = {0: "nearest", 1: "bicubic", 2: "bilinear", 3: "bicubic", 4: "area", 5: "bilinear"}


@dataclass(frozen=True)
class ImageTransform:
    """A preprocessing recipe; call it on float ``(n, 3, H, W)`` images with values in 0–255."""

    #: ("shortest_edge", s) | ("size", h, w) | ("convnext", s, crop_pct) | None
    resize: tuple[Any, ...] | None
    mode: str
    crop: tuple[int, int] | None
    rescale: float | None
    mean: tuple[float, float, float] | None
    std: tuple[float, float, float] | None

    @classmethod
    def from_processor(cls, processor: Any) -> ImageTransform:
        """Build from a ``transformers`` image processor instance (any backend)."""
        size = getattr(processor, "size", None)
        resize: tuple[Any, ...] | None = None
        if getattr(processor, "do_resize", False) and size is not None:
            get = size.get if isinstance(size, dict) else (lambda k: getattr(size, k, None))
            shortest, height, width = get("shortest_edge"), get("height"), get("width")
            if type(processor).__name__.startswith("ConvNext") and shortest:
                resize = ("convnext", int(shortest), float(getattr(processor, "crop_pct", None) or 224 / 256))
            elif shortest:
                resize = ("shortest_edge", int(shortest))
            elif height and width:
                resize = ("size", int(height), int(width))
            else:
                raise ValueError(
                    f"{type(processor).__name__}: unsupported resize size {size!r} "
                    "(expected shortest_edge or height and width)"
                )
        crop = None
        crop_size = getattr(processor, "crop_size", None)
        if getattr(processor, "do_center_crop", False) and crop_size is not None:
            get = crop_size.get if isinstance(crop_size, dict) else (lambda k: getattr(crop_size, k, None))
            crop = (int(get("height")), int(get("width")))
        resample = getattr(processor, "resample", 3)
        mode = _MODES.get(int(resample) if resample is not None else 2, "bicubic")
        rescale = float(processor.rescale_factor) if getattr(processor, "do_rescale", False) else None
        mean = std = None
        if getattr(processor, "do_normalize", False):
            m, s = processor.image_mean, processor.image_std
            mean = tuple(float(v) for v in (m if isinstance(m, (list, tuple)) else [m] * 3))
            std = tuple(float(v) for v in (s if isinstance(s, (list, tuple)) else [s] * 3))
        return cls(resize=resize, mode=mode, crop=crop, rescale=rescale, mean=mean, std=std)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def output_size(self, height: int, width: int) -> tuple[int, int]:
        """The ``(H, W)`` of the model input for an input image of ``height × width`` pixels."""
        h, w = self._resized_size(height, width)
        if self.resize is not None and self.resize[0] == "convnext" and self.resize[1] < 384:
            h = w = self.resize[1]
        if self.crop is not None:
            h, w = self.crop
        return h, w

    def _resized_size(self, height: int, width: int) -> tuple[int, int]:
        if self.resize is None:
            return height, width
        kind = self.resize[0]
        if kind == "size":
            return self.resize[1], self.resize[2]
        s = self.resize[1]
        if kind == "convnext":
            if s >= 384:
                return s, s
            s = int(s / self.resize[2])
        short, long = min(height, width), max(height, width)
        new_long = int(s * long / short)
        return (s, new_long) if height <= width else (new_long, s)

    def describe(self, height: int, width: int) -> str:
        h, w = self._resized_size(height, width)
        text = f"{self.mode} resize to {h}×{w}"
        oh, ow = self.output_size(height, width)
        if (oh, ow) != (h, w):
            text += f", centre crop {oh}×{ow}"
        return text + ", as the model's image processor prescribes"

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """Float ``(n, 3, H, W)`` images in 0–255 → the normalised model input ``(n, 3, H', W')``."""
        h, w = x.shape[-2:]
        rh, rw = self._resized_size(h, w)
        if (rh, rw) != (h, w):
            if self.mode in ("nearest", "area"):
                x = F.interpolate(x, size=(rh, rw), mode=self.mode)
            else:
                x = F.interpolate(x, size=(rh, rw), mode=self.mode, antialias=True, align_corners=False)
            x = x.round().clamp(0.0, 255.0)
        if self.resize is not None and self.resize[0] == "convnext" and self.resize[1] < 384:
            x = _center_crop(x, self.resize[1], self.resize[1])
        if self.crop is not None:
            x = _center_crop(x, *self.crop)
        if self.rescale is not None:
            x = x * self.rescale
        if self.mean is not None and self.std is not None:
            mean = torch.tensor(self.mean, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
            std = torch.tensor(self.std, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
            x = (x - mean) / std
        return x


def _center_crop(x: torch.Tensor, ch: int, cw: int) -> torch.Tensor:
    h, w = x.shape[-2:]
    if h < ch or w < cw:  # zero-pad symmetrically first, as transformers does
        ph, pw = max(0, ch - h), max(0, cw - w)
        x = F.pad(x, (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2))
        h, w = x.shape[-2:]
    top, left = (h - ch) // 2, (w - cw) // 2
    return x[..., top : top + ch, left : left + cw]
