"""The base scale per regime (components/posterior/regime.py, temperature.py): a proper density for every context,
the gate's logistic regression, and both τ recovered from data drawn with known ones.

Known answers: a flow whose draws come from its own tempered version has the true τ (here one per regime, blended by
the gate). On the 2-D toy of tests/test_posterior_calibration.py the regime is "the sun below the horizon", which the
toy's second feature shows with noise (σ = 0.15 of the range): most inputs have a gate near 0 or 1, a band around the
horizon does not. The fit from N = 4000 pairs has a relative standard error of ~1/√(2 · 2000) ≈ 1.6 % per regime for
one flow; a 6 % tolerance is > 3.5 standard errors (an ensemble's members mix: 10 %).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks.studies.bench_regime import with_flows_of
from components.core import seeding
from components.posterior.model import NPE, FlowConfig
from components.posterior.regime import RegimeTemperature, fit_gate
from components.posterior.temperature import Regime, calibrate, fit_regime_gate
from tests.test_posterior_calibration import BOX, _fit, simulate
from tests.test_temperature import assert_gain_holds_on_new_pairs, assert_proper_and_self_consistent

torch.set_num_threads(1)
NIGHT = Regime(index=1, below=0.0, name="night")
TAU = torch.tensor([[1.5, 0.8], [0.7, 1.3]])  # rows: outside (day), inside (night)


def _model(ensemble: int, seed: int, regime: bool = True) -> NPE:
    config = FlowConfig(transforms=2, hidden_features=(16,), bins=6, ensemble=ensemble, regime_temperature=regime)
    return NPE(None, 3, BOX, config, seed=seed).eval()


def _gated(model: NPE, seed: int) -> NPE:
    """``model`` with its gate fitted on 3000 of the toy's simulations."""
    x, theta = simulate(seeding.rng(seed, "regime", "gate"), 3000)
    report = fit_regime_gate(model, torch.tensor(x), torch.tensor(theta), NIGHT)
    assert 0.4 < report["regime_share"] < 0.6 and report["regime_gate_train_accuracy"] > 0.85, report
    return model


def test_regime_density_integrates_to_one_and_matches_its_draws() -> None:
    """The toy's trained NPE (posteriors ≥ 0.08 of the range wide: a 300 × 300 grid resolves them) with two τ."""
    model = _gated(with_flows_of(_fit(), regime=True), 0)
    tau = torch.tensor([[1.2, 0.8], [0.8, 0.9]])
    model.set_temperature(tau)
    # a clear day, a clear night and one near the horizon
    x = torch.tensor([[0.5, 0.8, 0.0], [0.5, 0.2, 0.0], [0.5, 0.5, 0.0]])
    p = model.regime_probability(model.context(x))
    assert p[0] < 0.05 and p[1] > 0.95 and 0.2 < p[2] < 0.8, p
    assert_proper_and_self_consistent(model, x)
    torch.testing.assert_close(model.temperature, tau, rtol=1e-6, atol=0)


def test_the_regimes_scale_their_own_inputs() -> None:
    """A night input's spread follows τ_in, a day input's τ_out: their base points, mapped back, differ by the ratio."""
    model = _gated(_model(1, 5), 1)
    x = torch.tensor([[0.5, 0.9, 0.0], [0.5, 0.1, 0.0]])
    c = model.context(x)
    model.set_temperature(TAU)
    last = model.flows[0].transform.transforms[-1]
    assert isinstance(last, RegimeTemperature)
    tau = last.log_temperature(c).exp()
    torch.testing.assert_close(tau[0], TAU[0], rtol=0.02, atol=0)
    torch.testing.assert_close(tau[1], TAU[1], rtol=0.02, atol=0)


@pytest.mark.parametrize(("ensemble", "tolerance"), [(1, 0.06), (2, 0.10)])
def test_fit_recovers_known_regime_temperatures(ensemble: int, tolerance: float) -> None:
    model = _gated(_model(ensemble, 7), 2)
    x = torch.tensor(simulate(seeding.rng(0, "regime", "fit"), 4000)[0])
    model.set_temperature(TAU)
    with torch.no_grad():
        theta = model.sample(x, 1, rng=2)[:, 0].double()  # θ ~ q_τ(θ | x): the true τ are TAU
    model.set_temperature(torch.ones(2))
    report = calibrate(model, x, theta, NIGHT)
    np.testing.assert_allclose(model.temperature.numpy(), TAU.numpy(), rtol=tolerance)
    fresh = torch.tensor(simulate(seeding.rng(0, "regime", "fresh"), 4000)[0])
    assert_gain_holds_on_new_pairs(model, TAU, fresh, report["heldout_nll_gain"])
    assert set(report) == {
        "temperature.cloudiness",
        "temperature.sun_altitude_angle",
        "temperature_night.cloudiness",
        "temperature_night.sun_altitude_angle",
        "regime_gate_accuracy",
        "heldout_nll_gain",
    }
    np.testing.assert_allclose(report["temperature_night.sun_altitude_angle"], float(model.temperature[1, 1]))


