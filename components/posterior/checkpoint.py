"""Atomic checkpoint files: a run killed at any moment leaves either the previous or the new checkpoint, whole.

The state is written to a temporary file in the same directory, flushed to disk, then renamed over the target
with ``os.replace`` (atomic on POSIX and Windows within one file system): :func:`components.core.files.atomic_path`.

Used by the ``train`` stage; the ``export`` stage imports it only through
:mod:`components.posterior`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from components.core.files import atomic_path

__all__ = ["save_checkpoint", "load_checkpoint"]


def save_checkpoint(state: dict[str, Any], path: str | Path) -> None:
    """Write ``state`` (tensors, numbers, strings, lists, dicts) to ``path`` atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(state, f)


def load_checkpoint(path: str | Path) -> dict[str, Any] | None:
    """The state saved at ``path``, or ``None`` when there is no file. A corrupt file is a ``ValueError`` naming it."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises several types for a truncated or foreign file
        raise ValueError(
            f"checkpoint {path} cannot be read ({type(err).__name__}: {err}); delete it to start over"
        ) from None
    if not isinstance(state, dict):
        raise ValueError(f"checkpoint {path} does not hold a training state (got {type(state).__name__})")
    return state
