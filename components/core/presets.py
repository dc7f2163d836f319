"""CARLA's weather presets (``carla.WeatherParameters.ClearNoon`` …) as data, and which of them pidc renders.

CARLA 0.9.16 names 22 presets: seven at noon (sun altitude 45°), seven at sunset (15°), seven at night (−90°) and
``DustStorm`` (its ``Default`` is no weather: every field "unchanged"). Each sets the 14 fields of
``carla.WeatherParameters``: the 13 of pidc's weather space (:mod:`components.core.weather`) and ``dust_storm``, which
pidc does not model (its CARLA backend sets it to 0).

A preset is *usable* when it keeps every fixed parameter at pidc's value (:data:`components.core.weather.FIXED`: fog
distance 0.75, fog falloff 0.1, the three scattering parameters, wetness 0) and ``dust_storm`` at 0; 15 presets are.
The other seven are *refused*, naming each field that differs with both values: ``ClearNight`` and ``WetNight`` set a
fog distance of 75 and a falloff of 1, five night presets set wetness, ``DustStorm`` sets ``dust_storm`` 100.

CARLA's presets leave the sun azimuth unchanged (−1, the server keeps its current one). A pidc render has no current
azimuth (it is a function of the weather and the scene only), so :func:`preset_weather` sets the nuisance azimuth to
:data:`PRESET_SUN_AZIMUTH` (0°) unless given another. The azimuth counts from the scene's heading, which the scene
seed draws, so the sun's direction seen from the camera still varies from scene to scene.

No ``carla`` import: the table is written out from CARLA's ``LibCarla/source/carla/rpc/WeatherParameters.cpp``
(0.9.16), and ``tests/test_presets.py`` compares it with the installed client's ``carla.WeatherParameters``.

Used by the ``pidc`` CLI (``pidc weather``, ``pidc render --preset``).

Examples:
    >>> from components.core import presets
    >>> w = presets.preset_weather("ClearNoon")
    >>> w["sun_altitude_angle"], w["fog_density"], w["sun_azimuth_angle"]
    (45.0, 2.0, 0.0)
    >>> len(presets.USABLE), presets.REFUSED["ClearNight"]
    (15, "ClearNight: fog_distance 75 vs pidc's fixed 0.75, fog_falloff 1 vs pidc's fixed 0.1")
    >>> presets.preset_weather("DustStorm")
    Traceback (most recent call last):
    ...
    ValueError: DustStorm: dust_storm 100 vs 0 (pidc does not model it)
"""

from __future__ import annotations

import math

from components.core import weather

__all__ = [
    "CARLA_VERSION",
    "FIELDS",
    "UNMODELLED",
    "PRESETS",
    "PRESET_SUN_AZIMUTH",
    "differences",
    "preset_weather",
    "USABLE",
    "REFUSED",
]

#: The CARLA release whose presets :data:`PRESETS` holds.
CARLA_VERSION = "0.9.16"

#: The fields of ``carla.WeatherParameters``, in the order of CARLA's preset table (and of its constructor).
FIELDS: tuple[str, ...] = (
    "cloudiness",
    "precipitation",
    "precipitation_deposits",
    "wind_intensity",
    "sun_azimuth_angle",
    "sun_altitude_angle",
    "fog_density",
    "fog_distance",
    "fog_falloff",
    "wetness",
    "scattering_intensity",
    "mie_scattering_scale",
    "rayleigh_scattering_scale",
    "dust_storm",
)

#: CARLA's weather fields that pidc does not model, and the value pidc renders them at.
UNMODELLED: dict[str, float] = {"dust_storm": 0.0}

