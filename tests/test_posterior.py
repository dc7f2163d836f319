"""The posterior estimator's mechanics: bijection, densities, sampling, loss, training loop, resume.

Statistical tests state their tolerance next to the assertion. The calibration of trained estimators on a toy
with a known posterior is in ``test_posterior_calibration.py``.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from components.core import seeding, weather
from components.posterior import model as model_module
from components.posterior.bijection import Z_MAX, IntervalBox, ScaledLogit, as_interval_box
from components.posterior.checkpoint import load_checkpoint
from components.posterior.loss import balance_penalty, npe_loss
from components.posterior.metrics import mean_nll
from components.posterior.mixture import EqualMixture
from components.posterior.model import NPE, FlowConfig, finite_rows
from components.posterior.train import History, TrainingConfig, train

torch.set_num_threads(1)

BOX = weather.Box.full()
SMALL = FlowConfig(transforms=2, hidden_features=(16, 16), bins=6)


def _edge_points(box: weather.Box, rng: np.random.Generator, n: int) -> np.ndarray:
    """Uniform points, with a third of the coordinates put exactly on a face."""
    th = box.sample(rng, n)
    face = rng.random(th.shape) < 1 / 3
    side = np.where(rng.random(th.shape) < 0.5, box.low, box.high)
    return np.where(face, side, th)


# --- bijection ---------------------------------------------------------------------------------------------


def test_bijection_matches_numpy_in_float64() -> None:
    rng = seeding.rng(0, "test", "bijection")
    box = weather.Box.from_mapping({"cloudiness": (10, 80), "sun_altitude_angle": (-30, 60)})
    bij = ScaledLogit(box)
    theta = _edge_points(box, rng, 2000)
    z_np = weather.to_unbounded(theta, box)
    z_t = bij.to_unbounded(torch.tensor(theta))
    np.testing.assert_allclose(z_t.numpy(), z_np, rtol=0, atol=1e-9)
    z = rng.normal(scale=6.0, size=(2000, 6))
    np.testing.assert_allclose(bij.to_physical(torch.tensor(z)).numpy(), weather.to_physical(z, box), rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        bij.log_abs_det_jacobian(torch.tensor(z)).numpy(), weather.log_abs_det_jacobian(z, box), rtol=0, atol=1e-9
    )
    # far tails, where torch.softplus would switch to the identity
    zt = np.array([[25.0, -25.0, 40.0, -40.0, 19.9, -20.1]])
    np.testing.assert_allclose(
        bij.log_abs_det_jacobian(torch.tensor(zt)).numpy(), weather.log_abs_det_jacobian(zt, box), atol=1e-9
    )


def test_bijection_inverse_and_faces() -> None:
    rng = seeding.rng(0, "test", "inverse")
    bij = ScaledLogit(BOX)
    theta = torch.tensor(BOX.sample(rng, 5000))
    back = bij.to_physical(bij.to_unbounded(theta))
    # relative to each parameter's width: float64 logit/sigmoid round trip
    assert float(((back - theta).abs() / torch.tensor(BOX.width)).max()) < 1e-9
    faces = torch.tensor(np.stack([BOX.low, BOX.high]))
    z = bij.to_unbounded(faces)
    assert torch.isfinite(z).all() and torch.isfinite(bij.log_abs_det_jacobian(z)).all()
    assert float(z.abs().max()) == pytest.approx(Z_MAX, rel=1e-12)
    assert bool(bij.contains(bij.to_physical(torch.tensor([[1e3] * 6, [-1e3] * 6], dtype=torch.float64))).all())


def test_log_det_equals_autograd() -> None:
    rng = seeding.rng(0, "test", "jacobian")
    bij = ScaledLogit(BOX)
    for z0 in rng.normal(scale=4.0, size=(20, 6)):
        z = torch.tensor(z0, requires_grad=True)
        jac = torch.autograd.functional.jacobian(bij.to_physical, z)
        _, logdet = torch.linalg.slogdet(jac)
        assert float(bij.log_abs_det_jacobian(z).detach()) == pytest.approx(float(logdet), abs=1e-9)


def test_interval_box_any_dimension_and_errors() -> None:
    b = as_interval_box(BOX)
    assert b.dim == 6 and b.names == weather.PREDICTED and b.log_volume() == pytest.approx(BOX.log_volume())
    assert b is BOX and b == weather.Box.full() and b != IntervalBox(BOX.low, BOX.high)  # names differ
    one = IntervalBox(np.array([2.0]), np.array([5.0]), ("fog_density",))
    assert one.dim == 1 and bool(one.contains(np.array([[5.0]]))[0])
    with pytest.raises(ValueError, match="fog_density"):
        IntervalBox(np.array([5.0]), np.array([2.0]), ("fog_density",))
    with pytest.raises(ValueError, match="'θ1' = 7.0 at row 0"):
        IntervalBox(np.zeros(2), np.ones(2)).check(np.array([[0.5, 7.0]]))
    with pytest.raises(TypeError, match="box must be"):
        as_interval_box((0, 1))


def test_clamp_inward_keeps_float32_inside_float64_box() -> None:
    box = IntervalBox(np.array([0.1, -37.3]), np.array([37.3, 0.7]))
    bij = ScaledLogit(box)
    theta = torch.tensor([[0.1, -37.3], [37.3, 0.7]], dtype=torch.float64).float()  # rounds outward for some
    assert bool(bij.contains(bij.clamp_inward(theta)).all())


# --- the estimator -----------------------------------------------------------------------------------------


def _model(
    ensemble: int = 1,
    dtype: torch.dtype = torch.float32,
    box: object = BOX,
    features: int = 5,
    context_layers: tuple[int, ...] = (),
) -> NPE:
    cfg = FlowConfig(transforms=2, hidden_features=(16, 16), bins=6, ensemble=ensemble, context_layers=context_layers)
    return NPE(None, features, box, cfg, seed=7).to(dtype)  # type: ignore[arg-type]


def test_log_prob_shapes_faces_and_outside() -> None:
    m = _model()
    x = torch.randn(4, 5, generator=torch.Generator().manual_seed(0))
    faces = torch.tensor(np.stack([BOX.low, BOX.high, BOX.low, BOX.high]))
    lp = m.log_prob(faces, x)
    assert lp.shape == (4,) and torch.isfinite(lp).all()
    outside = faces.clone()
    outside[:, 3] = torch.tensor([-90.001, 90.001, -100.0, 1e9], dtype=torch.float64)
    assert torch.equal(m.log_prob(outside, x), torch.full((4,), -math.inf))
    many = torch.tensor(BOX.sample(seeding.rng(1, "t"), 4 * 3).reshape(4, 3, 6))
    assert m.log_prob(many, x).shape == (4, 3)
    with pytest.raises(ValueError, match="θ must have shape"):
        m.log_prob(many[:2], x)
    with pytest.raises(ValueError, match="x must have shape"):
        m.log_prob(faces, torch.zeros(4, 6))
    with pytest.raises(ValueError, match="NaN"):
        m.log_prob(faces, torch.full((4, 5), math.nan))


@pytest.mark.parametrize("ensemble", [1, 3])
def test_samples_stay_in_box_and_log_prob_agrees(ensemble: int) -> None:
    m = _model(ensemble, torch.float64)
    # push the flows' context to extremes so that many draws land at the faces
    x = 30.0 * torch.randn(8, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    with torch.no_grad():
        theta, log_q = m.sample_and_log_prob(x, 2000, rng=3)
        direct = m.log_prob(theta, x)
    assert theta.shape == (8, 2000, 6) and log_q.shape == (8, 2000)
    assert bool(torch.tensor(BOX.contains(theta.numpy())).all())
    inner = (direct > -1e30) & (m.bijection.to_unbounded(theta).abs().max(-1).values < Z_MAX - 1e-3)
    assert int(inner.sum()) > 2000  # enough draws away from the clipped faces to compare
    torch.testing.assert_close(direct[inner], log_q[inner], rtol=0, atol=1e-6)
    # same seed → same draws; another seed → other draws
    assert torch.equal(m.sample(x, 5, rng=11), m.sample(x, 5, rng=11))
    assert not torch.equal(m.sample(x, 5, rng=11), m.sample(x, 5, rng=12))
    # float32 model: inside the float64 box too
    m32 = _model(ensemble)
    assert bool(torch.tensor(BOX.contains(m32.sample(x.float(), 2000, rng=4).double().numpy())).all())


def test_ensemble_is_equal_weight_mixture_and_flow_is_z_space() -> None:
    m = _model(3, torch.float64)
    x = torch.randn(6, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    theta = torch.tensor(BOX.sample(seeding.rng(2, "t"), 6))
    members = m.log_prob_members(theta, m.context(x))
    assert members.shape == (3, 6)
    expected = torch.logsumexp(members, 0) - math.log(3)
    torch.testing.assert_close(m.log_prob(theta, x), expected, rtol=0, atol=1e-12)
    assert not torch.allclose(members[0], members[1])  # members are initialized independently
    dist = m.flow(x)
    assert isinstance(dist, EqualMixture)
    z = m.bijection.to_unbounded(theta)
    torch.testing.assert_close(
        dist.log_prob(z) - m.bijection.log_abs_det_jacobian(z), m.log_prob(theta, x), rtol=0, atol=1e-10
    )
    single = _model(1, torch.float64)
    d1 = single.flow(x)
    torch.testing.assert_close(
        d1.log_prob(z) - single.bijection.log_abs_det_jacobian(z), single.log_prob(theta, x), rtol=0, atol=1e-10
    )
    assert dist.sample((4,), generator=torch.Generator().manual_seed(0)).shape == (4, 6, 6)


BOX_2D = IntervalBox(np.array([0.0, -90.0]), np.array([100.0, 90.0]), ("cloudiness", "sun_altitude_angle"))


@pytest.mark.parametrize(("ensemble", "context_layers"), [(1, ()), (2, ()), (2, (12, 7))])
def test_density_integrates_to_one_over_the_box(ensemble: int, context_layers: tuple[int, ...]) -> None:
    """∫_box q(θ | x) dθ = 1 (2-D box): Monte Carlo with n uniform points, volume × mean q, within 4 standard errors.

    (On the 6-D box an untrained flow piles density near the faces and corners, and uniform Monte Carlo needs
    millions of points to be informative; the code path does not depend on d.)
    """
    m = _model(ensemble, torch.float64, box=BOX_2D, context_layers=context_layers)
    x = torch.randn(2, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    n = 60_000
    theta = torch.tensor(BOX_2D.sample(seeding.rng(3, "mc", ensemble, *context_layers), 2 * n).reshape(2, n, 2))
    with torch.no_grad():
        q = torch.exp(m.log_prob(theta, x) + BOX_2D.log_volume()).numpy()  # volume × q(θ), (2, n)
    integral, se = q.mean(axis=1), q.std(axis=1) / math.sqrt(n)
    assert (se < 0.05).all()  # the check is informative: a 20 % normalization error would fail
    assert (np.abs(integral - 1.0) < 4 * se).all(), (integral, se)


def test_density_integrates_to_one_in_1d_by_quadrature() -> None:
    """1-D box: midpoint rule with 100k cells; the flow is smooth, so the rule's error is far below 1e-3."""
    box = IntervalBox(np.array([-90.0]), np.array([90.0]), ("sun_altitude_angle",))
    m = _model(1, torch.float64, box=box)
    n = 100_000
    grid = torch.tensor(box.low + (np.arange(n) + 0.5) / n * box.width).reshape(1, n, 1)
    x = torch.randn(1, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(6))
    with torch.no_grad():
        integral = float(torch.exp(m.log_prob(grid, x)).sum()) * float(box.width[0]) / n
    assert integral == pytest.approx(1.0, abs=1e-3)


