"""Trained estimators against a posterior known in closed form (2-D toy), plain, balanced and ensemble.

Toy: θ ~ U(box) on [0, 100] % × [−90, 90] deg, u = (θ − low)/(high − low) ∈ [0, 1]², and
x = (u₁ + σ₁ε₁, u₂ + σ₂ε₂, ε₃) with σ = (0.08, 0.15) and a pure-noise third feature. The exact posterior is a
product of normals N(xᵢ, σᵢ²) in u truncated to [0, 1] (often cut by a face: tests the edges), divided by the widths.

Tolerances (seeded, so deterministic; chosen with margin over the measured values, stated per assertion):
* KL(p‖q) estimated with 300 × 100 exact posterior draws (standard error ≈ 0.002 nat): < 0.12 nat for plain
  NPE and the ensemble (measured 0.060 and 0.048), < 0.15 for balanced NPE (measured 0.096); the prior as q
  scores > 1 nat, so the check can fail;
* calibration error max_l |c(l) − l| over 1000 test images, 300 draws each: < 0.1 (the KS 99 % band of 1000
  uniform values is 0.052, plus 0.05 for the estimator; measured 0.062, slightly overconfident);
* balanced / ensemble: calibration error ≤ plain's + 0.04 (measured: balanced 0.076, ensemble of 2 0.055).
  At this small training budget balancing does not beat plain NPE on this toy (see the report); the test
  guards against either option making calibration worse.
* input noise ν = 0.5: KL to the posterior of the noisier observation σ' = √(σ² + ν²·std²) < 0.12 nat (measured
  0.023), to σ's > 0.3 (measured 0.40).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import stats

from components.core import seeding
from components.evaluate.diagnostics import calibration_error, coverage_error, expected_coverage, hpd_credibility
from components.posterior.bijection import IntervalBox
from components.posterior.model import NPE, FlowConfig
from components.posterior.train import TrainingConfig, train

torch.set_num_threads(1)

BOX = IntervalBox(np.array([0.0, -90.0]), np.array([100.0, 90.0]), ("cloudiness", "sun_altitude_angle"), ("%", "deg"))
SIGMA = np.array([0.08, 0.15])


def simulate(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    theta = BOX.sample(rng, n)
    u = (theta - BOX.low) / BOX.width
    x = np.concatenate([u + SIGMA * rng.standard_normal((n, 2)), rng.standard_normal((n, 1))], axis=1)
    return x.astype(np.float32), theta


def _truncation(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m = x[..., :2]
    return m, (0.0 - m) / SIGMA, (1.0 - m) / SIGMA


def true_log_prob(theta: np.ndarray, x: np.ndarray) -> np.ndarray:
    """log p(θ | x) in physical units; θ (..., 2), x broadcastable (..., 3)."""
    m, a, b = _truncation(x)
    u = (theta - BOX.low) / BOX.width
    return (stats.truncnorm.logpdf(u, a, b, loc=m, scale=SIGMA) - np.log(BOX.width)).sum(-1)


def true_sample(rng: np.random.Generator, x: np.ndarray, n: int) -> np.ndarray:
    """n exact posterior draws per x: (B, 3) → (B, n, 2)."""
    m, a, b = _truncation(x[:, None, :])
    u = stats.truncnorm.rvs(a, b, loc=m, scale=SIGMA, size=(x.shape[0], n, 2), random_state=rng)
    return BOX.low + u * BOX.width


FLOW = FlowConfig(transforms=2, hidden_features=(32, 32), bins=8)


def _fit(ensemble: int = 1, balance: float = 0.0) -> NPE:
    rng = seeding.rng(0, "toy", "train")
    x, theta = simulate(rng, 2000)
    xv, thv = simulate(rng, 600)
    model = NPE(None, 3, BOX, FlowConfig(**{**FLOW.__dict__, "ensemble": ensemble}), seed=1)
    cfg = TrainingConfig(epochs=25, batch_size=128, lr=3e-3, patience=8, seed=3, balance=balance)
    train(model, (x, theta), (xv, thv), cfg, progress=False)
    return model.eval()


@pytest.fixture(scope="module")
def test_set() -> tuple[np.ndarray, np.ndarray]:
    return simulate(seeding.rng(0, "toy", "test"), 1000)


@pytest.fixture(scope="module")
def plain() -> NPE:
    return _fit()


@pytest.fixture(scope="module")
def plain_credibility(plain: NPE, test_set: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    return _credibility(plain, *test_set)


def _kl(model: NPE, x: np.ndarray) -> float:
    rng = seeding.rng(0, "toy", "kl")
    draws = true_sample(rng, x[:300], 100)
    with torch.no_grad():
        log_q = model.log_prob(torch.tensor(draws), torch.tensor(x[:300])).numpy()
    return float((true_log_prob(draws, x[:300, None, :]) - log_q).mean())


def _credibility(model: NPE, x: np.ndarray, theta: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        _, log_q = model.sample_and_log_prob(torch.tensor(x), 300, rng=5)
        log_truth = model.log_prob(torch.tensor(theta), torch.tensor(x))
    return hpd_credibility(log_q.numpy(), log_truth.numpy())


def test_plain_npe_density_is_close_to_the_exact_posterior(plain: NPE, test_set: tuple[np.ndarray, np.ndarray]) -> None:
    x, _ = test_set
    kl = _kl(plain, x)
    assert kl < 0.12, kl
    # the same estimate for the prior (q = uniform) is large: the KL check can fail
    draws = true_sample(seeding.rng(0, "toy", "kl"), x[:300], 100)
    kl_prior = float((true_log_prob(draws, x[:300, None, :]) + BOX.log_volume()).mean())
    assert kl_prior > 1.0


def test_plain_npe_is_calibrated_and_stays_in_box(
    plain: NPE, plain_credibility: np.ndarray, test_set: tuple[np.ndarray, np.ndarray]
) -> None:
    x, _ = test_set
    cred = plain_credibility
    assert calibration_error(cred) < 0.1, expected_coverage(cred, np.linspace(0, 1, 11))
    samples = plain.sample(torch.tensor(x[:50]), 1000, rng=9)
    assert bool(BOX.contains(samples.double().numpy()).all())


def test_trained_density_integrates_to_one(plain: NPE, test_set: tuple[np.ndarray, np.ndarray]) -> None:
    """Midpoint rule on a 250 × 250 grid over the box, for 4 test images (a posterior near a face included)."""
    x = test_set[0][:4]
    k = 250
    g = [BOX.low[i] + (np.arange(k) + 0.5) / k * BOX.width[i] for i in range(2)]
    grid = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(1, -1, 2).repeat(4, 0)
    with torch.no_grad():
        q = torch.exp(plain.log_prob(torch.tensor(grid), torch.tensor(x))).numpy()
    integral = q.sum(1) * np.prod(BOX.width) / k**2
    # posteriors are ≥ 0.08 × 100 % wide, so 0.4 % cells resolve them: quadrature error well below 2 %
    np.testing.assert_allclose(integral, 1.0, atol=0.02)


@pytest.mark.parametrize(("ensemble", "balance"), [(1, 100.0), (2, 0.0)])
def test_balanced_and_ensemble_are_no_less_calibrated(
    plain_credibility: np.ndarray, test_set: tuple[np.ndarray, np.ndarray], ensemble: int, balance: float
) -> None:
    x, theta = test_set
    model = _fit(ensemble, balance)
    # balancing trades a little density accuracy for calibration (Delaunoy et al.): a looser KL bound
    assert _kl(model, x) < (0.15 if balance > 0 else 0.12)
    cred = _credibility(model, x, theta)
    err = calibration_error(cred)
    err_plain = calibration_error(plain_credibility)
    assert err <= err_plain + 0.04, (err, err_plain, coverage_error(cred))
    samples = model.sample(torch.tensor(x[:50]), 500, rng=2)
    assert bool(BOX.contains(samples.double().numpy()).all())


def _kl_to(model: NPE, x: np.ndarray, sigma: np.ndarray) -> float:
    """KL(p_σ ‖ q) on 300 × 100 draws of the toy's exact posterior with observation noise ``sigma``."""
    m = x[:300, None, :2]
    a, b = (0.0 - m) / sigma, (1.0 - m) / sigma
    u = stats.truncnorm.rvs(a, b, loc=m, scale=sigma, size=(300, 100, 2), random_state=seeding.rng(0, "toy", "klσ"))
    draws = BOX.low + u * BOX.width
    log_p = (stats.truncnorm.logpdf(u, a, b, loc=m, scale=sigma) - np.log(BOX.width)).sum(-1)
    with torch.no_grad():
        log_q = model.log_prob(torch.tensor(draws), torch.tensor(x[:300])).numpy()
    return float((log_p - log_q).mean())


