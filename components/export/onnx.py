"""Export a trained posterior q(θ | x) to ONNX graphs and a JSON model card, for the torch-free runtime.

The exported folder holds three kinds of graph, all float32 with a dynamic batch dimension ``B``:

``context.onnx``
    ``x (B, *input_shape) → context (B, features)``: the standardization ``(x − mean)/std``, the embedding
    (the identity for frozen features; the CNN for a trainable backbone, whose input is ``backbone.preprocess``'s
    tensor) and the context network (``FlowConfig.context_layers``); ``features`` is the flows' context size.
``log_prob_<k>.onnx`` (k = 0 … K−1)
    ``(context (B, features), z (B, d)) → log_qz (B,)``: member k's z-space log-density ``log qₖ(z | c)`` (the fixed
    division by ``Z_SCALE`` included), one graph per member of the equal-weight mixture: a draw of member k has its
    ``log qₖ`` from the inverse pass already, so the runtime asks only the other members (card format 2; format 1 had
    one graph of all K).
``sample_<k>.onnx`` (k = 0 … K−1)
    ``(context (B, features), eps (B, n, d)) → (z (B, n, d), log_qz (B, n))``: member k's inverse pass
    ``z = fₖ⁻¹(ε | c)`` for n draws per input from standard-normal base noise ε, and
    ``log qₖ(z | c) = log N(ε; 0, I) + log|det ∂fₖ(z)/∂z|`` (n is dynamic too; see :class:`_SampleGraph`).
``density.onnx``
    ``(x (B, *input_shape), θ (B, d)) → log_prob (B,)``: the whole log-density in physical units in one graph, for
    consumers that run one ONNX model (the MLflow ONNX flavor); the runtime does not use it.

Apart from ``density.onnx``, the bijection to physical units (θ = scaled sigmoid of z, :mod:`components.core.weather`)
is not in the graphs: the runtime applies it in float64 numpy. ``card.json`` describes everything the runtime needs
(θ names, units, box, bijection, input spec, the graphs' file names and sha256) merged with the caller's card
(backbone, training size, metrics, versions). The folder is written atomically: a temporary sibling folder, then a
rename (:func:`components.core.files.atomic_folder`).

Used by the ``export`` stage.
"""

from __future__ import annotations

import copy
import functools
import io
import json
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime
import torch
from torch import Tensor, nn
from torch.distributions import Transform
from torch.nn import functional as F
from zuko.flows.autoregressive import MaskedAutoregressiveTransform
from zuko.nn import MaskedLinear
from zuko.transforms import DependentTransform, MonotonicRQSTransform
from zuko.utils import unpack

from components.core import weather
from components.core.files import atomic_folder, sha256_file
from components.posterior.bijection import Z_MAX
from components.posterior.mixture import draw_flow
from components.posterior.model import NPE, Z_SCALE

__all__ = ["export_posterior", "CARD_FORMAT", "CARD_KIND", "OPSET", "EXPORTERS"]

#: Version of the exported folder's layout; :mod:`components.export.runtime` refuses any other.
CARD_FORMAT: int = 2
#: The ``kind`` field of the card.
CARD_KIND: str = "pidc-onnx-posterior"
#: ONNX opset of the exported graphs.
OPSET: int = 18
#: The torch → ONNX exporters :func:`export_posterior` can use.
EXPORTERS: tuple[str, ...] = ("dynamo", "torchscript")


class _ContextGraph(nn.Module):
    """``x (B, *input_shape) → c (B, context_features)``: standardization, embedding and context network (NPE.context
    without the checks)."""

    def __init__(self, model: NPE) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: Tensor) -> Tensor:
        m = self.model
        if m.config.standardize:
            x = (x - m.feature_mean) / m.feature_std
        return m.context_net(m.embedding(x))


class _LogProbGraph(nn.Module):
    """``(c (B, features), z (B, d)) → log qₖ(z | c) (B,)``: one member's z-space log-density.

    The graph is of :func:`_one_hot_splines`'s copy of the flow (the same values to the bit)."""

    def __init__(self, flow: nn.Module) -> None:
        super().__init__()
        self.flow = _one_hot_splines(flow)

    def forward(self, context: Tensor, z: Tensor) -> Tensor:
        return self.flow(context).log_prob(z)


