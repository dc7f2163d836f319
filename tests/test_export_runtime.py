"""ONNX export of the posterior and the torch-free runtime: parity with the torch NPE, the box, errors, no torch.

Models are small NPEs built here (frozen features; an ensemble of 2; a trainable CNN embedding), with their
standardization fitted on random data: the properties tested (the same density and the same draws from the
same base noise as torch, in float32) do not depend on training.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from components.core import seeding, weather
from components.domains.absolute import Domain, Posterior
from components.export.onnx import OPSET, export_posterior
from components.export.runtime import OnnxPosterior, _even_blocks
from components.features.backbones import get_backbone
from components.posterior.mixture import EqualMixture, draw_flow
from components.posterior.model import NPE, FlowConfig

ROOT = Path(__file__).resolve().parents[1]
BOX = weather.Box.full()


def _features_model(
    ensemble: int, seed: int, context_layers: tuple[int, ...] = (), regime_temperature: bool = False
) -> NPE:
    config = FlowConfig(
        transforms=2,
        hidden_features=(24, 24),
        bins=6,
        ensemble=ensemble,
        context_layers=context_layers,
        regime_temperature=regime_temperature,
    )
    model = NPE(None, 12, BOX, config, seed=seed)
    rng = seeding.rng(seed, "test", "standardization")
    model.fit_standardization(torch.as_tensor(rng.normal(2.0, 3.0, (200, 12)), dtype=torch.float32))
    return model.eval()


def _cnn_model(seed: int) -> NPE:
    embedding = get_backbone("cnn", seed=seed, dim=8, width=4)
    config = FlowConfig(transforms=1, hidden_features=(16,), bins=4, passes=None)
    model = NPE(embedding, 8, BOX, config, input_shape=(3, 64, 64), seed=seed)
    rng = seeding.rng(seed, "test", "standardization")
    model.fit_standardization(torch.as_tensor(rng.random((16, 3, 64, 64)), dtype=torch.float32))
    return model.eval()


def _inputs(model: NPE, b: int, seed: int) -> np.ndarray:
    """Fresh inputs of the model's shape, spread like its training inputs."""
    rng = seeding.rng(seed, "test", "inputs")
    x = rng.standard_normal((b, *model.input_shape)) * model.feature_std.numpy() + model.feature_mean.numpy()
    return x.astype(np.float32)


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict[str, tuple[NPE, OnnxPosterior, Path]]:
    """Three models exported (with the fast torchscript exporter) and loaded back.

    ``features``: a coupling flow (2 transforms); ``ensemble``: two of them after a context network (12 → 16 → 10);
    ``cnn``: a trainable CNN embedding and a fully autoregressive flow (6 inversion passes); ``regime``: the ensemble
    with a base scale per regime, its gate's probability spread over (0, 1) by the inputs. The ensemble and the CNN
    model have a base scale τ ≠ 1 (the post-hoc temperature), so every graph check covers a tempered flow too.
    """
    root = tmp_path_factory.mktemp("registry")
    out = {}
    for name, model in (
        ("features", _features_model(1, 1)),
        ("ensemble", _features_model(2, 2, context_layers=(16, 10))),
        ("cnn", _cnn_model(3)),
        ("regime", _features_model(2, 4, context_layers=(16, 10), regime_temperature=True)),
    ):
        if name == "regime":
            model.set_temperature(
                torch.stack([torch.linspace(0.7, 1.3, model.dim), torch.linspace(1.4, 0.8, model.dim)])
            )
            with torch.no_grad():  # a gate centred on the model's inputs: p(c) spreads over (0, 1)
                c = model.context(torch.as_tensor(_inputs(model, 256, seed=99)))
            weight = 3.0 * torch.linspace(-1.0, 1.0, 10) / c.std(0)
            model.set_regime_gate(weight, -(c.mean(0) @ weight))
        elif name != "features":
            model.set_temperature(torch.linspace(0.7, 1.3, model.dim))
        folder = export_posterior(model, root / name, card={"backbone": name, "train_size": 7}, exporter="torchscript")
        out[name] = (model, OnnxPosterior.load(folder), folder)
    return out


