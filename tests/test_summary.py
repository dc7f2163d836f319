"""Highest-density intervals of marginals from draws, and the per-parameter summary table."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from components.core import weather
from components.core.seeding import rng
from components.evaluate.summary import HDI_MASS, format_summary, hdi, summarize


def test_hdi_is_the_shortest_window_of_the_sorted_draws():
    # 10 draws, mass 0.3 → 3 draws per window; the tightest triple is {4.0, 4.1, 4.3}
    draws = np.array([9.0, 0.0, 4.1, 1.0, 4.3, 2.5, 7.0, 4.0, 8.0, 5.5])
    assert hdi(draws, 0.3) == (4.0, 4.3)
    assert hdi(draws, 1.0) == (0.0, 9.0)
    assert hdi(draws, 0.01) == (0.0, 0.0)  # one draw: a zero-width interval at the first minimum


def test_hdi_of_known_distributions():
    r = rng(0, "test", "hdi")
    m = 200_000
    normal = r.normal(3.0, 2.0, m)
    low, high = hdi(normal)
    # the width is sharply determined (±1σ), the centre only to second order (the width is flat near the optimum)
    assert high - low == pytest.approx(4.0, abs=0.02) and (low + high) / 2 == pytest.approx(3.0, abs=0.1)
    # a decreasing density: the HDI starts at the mode 0 and holds 68.27 %
    expo = r.exponential(1.0, m)
    low, high = hdi(expo)
    assert low < 1e-3 and high == pytest.approx(-np.log(1 - HDI_MASS), abs=0.02)
    # skewed: shorter than the central interval with the same mass
    gamma = r.gamma(2.0, 1.0, m)
    low, high = hdi(gamma)
    central = stats.gamma(2.0).ppf([(1 - HDI_MASS) / 2, (1 + HDI_MASS) / 2])
    assert high - low < central[1] - central[0]
    assert np.mean((gamma >= low) & (gamma <= high)) == pytest.approx(HDI_MASS, abs=1e-4)


def test_hdi_columns_and_errors():
    r = rng(1, "test", "hdi")
    draws = np.column_stack([r.normal(0, 1, 5000), r.uniform(10, 20, 5000)])
    low, high = hdi(draws)
    assert low.shape == high.shape == (2,)
    assert (low[0], high[0]) == hdi(draws[:, 0]) and (low[1], high[1]) == hdi(draws[:, 1])
    assert high[1] - low[1] == pytest.approx(6.827, abs=0.15)
    with pytest.raises(ValueError, match="shape"):
        hdi(np.zeros((0, 2)))
    with pytest.raises(ValueError, match="finite"):
        hdi(np.array([1.0, np.nan]))
    with pytest.raises(ValueError, match="mass must be in"):
        hdi(np.ones(3), 0.0)


def test_summary_and_table():
    box = weather.Box.full()
    draws = box.sample(rng(2, "test", "summary"), 4000)
    s = summarize(draws)
    np.testing.assert_allclose(s.median, np.median(draws, axis=0))
    np.testing.assert_allclose(s.std, draws.std(axis=0, ddof=1))
    assert np.all(s.low <= s.median) and np.all(s.median <= s.high) and s.draws == 4000
    text = format_summary(s, box, moments=True)
    lines = text.splitlines()
    assert lines[0].split() == ["parameter", "median", "68.27", "%", "HDI", "mean", "std"]
    assert lines[4].startswith("sun_altitude_angle [deg]") and len(lines) == 7
    assert f"[{s.low[3]:.2f}, {s.high[3]:.2f}]" in lines[4] and f"{s.mean[3]:.2f}" in lines[4]
    assert "mean" not in format_summary(s, box)
    with pytest.raises(ValueError, match="the box has 6 parameters, the summary 2"):
        format_summary(summarize(draws[:, :2]), box)
    # as JSON: the same numbers under the box's names and units
    d = s.to_dict(box)
    assert d["hdi_mass"] == HDI_MASS and d["draws"] == 4000 and list(d["parameters"]) == list(box.names)
    sun = d["parameters"]["sun_altitude_angle"]
    assert sun["unit"] == "deg" and (sun["median"], sun["hdi_low"], sun["hdi_high"]) == (
        s.median[3],
        s.low[3],
        s.high[3],
    )
    with pytest.raises(ValueError, match="the box has 6 parameters, the summary 2"):
        summarize(draws[:, :2]).to_dict(box)
