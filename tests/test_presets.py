"""CARLA's weather presets as pidc holds them: the table equals the installed client's ``carla.WeatherParameters``,
and the presets that keep pidc's fixed parameters are the usable ones, the others refused by the field that differs."""

from __future__ import annotations

import math

import pytest

from components.core import presets, weather


def test_the_table_is_carlas_installed_presets() -> None:
    """Every field of every preset equals the installed ``carla`` client's (CARLA stores float32: 1e-6 relative)."""
    carla = pytest.importorskip("carla")  # the optional `carla` extra is part of the development environment
    installed = {n for n in dir(carla.WeatherParameters) if n[:1].isupper()}
    # the client's names are CARLA's 22 presets and `Default` (every field "unchanged": no weather)
    assert installed == set(presets.PRESETS) | {"Default"}
    fields = {f for f in dir(carla.WeatherParameters.ClearNoon) if not f.startswith("_") and f[:1].islower()}
    assert fields == set(presets.FIELDS)
    for name, values in presets.PRESETS.items():
        carla_preset = getattr(carla.WeatherParameters, name)
        for field in presets.FIELDS:
            assert getattr(carla_preset, field) == pytest.approx(values[field], rel=1e-6, abs=1e-7), (name, field)


def test_fields_cover_pidcs_weather_and_the_unmodelled_ones() -> None:
    assert set(presets.FIELDS) == set(weather.ALL_NAMES) | set(presets.UNMODELLED)
    assert len(presets.PRESETS) == 22


def test_fifteen_presets_keep_pidcs_fixed_parameters() -> None:
    """The issue's count: 15 of the 22 keep fog distance 0.75, falloff 0.1, wetness 0 (and no dust storm)."""
    assert len(presets.USABLE) == 15 and len(presets.REFUSED) == 7
    assert set(presets.USABLE) | set(presets.REFUSED) == set(presets.PRESETS)
    for name in presets.USABLE:
        w = presets.preset_weather(name)
        assert tuple(w) == weather.ALL_NAMES
        for field, fixed in weather.FIXED.items():
            assert w[field] == fixed and math.isclose(presets.PRESETS[name][field], fixed, rel_tol=1e-9)
        for field in weather.PREDICTED:
            assert w[field] == presets.PRESETS[name][field]
        assert presets.PRESETS[name]["dust_storm"] == 0.0


def test_a_preset_leaves_the_azimuth_to_pidc() -> None:
    assert all(p["sun_azimuth_angle"] == -1.0 for p in presets.PRESETS.values())  # CARLA: "unchanged"
    assert presets.preset_weather("ClearNoon")["sun_azimuth_angle"] == presets.PRESET_SUN_AZIMUTH == 0.0
    assert presets.preset_weather("ClearNoon", sun_azimuth_angle=270)["sun_azimuth_angle"] == 270.0
    with pytest.raises(ValueError, match=r"CARLA preset ClearNoon: .*'sun_azimuth_angle' = 400 is outside"):
        presets.preset_weather("ClearNoon", sun_azimuth_angle=400)


@pytest.mark.parametrize(
    "name, message",
    [
        ("ClearNight", "ClearNight: fog_distance 75 vs pidc's fixed 0.75, fog_falloff 1 vs pidc's fixed 0.1"),
        (
            "WetNight",
            "WetNight: fog_distance 75 vs pidc's fixed 0.75, fog_falloff 1 vs pidc's fixed 0.1, "
            "wetness 60 vs pidc's fixed 0",
        ),
        ("WetCloudyNight", "WetCloudyNight: wetness 60 vs pidc's fixed 0"),
        ("SoftRainNight", "SoftRainNight: wetness 60 vs pidc's fixed 0"),
        ("MidRainyNight", "MidRainyNight: wetness 80 vs pidc's fixed 0"),
        ("HardRainNight", "HardRainNight: wetness 100 vs pidc's fixed 0"),
        ("DustStorm", "DustStorm: dust_storm 100 vs 0 (pidc does not model it)"),
    ],
)
def test_a_refused_preset_names_each_field_that_differs(name: str, message: str) -> None:
    assert presets.REFUSED[name] == message
    with pytest.raises(ValueError) as info:
        presets.preset_weather(name)
    assert str(info.value) == message


def test_an_unknown_name_lists_carlas_presets() -> None:
    for bad in ("clear_noon", "Default", "clearnoon"):
        with pytest.raises(ValueError, match=rf"unknown CARLA preset '{bad}'; CARLA 0\.9\.16's: ClearNoon, CloudyNoon"):
            presets.preset_weather(bad)
