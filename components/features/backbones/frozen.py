"""Frozen networks of the cues: weights learned once from the renderer's labels, shipped beside their card.

A card is a JSON file beside the weights: what the network is, the data and seed it learned from, its validation
figures, the command that made it and the weights' sha256. :func:`load_frozen` refuses weights that the card does not
describe, so a cached feature can never come from other weights than the fingerprint says.

Used by :mod:`components.features.backbones.wet_road` and :mod:`components.features.backbones.weather_reader`.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import torch
from torch import nn

from components.core.files import sha256_file

__all__ = ["load_frozen"]

M = TypeVar("M", bound=nn.Module)


def load_frozen(build: Callable[[dict[str, Any]], M], weights: Path, card: Path, what: str, script: str) -> M:
    """``build(card)``'s network with ``weights`` loaded, frozen (no gradients) and in eval mode.

    Arguments:
        build: makes the untrained network from the card's fields (e.g. its channels).
        weights: the ``.pt`` state dict.
        card: its JSON card (with ``"sha256"``).
        what: the network's name, for the errors.
        script: the command that trains it, for the errors.

    Raises:
        FileNotFoundError: the weights or the card are missing.
        ValueError: the card is not JSON or lacks a field ``build`` needs, the weights differ from the card's sha256,
            or do not fit the network.
    """
    for path in (weights, card):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: the {what} of the cues is missing (train it: python {script})")
    try:
        meta = json.loads(card.read_text())
    except ValueError as e:
        raise ValueError(f"{card}: the {what}'s card is not valid JSON ({e}); retrain with python {script}") from None
    digest = sha256_file(weights)
    if digest != meta.get("sha256"):
        raise ValueError(
            f"{weights}: sha256 {digest[:16]}… differs from {card}'s {str(meta.get('sha256'))[:16]}… "
            f"(a modified or foreign file; retrain with python {script})"
        )
    try:
        net = build(meta)
    except KeyError as e:
        raise ValueError(f"{card}: the {what}'s card has no field {e} (retrain with python {script})") from None
    except (TypeError, ValueError) as e:
        raise ValueError(f"{card}: the {what}'s card describes no network this pidc can build ({e})") from None
    try:
        net.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
    except (RuntimeError, KeyError) as e:
        raise ValueError(f"{weights}: the weights do not fit the {what} ({e})") from None
    for p in net.parameters():
        p.requires_grad_(False)
    return net.eval()