class _DensityGraph(nn.Module):
    """``(x (B, *input_shape), θ (B, d)) → log q(θ | x) (B,)`` float64 in physical units: the whole posterior density.

    The same function as :meth:`NPE.log_prob` in one graph (context, every member, the equal-weight mixture, the
    scaled-logit Jacobian in float64, ``-inf`` outside the closed box), for consumers that run a single ONNX model,
    e.g. the MLflow ONNX flavor. The runtime itself composes the smaller graphs.
    """

    def __init__(self, model: NPE) -> None:
        super().__init__()
        self.context = _ContextGraph(model)
        self.flows = model.flows
        self.bijection = model.bijection

    def forward(self, x: Tensor, theta: Tensor) -> Tensor:
        c = self.context(x)
        t = theta.to(torch.float64)
        z64 = self.bijection.to_unbounded(t)
        z = z64.to(c.dtype)
        log_qz = torch.stack([flow(c).log_prob(z) for flow in self.flows], dim=0).to(torch.float64)
        # log |∂θ/∂z| = Σ [log(high − low) + log σ(z) + log σ(−z)], with log σ(z) + log σ(−z) = −|z| − 2 log(1 + e^−|z|)
        # (written out: the exporters have no logaddexp)
        a = z64.abs()
        width = (self.bijection.high - self.bijection.low).to(torch.float64)
        ladj = (torch.log(width) - a - 2.0 * torch.log1p(torch.exp(-a))).sum(dim=-1)
        log_q = torch.logsumexp(log_qz, dim=0) - math.log(len(self.flows)) - ladj
        return torch.where(self.bijection.contains(t), log_q, torch.full_like(log_q, -math.inf))


class _SampleGraph(nn.Module):
    """``(c (B, features), ε (B, n, d)) → (z (B, n, d), log qₖ(z | c) (B, n))``: one member's inverse pass.

    The same function as :func:`components.posterior.mixture.draw_flow` on the context broadcast over the n draws,
    computed with fewer conditioner (hyper-network) evaluations than zuko's generic inverse:

    * an autoregressive transform is inverted by P fixed-point passes ``x ← f(x)⁻¹(y)`` from ``x = 0``; the first
      pass sees ``x = 0``, so its conditioner depends on the context only and runs once per input (``(B, 1, ·)``,
      broadcast over the n draws) instead of once per draw;
    * the log-Jacobian reuses the last pass's spline: after P passes (the DAG's depth) every parameter of the
      spline has its final value, so ``f(x_final) = f(x_{P−1})`` exactly (zuko evaluates the conditioner again);
    * the context's share of the conditioner's first layer is computed once per input (:class:`_Conditioner`);
    * the splines look their bins up by one-hot sums instead of gathers (:func:`_one_hot_splines`), to the bit the
      same.

    For a coupling flow (P = 2) a draw costs one conditioner evaluation per transform instead of three. The export
    checks the graph against zuko's own inverse (:func:`~components.posterior.mixture.draw_flow`).
    """

    def __init__(self, flow: nn.Module) -> None:
        super().__init__()
        self.flow = _one_hot_splines(flow)

    def forward(self, context: Tensor, eps: Tensor) -> tuple[Tensor, Tensor]:
        c = context.unsqueeze(-2)  # (B, 1, features): broadcast over the draws
        y = eps
        ladj = torch.zeros(eps.shape[:-1], dtype=eps.dtype, device=eps.device)
        for t in reversed(self.flow.transform.transforms):
            if isinstance(t, MaskedAutoregressiveTransform):
                conditioner = _Conditioner(t, c)
                f = conditioner.at_zero()
                x = f.inv(y)
                for _ in range(t.passes - 1):
                    f = conditioner(x)
                    x = f.inv(y)
                step = f.log_abs_det_jacobian(x, y)
            else:  # an unconditional transform (the fixed scaling by 1/Z_SCALE)
                f = t(c)
                x = f.inv(y)
                step = f.log_abs_det_jacobian(x, y)
                if step.shape == y.shape:  # element-wise (event_dim 0)
                    step = step.sum(dim=-1)
            ladj = ladj + step  # log |det ∂y/∂x| of the forward direction z → ε
            y = x
        log_base = -0.5 * (eps**2).sum(dim=-1) - 0.5 * eps.shape[-1] * math.log(2.0 * math.pi)
        return y, log_base + ladj  # log q(z) = log N(ε) + log |det ∂ε/∂z|


