"""The weather space: names, ranges, validation, the prior box and the bijection."""

import math

import numpy as np
import pytest

from components.core import weather


def test_table_has_the_papers_13_parameters_in_order():
    assert len(weather.ALL_NAMES) == 13
    assert weather.PREDICTED == (
        "cloudiness",
        "fog_density",
        "precipitation",
        "sun_altitude_angle",
        "wind_intensity",
        "precipitation_deposits",
    )
    assert weather.NUISANCE == ("sun_azimuth_angle",)
    assert weather.FIXED == {
        "fog_distance": 0.75,
        "fog_falloff": 0.1,
        "mie_scattering_scale": 0.03,
        "rayleigh_scattering_scale": 0.0331,
        "scattering_intensity": 1.0,
        "wetness": 0.0,
    }
    assert weather.PARAMETERS["sun_altitude_angle"].low == -90 and weather.PARAMETERS["sun_altitude_angle"].high == 90


def _good():
    return {n: (weather.PARAMETERS[n].low + weather.PARAMETERS[n].high) / 2 for n in weather.PREDICTED} | {
        "sun_azimuth_angle": 10.0
    }


def test_complete_fills_fixed_values_in_canonical_order():
    w = weather.complete_weather(_good())
    assert list(w) == list(weather.ALL_NAMES)
    assert w["wetness"] == 0.0 and w["fog_distance"] == 0.75
    assert weather.weather_array(_good()).shape == (13,)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"fog_density": 100.5}, r"'fog_density' = 100.5 is outside its range \[0, 100\] %"),
        ({"sun_altitude_angle": -91}, r"'sun_altitude_angle' = -91 is outside its range \[-90, 90\] deg"),
        ({"cloudiness": float("nan")}, r"'cloudiness' must be finite"),
        ({"precipitation": float("inf")}, r"'precipitation' must be finite"),
        ({"rain": 3}, r"unknown weather parameter 'rain'; known: cloudiness"),
        ({"wind_intensity": "strong"}, r"'wind_intensity' must be a number"),
        ({"wetness": 50}, r"'wetness' is fixed to 0"),
    ],
)
def test_validation_names_parameter_and_range(change, message):
    with pytest.raises(ValueError, match=message):
        weather.complete_weather(_good() | change)


def test_missing_required_parameter_is_named():
    w = _good()
    del w["sun_azimuth_angle"]
    with pytest.raises(ValueError, match=r"missing 'sun_azimuth_angle'.*\[0, 360\] deg"):
        weather.complete_weather(w)


def test_theta_round_trip():
    w = weather.complete_weather(_good())
    theta = weather.theta_from_weather(w)
    assert theta.shape == (6,)
    assert weather.weather_from_theta(theta, 10.0) == w
    rows = np.stack([weather.weather_array(w)] * 3)
    np.testing.assert_array_equal(weather.theta_from_weather(rows), np.stack([theta] * 3))


def test_box_validation_and_sampling():
    box = weather.Box.from_mapping({"fog_density": [10, 20]})
    assert box.low[1] == 10 and box.high[1] == 20 and box.high[0] == 100
    rng = np.random.default_rng(0)
    theta = box.sample(rng, 10_000)
    assert box.contains(theta).all()
    # uniform: each coordinate's mean is the box centre within 4 standard errors
    se = box.width / math.sqrt(12 * 10_000)
    assert np.all(np.abs(theta.mean(0) - (box.low + box.high) / 2) < 4 * se)
    np.testing.assert_allclose(box.log_prob(theta[:3]), -box.log_volume())
    assert box.log_prob(np.array([[101, 15, 0, 0, 0, 0]]))[0] == -np.inf
    with pytest.raises(ValueError, match="'fog_density' needs finite low < high"):
        weather.Box.from_mapping({"fog_density": [20, 10]})
    with pytest.raises(ValueError, match="'cloudiness' = 120 is outside"):
        weather.Box.from_mapping({"cloudiness": [0, 120]})
    with pytest.raises(ValueError, match="unknown predicted parameter"):
        weather.Box.from_mapping({"sun_azimuth_angle": [0, 10]})
    with pytest.raises(ValueError, match=r"'precipitation' = nan at row 1 is outside the prior box"):
        box.check(np.array([[50, 15, 1, 0, 0, 0], [50, 15, np.nan, 0, 0, 0]]))


def test_bijection_inverse_and_jacobian():
    box = weather.Box.full()
    theta = box.sample(np.random.default_rng(1), 1000)
    z = weather.to_unbounded(theta, box)
    np.testing.assert_allclose(weather.to_physical(z, box), theta, rtol=0, atol=1e-9)
    # the log-Jacobian matches finite differences of the (diagonal) map
    eps = 1e-6
    fd = (weather.to_physical(z + eps, box) - weather.to_physical(z - eps, box)) / (2 * eps)
    np.testing.assert_allclose(weather.log_abs_det_jacobian(z, box), np.log(fd).sum(-1), rtol=1e-6)
    # faces map to finite points, and far z never leaves the box
    faces = np.stack([box.low, box.high])
    assert np.isfinite(weather.to_unbounded(faces, box)).all()
    far = weather.to_physical(np.array([[1e4] * 6, [-1e4] * 6]), box)
    assert box.contains(far).all()
    assert np.isfinite(weather.log_abs_det_jacobian(np.array([[40.0] * 6]), box)).all()


def test_density_change_of_variables_integrates_to_one():
    """A standard normal in z, pushed to the box, integrates to one in physical units (1-D check per axis)."""
    box = weather.Box.full()
    grid = np.linspace(box.low, box.high, 200_001)[1:-1]
    z = weather.to_unbounded(grid, box)
    # the library's log-Jacobian, axis by axis (each a one-parameter box: the map is diagonal)
    per_axis_logdet = np.stack(
        [
            weather.log_abs_det_jacobian(z[:, j : j + 1], weather.Box(box.low[j : j + 1], box.high[j : j + 1]))
            for j in range(z.shape[1])
        ],
        axis=1,
    )
    density = np.exp(-0.5 * z**2) / math.sqrt(2 * math.pi) / np.exp(per_axis_logdet)
    integral = np.trapezoid(density, grid, axis=0)
    np.testing.assert_allclose(integral, 1.0, atol=2e-3)