def test_standardization_fitted_and_embedding_path() -> None:
    rng = seeding.rng(0, "test", "embed")
    theta = BOX.sample(rng, 256)
    x = np.concatenate([theta / 50.0 + 3.0, rng.normal(size=(256, 4))], axis=1).astype(np.float32)
    torch.manual_seed(0)  # the caller initializes its own embedding; this test's only global-RNG use
    embedding = nn.Sequential(nn.Linear(10, 8), nn.Tanh())
    before = embedding[0].weight.detach().clone()
    m = NPE(embedding, 8, BOX, SMALL, input_shape=(10,), seed=1)
    hist = train(
        m, (x[:192], theta[:192]), (x[192:], theta[192:]), TrainingConfig(epochs=3, batch_size=64), progress=False
    )
    assert len(hist.records) == 3
    np.testing.assert_allclose(m.feature_mean.numpy(), x[:192].mean(0), rtol=1e-5, atol=1e-5)
    assert not torch.equal(before, embedding[0].weight)  # the embedding is trained with the flow
    with pytest.raises(ValueError, match="input_shape"):
        NPE(nn.Linear(10, 8), 8, BOX, SMALL)


def test_context_network_shapes_seeding_sharing_and_errors() -> None:
    """The context network maps the features (B, F) to the flows' context (B, last width): an MLP of the given widths,
    the same weights for the same seed, one network shared by an ensemble's flows, trained with them; bad widths are
    refused with the setting's name."""
    m = _model(2, features=5, context_layers=(12, 7))
    assert m.context_features == 7 and m.features == 5
    widths = [layer.out_features for layer in m.context_net if isinstance(layer, nn.Linear)]
    assert widths == [12, 7]
    x = torch.randn(4, 5, generator=torch.Generator().manual_seed(1))
    assert m.context(x).shape == (4, 7)
    assert all(flow.transform.transforms[1].hyper[0].in_features == BOX.dim + 7 for flow in m.flows)  # θ + context
    again = _model(2, features=5, context_layers=(12, 7))
    assert all(torch.equal(a, b) for a, b in zip(m.state_dict().values(), again.state_dict().values(), strict=True))
    assert sum(isinstance(mod, nn.Linear) and mod.in_features == 5 for mod in m.modules()) == 1  # one shared network
    assert _model().context_features == 5 and isinstance(_model().context_net, nn.Identity)

    rng = seeding.rng(2, "test", "context")
    theta = BOX.sample(rng, 256)
    feats = np.concatenate([theta / 50.0, rng.normal(size=(256, 2))], axis=1)[:, :5].astype(np.float32)
    before = m.context_net[0].weight.detach().clone()
    train(
        m,
        (feats[:192], theta[:192]),
        (feats[192:], theta[192:]),
        TrainingConfig(epochs=2, batch_size=64),
        progress=False,
    )
    assert not torch.equal(before, m.context_net[0].weight)  # trained with the flows

    for bad in [(0,), (8, -1), (True,), "8", (8.0,), 8, None, {8: 8}]:
        with pytest.raises(ValueError, match="context_layers"):
            FlowConfig(context_layers=bad)  # type: ignore[arg-type]
    for bad in [8, (8.0, 8), ("8",), (True, 8)]:
        with pytest.raises(ValueError, match="hidden_features"):
            FlowConfig(hidden_features=bad)  # type: ignore[arg-type]