class _OneHotRQS(MonotonicRQSTransform):
    """zuko's monotonic rational-quadratic spline whose bin lookup is a one-hot sum instead of a gather.

    For bin indices k ``(*)`` each knot table ``(*, K + 1)`` is read as ``Σⱼ tableⱼ · [j = k]``: every term but one is an
    exact zero, so the sum is ``table[k]`` to the bit (the knots and derivatives are finite: zuko bounds them). In the
    exported graph this is Equal, Mul and ReduceSum, which onnxruntime runs faster than GatherElements on tables
    expanded to every draw: ~1.2× a draw of the sample graph, ~1.06× a point of the density graph (docs/studies/
    spline-one-hot.md; the compiled training step is faster with zuko's gathers and keeps them). ``bin``
    is zuko's method (zuko 1.x); ``tests/test_export_runtime.py`` checks the two against each other.
    """

    def bin(self, k: Tensor) -> tuple[Tensor, ...]:
        mask = torch.logical_and(0 <= k, k < self.bins)
        k = (k % self.bins).unsqueeze(-1)
        j = torch.arange(self.bins + 1, device=k.device)
        at_k0 = (j == k).to(self.horizontal.dtype)  # (*, K + 1)
        at_k1 = (j == k + 1).to(self.horizontal.dtype)
        x0, x1 = (self.horizontal * at_k0).sum(-1), (self.horizontal * at_k1).sum(-1)
        y0, y1 = (self.vertical * at_k0).sum(-1), (self.vertical * at_k1).sum(-1)
        d0, d1 = (self.derivatives * at_k0).sum(-1), (self.derivatives * at_k1).sum(-1)
        s = (y1 - y0) / (x1 - x0)
        return mask, x0, x1, y0, y1, d0, d1, s


def _one_hot_univariate(univariate: Any) -> Any:
    """``univariate`` with :class:`_OneHotRQS` for zuko's spline (``NSF``'s ``partial(MonotonicRQSTransform, …)``);
    any other univariate transform as it is."""
    if isinstance(univariate, functools.partial) and univariate.func is MonotonicRQSTransform:
        return functools.partial(_OneHotRQS, *univariate.args, **univariate.keywords)
    if univariate is MonotonicRQSTransform:
        return _OneHotRQS
    return univariate


def _one_hot_splines(flow: nn.Module) -> nn.Module:
    """A copy of ``flow`` whose autoregressive transforms build :class:`_OneHotRQS` splines (the exported graphs');
    ``flow`` itself is left as it is."""
    flow = copy.deepcopy(flow)
    for t in flow.modules():
        if isinstance(t, MaskedAutoregressiveTransform):
            t.univariate = _one_hot_univariate(t.univariate)
    return flow


class _Conditioner:
    """zuko's ``MaskedAutoregressiveTransform.meta(c, x)`` with the context's share of the first layer computed once.

    The hyper-network's first layer acts on ``cat(x, c)``: ``W·cat(x, c) + b = W_x·x + (W_c·c + b)``; the bracket is
    computed once per input ``(B, 1, H)`` and shared by the n draws. Other layer layouts use ``meta`` as it is.
    """

    def __init__(self, t: MaskedAutoregressiveTransform, c: Tensor) -> None:
        self.t = t
        self.c = c
        layers = list(t.hyper)
        self.split = isinstance(layers[0], MaskedLinear)
        if self.split:
            first = layers[0]
            weight = first.mask * first.weight
            d = weight.shape[1] - c.shape[-1]
            self.weight_x = weight[:, :d]
            self.from_context = F.linear(c, weight[:, d:], first.bias)  # (B, 1, H)
            self.rest = layers[1:]

    def _transform(self, h: Tensor) -> Transform:
        for layer in self.rest:
            h = layer(h)
        phi = unpack(h.unflatten(-1, (-1, self.t.total)), self.t.shapes)
        return DependentTransform(self.t.univariate(*phi), 1)

    def at_zero(self) -> Transform:
        """The transform at x = 0 (the first inversion pass), once per input: parameters ``(B, 1, ...)``."""
        if not self.split:
            d = self.t.order.shape[0]
            return self.t.meta(self.c, self.c.new_zeros((*self.c.shape[:-1], d)))
        return self._transform(self.from_context)

    def __call__(self, x: Tensor) -> Transform:
        """The transform at x ``(B, n, d)``."""
        if not self.split:
            return self.t.meta(self.c, x)
        return self._transform(F.linear(x, self.weight_x) + self.from_context)