# one row per preset, in FIELDS order: CARLA's own table, value for value (−1: "unchanged")
_ROWS: dict[str, tuple[float, ...]] = {
    "ClearNoon": (5, 0, 0, 10, -1, 45, 2, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "CloudyNoon": (60, 0, 0, 10, -1, 45, 3, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "WetNoon": (5, 0, 50, 10, -1, 45, 3, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "WetCloudyNoon": (60, 0, 50, 10, -1, 45, 3, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "MidRainyNoon": (60, 60, 60, 60, -1, 45, 3, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "HardRainNoon": (100, 100, 90, 100, -1, 45, 7, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "SoftRainNoon": (20, 30, 50, 30, -1, 45, 3, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "ClearSunset": (5, 0, 0, 10, -1, 15, 2, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "CloudySunset": (60, 0, 0, 10, -1, 15, 3, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "WetSunset": (5, 0, 50, 10, -1, 15, 2, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "WetCloudySunset": (60, 0, 50, 10, -1, 15, 2, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "MidRainSunset": (60, 60, 60, 60, -1, 15, 3, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "HardRainSunset": (100, 100, 90, 100, -1, 15, 7, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "SoftRainSunset": (20, 30, 50, 30, -1, 15, 2, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "ClearNight": (5, 0, 0, 10, -1, -90, 60, 75, 1, 0, 1, 0.03, 0.0331, 0),
    "CloudyNight": (60, 0, 0, 10, -1, -90, 60, 0.75, 0.1, 0, 1, 0.03, 0.0331, 0),
    "WetNight": (5, 0, 50, 10, -1, -90, 60, 75, 1, 60, 1, 0.03, 0.0331, 0),
    "WetCloudyNight": (60, 0, 50, 10, -1, -90, 60, 0.75, 0.1, 60, 1, 0.03, 0.0331, 0),
    "SoftRainNight": (60, 30, 50, 30, -1, -90, 60, 0.75, 0.1, 60, 1, 0.03, 0.0331, 0),
    "MidRainyNight": (80, 60, 60, 60, -1, -90, 60, 0.75, 0.1, 80, 1, 0.03, 0.0331, 0),
    "HardRainNight": (100, 100, 90, 100, -1, -90, 100, 0.75, 0.1, 100, 1, 0.03, 0.0331, 0),
    "DustStorm": (100, 0, 0, 100, -1, 45, 2, 0.75, 0.1, 0, 1, 0.03, 0.0331, 100),
}

#: CARLA's 22 presets by CARLA's name (its order): every field of ``carla.WeatherParameters`` as CARLA sets it,
#: the sun azimuth −1 ("unchanged") included.
PRESETS: dict[str, dict[str, float]] = {
    name: {f: float(v) for f, v in zip(FIELDS, row, strict=True)} for name, row in _ROWS.items()
}

#: The nuisance sun azimuth (degrees) of a preset rendered by pidc, where CARLA keeps the server's (−1).
PRESET_SUN_AZIMUTH = 0.0


def _known(name: str) -> dict[str, float]:
    try:
        return PRESETS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown CARLA preset {name!r}; CARLA {CARLA_VERSION}'s: {', '.join(PRESETS)}") from None


def differences(name: str) -> list[str]:
    """The fields of preset ``name`` that pidc cannot render as CARLA sets them; empty for a usable preset.

    Arguments:
        name: one of CARLA's preset names (:data:`PRESETS`), e.g. ``"ClearNight"``.

    Returns:
        One ``"<field> <CARLA's value> vs …"`` per fixed parameter off pidc's value and per unmodelled field off 0,
        in :data:`FIELDS` order.

    Raises:
        ValueError: for a name that is not one of CARLA's presets (listing them).
    """
    values = _known(name)
    out = []
    for field in FIELDS:
        v = values[field]
        if field in weather.FIXED and not math.isclose(v, weather.FIXED[field], rel_tol=1e-9, abs_tol=1e-12):
            out.append(f"{field} {v:g} vs pidc's fixed {weather.FIXED[field]:g}")
        elif field in UNMODELLED and v != UNMODELLED[field]:
            out.append(f"{field} {v:g} vs {UNMODELLED[field]:g} (pidc does not model it)")
    return out


def preset_weather(name: str, *, sun_azimuth_angle: float = PRESET_SUN_AZIMUTH) -> dict[str, float]:
    """CARLA's preset ``name`` as a complete pidc weather (:func:`components.core.weather.complete_weather`).

    Arguments:
        name: one of CARLA's preset names (:data:`PRESETS`), e.g. ``"ClearNoon"``.
        sun_azimuth_angle: the nuisance sun azimuth in degrees, [0, 360] (CARLA's presets leave it unchanged).

    Returns:
        All 13 parameters of :data:`components.core.weather.ALL_NAMES` → ``float``: the six predicted ones as CARLA
        sets them, the azimuth, the fixed ones (equal to CARLA's).

    Raises:
        ValueError: one line, for an unknown name, or for a refused preset naming it and each field that differs
            with both values (e.g. ``ClearNight: fog_distance 75 vs pidc's fixed 0.75, …``).

    Example:
        >>> preset_weather("HardRainNoon", sun_azimuth_angle=90)["precipitation_deposits"]
        90.0
    """
    diffs = differences(name)
    if diffs:
        raise ValueError(f"{name}: {', '.join(diffs)}")
    values = PRESETS[name]
    w = {n: values[n] for n in weather.PREDICTED}
    w["sun_azimuth_angle"] = sun_azimuth_angle
    return weather.complete_weather(w, where=f"CARLA preset {name}: ")


#: The presets pidc renders (they keep its fixed parameters), in CARLA's order.
USABLE: tuple[str, ...] = tuple(n for n in PRESETS if not differences(n))
#: The refused presets → the one-line reason (:func:`preset_weather`'s message).
REFUSED: dict[str, str] = {n: f"{n}: {', '.join(differences(n))}" for n in PRESETS if differences(n)}