def test_saved_model_keeps_its_context_network(tmp_path: Path) -> None:
    """A model file holds the context network (weights and widths); a file of a pidc before it (no
    ``context_layers`` in its header) loads as a model without one."""
    from components.posterior.store import load_npe, save_npe

    m = _model(2, features=5, context_layers=(12, 7)).eval()
    save_npe(tmp_path / "m.pt", m, backbone="toy", backbone_options={})
    loaded, header = load_npe(tmp_path / "m.pt")
    assert list(header["flow"]["context_layers"]) == [12, 7]
    x = torch.randn(3, 5, generator=torch.Generator().manual_seed(4))
    theta = torch.tensor(BOX.sample(seeding.rng(4, "t"), 3))
    with torch.no_grad():
        assert torch.equal(loaded.log_prob(theta, x), m.log_prob(theta, x))
    plain = _model(1).eval()
    save_npe(tmp_path / "old.pt", plain, backbone="toy", backbone_options={})
    blob = torch.load(tmp_path / "old.pt", weights_only=True)
    del blob["header"]["flow"]["context_layers"]
    torch.save(blob, tmp_path / "old.pt")
    old, _ = load_npe(tmp_path / "old.pt")
    assert old.config.context_layers == () and isinstance(old.context_net, nn.Identity)