KINDS = ["features", "ensemble", "cnn", "regime"]


def _theta(b: int, seed: int) -> np.ndarray:
    """θ over the whole box, a few on or within 1e-3 of a face."""
    rng = seeding.rng(seed, "test", "theta")
    theta = BOX.sample(rng, b)
    theta[0] = BOX.low
    theta[1] = BOX.high - 1e-3 * BOX.width
    return theta


def _torch_draws(model: NPE, x: np.ndarray, eps: np.ndarray, members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The torch model's θ (b, n, d) and log q(θ | x) (b, n) pushed from the same ε and members."""
    with torch.no_grad():
        c = model.context(torch.as_tensor(x))
        cn = c.unsqueeze(1).expand(c.shape[0], eps.shape[1], c.shape[1])
        e = torch.as_tensor(eps)
        z = torch.zeros_like(e)
        log_qz = torch.zeros(eps.shape[:2])
        for k, flow in enumerate(model.flows):
            zk, lk = draw_flow(flow(cn), e)
            pick = torch.as_tensor(members == k)
            z = torch.where(pick.unsqueeze(-1), zk, z)
            log_qz = torch.where(pick, lk, log_qz)
        if len(model.flows) > 1:
            log_qz = EqualMixture([flow(cn) for flow in model.flows]).log_prob(z)
        z64 = z.double()
        theta = model.bijection.to_physical(z64)
        return theta.numpy(), (log_qz.double() - model.bijection.log_abs_det_jacobian(z64)).numpy()


def test_the_regime_models_inputs_span_both_regimes(exported):
    """The graph checks of the ``regime`` model (9 inputs of seed 11) see gates near 0, near 1 and between."""
    model, _, _ = exported["regime"]
    with torch.no_grad():
        p = model.regime_probability(model.context(torch.as_tensor(_inputs(model, 9, seed=11)))).numpy()
    assert p.min() < 0.1 and p.max() > 0.9 and ((p > 0.2) & (p < 0.8)).any(), np.sort(p)


@pytest.mark.parametrize("kind", KINDS)
def test_log_prob_matches_torch(exported, kind):
    model, runtime, _ = exported[kind]
    x = _inputs(model, 9, seed=11)
    theta = _theta(9, seed=12)
    with torch.no_grad():
        expected = model.log_prob(torch.as_tensor(theta), torch.as_tensor(x)).double().numpy()
    got = runtime.log_prob(theta, x)
    assert got.shape == (9,) and got.dtype == np.float64
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-4)
    np.testing.assert_allclose(
        runtime.context(x), model.context(torch.as_tensor(x)).detach().numpy(), rtol=0, atol=1e-4
    )
    # several θ per input, and points outside the box
    many = np.stack([_theta(9, seed=13), _theta(9, seed=14)], axis=1)
    many[2, 1, 3] = BOX.high[3] + 0.5
    with torch.no_grad():
        expected_many = model.log_prob(torch.as_tensor(many), torch.as_tensor(x)).double().numpy()
    got_many = runtime.log_prob(many, x)
    assert got_many[2, 1] == -math.inf and expected_many[2, 1] == -math.inf
    finite = np.isfinite(expected_many)
    np.testing.assert_allclose(got_many[finite], expected_many[finite], rtol=0, atol=1e-4)


@pytest.mark.parametrize("kind", KINDS)
def test_whole_density_graph_matches_torch(exported, kind):
    """density.onnx (the MLflow ONNX flavor's model): (x, θ) → log q(θ | x) in physical units, −inf outside the box."""
    import onnxruntime

    model, _, folder = exported[kind]
    x = _inputs(model, 7, seed=15)
    theta = _theta(7, seed=16)
    theta[3, 0] = BOX.low[0] - 1.0
    with torch.no_grad():
        expected = model.log_prob(torch.as_tensor(theta), torch.as_tensor(x)).double().numpy()
    session = onnxruntime.InferenceSession(str(folder / "density.onnx"), providers=["CPUExecutionProvider"])
    got = session.run(None, {"x": x.astype(np.float32), "theta": theta.astype(np.float32)})[0]
    assert got.shape == (7,) and got[3] == -math.inf and expected[3] == -math.inf
    finite = np.isfinite(expected)
    # θ enters in float32 (the flavor's signature): the bijection of a float32 θ differs by ~1e-5 near the faces
    np.testing.assert_allclose(got[finite], expected[finite], rtol=0, atol=1e-3)


