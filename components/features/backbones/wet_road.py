"""The wet road by distance: a small frozen detector of flooded road pixels, for the ``cues`` (from version 5).

Why. Deposits flood a road pixel where the renderer's static puddle noise lies below a level set by
``precipitation_deposits`` (:mod:`components.simulate.procedural.reflections`), so the *wet share of the road* follows
deposits, up to which part of the noise a scene shows. Near the car a camera sees a few noise periods and the share
varies from scene to scene; 10–25 m ahead it averages many: a reader of the exact wet share of the road in distance
bands would read deposits to 3.0 (median error, deposits in %; ``benchmarks/studies/bench_puddles.py``,
docs/studies/deposits.md), where the hand-made cues read them to ~7. Telling a wet pixel from a
dry one is the hard part: a puddle mirrors whatever lies above the horizon, darker or brighter than the road, and far
away it is a sliver of one pixel. No hand-made rule did it; this detector is learned, once, from the renderer's own
masks, and then frozen like the other cues.

What it is. A fully convolutional network on the rows :data:`ROWS` of the 128×128 sRGB image (the road from just below
the horizon to ~5 m ahead at the simulators' pitch), with the row's position as a fourth input channel: four 3×3
convolutions of :data:`CHANNELS` channels with dilations 1, 2, 4, 8 (a 31-pixel receptive field), batch norm and ReLU,
the last two residual, then a 1×1 convolution to three classes per pixel: not road, dry road, wet road. Every kernel is
symmetric left-right (it is parametrized as ``(w + flip(w))/2``), so the output of a mirrored image is the mirrored
output and the features below are exactly mirror-invariant (``train.mirror``).

The features (:data:`FEATURE_NAMES`, 2 per band of :data:`BANDS`): in each row band, the wet share of the road
``Σ p_wet / Σ (p_dry + p_wet)`` and the road's share of the band ``Σ (p_dry + p_wet) / pixels``, from the softmax
probabilities. The convolutions round by the call's batch (to ~1e-7): the same images in other
chunks give these 18 columns to 1e-6, not to the bit; the features stage always calls the cues in the same chunks.

Training (``python scripts/train_wet_road.py``): images of the
embedded renderer under weathers drawn from the uniform prior (the sun azimuth too), two per scene, labelled with the
scene's road mask and its wet mask (the puddle weight above ½), from scene seeds that the dataset splits do not use;
cross-entropy, AdamW with a one-cycle learning rate, every draw from the given seed. The shipped weights learned from
100 000 images in 12 epochs on a GPU (cues version 6; version 5's from 7 500 in 10 on this CPU: a day-time pixel AUC of
0.93 against 0.86, and wet-share correlations of 0.49–0.91 against 0.21–0.79 by band). The weights and a card (data,
seed, machine, validation figures, sha256) are :data:`WEIGHTS` and :data:`CARD`; :func:`load_detector` checks the
weights against the card.

Used by :mod:`components.features.backbones.cues` (every stage but ``generate``, and the ``pidc`` CLI) and by
``scripts/train_wet_road.py``.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from components.features.backbones.frozen import load_frozen

__all__ = [
    "BANDS",
    "CARD",
    "CHANNELS",
    "FEATURE_NAMES",
    "ROWS",
    "WEIGHTS",
    "WetRoadNet",
    "load_detector",
    "wet_road_features",
]

#: image rows (of 128) the detector sees: from just below the horizon to ~5 m ahead
ROWS: tuple[int, int] = (58, 106)
#: row bands of the features, far to near (rows of the 128-row image; 60–86 is ~10–25 m ahead at the default pitch)
BANDS: tuple[tuple[int, int], ...] = (
    (60, 64),
    (64, 67),
    (67, 71),
    (71, 76),
    (76, 81),
    (81, 86),
    (86, 93),
    (93, 100),
    (100, 106),
)
#: channels of the hidden layers
CHANNELS: int = 12
#: the pixel classes of the detector's output
CLASSES: tuple[str, ...] = ("other", "dry_road", "wet_road")
#: the frozen weights and their card, beside this module
WEIGHTS: Path = Path(__file__).with_name("wet_road.pt")
CARD: Path = Path(__file__).with_name("wet_road.json")

FEATURE_NAMES: tuple[str, ...] = tuple(
    f"wet_road_{what}_r{a}_{b}" for a, b in BANDS for what in ("wet_share", "road_share")
)


def _symmetric(w: torch.Tensor) -> torch.Tensor:
    """A kernel made symmetric left-right: ``(w + flip(w)) / 2`` over the last (column) axis."""
    return 0.5 * (w + w.flip(-1))


class WetRoadNet(nn.Module):
    """Per-pixel class logits ``(n, 3, R, W)`` of the rows :data:`ROWS` of sRGB images ``(n, 3, H, W)`` in [0, 1].

    Classes :data:`CLASSES`. Mirror-equivariant: ``net(x.flip(-1)) == net(x).flip(-1)`` to float rounding.
    """

    def __init__(self, channels: int = CHANNELS) -> None:
        super().__init__()
        c = channels
        self.convs = nn.ModuleList(
            [nn.Conv2d(4, c, 3, padding=1)] + [nn.Conv2d(c, c, 3, padding=d, dilation=d) for d in (2, 4, 8)]
        )
        self.norms = nn.ModuleList([nn.BatchNorm2d(c) for _ in range(4)])
        self.head = nn.Conv2d(c, len(CLASSES), 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r0, r1 = ROWS
        x = x[:, :, r0:r1]
        n, _, h, w = x.shape
        row = torch.linspace(0.0, 1.0, h, dtype=x.dtype, device=x.device).view(1, 1, h, 1).expand(n, 1, h, w)
        h_ = torch.cat([x, row], dim=1)
        for k, (conv, norm) in enumerate(zip(self.convs, self.norms, strict=True)):
            y = F.relu(
                norm(F.conv2d(h_, _symmetric(conv.weight), conv.bias, padding=conv.padding, dilation=conv.dilation))
            )
            h_ = h_ + y if k >= 2 else y
        return self.head(h_)


def wet_road_features(net: WetRoadNet, x: torch.Tensor) -> torch.Tensor:
    """sRGB images ``(n, 3, 128, 128)`` in [0, 1] → ``(n, 18)`` (:data:`FEATURE_NAMES`): per band of :data:`BANDS`,
    the road's wet share and the road's share of the band (soft, from the class probabilities)."""
    p = F.softmax(net(x), dim=1)  # (n, 3, R, W)
    r0 = ROWS[0]
    out = []
    for a, b in BANDS:
        band = p[:, :, a - r0 : b - r0]
        wet, road = band[:, 2].sum((1, 2)), (band[:, 1] + band[:, 2]).sum((1, 2))
        out += [wet / (road + 1e-3), road / (band.shape[2] * band.shape[3])]
    return torch.stack(out, dim=1)


def load_detector(weights: Path = WEIGHTS, card: Path = CARD) -> WetRoadNet:
    """The frozen detector, in eval mode, its weights checked against the card's sha256
    (:func:`components.features.backbones.frozen.load_frozen`: FileNotFoundError, ValueError)."""
    return load_frozen(
        lambda meta: WetRoadNet(int(meta.get("channels", CHANNELS))),
        weights,
        card,
        "wet-road detector",
        "scripts/train_wet_road.py",
    )
