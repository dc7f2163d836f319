"""The local model registry ``registry/``: one exported folder per model, and the champion pointer.

``registry/<model id>/`` holds what :func:`components.export.onnx.export_posterior` writes (ONNX graphs +
``card.json``). The champion pointer ``reports/task1/champion.json`` (beside ``registry/`` in the project; written by
the evaluate stage) names the model the Task I evaluation found best calibrated. A model is used on images through its
backbone (named in the card): :class:`RegisteredPosterior` pairs the torch-free
:class:`~components.export.runtime.OnnxPosterior` with the backbone that turns uint8 images into the posterior's input.

Used by the ``evaluate``, ``task2`` and ``task3`` stages, the scheduled monitoring and the ``pidc`` CLI.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from components.core.images import render_shape
from components.export.runtime import OnnxPosterior

__all__ = ["CHAMPION_POINTER", "RegisteredPosterior", "resolve_model", "read_champion", "load_registered"]

#: The champion pointer, relative to the project folder that holds ``registry/`` (written by the evaluate stage).
CHAMPION_POINTER = Path("reports") / "task1" / "champion.json"


def read_champion(registry: str | Path) -> dict[str, Any]:
    """The champion pointer of ``registry`` (``<project>/reports/task1/champion.json``): ``{"model": id, "rule":
    branch, "reason": …, "metrics": {...}, "runner_up": {...}, ...}`` (:mod:`components.evaluate.champion`); clear
    errors when absent."""
    path = Path(registry).resolve().parent / CHAMPION_POINTER
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no champion yet; run the evaluation (`dvc repro evaluate`) or name a model id instead of 'champion'"
        )
    try:
        champion = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(champion, dict) or not isinstance(champion.get("model"), str):
        raise ValueError(f"{path}: expected an object with a 'model' id")
    return champion


def resolve_model(model: str | Path, registry: str | Path = "registry") -> Path:
    """The exported folder of ``model``: a folder path, a model id under ``registry``, or ``champion``."""
    registry = Path(registry)
    name = str(model)
    if name == "champion":
        name = read_champion(registry)["model"]
    candidate = Path(model)
    if candidate.is_dir() and (candidate / "card.json").exists():
        return candidate
    folder = registry / name
    if not folder.is_dir():
        known = sorted(p.name for p in registry.glob("*") if (p / "card.json").is_file()) if registry.is_dir() else []
        raise FileNotFoundError(
            f"{folder}: no exported model {name!r} in {registry} (known: {', '.join(known) or 'none'}; "
            "run `dvc repro export`)"
        )
    return folder


@dataclass(frozen=True)
class RegisteredPosterior:
    """A registry model ready for images: ``posterior`` (onnxruntime) and the ``backbone`` making its input.

    Attributes:
        folder: the exported folder.
        posterior: q(θ | x), :class:`~components.export.runtime.OnnxPosterior`.
        backbone: the image backbone named by the card (:func:`components.features.backbones.get_backbone`).
    """

    folder: Path
    posterior: OnnxPosterior
    backbone: Any

    @property
    def name(self) -> str:
        return str(self.posterior.card.get("model_id", self.folder.name))

    @property
    def training_renders(self) -> tuple[int, int, tuple[int, int] | None] | None:
        """The images the model learned from, as its card's ``training_renders`` (written by the export stage) names
        them: ``(height, width, render_sizes)``, render_sizes None for the renderer's own ``height × width`` images or
        ``(low, high)`` for renders low..high pixels high shrunk to that size (``simulator.render_sizes``); None for a
        card exported before it recorded them."""
        renders = self.posterior.card.get("training_renders") or {}
        h, w = renders.get("height"), renders.get("width")
        if h is None or w is None:
            return None
        sizes = renders.get("render_sizes")
        return int(h), int(w), (None if sizes is None else (int(sizes[0]), int(sizes[1])))

    def learned_size(self, size: tuple[int, int]) -> bool | None:
        """Whether images of ``size = (H, W)`` pixels are of a size the model learned from; None when its card does not
        name its images (:attr:`training_renders`).

        A model of the renderer's own images learned their size alone: images of another size are area-resized to the
        backbone's input, and the pipeline's calibration does not cover them (docs/studies/other-resolutions.md). A model of resized renders learned frames low..high pixels high at the renders' aspect, shrunk
        to ``height × width``, so that size too (images taken as already shrunk; the renderer's own unresized images of
        that size are not what it learned: docs/studies/camera-renders.md)."""
        renders = self.training_renders
        if renders is None:
            return None
        height, width, sizes = renders
        h, w = int(size[0]), int(size[1])
        if (h, w) == (height, width):
            return True
        return sizes is not None and sizes[0] <= h <= sizes[1] and (h, w) == render_shape(height, width, h)

    @property
    def learned_from(self) -> str | None:
        """The images the model learned from, in words (``"128×128 renders"``); None when its card does not say."""
        renders = self.training_renders
        if renders is None:
            return None
        height, width, sizes = renders
        if sizes is None:
            return f"{width}×{height} renders"
        return f"renders {sizes[0]}–{sizes[1]} pixels high, area-resized to {width}×{height}"

    def inputs(self, images: np.ndarray, batch_size: int = 256) -> np.ndarray:
        """uint8 images ``(n, H, W, 3)`` → the posterior's input ``x`` (float32)."""
        from components.features.cache import posterior_inputs

        return posterior_inputs(self.backbone, images, batch_size)


def load_registered(model: str | Path, registry: str | Path = "registry", *, threads: int = 1) -> RegisteredPosterior:
    """Open a registry model (:func:`resolve_model`) with its backbone.

    Raises ``FileNotFoundError``/``ValueError`` for a missing or damaged folder, a card without a backbone, or a
    backbone whose code differs from the one the model was trained with (fingerprint).
    """
    from components.features.backbones import get_backbone

    folder = resolve_model(model, registry)
    posterior = OnnxPosterior.load(folder, intra_op_num_threads=threads)
    card = posterior.card
    if not isinstance(card.get("backbone"), str):
        raise ValueError(
            f"{folder / 'card.json'}: the card names no backbone; re-export the model with the export stage"
        )
    backbone = get_backbone(card["backbone"], **(card.get("backbone_options") or {}))
    expected = card.get("backbone_fingerprint")
    if expected and not backbone.trainable and backbone.fingerprint() != expected:
        raise ValueError(
            f"{folder}: backbone {card['backbone']!r} has fingerprint {backbone.fingerprint()[:12]}… but the model was "
            f"trained on features of {str(expected)[:12]}…; retrain and re-export (`dvc repro`)"
        )
    return RegisteredPosterior(folder, posterior, backbone)