@pytest.mark.parametrize("kind", KINDS)
def test_draws_from_the_same_noise_match_torch(exported, kind):
    model, runtime, _ = exported[kind]
    b, n = 4, 50
    x = _inputs(model, b, seed=21)
    rng = seeding.rng(5, "test", "noise")
    eps = rng.standard_normal((b, n, BOX.dim)).astype(np.float32)
    members = rng.integers(runtime.ensemble, size=(b, n))
    theta, log_q = runtime.sample_from_noise(x, eps, members if runtime.ensemble > 1 else None)
    theta_t, log_q_t = _torch_draws(model, x, eps, members)
    assert theta.shape == (b, n, BOX.dim) and log_q.shape == (b, n)
    # the same draws, to 1e-4 of each parameter's range (float32 spline inverses on both sides)
    np.testing.assert_allclose((theta - theta_t) / BOX.width, 0.0, atol=1e-4)
    np.testing.assert_allclose(log_q, log_q_t, rtol=0, atol=1e-3)
    assert BOX.contains(theta).all()


@pytest.mark.parametrize("kind", KINDS)
def test_sampling_is_seeded_inside_the_box_and_self_consistent(exported, kind):
    model, runtime, _ = exported[kind]
    x = _inputs(model, 3, seed=31)
    theta, log_q = runtime.sample_and_log_prob(x, 400, seed=7)
    assert theta.shape == (3, 400, BOX.dim) and log_q.shape == (3, 400)
    assert BOX.contains(theta).all()
    np.testing.assert_array_equal(runtime.sample(x, 400, seed=7), theta)
    assert not np.array_equal(runtime.sample(x, 400, seed=8), theta)
    # the density of a draw equals log_prob at that draw (away from the faces, where θ is clipped)
    z = weather.to_unbounded(theta, BOX)
    interior = np.abs(z).max(axis=-1) < 12.0
    assert interior.mean() > 0.9
    np.testing.assert_allclose(runtime.log_prob(theta, x)[interior], log_q[interior], rtol=0, atol=1e-3)
    if runtime.ensemble > 1:  # the member of each draw is chosen by the same generator, uniformly
        eps, members = runtime._noise(3, 400, seed=7)
        assert abs(float(np.mean(members == 1)) - 0.5) < 0.06


def test_runtime_is_a_posterior_for_domains(exported):
    model, runtime, _ = exported["ensemble"]
    assert isinstance(runtime, Posterior)
    bag = _inputs(model, 5, seed=41)
    domain = Domain(runtime, bag, weights=[1, 2, 3, 0, 4])
    draws = domain.sample(300, seed=3)
    assert BOX.contains(draws).all()
    theta = _theta(6, seed=42)
    w = np.array([1, 2, 3, 0, 4]) / 10
    per_member = np.stack([runtime.log_prob(theta, np.repeat(bag[i : i + 1], 6, axis=0)) for i in range(5)])
    expected = np.log(np.sum(w[:, None] * np.exp(per_member), axis=0))
    np.testing.assert_allclose(domain.log_prob(theta), expected, rtol=0, atol=1e-5)


