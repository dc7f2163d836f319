"""The weather reader: a small frozen convolutional network that reads θ from the whole image, for the ``cues``.

Why. The hand-made cues read the daytime sun to ~4.7° (median error of the champion's posterior median), while a
convolutional network trained end to end on full-resolution images read it to 3.1°: the sun's height shows in the
interplay of shading, shadows and sky colour across the whole frame, which fixed statistics summarize poorly. Trained
end to end inside the grid such a network costs the grid its speed and its small-budget models their footing; trained
once on many rendered images and frozen, it is a cue like the others, computed once per image by the features stage.

What it is. Five strided convolutions (stride 2; 128 → 4 pixels; :data:`WIDTHS` channels) with batch norm and ReLU,
the 4×4 map flattened (where things are in the frame matters: the sky is at the top), a hidden layer, and for each
parameter θ_k of :data:`components.core.weather.PREDICTED` a Gaussian guess: a mean ``μ_k`` of θ_k scaled to the prior
box ([0, 1]) and a log standard deviation ``log σ_k``. The reader is not a posterior: the flow downstream learns how
far to trust it (at night ``σ`` of the cloudiness is large and the flow learns to read nothing from ``μ``).

The features (:data:`FEATURE_NAMES`, 12): ``μ_k`` and ``log σ_k`` averaged over the image and its mirror, so they are
mirror-invariant by construction (the six parameters do not change under a left-right flip; ``train.mirror``).

Training (``python scripts/train_weather_reader.py``): images of the embedded renderer under weathers drawn from the
uniform prior (the sun azimuth too), from scene seeds that the dataset splits do not use; Gaussian negative log
likelihood, random mirroring, AdamW with a one-cycle learning rate. The weights and a card (data, seed, validation
figures, machine, sha256) are :data:`WEIGHTS` and :data:`CARD`; :func:`load_reader` checks the weights against the card.
The convolutions round by the call's batch (to ~1e-6): the same images in other chunks give these columns to ~1e-5,
not to the bit; the features stage always calls the cues in the same chunks.

Used by :mod:`components.features.backbones.cues` and ``scripts/train_weather_reader.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import nn

from components.core.weather import SHORT_NAMES
from components.features.backbones.frozen import load_frozen

__all__ = [
    "CARD",
    "FEATURE_NAMES",
    "SUN_CARD",
    "SUN_FEATURE_NAMES",
    "SUN_HIDDEN",
    "SUN_WEIGHTS",
    "SunHead",
    "WEIGHTS",
    "WIDTHS",
    "WeatherReader",
    "load_reader",
    "load_sun_head",
    "reader_features",
    "reader_maps",
]

#: channels of the five strided convolutions
WIDTHS: tuple[int, ...] = (16, 32, 48, 64, 96)
#: units of the hidden layer
HIDDEN: int = 256
#: the frozen weights and their card, beside this module
WEIGHTS: Path = Path(__file__).with_name("weather_reader.pt")
CARD: Path = Path(__file__).with_name("weather_reader.json")

FEATURE_NAMES: tuple[str, ...] = tuple(f"reader_{what}_{k}" for k in SHORT_NAMES for what in ("mean", "log_sd"))

#: hidden units of the sun head
SUN_HIDDEN: tuple[int, ...] = (512, 256)
#: the sun head's frozen weights and card
SUN_WEIGHTS: Path = Path(__file__).with_name("weather_reader_sun.pt")
SUN_CARD: Path = Path(__file__).with_name("weather_reader_sun.json")
#: the sun head's features: its mean (unit scale) and log standard deviation of the sun's altitude
SUN_FEATURE_NAMES: tuple[str, ...] = ("reader_sun_head_mean", "reader_sun_head_log_sd")


class WeatherReader(nn.Module):
    """sRGB images ``(n, 3, 128, 128)`` in [0, 1] → ``(n, 6, 2)``: per parameter θ_k, the mean on the prior box's
    unit scale and the log standard deviation of a Gaussian guess."""

    def __init__(self, widths: tuple[int, ...] = WIDTHS, hidden: int = HIDDEN) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c = 3
        for k, w in enumerate(widths):
            kernel = 4 if k == 0 else 3  # the first sees every pixel of its 2×2 stride (1-pixel rain streaks)
            layers += [nn.Conv2d(c, w, kernel, stride=2, padding=1, bias=False), nn.BatchNorm2d(w), nn.ReLU()]
            c = w
        self.features = nn.Sequential(*layers)
        side = 128 >> len(widths)
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(c * side * side, hidden), nn.ReLU(), nn.Linear(hidden, 12))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 4 or tuple(x.shape[1:]) != (3, 128, 128):
            raise ValueError(f"weather reader: expected images (n, 3, 128, 128), got shape {tuple(x.shape)}")
        return self.head(self.features(x)).view(-1, 6, 2)


class SunHead(nn.Module):
    """A second head on the reader's frozen convolutions, for the sun's altitude alone: the 4×4 map flattened
    ``(n, C·16)`` → ``(n, 1, 2)``, the mean of the altitude on the prior box's unit scale and its log standard
    deviation.

    Why. The reader's own head shares its 256 hidden units among six parameters and reads the daytime sun to ~4°; a
    wider head that reads only the sun, trained on the frozen map of 100 000 further images, reads it to ~3.5°
    (docs/studies/cues-7.md). A wider one on 200 000 images reads it alone to 3.1° but left the champion's
    sun where it was (measured, not adopted: docs/studies/sun-head-200k.md). Trained by
    ``python scripts/train_sun_head.py``; its card names the reader whose convolutions it reads (:func:`load_sun_head`
    refuses another).
    """

    def __init__(self, in_features: int, hidden: tuple[int, ...] = SUN_HIDDEN) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c = in_features
        for h in hidden:
            layers += [nn.Linear(c, h), nn.ReLU()]
            c = h
        self.net = nn.Sequential(*layers, nn.Linear(c, 2))

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return self.net(h).view(-1, 1, 2)


def reader_maps(net: WeatherReader, x: torch.Tensor) -> torch.Tensor:
    """The convolutions' flattened 4×4 maps ``(2n, C·16)`` of sRGB images ``(n, 3, 128, 128)`` in [0, 1]: the n images
    first, then their mirrors (left-right), in one call; what both heads read."""
    return net.features(torch.cat([x, x.flip(-1)])).flatten(1)


def reader_features(net: WeatherReader, x: torch.Tensor, sun: SunHead | None = None) -> torch.Tensor:
    """sRGB images ``(n, 3, 128, 128)`` in [0, 1] → ``(n, 12)`` (:data:`FEATURE_NAMES`), or ``(n, 14)`` with the sun
    head (:data:`SUN_FEATURE_NAMES` last): the reader's ``μ_k`` and ``log σ_k`` (and the sun head's) averaged over each
    image and its mirror (exactly mirror-invariant: the sum is commutative). The convolutions run once for both heads
    (:func:`reader_maps`)."""
    n, h = len(x), reader_maps(net, x)
    heads = [net.head] if sun is None else [net.head, sun]
    return torch.cat([(0.5 * (g[:n] + g[n:])).flatten(1) for g in (head(h) for head in heads)], dim=1)


def gaussian_nll(out: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean negative log likelihood (nats per parameter, without ½ log 2π) of targets ``(n, 6)`` on the unit scale under
    the reader's Gaussians ``out`` ``(n, 6, 2)``."""
    mean, log_sd = out[..., 0], out[..., 1].clamp(-7.0, 3.0)
    return (log_sd + 0.5 * ((target - mean) * torch.exp(-log_sd)) ** 2).mean()