def test_one_temperature_for_both_regimes_is_the_single_scale() -> None:
    """τ_in = τ_out: the regime model's density is the plain model's with that τ, whatever the gate says."""
    plain = _model(1, 11, regime=False)
    regime = _gated(with_flows_of(plain, regime=True), 3)
    plain.set_temperature(TAU[0])
    regime.set_temperature(TAU[0])
    x, theta = simulate(seeding.rng(0, "regime", "same"), 50)
    with torch.no_grad():
        a = plain.log_prob(torch.tensor(theta), torch.tensor(x))
        b = regime.log_prob(torch.tensor(theta), torch.tensor(x))
    torch.testing.assert_close(a, b, rtol=0, atol=1e-5)


def test_gate_separates_a_separable_regime() -> None:
    rng = seeding.rng(0, "regime", "separable")
    c = torch.tensor(rng.standard_normal((4000, 5)))
    margin = c[:, 0] - 0.5 * c[:, 3] - 0.2
    c, inside = c[margin.abs() > 0.2], margin[margin.abs() > 0.2] > 0  # a gap between the regimes
    weight, bias = fit_gate(c, inside)
    p = torch.sigmoid(c @ weight + bias)
    assert bool(((p >= 0.5) == inside).all())
    # the direction of the true boundary, up to scale
    direction = weight / weight.norm()
    truth = torch.tensor([1.0, 0.0, 0.0, -0.5, 0.0], dtype=torch.float64)
    assert float(direction @ (truth / truth.norm())) > 0.99


def test_bad_regimes_are_refused() -> None:
    c = torch.zeros(10, 3)
    with pytest.raises(ValueError, match=r"holds for 0 % of the 10 training pairs"):
        fit_gate(c, torch.zeros(10, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"holds for 100 % of the 10 training pairs"):
        fit_gate(c, torch.ones(10, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"contexts \(N, F\) and regime labels \(N,\)"):
        fit_gate(c, torch.ones(9, dtype=torch.bool))
    plain, regime = _model(1, 1, regime=False), _model(1, 1)
    x, theta = simulate(seeding.rng(0, "regime", "bad"), 20)
    with pytest.raises(ValueError, match=r"needs the regime"):
        calibrate(regime, torch.tensor(x), torch.tensor(theta))
    with pytest.raises(ValueError, match=r"needs the regime"):
        calibrate(plain, torch.tensor(x), torch.tensor(theta), NIGHT)
    with pytest.raises(ValueError, match=r"one base scale τ: build it with FlowConfig\(regime_temperature=True\)"):
        plain.set_regime_gate(torch.zeros(3), torch.tensor(0.0))
    with pytest.raises(ValueError, match=r"regime gate needs a finite weight \(3,\)"):
        regime.set_regime_gate(torch.zeros(4), torch.tensor(0.0))
    with pytest.raises(ValueError, match=r"temperature τ must be 2 finite positive numbers"):
        plain.set_temperature(TAU)
    with pytest.raises(ValueError, match=r"temperature τ must be 2 or 2 × 2 finite positive numbers"):
        regime.set_temperature(torch.ones(3, 2))


def test_saved_regime_model_keeps_its_temperatures_and_gate(tmp_path) -> None:
    from components.posterior.store import load_npe, save_npe

    model = _gated(_model(2, 13), 4)
    model.set_temperature(TAU)
    save_npe(tmp_path / "model.pt", model, backbone="toy", backbone_options={})
    loaded, header = load_npe(tmp_path / "model.pt")
    assert header["flow"]["regime_temperature"] is True
    torch.testing.assert_close(loaded.temperature, model.temperature)
    x = torch.tensor(simulate(seeding.rng(0, "regime", "saved"), 20)[0])
    torch.testing.assert_close(loaded.regime_probability(loaded.context(x)), model.regime_probability(model.context(x)))