# --- loss -----------------------------------------------------------------------------------------------------


def test_balancing_condition_holds_for_the_exact_posterior() -> None:
    """E_joint[d] + E_marginal[d] = 1 for d = σ(log p(θ|x) − log p(θ)) (Gaussian conjugate toy, B = 200k)."""
    rng = seeding.rng(0, "test", "balance")
    n, s = 200_000, 0.5
    theta = rng.normal(size=n)
    x = theta + s * rng.normal(size=n)
    theta_m = np.roll(theta, 1)

    def log_post(t: np.ndarray, scale: float = 1.0) -> torch.Tensor:
        mu, sd = x / (1 + s**2), scale * math.sqrt(s**2 / (1 + s**2))
        return torch.tensor(-0.5 * ((t - mu) / sd) ** 2 - math.log(sd) - 0.5 * math.log(2 * math.pi))

    def log_prior(t: np.ndarray) -> torch.Tensor:
        return torch.tensor(-0.5 * t**2 - 0.5 * math.log(2 * math.pi))

    exact = float(balance_penalty(log_post(theta), log_post(theta_m), log_prior(theta), log_prior(theta_m)))
    narrow = float(balance_penalty(log_post(theta, 0.3), log_post(theta_m, 0.3), log_prior(theta), log_prior(theta_m)))
    # the half-batch means have standard errors ~ 1e-3, so the exact penalty is ~1e-6; overconfidence breaks it
    assert abs(exact) < 2e-5
    assert narrow > 100 * abs(exact) and narrow > 1e-3
    # unbiased: on pairs whose a = d + d' − 1 is pure noise, the estimate averages to 0, not to Var(a)/B
    noise = torch.tensor(seeding.rng(1, "test", "noise").normal(size=(4000, 64)))
    zero = torch.zeros(())
    assert abs(float(balance_penalty(noise, noise, zero, zero).mean())) < 3 * float(
        balance_penalty(noise, noise, zero, zero).std()
    ) / math.sqrt(4000)


