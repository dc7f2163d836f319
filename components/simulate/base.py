"""The simulator protocol shared by the procedural renderer and the CARLA backend.

Used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the ``pidc`` CLI.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["Simulator", "make_simulator", "new_scene_simulator"]


@runtime_checkable
class Simulator(Protocol):
    """Renders a front-camera RGB image of a scene under a weather.

    ``weather`` maps CARLA parameter names to floats (:mod:`components.core.weather`); missing fixed
    parameters take their fixed values, the six predicted ones and the sun azimuth are required.
    The scene (map/layout, ego vehicle and camera, traffic, pedestrians, static noise fields) depends
    on ``scene_seed`` only, so the same scene can be re-rendered under other weathers.

    Returns an ``(height, width, 3)`` uint8 RGB array.
    """

    height: int
    width: int
    #: identifies the renderer and its calibration; recorded with every dataset
    version: str

    def render(self, weather: Mapping[str, float], scene_seed: int) -> np.ndarray: ...


def make_simulator(config) -> Simulator:
    """The simulator a :class:`components.core.config.SimulatorConfig` names (imported lazily): the procedural
    renderer, its renders resized (``render_sizes``, :class:`~components.simulate.resized.ResizedRenders`) or CARLA."""
    if config.backend == "procedural" and config.render_sizes is not None:
        from components.simulate.resized import ResizedRenders

        return ResizedRenders(config.height, config.width, config.render_sizes)
    if config.backend == "procedural":
        from components.simulate.procedural.renderer import ProceduralSimulator

        return ProceduralSimulator(config.height, config.width)
    if config.backend == "carla":
        from components.simulate.carla import CarlaSimulator

        return CarlaSimulator.from_config(config)
    if config.backend == "recorded":
        raise ValueError(
            "simulator.backend is recorded: no simulator renders recorded scenes (Task II's bag is rendered by "
            "simulator.recorded.renderer; the scheduled monitoring judges a recorded folder, monitor.source)"
        )
    raise ValueError(f"unknown simulator backend {config.backend!r}; known: procedural, carla")


def new_scene_simulator(config) -> Simulator | None:
    """The simulator of images in new scenes (Task II's bag): the backend's (:func:`make_simulator`), or with
    ``backend: recorded`` the one ``simulator.recorded.renderer`` names, rendering at ``height × width`` (None when it
    names none)."""
    if config.backend != "recorded":
        return make_simulator(config)
    if config.recorded.renderer is None:
        return None
    return make_simulator(config.model_copy(update={"backend": config.recorded.renderer}))