def test_input_noise_learns_the_posterior_of_the_noisier_observation(test_set):
    """Training inputs x + ν·std·ε make the toy's observation noise σ' = √(σ² + ν² std²): the flow then learns the
    exact posterior of that noisier observation (KL < 0.12 nat, as plain NPE learns σ's), not σ's (KL > 0.3), and
    the noise is seeded like every other draw of training."""
    rng = seeding.rng(0, "toy", "train")
    x, theta = simulate(rng, 2000)
    xv, thv = simulate(rng, 600)
    models = []
    for _ in range(2):
        model = NPE(None, 3, BOX, FLOW, seed=1)
        cfg = TrainingConfig(epochs=25, batch_size=128, lr=3e-3, patience=8, seed=3, input_noise=0.5)
        train(model, (x, theta), (xv, thv), cfg, progress=False)
        models.append(model.eval())
    for a, b in zip(models[0].state_dict().values(), models[1].state_dict().values(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    std = models[0].feature_std.numpy()[:2].astype(np.float64)
    wider = np.sqrt(SIGMA**2 + (0.5 * std) ** 2)
    assert _kl_to(models[0], test_set[0], wider) < 0.12 < 0.3 < _kl_to(models[0], test_set[0], SIGMA)
    with pytest.raises(ValueError, match="input_noise must be a finite number >= 0"):
        TrainingConfig(input_noise=-0.1)
