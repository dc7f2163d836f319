"""The embedded procedural renderer: physically based front-camera images under CARLA weathers.

Used by the ``generate`` stage (datasets), the ``evaluate`` stage (posterior predictive checks), ``task2``
(rendered bags) and the ``pidc`` CLI (``render``). :class:`ProceduralSimulator` is the entry point; the other modules
are its physics.
"""

from components.simulate.procedural.renderer import ProceduralSimulator

__all__ = ["ProceduralSimulator"]
