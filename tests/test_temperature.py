"""The post-hoc base scale τ (components/posterior/temperature.py): a proper density, the exact maximum-likelihood
τ, recovered from data drawn with a known τ, and an overconfident posterior made calibrated on a known problem.

Known answers: a flow whose draws come from its own tempered version has true τ; the fit from N = 4000 held-out pairs
has a relative standard error ≈ 1/√(2N) ≈ 1.1 % for one flow, so a 5 % tolerance is > 4 standard errors (an
ensemble: 8 %, its members share τ but mix). The calibration check uses the 2-D toy with a closed-form posterior of
tests/test_posterior_calibration.py.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from components.core import seeding
from components.evaluate import task1
from components.evaluate.diagnostics import calibration_error
from components.posterior.model import NPE, FlowConfig
from components.posterior.temperature import base_points, calibrate, fit_temperature, tempered_nll
from tests.test_posterior_calibration import BOX, DRAWS, IMAGES, LEVEL, _credibility, _fit, simulate

torch.set_num_threads(1)
TAU = torch.tensor([1.6, 0.7])


def _random_model(ensemble: int, seed: int) -> NPE:
    return NPE(
        None, 3, BOX, FlowConfig(transforms=2, hidden_features=(16,), bins=6, ensemble=ensemble), seed=seed
    ).eval()


@pytest.fixture(scope="module")
def toy() -> NPE:
    """The toy's trained plain NPE (posteriors ≥ 0.08 of the range wide: a 300 × 300 grid resolves them)."""
    return _fit()


def assert_proper_and_self_consistent(model: NPE, x: torch.Tensor, k: int = 300) -> None:
    """The toy model's density at inputs ``x`` integrates to one on a k × k grid of the box, and the log-density of its
    draws equals its density at them."""
    g = [BOX.low[i] + (np.arange(k) + 0.5) / k * BOX.width[i] for i in range(2)]
    grid = torch.tensor(np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(1, -1, 2).repeat(len(x), 0))
    with torch.no_grad():
        q = torch.exp(model.log_prob(grid, x)).double().numpy()
        theta, log_q = model.sample_and_log_prob(x, 50, rng=1)
        again = model.log_prob(theta.double(), x)
    np.testing.assert_allclose(q.sum(1) * np.prod(BOX.width) / k**2, 1.0, atol=0.02)
    np.testing.assert_allclose(log_q.numpy(), again.numpy(), atol=2e-3)


def test_tempered_density_integrates_to_one_and_matches_its_draws(toy: NPE) -> None:
    model = copy.deepcopy(toy)
    model.set_temperature(torch.tensor([1.3, 0.8]))
    assert_proper_and_self_consistent(model, torch.tensor(simulate(seeding.rng(0, "temperature", "x"), 3)[0]))
    np.testing.assert_allclose(model.temperature.numpy(), [1.3, 0.8], rtol=1e-6)


def assert_gain_holds_on_new_pairs(model: NPE, true_tau: torch.Tensor, x: torch.Tensor, reported: float) -> None:
    """The NLL that the fitted τ saves, as ``calibrate`` reports it from the pairs it fitted τ on (≥ 0 there by
    construction), is what it saves on new pairs ``(x, θ)``, θ drawn with the true τ: positive beyond 5 standard
    errors of the new pairs' mean and within 4 of the report (the report's own noise is about as large; measured
    differences 0.8–2.4 standard errors on the toys of these tests)."""
    truth, plain = copy.deepcopy(model), copy.deepcopy(model)
    truth.set_temperature(true_tau)
    plain.set_temperature(torch.ones(model.dim))
    with torch.no_grad():
        theta = truth.sample(x, 1, rng=5)[:, 0].double()
        saved = (model.log_prob(theta, x) - plain.log_prob(theta, x)).double()
    mean, se = float(saved.mean()), float(saved.std() / len(saved) ** 0.5)
    assert mean > 5 * se and abs(mean - reported) < 4 * se, (mean, se, reported)


@pytest.mark.parametrize(("ensemble", "tolerance"), [(1, 0.05), (2, 0.08)])
def test_fit_recovers_a_known_temperature(ensemble: int, tolerance: float) -> None:
    model = _random_model(ensemble, 7)
    x = torch.tensor(simulate(seeding.rng(0, "temperature", "fit"), 4000)[0])
    model.set_temperature(TAU)
    with torch.no_grad():
        theta = model.sample(x, 1, rng=2)[:, 0].double()  # θ ~ q_τ(θ | x): the true τ is TAU
    model.set_temperature(torch.ones(2))
    report = calibrate(model, x, theta)
    np.testing.assert_allclose(model.temperature.numpy(), TAU.numpy(), rtol=tolerance)
    fresh = torch.tensor(simulate(seeding.rng(0, "temperature", "fresh"), 4000)[0])
    assert_gain_holds_on_new_pairs(model, TAU, fresh, report["heldout_nll_gain"])
    assert set(report) == {"temperature.cloudiness", "temperature.sun_altitude_angle", "heldout_nll_gain"}


