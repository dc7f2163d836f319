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

from pathlib import Path

import torch
from torch import nn

from components.core.weather import SHORT_NAMES
from components.features.backbones.frozen import load_frozen

__all__ = ["CARD", "FEATURE_NAMES", "WEIGHTS", "WIDTHS", "WeatherReader", "load_reader", "reader_features"]

#: channels of the five strided convolutions
WIDTHS: tuple[int, ...] = (16, 32, 48, 64, 96)
#: units of the hidden layer
HIDDEN: int = 256
#: the frozen weights and their card, beside this module
WEIGHTS: Path = Path(__file__).with_name("weather_reader.pt")
CARD: Path = Path(__file__).with_name("weather_reader.json")

FEATURE_NAMES: tuple[str, ...] = tuple(f"reader_{what}_{k}" for k in SHORT_NAMES for what in ("mean", "log_sd"))


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


def reader_features(net: WeatherReader, x: torch.Tensor) -> torch.Tensor:
    """sRGB images ``(n, 3, 128, 128)`` in [0, 1] → ``(n, 12)`` (:data:`FEATURE_NAMES`): the reader's ``μ_k`` and
    ``log σ_k`` averaged over each image and its mirror (exactly mirror-invariant: the sum is commutative)."""
    both = net(torch.cat([x, x.flip(-1)]))
    a, b = both[: len(x)], both[len(x) :]
    return (0.5 * (a + b)).flatten(1)


def gaussian_nll(out: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean negative log likelihood (nats per parameter, without ½ log 2π) of targets ``(n, 6)`` on the unit scale under
    the reader's Gaussians ``out`` ``(n, 6, 2)``."""
    mean, log_sd = out[..., 0], out[..., 1].clamp(-7.0, 3.0)
    return (log_sd + 0.5 * ((target - mean) * torch.exp(-log_sd)) ** 2).mean()


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