def load_sun_head(weights: Path = SUN_WEIGHTS, card: Path = SUN_CARD, reader_card: Path = CARD) -> SunHead:
    """The frozen sun head, in eval mode, its weights checked against its card's sha256
    (:func:`components.features.backbones.frozen.load_frozen`) and its card's ``reader_sha256`` against the reader's
    card: a head trained on another reader's convolutions reads nothing (ValueError)."""
    fields: dict = {}

    def build(meta: dict) -> SunHead:
        fields.update(meta)  # the card as load_frozen read it: read once
        return SunHead(int(meta["in_features"]), tuple(meta.get("hidden", SUN_HIDDEN)))

    head = load_frozen(build, weights, card, "reader's sun head", "scripts/train_sun_head.py")
    want = json.loads(reader_card.read_text()).get("sha256") if reader_card.is_file() else None
    got = fields.get("reader_sha256")
    if got != want:
        raise ValueError(
            f"{card}: the sun head was trained on the reader {str(got)[:16]}…, not on {reader_card}'s "
            f"{str(want)[:16]}… (retrain it: python scripts/train_sun_head.py)"
        )
    return head


def load_reader(weights: Path = WEIGHTS, card: Path = CARD) -> WeatherReader:
    """The frozen reader, in eval mode, its weights checked against the card's sha256
    (:func:`components.features.backbones.frozen.load_frozen`: FileNotFoundError, ValueError)."""
    return load_frozen(
        lambda meta: WeatherReader(tuple(meta.get("widths", WIDTHS)), int(meta.get("hidden", HIDDEN))),
        weights,
        card,
        "weather reader",
        "scripts/train_weather_reader.py",
    )