def test_fitted_temperature_is_the_likelihood_maximum() -> None:
    model = _random_model(2, 9)
    x = torch.tensor(simulate(seeding.rng(0, "temperature", "max"), 500)[0])
    with torch.no_grad():
        theta = model.sample(x, 1, rng=3)[:, 0].double()
    eps, ladj = base_points(model, x, theta)
    tau = fit_temperature(eps, ladj)
    best = float(tempered_nll(eps, ladj, tau))
    for step in ([1.05, 1.0], [0.95, 1.0], [1.0, 1.05], [1.0, 0.95]):
        assert float(tempered_nll(eps, ladj, tau * torch.tensor(step, dtype=tau.dtype))) > best
    # one flow: the closed form, exactly
    single = fit_temperature(eps[:1], ladj[:1])
    torch.testing.assert_close(single, eps[0].pow(2).mean(0).sqrt())


def test_calibration_repairs_an_overconfident_posterior(toy: NPE) -> None:
    """The toy's trained NPE made overconfident (τ = 0.6), then re-fitted on held-out pairs: calibrated again."""
    model = copy.deepcopy(toy)
    x, theta = simulate(seeding.rng(0, "toy", "test"), IMAGES)
    model.set_temperature(torch.full((2,), 0.6))
    sharp = calibration_error(_credibility(model, x, theta))
    xv, thv = simulate(seeding.rng(0, "temperature", "heldout"), 2000)
    calibrate(model, torch.tensor(xv), torch.tensor(thv))
    repaired = calibration_error(_credibility(model, x, theta))
    assert sharp > 0.2, sharp
    # inside the band the plain toy model is held to (test_posterior_calibration: 0.999 quantile, 0.061; measured 0.032)
    band = task1.calibration_band(IMAGES, DRAWS, LEVEL, 20_000, 0)
    assert repaired < band, (repaired, band)
    # τ is absolute: the fit from the overconfident 0.6 lands where the fit from the plain model's 1 does
    plain = copy.deepcopy(toy)
    calibrate(plain, torch.tensor(xv), torch.tensor(thv))
    torch.testing.assert_close(model.temperature, plain.temperature, rtol=1e-5, atol=0)


def test_bad_temperatures_are_refused() -> None:
    model = _random_model(1, 1)
    for bad in ([1.0], [1.0, 0.0], [1.0, float("nan")], [-1.0, 1.0]):
        with pytest.raises(ValueError, match="temperature"):
            model.set_temperature(torch.tensor(bad))
    with pytest.raises(ValueError, match="base points"):
        fit_temperature(torch.zeros(1, 1, 2), torch.zeros(1, 1))


def test_regime_temperature_needs_the_weight_of_two_pairs_per_side() -> None:
    """The gated fit needs two pairs on each side of p = ½ or a weight of two (Σ(1 − p), Σ p): a side of one pair but
    enough weight (gates near ½) is fitted, from the gate-weighted closed form, to the likelihood maximum."""
    g = torch.Generator().manual_seed(0)
    eps = torch.randn(1, 8, 2, generator=g, dtype=torch.float64) * torch.tensor([1.3, 0.8], dtype=torch.float64)
    ladj = torch.zeros(1, 8, dtype=torch.float64)
    near_half = torch.tensor([0.03, 0.79, 0.51, 0.96, 0.999, 0.999, 0.999, 0.51], dtype=torch.float64)
    tau = fit_temperature(eps, ladj, near_half)  # one pair under ½, a weight of 2.2 outside the regime
    assert tau.shape == (2, 2) and bool(torch.isfinite(tau).all() and (tau > 0).all())

    def nll(t: torch.Tensor) -> float:
        w = near_half.unsqueeze(-1)
        return float(tempered_nll(eps, ladj, torch.exp((1 - w) * t[0].log() + w * t[1].log())))

    best = nll(tau)
    for i in range(2):
        for j in range(2):
            for f in (1.05, 0.95):
                step = torch.ones(2, 2, dtype=tau.dtype)
                step[i, j] = f
                assert nll(tau * step) > best - 1e-9
    with pytest.raises(
        ValueError, match=r"puts 7 of the 8 held-out pairs in the regime, a weight of 6\.40 .* against 1\.60"
    ):
        fit_temperature(eps, ladj, torch.tensor([0.9] * 7 + [0.1], dtype=torch.float64))


def test_saved_model_keeps_its_temperature_and_an_older_file_is_named(tmp_path) -> None:
    from components.posterior.store import load_npe, save_npe

    model = _random_model(1, 2)
    model.set_temperature(torch.tensor([1.2, 0.9]))
    path = tmp_path / "model.pt"
    save_npe(path, model, backbone="toy", backbone_options={})
    loaded, _ = load_npe(path)
    np.testing.assert_allclose(loaded.temperature.numpy(), [1.2, 0.9], rtol=1e-6)
    # a file written before the base scale existed (no τ buffers): a clear error, not torch's key listing
    blob = torch.load(path, weights_only=True)
    blob["state_dict"] = {
        k: v for k, v in blob["state_dict"].items() if not k.startswith("flows.0.transform.transforms.3")
    }
    torch.save(blob, tmp_path / "old.pt")
    with pytest.raises(ValueError, match=r"old\.pt: its weights do not fit .*missing .*re-run the train stage"):
        load_npe(tmp_path / "old.pt")