def test_npe_loss_is_mean_negative_log_prob() -> None:
    m = _model(2, torch.float64)
    rng = seeding.rng(0, "test", "loss")
    theta = torch.tensor(BOX.sample(rng, 32))
    x = torch.tensor(rng.normal(size=(32, 5)))
    with torch.no_grad():
        plain = npe_loss(m, theta, x)
        members = m.log_prob_members(theta, m.context(x))
        balanced = npe_loss(m, theta, x, balance=10.0)
    assert float(plain.loss) == pytest.approx(float(-members.mean()), abs=1e-10) and plain.penalty == 0.0
    assert balanced.penalty > 0 and float(balanced.loss) == pytest.approx(
        plain.nll + 10.0 * balanced.penalty, rel=1e-10
    )


def test_mean_nll_is_the_mean_negative_log_density_in_any_batching() -> None:
    """The stages' ``test_nll`` (and the information gain, the champion rule's score) is −(1/N) Σ log q(θᵢ | xᵢ):
    the same as one ``log_prob`` call summed in float64, whatever the batch (7 leaves a last batch of 1 of 1 030),
    and for θ on the box's faces too."""
    m = _model(2)
    rng = seeding.rng(0, "test", "mean-nll")
    theta = BOX.sample(rng, 1030)
    theta[:40] = _edge_points(BOX, rng, 40)
    x = torch.tensor(rng.normal(size=(1030, 5)), dtype=torch.float32)
    with torch.no_grad():
        expected = -float(m.log_prob(torch.tensor(theta, dtype=torch.float32), x).double().mean())
        assert math.isfinite(expected)
        for batch in (7, 512, 1030, 5000):
            assert mean_nll(m, x, theta, batch) == pytest.approx(expected, rel=1e-12, abs=1e-9), batch
        # one pair: its own −log q, not an average over the batches
        one = -float(m.log_prob(torch.tensor(theta[3:4], dtype=torch.float32), x[3:4]).double().sum())
        assert mean_nll(m, x[3:4], theta[3:4], 7) == pytest.approx(one, rel=1e-12)


# --- training -------------------------------------------------------------------------------------------------


def _data(n: int, seed: int = 0, features: int = 5) -> tuple[np.ndarray, np.ndarray]:
    rng = seeding.rng(seed, "test", "data", n)
    theta = BOX.sample(rng, n)
    u = (theta - BOX.low) / BOX.width
    x = u[:, :features] + 0.1 * rng.normal(size=(n, features))
    return x.astype(np.float32), theta