def _check_standard_normal_base(flow: nn.Module) -> None:
    """The sampling graph assumes base noise N(0, I) (as zuko's NSF builds it); anything else is an error."""
    base = flow.base()
    loc, scale = base.base_dist.loc, base.base_dist.scale
    if not (bool((loc == 0).all()) and bool((scale == 1).all())):
        raise ValueError("the flow's base distribution is not the standard normal N(0, I): cannot export its sampler")


def _export_graph(
    module: nn.Module,
    args: tuple[Tensor, ...],
    path: Path,
    input_names: list[str],
    output_names: list[str],
    exporter: str,
    dynamic: dict[str, tuple[str, ...]],
) -> None:
    """Export ``module(*args)`` to ``path`` (one self-contained file) and check it.

    ``dynamic`` names the dynamic leading axes of every input and output (e.g. ``{"eps": ("batch", "draws")}``).

    ``exporter`` is ``"dynamo"`` (``torch.export`` + onnxscript, torch's maintained route; ~15 s a graph here) or
    ``"torchscript"`` (the legacy tracer, deprecated by torch but ~5× faster to export; same graphs to ~1e-6).
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporters' deprecation and progress chatter
        try:
            if exporter == "dynamo":
                dims = {name: torch.export.Dim(name, min=1) for name in ("batch", "draws")}
                program = torch.onnx.export(
                    module,
                    args,
                    dynamo=True,
                    input_names=input_names,
                    output_names=output_names,
                    dynamic_shapes={n: {i: dims[a] for i, a in enumerate(dynamic[n])} for n in input_names},
                    opset_version=OPSET,
                    external_data=False,
                    optimize=True,
                    verbose=False,
                )
                assert program is not None
                proto = program.model_proto
            else:
                buffer = io.BytesIO()
                torch.onnx.export(
                    module,
                    args,
                    buffer,
                    dynamo=False,
                    input_names=input_names,
                    output_names=output_names,
                    dynamic_axes={n: dict(enumerate(dynamic[n])) for n in input_names + output_names},
                    opset_version=OPSET,
                    do_constant_folding=True,
                )
                proto = onnx.load_from_string(buffer.getvalue())
        except Exception as e:  # the exporters' errors are long traces; say which graph failed
            raise RuntimeError(
                f"ONNX export of {path.name} failed ({exporter}): {type(e).__name__}: {str(e)[:2000]}"
            ) from e
    onnx.checker.check_model(proto, full_check=True)
    path.write_bytes(proto.SerializeToString())


def _input_description(model: NPE) -> str:
    if isinstance(model.embedding, nn.Identity):
        return "frozen backbone features (float32), as written by the features stage; standardized inside the graph"
    name = getattr(model.embedding, "name", type(model.embedding).__name__)
    return (
        f"the tensor of backbone {name!r}.preprocess(images) (float32), e.g. sRGB in [0, 1] as (n, C, H, W); "
        "standardization and the embedding are inside the graph"
    )


def _json_safe(value: Any) -> Any:
    """Round-trip through JSON (numpy scalars/arrays → lists); a value JSON cannot hold is a ``TypeError``."""

    def default(o: Any) -> Any:
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f"card: value of type {type(o).__name__} is not JSON-serializable")

    return json.loads(json.dumps(value, default=default, allow_nan=False))


def export_posterior(model: NPE, folder: str | Path, *, card: dict[str, Any], exporter: str = "dynamo") -> Path:
    """Export ``model`` to ``folder`` (replaced atomically): ONNX graphs and ``card.json``; returns the folder.

    Arguments:
        model: a trained :class:`~components.posterior.model.NPE` (a float32 copy in eval mode is exported; the
            model itself is not modified).
            Its ``input_shape`` must be known (always the case for frozen features; given for a trainable embedding).
        folder: the destination (e.g. ``registry/<backbone>-<size>``); its parent is created if needed.
        card: the caller's metadata (backbone, training size, metrics, data and code versions): JSON-able, merged
            under the runtime's fields, which take precedence.

    Raises:
        TypeError: ``model`` is not an NPE or ``card`` not a dict / not JSON-able.
        ValueError: the model's input shape is unknown.
        RuntimeError: a graph does not export, or onnxruntime's output disagrees with torch (> 1e-3).
    """
    if not isinstance(model, NPE):
        raise TypeError(f"model must be a components.posterior.model.NPE, got {type(model).__name__}")
    if not isinstance(card, dict):
        raise TypeError(f"card must be a dict of JSON-able metadata, got {type(card).__name__}")
    if exporter not in EXPORTERS:
        raise ValueError(f"exporter must be one of {', '.join(EXPORTERS)}, got {exporter!r}")
    if model.input_shape is None:
        raise ValueError(
            "the model has no input_shape: build the NPE with input_shape=(one input's shape) to export it"
        )
    user_card = _json_safe(card)
    folder = Path(folder)

    export_model = copy.deepcopy(model).float().eval()  # the caller's model is left as it is
    with atomic_folder(folder) as tmp:
        files = _write_graphs(export_model, tmp, exporter)
        full_card = _card(export_model, user_card, files, tmp, exporter)
        (tmp / "card.json").write_text(json.dumps(full_card, indent=1, allow_nan=False) + "\n")
    return folder


def _write_graphs(model: NPE, tmp: Path, exporter: str) -> dict[str, str]:
    """Write the graphs into ``tmp`` and check each against torch with onnxruntime; ``{role: file name}``."""
    assert model.input_shape is not None
    gen = torch.Generator().manual_seed(0)
    b = 3
    x = torch.randn((b, *model.input_shape), generator=gen)
    if model.config.standardize:
        x = x * model.feature_std.float() + model.feature_mean.float()
    eps = torch.randn((b, 2, model.dim), generator=gen)  # (batch, draws, d)
    files: dict[str, str] = {"context": "context.onnx"}
    with torch.no_grad():
        ctx_module = _ContextGraph(model)
        c = ctx_module(x)
        _export_graph(
            ctx_module,
            (x,),
            tmp / files["context"],
            ["x"],
            ["context"],
            exporter,
            {"x": ("batch",), "context": ("batch",)},
        )
        z = torch.randn((b, model.dim), generator=gen) * 3.0
        checks: list[tuple[str, dict[str, np.ndarray], list[Tensor]]] = [(files["context"], {"x": x.numpy()}, [c])]
        for k, flow in enumerate(model.flows):
            files[f"log_prob_{k}"] = f"log_prob_{k}.onnx"
            lp_module = _LogProbGraph(flow)
            _export_graph(
                lp_module,
                (c, z),
                tmp / files[f"log_prob_{k}"],
                ["context", "z"],
                ["log_qz"],
                exporter,
                {"context": ("batch",), "z": ("batch",), "log_qz": ("batch",)},
            )
            checks.append((files[f"log_prob_{k}"], {"context": c.numpy(), "z": z.numpy()}, [lp_module(c, z)]))
        files["density"] = "density.onnx"
        theta = model.box.low + torch.rand((b, model.dim), generator=gen, dtype=torch.float64).numpy() * model.box.width
        theta_t = torch.from_numpy(theta).float()
        d_module = _DensityGraph(model)
        _export_graph(
            d_module,
            (x, theta_t),
            tmp / files["density"],
            ["x", "theta"],
            ["log_prob"],
            exporter,
            {"x": ("batch",), "theta": ("batch",), "log_prob": ("batch",)},
        )
        checks.append((files["density"], {"x": x.numpy(), "theta": theta_t.numpy()}, [model.log_prob(theta_t, x)]))
        for k, flow in enumerate(model.flows):
            name = f"sample_{k}.onnx"
            files[f"sample_{k}"] = name
            _check_standard_normal_base(flow)
            s_module = _SampleGraph(flow)
            axes = ("batch", "draws")
            _export_graph(
                s_module,
                (c, eps),
                tmp / name,
                ["context", "eps"],
                ["z", "log_qz"],
                exporter,
                {"context": ("batch",), "eps": axes, "z": axes, "log_qz": axes},
            )
            reference = draw_flow(flow(c.unsqueeze(1).expand(b, eps.shape[1], c.shape[1])), eps)  # zuko's inverse
            checks.append((name, {"context": c.numpy(), "eps": eps.numpy()}, list(reference)))
    _check_graphs(tmp, checks)
    return files


def _check_graphs(tmp: Path, checks: list[tuple[str, dict[str, np.ndarray], list[Tensor]]]) -> None:
    """Run each graph file of ``tmp`` on its feeds with onnxruntime (one thread, CPU) and compare its outputs with
    torch's; a ``RuntimeError`` naming the graph when onnxruntime cannot run it or it disagrees by more than 1e-3."""
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = 1
    for name, feeds, expected in checks:
        try:
            session = onnxruntime.InferenceSession(str(tmp / name), options, providers=["CPUExecutionProvider"])
            got = session.run(None, feeds)
        except Exception as e:  # onnxruntime's own exception types
            raise RuntimeError(f"onnxruntime cannot run the exported {name} ({type(e).__name__}: {e})") from e
        for g, e in zip(got, expected, strict=False):
            err = float(np.max(np.abs(g - e.numpy()))) if g.size else 0.0
            if not math.isfinite(err) or err > 1e-3:
                raise RuntimeError(f"exported {name} disagrees with torch by {err:.3g} (onnxruntime vs torch)")


