"""Trained estimators against a posterior known in closed form (2-D toy), plain, balanced and ensemble.

Toy: θ ~ U(box) on [0, 100] % × [−90, 90] deg, u = (θ − low)/(high − low) ∈ [0, 1]², and
x = (u₁ + σ₁ε₁, u₂ + σ₂ε₂, ε₃) with σ = (0.08, 0.15) and a pure-noise third feature. The exact posterior is a
product of normals N(xᵢ, σᵢ²) in u truncated to [0, 1] (often cut by a face: tests the edges), divided by the widths.

Training budget: 8000 simulations, batches of 512, 25 epochs (400 steps, the step count and about the run time of the
former 2000 × 128 budget, whose flows were overconfident: calibration error on the 1000 test images plain 0.056, just
inside the 0.999 band below (0.061), balanced 0.070, outside it; with 4× the simulations plain NPE measures
0.021–0.029 and balanced 0.026–0.039 over three training seeds).

Tolerances (seeded, so deterministic):
* KL(p‖q) estimated with 300 × 100 exact posterior draws (standard error ≈ 0.002 nat): < 0.12 nat for plain
  NPE and the ensemble, < 0.15 for balanced NPE (measured 0.031, 0.040 and 0.025 at this budget); the prior as q
  scores > 1 nat, so the check can fail;
* calibration error max_l |c(l) − l| at the levels 0, 0.01, …, 1 over 1000 test images, 300 draws each: at most the
  0.999 quantile of a perfectly calibrated model's calibration error on 1000 images × 300 draws
  (:func:`components.evaluate.task1.calibration_band`, 20 000 simulated evaluations: 0.061). A calibrated model fails
  it on 1 test set in 1000. The toy's flows are not exact: on 4000 images plain NPE measures 0.021–0.036 against a
  0.999 band of 0.030, a miscalibration of ≈ 0.02 that 1000 images cannot resolve; the test claims "calibrated
  within the noise of 1000 images". Power: the plain flow with its base narrowed to τ = 0.885 (the 68 % region of a
  2-D normal then holds 59 %, the audit's example) measures 0.078–0.118 over 9 test sets and training seeds;
* balanced / ensemble no less calibrated than plain: each within the same band, and the paired difference
  Δ = err(model) − err(plain) on the same images at most z₀.₉₉₉ = 3.09 times its paired bootstrap standard deviation
  over the images (one-sided, level 0.999). The bootstrap sd overstates Δ's sd when both models are calibrated
  (simulated: 0 of 2000 pairs of calibrated credibilities correlated 0.95–0.98, as measured between plain and
  balanced, exceed 3.09 sd; z's sd 0.74–0.83), so it is conservative. Measured at this budget: balanced 0.026 vs
  plain 0.026 (Δ/sd = 0.0), ensemble of 2 0.024 (−0.4); the τ = 0.885 flow: +3.8 sd (3.0–8.9 over 9 test sets and
  training seeds), and outside the band besides.
* input noise ν = 0.5: KL to the posterior of the noisier observation σ' = √(σ² + ν²·std²) < 0.12 nat (measured
  0.023), to σ's > 0.3 (measured 0.40); with the second feature spared (``spared_noise=0``) to (σ₁', σ₂)'s < 0.12
  (measured 0.033), to σ''s at least 0.1 more (measured 0.151).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from scipy import stats

from components.core import seeding
from components.evaluate import task1
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
IMAGES, DRAWS = 1000, 300  # test images, posterior draws per image
LEVEL = 0.999  # the level of every calibration bound: a calibrated model fails one in 1000 test sets
# the overconfident counterexample: base scale τ with P(χ²₂ ≤ τ² q₀.₆₈) = 0.59, i.e. exp(−τ² q/2) = 0.41 with
# exp(−q/2) = 0.32: the 68 % HPD region of a 2-D normal then holds 59 % of the truths
TAU_OVERCONFIDENT = float(np.sqrt(np.log(1 / 0.41) / np.log(1 / 0.32)))


def _fit(ensemble: int = 1, balance: float = 0.0) -> NPE:
    rng = seeding.rng(0, "toy", "train")
    x, theta = simulate(rng, 8000)
    xv, thv = simulate(rng, 2000)
    model = NPE(None, 3, BOX, FlowConfig(**{**FLOW.__dict__, "ensemble": ensemble}), seed=1)
    cfg = TrainingConfig(epochs=25, batch_size=512, lr=3e-3, patience=8, seed=3, balance=balance)
    train(model, (x, theta), (xv, thv), cfg, progress=False)
    return model.eval()


@pytest.fixture(scope="module")
def test_set() -> tuple[np.ndarray, np.ndarray]:
    return simulate(seeding.rng(0, "toy", "test"), IMAGES)


@pytest.fixture(scope="module")
def band() -> float:
    """The 0.999 quantile of a perfectly calibrated model's calibration error (at task1.LEVELS) on IMAGES × DRAWS,
    from 20 000 simulated evaluations (the quantile's level is then 0.999 ± 0.0002, one Monte Carlo sd)."""
    return task1.calibration_band(IMAGES, DRAWS, LEVEL, 20_000, 0)


@pytest.fixture(scope="module")
def plain() -> NPE:
    return _fit()


@pytest.fixture(scope="module")
def plain_credibility(plain: NPE, test_set: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    return _credibility(plain, *test_set)


@pytest.fixture(scope="module")
def overconfident_credibility(plain: NPE, test_set: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The plain flow with its base narrowed to τ = TAU_OVERCONFIDENT: a model the calibration checks must reject."""
    narrow = copy.deepcopy(plain)
    narrow.set_temperature(torch.full((2,), TAU_OVERCONFIDENT))
    return _credibility(narrow, *test_set)


def _error(cred: np.ndarray) -> float:
    return calibration_error(cred, task1.LEVELS)


def _paired_z(cred: np.ndarray, cred_plain: np.ndarray, replicates: int = 2000) -> float:
    """Δ = err(cred) − err(cred_plain) in units of its paired bootstrap sd (images resampled jointly for both models)."""
    rng = seeding.rng(0, "toy", "paired-bootstrap")
    n = cred.size
    boot = np.empty(replicates)
    for r in range(replicates):
        i = rng.integers(0, n, n)
        boot[r] = _error(cred[i]) - _error(cred_plain[i])
    return (_error(cred) - _error(cred_plain)) / boot.std(ddof=1)


def _no_less_calibrated(cred: np.ndarray, cred_plain: np.ndarray, band: float) -> tuple[bool, float]:
    """Within the calibrated band, and not worse than plain beyond the paired noise (one-sided, level 0.999)."""
    z = _paired_z(cred, cred_plain)
    return _error(cred) <= band and z <= stats.norm.ppf(LEVEL), z


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
    plain: NPE,
    plain_credibility: np.ndarray,
    overconfident_credibility: np.ndarray,
    band: float,
    test_set: tuple[np.ndarray, np.ndarray],
) -> None:
    x, _ = test_set
    cred = plain_credibility
    assert _error(cred) <= band, (_error(cred), band, expected_coverage(cred, np.linspace(0, 1, 11)))
    # the bound has power: a flow whose 68 % region holds ≈ 59 % is outside it
    wrong = overconfident_credibility
    assert _error(wrong) > band, (_error(wrong), band, expected_coverage(wrong, [0.68]))
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
    plain_credibility: np.ndarray,
    overconfident_credibility: np.ndarray,
    band: float,
    test_set: tuple[np.ndarray, np.ndarray],
    ensemble: int,
    balance: float,
) -> None:
    x, theta = test_set
    model = _fit(ensemble, balance)
    # balancing trades a little density accuracy for calibration (Delaunoy et al.): a looser KL bound
    assert _kl(model, x) < (0.15 if balance > 0 else 0.12)
    cred = _credibility(model, x, theta)
    ok, z = _no_less_calibrated(cred, plain_credibility, band)
    assert ok, (_error(cred), _error(plain_credibility), band, z, coverage_error(cred))
    # the check has power: the overconfident flow fails it
    assert not _no_less_calibrated(overconfident_credibility, plain_credibility, band)[0]
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


def test_features_spared_by_the_noise_keep_their_precision(test_set):
    """With the second feature spared by the noise (``spared=(1,)``, ``spared_noise=0``) the same noise ν = 0.5 widens
    only the first: the flow
    learns the exact posterior of observation noise (σ₁', σ₂) (KL < 0.12 nat; measured 0.033), not that of (σ₁', σ₂')
    where both are noisy (KL > 0.1 more; measured 0.151): a feature the noise spares keeps its precision. Indices outside the features, out of
    order or repeated are refused, naming the setting."""
    rng = seeding.rng(0, "toy", "train")
    x, theta = simulate(rng, 2000)
    xv, thv = simulate(rng, 600)
    model = NPE(None, 3, BOX, FLOW, seed=1)
    cfg = TrainingConfig(
        epochs=25, batch_size=128, lr=3e-3, patience=8, seed=3, input_noise=0.5, spared=(1,), spared_noise=0.0
    )
    train(model, (x, theta), (xv, thv), cfg, progress=False)
    model.eval()
    std = model.feature_std.numpy()[:2].astype(np.float64)
    wider = np.sqrt(SIGMA**2 + (0.5 * std) ** 2)
    spared = np.array([wider[0], SIGMA[1]])
    kl_spared, kl_wider = _kl_to(model, test_set[0], spared), _kl_to(model, test_set[0], wider)
    assert kl_spared < 0.12 and kl_wider > kl_spared + 0.1, (kl_spared, kl_wider)
    for bad in ((1, 1), (2, 1), (-1,), [1]):
        with pytest.raises(ValueError, match="TrainingConfig.spared"):
            TrainingConfig(spared=bad)
    with pytest.raises(ValueError, match="spared_noise must be a finite number >= 0"):
        TrainingConfig(spared_noise=-0.5)
    outside = TrainingConfig(input_noise=0.5, spared=(3,), spared_noise=0.0)
    with pytest.raises(ValueError, match="spared names feature 3, but the inputs have 3 features"):
        train(NPE(None, 3, BOX, FLOW, seed=1), (x, theta), (xv, thv), outside)
