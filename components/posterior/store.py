"""Saving and loading a trained :class:`NPE` with everything needed to rebuild it.

A model file (``models/<backbone>-<size>/model.pt``) holds the state dict and a JSON-able header:
the backbone's name and options (for a backbone trained jointly with the flow, it is rebuilt and its
trained weights come from the state dict), the context size, one input's shape, the flow's
hyper-parameters, the prior box and the θ names and units. ``load_npe`` refuses a file whose format
it does not know.

Used by the ``train`` and ``export`` stages.
"""

from __future__ import annotations

import io
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from components.core import weather
from components.core.files import atomic_write_bytes
from components.posterior.model import NPE, FlowConfig

__all__ = ["save_npe", "load_npe", "MODEL_FORMAT"]

MODEL_FORMAT = 1


def save_npe(
    path: str | Path, model: NPE, *, backbone: str, backbone_options: dict[str, Any], extra: dict | None = None
) -> None:
    """Write ``model`` and its header atomically to ``path``."""
    embedded = not isinstance(model.embedding, torch.nn.Identity)
    header = {
        "format": MODEL_FORMAT,
        "backbone": backbone,
        "backbone_options": dict(backbone_options),
        "trainable_backbone": embedded,
        "features": model.features,
        "input_shape": list(model.input_shape) if model.input_shape is not None else None,
        "flow": asdict(model.config),
        "box": {
            "low": model.box.low.tolist(),
            "high": model.box.high.tolist(),
            "names": list(model.box.names),
            "units": list(model.box.units),
        },
        "extra": extra or {},
    }
    buf = io.BytesIO()
    torch.save({"header": header, "state_dict": model.state_dict()}, buf)
    atomic_write_bytes(path, buf.getvalue())


def load_npe(path: str | Path) -> tuple[NPE, dict[str, Any]]:
    """Rebuild the model saved at ``path``; returns ``(model in eval mode, header)``."""
    path = Path(path)
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no model file; run the train stage") from None
    except Exception as e:  # a truncated or foreign file
        raise ValueError(f"{path}: not a pidc model file ({type(e).__name__}: {e})") from None
    header = blob.get("header", {}) if isinstance(blob, dict) else {}
    if header.get("format") != MODEL_FORMAT:
        raise ValueError(f"{path}: model format {header.get('format')!r}, this pidc reads {MODEL_FORMAT}")
    box = weather.Box(
        np.array(header["box"]["low"]),
        np.array(header["box"]["high"]),
        tuple(header["box"]["names"]),
        tuple(header["box"]["units"]),
    )
    flow = dict(header["flow"])
    flow["hidden_features"] = tuple(flow["hidden_features"])
    flow["context_layers"] = tuple(flow.get("context_layers", ()))  # files written before the context network: none
    embedding = None
    if header["trainable_backbone"]:
        from components.features.backbones import get_backbone

        embedding = get_backbone(header["backbone"], **header["backbone_options"])
    input_shape = tuple(header["input_shape"]) if header["input_shape"] is not None else None
    model = NPE(embedding, header["features"], box, FlowConfig(**flow), input_shape=input_shape)
    try:
        model.load_state_dict(blob["state_dict"])
    except RuntimeError as e:  # e.g. a file of an older pidc, without the flows' base scale τ
        missing = sorted(set(model.state_dict()) - set(blob["state_dict"]))
        unexpected = sorted(set(blob["state_dict"]) - set(model.state_dict()))
        what = (
            f"missing {missing[:4]}, unexpected {unexpected[:4]}{', …' if len(missing) > 4 or len(unexpected) > 4 else ''}"
            if missing or unexpected
            else str(e).strip().splitlines()[-1].strip()  # same names, other shapes: torch's line naming one
        )
        raise ValueError(
            f"{path}: its weights do not fit this pidc's model ({what}): a file of another pidc version; "
            "re-run the train stage"
        ) from None
    model.eval()
    return model, header