def test_card_describes_the_model(exported):
    model, runtime, folder = exported["cnn"]
    card = json.loads((folder / "card.json").read_text())
    assert card["backbone"] == "cnn" and card["train_size"] == 7  # the caller's card, merged
    assert card["theta"]["names"] == list(weather.PREDICTED)
    assert card["theta"]["units"] == [weather.PARAMETERS[n].unit for n in weather.PREDICTED]
    assert card["bijection"]["name"] == "scaled_logit" and card["bijection"]["edge_eps"] == weather.EDGE_EPS
    assert card["bijection"]["low"] == BOX.low.tolist() and card["bijection"]["high"] == BOX.high.tolist()
    assert card["input"]["shape"] == ["batch", 3, 64, 64] and card["input"]["dtype"] == "float32"
    assert card["ensemble"] == 1 and card["opset"] >= 18
    assert sorted(card["files"]) == ["context", "density", "log_prob_0", "sample_0"]
    for entry in card["files"].values():
        proto = onnx.load(str(folder / entry["name"]))
        onnx.checker.check_model(proto)
        assert max(op.version for op in proto.opset_import if op.domain in ("", "ai.onnx")) >= OPSET
    assert sorted(p.name for p in folder.iterdir()) == [
        "card.json",
        "context.onnx",
        "density.onnx",
        "log_prob_0.onnx",
        "sample_0.onnx",
    ]
    ens = json.loads((exported["ensemble"][2] / "card.json").read_text())  # the flows' context: the network's output
    assert ens["features"] == 10 and ens["flow"]["context_layers"] == [16, 10]
    assert ens["graphs"]["context"]["outputs"]["context"] == ["batch", 10] and ens["input"]["shape"] == ["batch", 12]
    assert exported["ensemble"][1].features == 10
    # one density graph per member: a draw's own member's density comes from its inverse pass
    assert sorted(ens["files"]) == ["context", "density", "log_prob_0", "log_prob_1", "sample_0", "sample_1"]