def test_finite_rows_in_pieces_name_the_rows_that_whole_arrays_do(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(model_module, "_ROWS_PER_CHECK", 3)
    rng = seeding.rng(0, "test", "finite")
    for dtype in (torch.float32, torch.float64, torch.float16):
        x = torch.as_tensor(rng.normal(size=(11, 2, 3))).to(dtype)
        x[4, 1, 2], x[9, 0, 0], x[10, 1, 1] = float("nan"), float("inf"), -float("inf")
        expected = torch.isfinite(x.reshape(11, -1)).all(dim=1)
        assert torch.equal(finite_rows(x), expected) and expected.sum() == 8
    assert finite_rows(torch.zeros(0, 4)).shape == (0,)


def test_standardization_in_pieces_gives_the_whole_arrays_moments_to_the_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    """The moments are computed a few elements at a time (the cnn's 50 000 × 3 × 64 × 64 inputs): the same bits as
    float64 moments of the whole array, constant elements (std 0) included."""
    rng = seeding.rng(1, "test", "moments")
    x = torch.as_tensor(rng.gamma(2.0, 3.0, size=(500, 3, 7, 5)), dtype=torch.float32)
    x[:, 1, 2, 3] = 4.25
    whole = x.to(torch.float64)
    mean, std = whole.mean(dim=0), whole.std(dim=0, unbiased=False)
    std = torch.where(std > 1e-8 * (1.0 + mean.abs()), std, torch.ones_like(std))
    monkeypatch.setattr(model_module, "_ELEMENTS_PER_MOMENT", 16)  # 105 elements: 7 pieces, the last one short
    m = NPE(nn.Flatten(), 105, BOX, FlowConfig(transforms=1, hidden_features=(8,)), input_shape=(3, 7, 5), seed=0)
    m.fit_standardization(x)
    assert torch.equal(m.feature_mean, mean.to(torch.float32)) and torch.equal(m.feature_std, std.to(torch.float32))
    assert float(m.feature_std[1, 2, 3]) == 1.0


def test_training_input_validation_names_the_problem() -> None:
    m = _model()
    x, th = _data(64)
    cfg = TrainingConfig(epochs=1, batch_size=32)
    bad_x = x.copy()
    bad_x[7, 2] = np.nan
    with pytest.raises(ValueError, match=r"train x contains NaN or infinite values .*row 7"):
        train(m, (bad_x, th), (x, th), cfg, progress=False)
    bad_th = th.copy()
    bad_th[3, 1] = 101.0
    with pytest.raises(
        ValueError, match=r"val θ: 'fog_density' = 101.0 at row 3 is outside the prior box \[0, 100\] %"
    ):
        train(m, (x, th), (x, bad_th), cfg, progress=False)
    with pytest.raises(ValueError, match="val split is empty"):
        train(m, (x, th), (x[:0], th[:0]), cfg, progress=False)
    with pytest.raises(ValueError, match="train split: x has 64 rows but θ has 63"):
        train(m, (x, th[:-1]), (x, th), cfg, progress=False)
    with pytest.raises(ValueError, match=r"train x must have shape \(n, 5\)"):
        train(m, (x[:, :4], th), (x, th), cfg, progress=False)
    with pytest.raises(ValueError, match="TrainingConfig.batch_size"):
        TrainingConfig(batch_size=0)
    with pytest.raises(ValueError, match="FlowConfig.ensemble"):
        FlowConfig(ensemble=0)


def test_mirrored_training_learns_the_mirror_symmetric_posterior() -> None:
    """TrainingConfig.mirror trains on the law of the data made symmetric: here x₀ reads the cloudiness and x₁ is noise,
    the mirror swaps them. Trained plainly, the flow's posterior changes when the input is swapped (it reads x₀ only);
    trained with the mirror, q(θ | x) ≈ q(θ | swap(x)) (the symmetric law cannot tell x₀ from x₁). Seeded; the
    margins below are > 5× the swapped-input differences measured."""
    rng = seeding.rng(3, "test", "mirror")
    theta = BOX.sample(rng, 3000)
    x = np.stack([(theta[:, 0] - BOX.low[0]) / BOX.width[0], rng.uniform(size=3000)], axis=1)
    x = (x + 0.03 * rng.normal(size=x.shape)).astype(np.float32)

    def swap(v: torch.Tensor) -> torch.Tensor:
        return v.flip(-1)

    with pytest.raises(ValueError, match=r"TrainingConfig.mirror needs train\(..., mirror="):
        train(_model(features=2), (x[:64], theta[:64]), (x[:64], theta[:64]), TrainingConfig(mirror=True))
    with pytest.raises(ValueError, match=r"mirror maps inputs \(2, 2\) to \(2, 1\), not to their shape"):
        cfg = TrainingConfig(mirror=True)
        train(_model(features=2), (x[:64], theta[:64]), (x[:64], theta[:64]), cfg, mirror=lambda v: v[:, :1])
    gaps = {}
    for mirror in (False, True):
        m = _model(features=2)
        cfg = TrainingConfig(epochs=15, batch_size=128, lr=3e-3, seed=4, mirror=mirror)
        train(m, (x[:2500], theta[:2500]), (x[2500:], theta[2500:]), cfg, progress=False, mirror=swap)
        xt, tt = torch.from_numpy(x[2500:]), torch.from_numpy(theta[2500:])
        with torch.no_grad():
            gaps[mirror] = float((m.log_prob(tt, xt) - m.log_prob(tt, swap(xt))).abs().mean())
    assert gaps[False] > 1.0, gaps  # the plain flow reads x₀: swapping the input costs nats
    assert gaps[True] < 0.25 * gaps[False], gaps  # the mirrored flow is (nearly) invariant to the swap


def test_compiled_training_is_eager_training_in_other_kernels() -> None:
    """TrainingConfig.compile changes the kernels, not the mathematics: two epochs of compiled training (three full
    batches compiled, the ragged fourth eager) follow eager training to float32 rounding, and repeat bit for bit."""
    x, th = _data(200, 3)
    xv, thv = _data(100, 4)
    cfg = TrainingConfig(epochs=2, batch_size=64, lr=1e-2, seed=2, compile=True)
    runs = []
    for config in (cfg, cfg, dataclasses.replace(cfg, compile=False)):
        m = _model()
        hist = train(m, (x, th), (xv, thv), config, progress=False)
        runs.append((hist.val_loss, m.state_dict()))
    (val_a, state_a), (val_b, state_b), (val_eager, state_eager) = runs
    assert val_a == val_b and all(torch.equal(state_a[k], state_b[k]) for k in state_a)  # reproducible
    assert val_a == pytest.approx(val_eager, rel=1e-4)  # the float order differs from eager torch's, little else
    drift = max(float((state_a[k] - state_eager[k]).abs().max()) for k in state_a if state_a[k].is_floating_point())
    assert 0 < drift < 1e-3, drift  # other kernels (not the eager path), the same optimization


def test_compiled_training_without_a_compiler_names_the_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    """No working C++ compiler: a clear error naming the setting that turns compilation off, not inductor's trace."""
    import torch._inductor.config as inductor

    monkeypatch.setattr(inductor.cpp, "cxx", ("/nonexistent/g++",))
    monkeypatch.setattr(inductor, "fx_graph_cache", False)  # compile for real, not from the disk cache
    torch._dynamo.reset()
    x, th = _data(40, 5)
    cfg = TrainingConfig(epochs=1, batch_size=16, seed=3, compile=True)
    try:
        with pytest.raises(RuntimeError, match=r"C\+\+ compiler.*train.compile_min_steps: null"):
            train(_model(), (x, th), (x, th), cfg, progress=False)
    finally:
        torch._dynamo.reset()


def test_training_history_schedule_early_stopping_and_best_weights(tmp_path: object) -> None:
    x, th = _data(96, 1)
    xv, thv = _data(400, 2)
    m = _model()
    seen: list[int] = []
    cfg = TrainingConfig(epochs=40, batch_size=32, lr=1e-2, patience=3, seed=1)
    hist = train(m, (x, th), (xv, thv), cfg, callback=lambda r: seen.append(r.epoch), progress=False)
    val = hist.val_loss
    assert seen == list(range(len(val)))
    assert hist.best_epoch == int(np.argmin(val)) and hist.best_val_loss == min(val)
    # a tiny training set overfits: early stopping ends the run `patience` epochs after the best one
    assert hist.stopped_early and len(val) - 1 - hist.best_epoch == cfg.patience
    assert hist.lr[0] == cfg.lr and all(a > b for a, b in zip(hist.lr, hist.lr[1:], strict=False))  # cosine decays
    assert all(t > 0 for t in hist.wall_time)
    with torch.no_grad():  # the model holds the best epoch's weights
        again = npe_loss(m, torch.tensor(thv), torch.tensor(xv))
    assert float(again.loss) == pytest.approx(hist.best_val_loss, rel=1e-4)

    # killed right after the early stop's checkpoint: the resumed run trains nothing more and ends the same
    last = len(val) - 1

    def kill_at_stop(record: object) -> None:
        if record.epoch == last:  # type: ignore[attr-defined]
            raise KeyboardInterrupt

    path = tmp_path / "stop.pt"  # type: ignore[operator]
    with pytest.raises(KeyboardInterrupt):
        train(_model(), (x, th), (xv, thv), cfg, checkpoint=path, callback=kill_at_stop, progress=False)
    more: list[int] = []
    m2 = _model()
    resumed = train(
        m2, (x, th), (xv, thv), cfg, checkpoint=path, callback=lambda r: more.append(r.epoch), progress=False
    )
    assert more == [] and resumed.val_loss == val and resumed.stopped_early
    assert all(torch.equal(a, b) for a, b in zip(m.state_dict().values(), m2.state_dict().values(), strict=True))


def test_without_patience_every_epoch_runs_and_the_best_weights_are_kept() -> None:
    """patience=None: the overfitting run of the test above goes on to the last epoch, and the model still ends with
    the weights of its best validation epoch (not the last one's)."""
    x, th = _data(96, 1)
    xv, thv = _data(400, 2)
    m = _model()
    cfg = TrainingConfig(epochs=20, batch_size=32, lr=1e-2, patience=None, seed=1)
    hist = train(m, (x, th), (xv, thv), cfg, progress=False)
    assert len(hist.val_loss) == cfg.epochs and not hist.stopped_early
    assert hist.best_epoch < cfg.epochs - 1 and hist.val_loss[-1] > hist.best_val_loss  # it overfits at the end
    with torch.no_grad():
        again = npe_loss(m, torch.tensor(thv), torch.tensor(xv))
    assert float(again.loss) == pytest.approx(hist.best_val_loss, rel=1e-4)
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match=r"TrainingConfig.patience must be a positive integer or None"):
            TrainingConfig(patience=bad)


