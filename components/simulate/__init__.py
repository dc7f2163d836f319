"""Simulators of front-camera images under CARLA weathers.

``Simulator`` is the protocol; ``ProceduralSimulator`` the embedded default renderer;
``CarlaSimulator`` (imported lazily, it needs the ``carla`` client) the CARLA backend.
"""

from __future__ import annotations

from typing import Any

from .base import Simulator
from .procedural import ProceduralSimulator

__all__ = ["Simulator", "ProceduralSimulator", "CarlaSimulator"]


def __getattr__(name: str) -> Any:
    if name == "CarlaSimulator":
        from .carla import CarlaSimulator

        return CarlaSimulator
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
