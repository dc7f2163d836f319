"""Axis labels of the weather parameters, with their physical units (from :mod:`components.core.weather`).

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

from components.core.weather import PARAMETERS, PREDICTED, SHORT_NAMES

__all__ = ["unit_symbol", "parameter_label", "short_label"]

_SYMBOLS = {"deg": "°", "%": "%"}


def unit_symbol(name: str) -> str:
    """The unit of a CARLA parameter as printed on an axis (``%``, ``°``, …)."""
    unit = PARAMETERS[name].unit
    return _SYMBOLS.get(unit, unit)


def parameter_label(i: int) -> str:
    """``"fog density [%]"``: the full name and unit of θ_i."""
    name = PREDICTED[i]
    return f"{name.replace('_', ' ')} [{unit_symbol(name)}]"


def short_label(i: int) -> str:
    """``"fog [%]"``: the short name and unit of θ_i (corner plots)."""
    return f"{SHORT_NAMES[i]} [{unit_symbol(PREDICTED[i])}]"