def test_killed_run_resumes_to_the_same_result(tmp_path: object) -> None:
    x, th = _data(256, 3)
    xv, thv = _data(128, 4)
    cfg = TrainingConfig(epochs=6, batch_size=64, lr=3e-3, patience=10, seed=5, balance=1.0, schedule="plateau")

    full = _model(2)
    ref = train(full, (x, th), (xv, thv), cfg, checkpoint=tmp_path / "full.pt", progress=False)  # type: ignore[operator]

    class Killed(Exception):
        pass

    def kill_after_epoch_2(record: object) -> None:
        if record.epoch == 2:  # type: ignore[attr-defined]
            raise Killed

    path = tmp_path / "resumed.pt"  # type: ignore[operator]
    with pytest.raises(Killed):
        train(_model(2), (x, th), (xv, thv), cfg, checkpoint=path, callback=kill_after_epoch_2, progress=False)
    state = load_checkpoint(path)
    assert state is not None and state["epoch"] == 2 and not state["finished"]
    assert not list(path.parent.glob(".resumed.pt.*"))  # no temporary files left

    resumed_model = _model(2)  # a fresh process: same construction, weights from the checkpoint
    epochs_run: list[int] = []
    resumed = train(
        resumed_model,
        (x, th),
        (xv, thv),
        cfg,
        checkpoint=path,
        callback=lambda r: epochs_run.append(r.epoch),
        progress=False,
    )
    assert epochs_run == [3, 4, 5]
    assert resumed.val_loss == ref.val_loss and resumed.train_loss == ref.train_loss and resumed.lr == ref.lr
    assert resumed.best_epoch == ref.best_epoch
    for (k, a), b in zip(full.state_dict().items(), resumed_model.state_dict().values(), strict=True):
        assert torch.equal(a, b), k

    # a finished checkpoint: nothing is trained again, the best weights are restored
    again_model = _model(2)
    again = train(
        again_model, (x, th), (xv, thv), cfg, checkpoint=path, callback=lambda r: epochs_run.append(-1), progress=False
    )
    assert isinstance(again, History) and again.val_loss == ref.val_loss and -1 not in epochs_run
    assert all(
        torch.equal(a, b) for a, b in zip(full.state_dict().values(), again_model.state_dict().values(), strict=True)
    )
    with pytest.raises(ValueError, match="other training settings \\(lr\\)"):
        train(
            _model(2),
            (x, th),
            (xv, thv),
            TrainingConfig(**{**cfg.__dict__, "lr": 1e-3}),
            checkpoint=path,
            progress=False,
        )
    with pytest.raises(ValueError, match="other training/validation data"):
        train(_model(2), (x, th), (xv[:64], thv[:64]), cfg, checkpoint=path, progress=False)