def _card(model: NPE, user_card: dict[str, Any], files: dict[str, str], tmp: Path, exporter: str) -> dict[str, Any]:
    """The model card: the caller's fields, overridden by what the runtime needs."""
    assert model.input_shape is not None
    box = model.box
    names = list(box.names)
    return {
        **user_card,
        "kind": CARD_KIND,
        "format": CARD_FORMAT,
        "theta": {
            "names": names,
            "units": list(box.units),
            "is_weather": tuple(names) == weather.PREDICTED,
        },
        "bijection": {
            "name": "scaled_logit",
            "low": box.low.tolist(),
            "high": box.high.tolist(),
            "edge_eps": weather.EDGE_EPS,
            "z_max": Z_MAX,
            "z_scale_inside_flow": Z_SCALE,
            "formula": "u = clip((θ − low)/(high − low), ε, 1 − ε); z = log u − log(1 − u); "
            "θ = low + (high − low)·σ(z); log q_θ = log q_z − Σ [log(high − low) + log σ(z) + log σ(−z)]",
        },
        "ensemble": len(model.flows),
        "features": model.context_features,
        "flow": {
            "transforms": model.config.transforms,
            "hidden_features": list(model.config.hidden_features),
            "bins": model.config.bins,
            "passes": model.config.passes,
            "standardize": model.config.standardize,
            "context_layers": list(model.config.context_layers),
        },
        "input": {
            "shape": ["batch", *model.input_shape],
            "dtype": "float32",
            "preprocessing": _input_description(model),
        },
        "graphs": {
            "context": {
                "inputs": {"x": ["batch", *model.input_shape]},
                "outputs": {"context": ["batch", model.context_features]},
            },
            "log_prob": {  # one graph per member: log_prob_<k>
                "inputs": {"context": ["batch", model.context_features], "z": ["batch", model.dim]},
                "outputs": {"log_qz": ["batch"]},
            },
            "density": {
                "inputs": {"x": ["batch", *model.input_shape], "theta": ["batch", model.dim]},
                "outputs": {"log_prob": ["batch"]},
            },
            "sample": {
                "inputs": {"context": ["batch", model.context_features], "eps": ["batch", "draws", model.dim]},
                "outputs": {"z": ["batch", "draws", model.dim], "log_qz": ["batch", "draws"]},
            },
        },
        "opset": OPSET,
        "exporter": exporter,
        "versions": {"onnx": onnx.__version__, "onnxruntime": onnxruntime.__version__, "torch": torch.__version__},
        "files": {role: {"name": name, "sha256": sha256_file(tmp / name)} for role, name in files.items()},
    }