def test_clear_errors(exported, tmp_path):
    model, runtime, folder = exported["features"]
    with pytest.raises(FileNotFoundError, match="no such exported posterior folder"):
        OnnxPosterior.load(tmp_path / "nowhere")
    # a corrupted graph
    broken = tmp_path / "broken"
    shutil.copytree(folder, broken)
    data = bytearray((broken / "log_prob_0.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (broken / "log_prob_0.onnx").write_bytes(bytes(data))
    with pytest.raises(ValueError, match="sha256"):
        OnnxPosterior.load(broken)
    (broken / "log_prob_0.onnx").unlink()
    with pytest.raises(FileNotFoundError, match="log_prob_0"):
        OnnxPosterior.load(broken)
    # a card of another format version
    future = tmp_path / "future"
    shutil.copytree(folder, future)
    card = json.loads((future / "card.json").read_text())
    card["format"] = 99
    (future / "card.json").write_text(json.dumps(card))
    with pytest.raises(ValueError, match="format 99"):
        OnnxPosterior.load(future)
    (future / "card.json").write_text("{not json")
    with pytest.raises(ValueError, match="JSON"):
        OnnxPosterior.load(future)
    # inputs of the wrong shape or dtype, bad θ, bad n
    x = _inputs(model, 2, seed=51)
    with pytest.raises(ValueError, match=r"\(batch, 12\)"):
        runtime.log_prob(_theta(2, seed=1), x[:, :10])
    with pytest.raises(TypeError, match="float32"):
        runtime.sample(x.astype(np.int64), 3, seed=0)
    with pytest.raises(ValueError, match=r"θ must have shape \(2, 6\)"):
        runtime.log_prob(_theta(3, seed=1), x)
    with pytest.raises(ValueError, match="NaN"):
        runtime.context(np.full_like(x, np.nan))
    with pytest.raises(ValueError, match="n must be a positive integer"):
        runtime.sample(x, 0, seed=0)
    _, ensemble, _ = exported["ensemble"]
    with pytest.raises(ValueError, match="members"):
        ensemble.sample_from_noise(x, np.zeros((2, 3, 6), np.float32))
    with pytest.raises(ValueError, match="intra_op_num_threads"):
        OnnxPosterior.load(folder, intra_op_num_threads=0)


_NO_TORCH = """
import sys, json
sys.modules["torch"] = None  # importing torch now fails
import numpy as np
from components.export.runtime import OnnxPosterior
posterior = OnnxPosterior.load(sys.argv[1], intra_op_num_threads=2)
x = np.load(sys.argv[2])
theta = np.load(sys.argv[3])
draws, log_q = posterior.sample_and_log_prob(x, 20, seed=9)
assert "zuko" not in sys.modules and sys.modules["torch"] is None
print(json.dumps({"log_prob": posterior.log_prob(theta, x).tolist(), "draws": draws.tolist(), "log_q": log_q.tolist()}))
"""


def test_runtime_runs_without_torch(exported, tmp_path):
    model, runtime, folder = exported["ensemble"]
    x = _inputs(model, 3, seed=61)
    theta = _theta(3, seed=62)
    np.save(tmp_path / "x.npy", x)
    np.save(tmp_path / "theta.npy", theta)
    done = subprocess.run(
        [sys.executable, "-c", _NO_TORCH, str(folder), str(tmp_path / "x.npy"), str(tmp_path / "theta.npy")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    np.testing.assert_allclose(out["log_prob"], runtime.log_prob(theta, x), rtol=0, atol=1e-9)
    draws, log_q = runtime.sample_and_log_prob(x, 20, seed=9)
    np.testing.assert_allclose(out["draws"], draws, rtol=0, atol=1e-9)
    np.testing.assert_allclose(out["log_q"], log_q, rtol=0, atol=1e-9)


def test_dynamo_export_of_a_float64_model(tmp_path):
    """torch's default (dynamo) exporter; the model itself stays float64 and the float32 graphs match it; re-export."""
    model = NPE(None, 4, BOX, FlowConfig(transforms=1, hidden_features=(8,), bins=4), seed=4).double().eval()
    model.fit_standardization(torch.as_tensor(seeding.rng(4, "test").normal(1.0, 2.0, (50, 4))))
    folder = export_posterior(model, tmp_path / "dyn", card={})
    assert model.dtype == torch.float64 and model.feature_mean.dtype == torch.float64
    runtime = OnnxPosterior.load(folder)
    assert runtime.card["exporter"] == "dynamo"
    x = _inputs(model, 6, seed=71)
    theta = _theta(6, seed=72)
    with torch.no_grad():
        expected = model.log_prob(torch.as_tensor(theta), torch.as_tensor(x, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(runtime.log_prob(theta, x), expected, rtol=0, atol=1e-4)
    eps = seeding.rng(4, "test", "eps").standard_normal((6, 30, BOX.dim)).astype(np.float32)
    theta_r, _ = runtime.sample_from_noise(x, eps)
    theta_t, _ = _torch_draws(model.float(), x, eps, np.zeros((6, 30), dtype=np.int64))
    np.testing.assert_allclose((theta_r - theta_t) / BOX.width, 0.0, atol=1e-4)
    one, _ = runtime.sample_from_noise(x, eps[:, :1])  # the graph's draws axis is dynamic down to 1
    np.testing.assert_allclose((one - theta_t[:, :1]) / BOX.width, 0.0, atol=1e-4)
    # re-exporting replaces the whole folder atomically (temp folder + rename), nothing left behind
    (folder / "stale.txt").write_text("from an older export")
    export_posterior(model, folder, card={"run": 2}, exporter="torchscript")
    assert OnnxPosterior.load(folder).card["run"] == 2
    assert not (folder / "stale.txt").exists()
    assert [p.name for p in folder.parent.iterdir()] == ["dyn"]
    with pytest.raises(TypeError, match="card"):
        export_posterior(model, tmp_path / "bad", card={"when": object()}, exporter="torchscript")
    with pytest.raises(ValueError, match="exporter"):
        export_posterior(model, tmp_path / "bad", card={}, exporter="jit")
    assert not (tmp_path / "bad").exists()


def test_each_inputs_draws_of_a_member_are_an_even_block():
    """onnxruntime computes rows in pairs: each input's rows go to the graphs as an even block, its last row repeated
    where it has an odd number, so that an input's draws keep their positions' parities however inputs are grouped."""
    rng = seeding.rng(3, "test", "blocks")
    n = 7
    rows = np.flatnonzero(rng.integers(2, size=40 * n) == 1)
    padded, real = _even_blocks(rows, n)
    np.testing.assert_array_equal(padded[real], rows)
    assert np.all(np.bincount(padded // n) % 2 == 0) and np.all(np.diff(padded) >= 0)
    assert np.all(padded[~real] == padded[np.flatnonzero(~real) - 1])  # a repeat follows its original
    assert (~real).sum() == np.sum(np.bincount(rows // n) % 2)
    empty, mask = _even_blocks(rows[:0], n)
    assert empty.size == 0 and mask.size == 0


def test_one_hot_spline_bins_are_zukos_to_the_bit():
    """The sample and log-density graphs look the spline's bins up by one-hot sums (:class:`_OneHotRQS`, faster in onnxruntime than
    gathers): every output of zuko's spline — the bin's knots and slopes, the forward and inverse maps and the
    log-Jacobian — is the same to the bit, inside the bins and outside the spline's bound (k = −1 and k = K)."""
    from zuko.flows import NSF
    from zuko.transforms import MonotonicRQSTransform

    from components.export.onnx import (
        _Conditioner,
        _LogProbGraph,
        _one_hot_splines,
        _one_hot_univariate,
        _OneHotRQS,
        _SampleGraph,
    )

    g = torch.Generator().manual_seed(0)
    bins = 8
    widths, heights = 3 * torch.randn(64, 6, bins, generator=g), 3 * torch.randn(64, 6, bins, generator=g)
    derivatives = 3 * torch.randn(64, 6, bins - 1, generator=g)
    zuko_spline = MonotonicRQSTransform(widths, heights, derivatives, slope=1e-3)
    ours = _OneHotRQS(widths, heights, derivatives, slope=1e-3)
    for k in range(-1, bins + 1):
        index = torch.full((64, 6), k)
        for a, b in zip(zuko_spline.bin(index), ours.bin(index), strict=True):
            assert torch.equal(a, b), k
    x = 6 * torch.randn(64, 6, generator=g)  # beyond the bound 5 too
    assert (x.abs() > 5).any()
    assert torch.equal(zuko_spline(x), ours(x))
    assert torch.equal(zuko_spline.inv(x), ours.inv(x))
    for a, b in zip(zuko_spline.call_and_ladj(x), ours.call_and_ladj(x), strict=True):
        assert torch.equal(a, b)
    # the exported graphs' copy of an NSF swaps its splines and nothing else, and leaves the flow alone
    flow = NSF(features=3, context=2, bins=bins, transforms=1, hidden_features=(8,))
    t = flow.transform.transforms[0]
    swapped = _one_hot_univariate(t.univariate)
    assert swapped.func is _OneHotRQS and swapped.keywords == t.univariate.keywords
    assert _one_hot_univariate(torch.distributions.ExpTransform) is torch.distributions.ExpTransform
    copy_ = _one_hot_splines(flow)
    one_hot = copy_.transform.transforms[0]
    assert one_hot.univariate.func is _OneHotRQS and t.univariate.func is MonotonicRQSTransform
    assert _SampleGraph(flow).flow.transform.transforms[0].univariate.func is _OneHotRQS
    c, x3 = torch.randn(5, 1, 2, generator=g), torch.randn(5, 4, 3, generator=g)
    with torch.no_grad():
        y = _Conditioner(one_hot, c)(x3)(x3)
        assert torch.equal(y, _Conditioner(t, c)(x3)(x3))
        assert torch.equal(_Conditioner(one_hot, c)(x3).inv(y), _Conditioner(t, c)(x3).inv(y))
    # the log-density graph: the same values
    log_prob = _LogProbGraph(flow)
    assert log_prob.flow.transform.transforms[0].univariate.func is _OneHotRQS
    c2, z = torch.randn(200, 2, generator=g), 3 * torch.randn(200, 3, generator=g)
    with torch.no_grad():
        assert torch.equal(log_prob(c2, z), flow(c2).log_prob(z))
