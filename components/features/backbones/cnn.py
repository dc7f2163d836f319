"""``cnn``: a small convolutional embedding network trained jointly with the flow (NPE), trainable.

What it sees. The image reduced to 64×64 by area interpolation (2×2 pixel means of the 128×128
render; other sizes likewise; said once), as sRGB values in [0, 1], plus one constant channel holding
the normalised image row (−1 at the top, +1 at the bottom): rows are a depth proxy in a forward
camera (sky and horizon far, road near), so filters can tell sky from road and haze at the horizon
from haze near the car. Architecture (``width = w``, default 16):

    (n, 4, 64, 64) → 4 × [conv3×3 stride 2, GroupNorm, SiLU]: w, 2w, 3w, 4w channels at 32, 16, 8, 4 px
                  → [conv3×3, GroupNorm, SiLU]: 6w channels at 4×4
                  → global mean and global max per channel (12w) → linear → dim (default 64)

The first convolution already strides (it still sees every pixel: 3×3 windows overlap), which
halves the cost of joint training compared with a full-resolution first layer (measured 2× on
this CPU) at the price of coarser localisation of the finest structures.

Global pooling makes the embedding a set of image-wide statistics of learned local detectors, which
suits weather (a global property); the max branch keeps rare events (lamps, a few streaks).
GroupNorm (not BatchNorm) keeps train and eval behaviour identical and batch-size independent.

Why. It is the learned end of the backbone comparison: the embedding is optimised for the posterior
loss, at the price of needing training data; comparing it with the frozen ``cues`` and ``tiny``
across training sizes is the point of the 3×3 grid. Its initial weights are a deterministic
function of ``seed`` (a stream of :mod:`components.core.seeding`), so the same seed gives the same network.

Used by every stage but ``generate``, and by the ``pidc`` CLI.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import torch
from torch import nn

from components.core import seeding
from components.core.checks import whole_number
from components.features.backbones.base import Backbone

__all__ = ["ConvBackbone"]


def _block(c_in: int, c_out: int, stride: int) -> nn.Sequential:
    groups = 4 if c_out % 4 == 0 else 1
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False),
        nn.GroupNorm(groups, c_out),
        nn.SiLU(),
    )


class ConvBackbone(Backbone):
    """Small CNN on 64×64 images → ``(n, dim)``; trained with the flow. See the module docstring."""

    name: ClassVar[str] = "cnn"
    version: ClassVar[str] = "1"
    trainable: bool = True
    input_size: tuple[int, int] = (64, 64)

    def __init__(self, seed: int = 0, dim: int = 64, width: int = 16) -> None:
        super().__init__()
        for key, value, lo, hi in (("dim", dim, 1, 4096), ("width", width, 4, 256)):
            whole_number(f"cnn: {key}", value, low=lo, high=hi)
        self.seed, self.dim, self.width = whole_number("cnn: seed", seed, low=0), dim, width
        w = width
        self.features = nn.Sequential(
            _block(4, w, 2),
            _block(w, 2 * w, 2),
            _block(2 * w, 3 * w, 2),
            _block(3 * w, 4 * w, 2),
            _block(4 * w, 6 * w, 1),
        )
        self.head = nn.Linear(12 * w, dim)
        rows = torch.linspace(-1.0, 1.0, self.input_size[0]).view(1, 1, -1, 1).expand(1, 1, *self.input_size)
        self.register_buffer("row_channel", rows.contiguous(), persistent=False)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Re-draw every weight from the ``(seed, "backbone", "cnn")`` stream (deterministic)."""
        gen = torch.Generator().manual_seed(seeding.derive_seed(self.seed, "backbone", "cnn"))
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_uniform_(m.weight, a=math.sqrt(5), generator=gen)
            elif isinstance(m, nn.GroupNorm):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
            elif isinstance(m, nn.Linear):
                nn.init.kaiming_uniform_(m.weight, a=math.sqrt(5), generator=gen)
                bound = 1.0 / math.sqrt(m.in_features)
                nn.init.uniform_(m.bias, -bound, bound, generator=gen)

    def config(self) -> dict[str, Any]:
        return {"seed": self.seed, "dim": self.dim, "width": self.width, "input_size": list(self.input_size)}

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """sRGB images ``(n, 3, 64, 64)`` in [0, 1] → embedding ``(n, dim)``."""
        if x.ndim != 4 or x.shape[1] != 3 or tuple(x.shape[2:]) != tuple(self.input_size):
            raise ValueError(
                f"cnn: expected a tensor (n, 3, {self.input_size[0]}, {self.input_size[1]}) "
                f"(use preprocess), got shape {tuple(x.shape)}"
            )
        x = (x - 0.5) / 0.25
        x = torch.cat([x, self.row_channel.to(x.dtype).expand(x.shape[0], -1, -1, -1)], dim=1)
        h = self.features(x)
        pooled = torch.cat([h.mean((2, 3)), h.amax((2, 3))], dim=1)
        return self.head(pooled)
