"""The neural posterior estimator q(θ | x): embedding → context → conditional neural spline flow over z.

Notation (paper): θ ∈ [low, high]ᵈ the physical weather parameters (d = 6 for pidc, any d for toys),
x an input (cached image features, or images for a trainable embedding), z = logit-scaled θ ∈ ℝᵈ
(:mod:`components.posterior.bijection`). The flow models q(z | x); densities in physical units are

    log q(θ | x) = log q_z(z(θ) | x) − log |det ∂θ/∂z|.

Inside the zuko flow, z is first divided by the fixed :data:`Z_SCALE` so that the image of the closed box,
|z| ≤ :data:`~components.posterior.bijection.Z_MAX` ≈ 13.8, lies in [−4, 4], inside the [−5, 5] domain where
zuko's splines act (outside it they are the identity). ``NPE.flow(x)`` returns the full z-space distribution,
this scaling included.

Each flow ends with the fixed scaling ε ↦ ε / τ, τ = :attr:`NPE.temperature` (ones until fitted on held-out data by
:mod:`components.posterior.temperature`): the base is N(0, diag τ²). With ``FlowConfig.regime_temperature`` τ depends
on the context, blended between two regimes (e.g. day and night) by a gate on the context
(:class:`~components.posterior.regime.RegimeTemperature`).

With ``FlowConfig.ensemble = K > 1`` the estimator is the equal-weight mixture of K flows with independent
initializations sharing the embedding and the context network: ``q(θ | x) = (1/K) Σₖ qₖ(θ | x)``. The members are
trained together on the same batches, each on its own NPE loss (the loss is their mean), so they differ by their
initialization only.

Used by the ``train`` and ``export`` stages.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import zuko
from torch import Tensor, nn
from torch.distributions import AffineTransform, Distribution

from components.core import seeding, weather
from components.core.checks import whole_number
from components.posterior.bijection import Z_MAX, ScaledLogit, as_interval_box
from components.posterior.mixture import EqualMixture, draw_flow, standard_normal
from components.posterior.regime import RegimeTemperature

__all__ = ["FlowConfig", "NPE", "Z_SCALE", "finite_rows"]

#: z is divided by this inside the flow: the closed box maps into [−4, 4] (zuko's splines act on [−5, 5]).
Z_SCALE: float = Z_MAX / 4.0

#: Rows per ``isfinite`` call and elements per float64 moment in :func:`finite_rows` and
#: :meth:`NPE.fit_standardization`: the cnn's 50 000 training inputs of 3 × 64 × 64 are 2.5 GB in float32, and whole-array
#: temporaries (a 0.6 GB bool copy, a 5 GB float64 copy and its squares) took ~36 s before its first epoch; in pieces the
#: same numbers come in ~12 s (``benchmarks/studies/bench_inputs.py``;
#: docs/studies/cnn-inputs-pieces.md).
_ROWS_PER_CHECK: int = 4096
_ELEMENTS_PER_MOMENT: int = 256


def finite_rows(x: Tensor) -> Tensor:
    """``(n,)`` bool: which rows of ``x (n, …)`` hold only finite values, checked a few thousand rows at a time (with
    numpy's ``isfinite`` for a float32/float64 CPU tensor: ~10× torch's on this project's CPU)."""
    flat = x.detach().reshape(x.shape[0], math.prod(x.shape[1:]))
    rows = range(0, flat.shape[0], _ROWS_PER_CHECK)
    if flat.device.type == "cpu" and flat.dtype in (torch.float32, torch.float64):
        a = flat.numpy()
        return torch.from_numpy(
            np.concatenate([np.isfinite(a[i : i + _ROWS_PER_CHECK]).all(axis=1) for i in rows] or [np.ones(0, bool)])
        )
    return torch.cat(
        [torch.isfinite(flat[i : i + _ROWS_PER_CHECK]).all(dim=1) for i in rows]
        or [torch.ones(0, dtype=torch.bool, device=x.device)]
    )


@dataclass(frozen=True)
class FlowConfig:
    """Hyper-parameters of the conditional flow.

    Attributes:
        transforms: number of spline transforms of each NSF.
        hidden_features: widths of each conditioner MLP's hidden layers.
        bins: number of rational-quadratic spline bins K.
        passes: 2 = coupling flow (fast sampling); ``None`` = fully autoregressive (d passes to sample).
        standardize: standardize the inputs x with a mean/std fitted on the training set (buffers).
        ensemble: number of flows K in the equal-weight mixture (1 = a single flow).
        context_layers: widths of the context network, a multilayer perceptron (SiLU between its linear layers)
            from the embedding's features to the flows' context ``c``, shared by the ensemble's members; its last width
            is the context size. ``()`` = none: the features are the context.
        regime_temperature: the flows' base scale τ(c) depends on the context, one τ per regime blended by the
            probability of the regime (:class:`~components.posterior.regime.RegimeTemperature`); False: one τ.
    """

    transforms: int = 3
    hidden_features: tuple[int, ...] = (128, 128)
    bins: int = 8
    passes: int | None = 2
    standardize: bool = True
    ensemble: int = 1
    context_layers: tuple[int, ...] = ()
    regime_temperature: bool = False

    def __post_init__(self) -> None:
        for name in ("hidden_features", "context_layers"):
            widths = getattr(self, name)
            if not isinstance(widths, (tuple, list)):
                raise ValueError(f"FlowConfig.{name} must be positive integer widths, got {widths!r}")
            checked = tuple(whole_number(f"FlowConfig.{name}[{i}]", w, low=1) for i, w in enumerate(widths))
            object.__setattr__(self, name, checked)
        for name, low in (("transforms", 1), ("bins", 2), ("ensemble", 1)):
            object.__setattr__(self, name, whole_number(f"FlowConfig.{name}", getattr(self, name), low=low))
        if not self.hidden_features:
            raise ValueError(f"FlowConfig.hidden_features must hold at least one width, got {self.hidden_features}")
        if self.passes is not None:
            passes = whole_number("FlowConfig.passes", self.passes, low=1, hint=" or None (autoregressive)")
            object.__setattr__(self, "passes", passes)


def _build_flow(dim: int, context: int, config: FlowConfig, seed: int) -> zuko.flows.Flow:
    """One conditional NSF over z ∈ ℝᵈ, preceded by the fixed scaling z ↦ z / Z_SCALE and followed by the base scale
    ε ↦ ε / τ (per regime with ``config.regime_temperature``); weights from ``seed``."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        nsf = zuko.flows.NSF(
            features=dim,
            context=context,
            transforms=config.transforms,
            bins=config.bins,
            passes=config.passes,
            hidden_features=config.hidden_features,
        )
    scale = zuko.flows.UnconditionalTransform(
        AffineTransform, loc=torch.tensor(0.0), scale=torch.tensor(1.0 / Z_SCALE), buffer=True
    )
    temper: zuko.flows.LazyTransform
    if config.regime_temperature:
        temper = RegimeTemperature(dim, context)
    else:
        temper = zuko.flows.UnconditionalTransform(
            AffineTransform, loc=torch.zeros(dim), scale=torch.ones(dim), buffer=True
        )
    return zuko.flows.Flow([scale, *nsf.transform.transforms, temper], nsf.base)


def context_network(features: int, widths: tuple[int, ...], seed: int) -> nn.Module:
    """The context network ``(B, features) → (B, widths[-1])``: linear layers of ``widths`` with SiLU between them,
    weights from ``seed``; the identity for ``widths = ()``."""
    if not widths:
        return nn.Identity()
    layers: list[nn.Module] = []
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        for i, (a, b) in enumerate(zip((features, *widths[:-1]), widths, strict=True)):
            layers += [nn.SiLU()] if i else []
            layers.append(nn.Linear(a, b))
    return nn.Sequential(*layers)


def _generator(rng: torch.Generator | int) -> torch.Generator:
    if isinstance(rng, torch.Generator):
        return rng
    seed = whole_number("rng", rng, error=TypeError, hint=" seed or a torch.Generator")
    return torch.Generator().manual_seed(seed)


class NPE(nn.Module):
    """Neural posterior estimator ``q(θ | x)`` with support exactly the prior box.

    Arguments:
        embedding: a module mapping inputs ``(B, *input_shape)`` to contexts ``(B, features)``, trained with the
            flow; ``None`` = identity (cached, frozen features of size ``features``).
        features: the embedding's output size (the input of the context network, ``FlowConfig.context_layers``).
        box: the prior box (:class:`components.core.weather.Box`, of any dimension d).
        config: the flow's hyper-parameters.
        input_shape: the shape of one input; defaults to ``(features,)`` without an embedding. Required with an
            embedding when ``config.standardize`` (the mean/std buffers have this shape: per-element standardization).
        seed: the flows' initial weights descend from it (member k from ``derive_seed(seed, "posterior", "flow", k)``,
            the context network from ``derive_seed(seed, "posterior", "context")``); the embedding is initialized by
            the caller.

    Attributes:
        feature_mean: standardization buffer of shape ``input_shape`` (zeros until :meth:`fit_standardization`).
        feature_std: standardization buffer of shape ``input_shape`` (ones until :meth:`fit_standardization`).

    References:
        Lueckmann et al., "Flexible statistical inference for mechanistic models of neural dynamics", NeurIPS 2017,
        and Greenberg, Nonnenmacher & Macke, "Automatic Posterior Transformation for Likelihood-Free Inference",
        ICML 2019 (neural posterior estimation); Durkan, Bekasov, Murray & Papamakarios,
        "Neural Spline Flows", NeurIPS 2019 (the flow); Rozet et al., zuko (its implementation); Halin, Piérard et
        al., "Physically Interpretable Probabilistic Domain Characterization" (its use for the weather).

    Examples:
        A posterior over a 2-D box (cloudiness in %, sun altitude in degrees) from 3 frozen features, untrained:

        >>> import numpy as np, torch
        >>> from components.core.weather import Box
        >>> from components.posterior import NPE, FlowConfig
        >>> box = Box(np.array([0.0, -90.0]), np.array([100.0, 90.0]), names=("cloudiness", "sun_altitude_angle"))
        >>> model = NPE(None, features=3, box=box, config=FlowConfig(transforms=1, hidden_features=(16,)), seed=0)
        >>> x = torch.randn(5, 3)  # a batch of 5 inputs
        >>> theta = model.sample(x, 100, rng=1)  # 100 draws per input, physical units
        >>> theta.shape, bool(box.contains(theta.double().numpy()).all())
        (torch.Size([5, 100, 2]), True)
        >>> model.log_prob(theta, x).shape  # log q(θ | x) in log(1 / (% · deg))
        torch.Size([5, 100])
        >>> model.log_prob(torch.tensor([[150.0, 0.0]]), x[:1])  # outside the box: zero density
        tensor([-inf], grad_fn=<SubBackward0>)
    """

    feature_mean: Tensor
    feature_std: Tensor

    def __init__(
        self,
        embedding: nn.Module | None,
        features: int,
        box: weather.Box,
        config: FlowConfig = FlowConfig(),
        *,
        input_shape: tuple[int, ...] | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__()
        whole_number("features (the context size)", features, low=1)
        if not isinstance(config, FlowConfig):
            raise TypeError(f"config must be a FlowConfig, got {type(config).__name__}")
        if embedding is not None and not isinstance(embedding, nn.Module):
            raise TypeError(f"embedding must be a torch.nn.Module or None, got {type(embedding).__name__}")
        self.box = as_interval_box(box)
        self.config = config
        self.features = features
        self.bijection = ScaledLogit(self.box)
        self.embedding = embedding if embedding is not None else nn.Identity()
        if embedding is None:
            if input_shape is not None and tuple(input_shape) != (features,):
                raise ValueError(
                    f"without an embedding the input shape is (features,) = ({features},), got {input_shape}"
                )
            input_shape = (features,)
        elif config.standardize and input_shape is None:
            raise ValueError("with an embedding and FlowConfig.standardize=True, give input_shape (one input's shape)")
        self.input_shape: tuple[int, ...] | None = (
            tuple(int(s) for s in input_shape) if input_shape is not None else None
        )
        if config.standardize:
            assert self.input_shape is not None
            self.register_buffer("feature_mean", torch.zeros(self.input_shape))
            self.register_buffer("feature_std", torch.ones(self.input_shape))
        self.context_net = context_network(
            features, config.context_layers, seeding.derive_seed(seed, "posterior", "context")
        )
        self.flows = nn.ModuleList(
            _build_flow(self.box.dim, self.context_features, config, seeding.derive_seed(seed, "posterior", "flow", k))
            for k in range(config.ensemble)
        )

    # --- shapes and inputs -------------------------------------------------------------------------------

    @property
    def context_features(self) -> int:
        """The size of the flows' context ``c``: the context network's last width, or ``features`` without one."""
        return self.config.context_layers[-1] if self.config.context_layers else self.features

    @property
    def dim(self) -> int:
        """d, the number of parameters θ."""
        return self.box.dim

    @property
    def temperature(self) -> Tensor:
        """τ, the base distribution's scale N(0, diag τ²) (ones until
        :func:`~components.posterior.temperature.calibrate`): ``(d,)``, or ``(2, d)`` with a regime temperature (rows:
        outside, inside the regime)."""
        last = self.flows[0].transform.transforms[-1]
        if isinstance(last, RegimeTemperature):
            return last.log_tau.exp()
        return 1.0 / last.scale

    @torch.no_grad()
    def set_temperature(self, tau: Tensor) -> None:
        """Set τ > 0 in every member: ``(d,)`` (with a regime temperature: the same in both regimes) or ``(2, d)``
        (a regime temperature's rows: outside, inside the regime)."""
        tau = torch.as_tensor(tau, dtype=torch.float64)
        regime = self.config.regime_temperature
        shapes = [(self.dim,), (2, self.dim)] if regime else [(self.dim,)]
        if tau.shape not in shapes or not bool(torch.isfinite(tau).all()) or not bool((tau > 0).all()):
            what = f"{self.dim} or 2 × {self.dim}" if regime else f"{self.dim}"
            raise ValueError(f"the temperature τ must be {what} finite positive numbers, got {tau.tolist()}")
        for flow in self.flows:
            last = flow.transform.transforms[-1]
            if regime:
                last.log_tau.copy_(tau.log().expand(2, self.dim).to(last.log_tau))
            else:
                last.scale.copy_((1.0 / tau).to(last.scale))

    def _regime(self) -> RegimeTemperature:
        last = self.flows[0].transform.transforms[-1]
        if not isinstance(last, RegimeTemperature):
            raise ValueError("this model has one base scale τ: build it with FlowConfig(regime_temperature=True)")
        return last

    @torch.no_grad()
    def set_regime_gate(self, weight: Tensor, bias: Tensor) -> None:
        """Set the gate p(c) = σ(w · c + b) of the regime temperature in every member: ``weight (F,)``, ``bias ()``."""
        features = self._regime().weight.shape[0]
        weight, bias = torch.as_tensor(weight), torch.as_tensor(bias)
        if weight.shape != (features,) or bias.shape != () or not bool(torch.isfinite(weight).all() & bias.isfinite()):
            raise ValueError(
                f"the regime gate needs a finite weight ({features},) and bias (), got {tuple(weight.shape)}, "
                f"{tuple(bias.shape)}"
            )
        for flow in self.flows:
            last = flow.transform.transforms[-1]
            last.weight.copy_(weight.to(last.weight))
            last.bias.copy_(bias.to(last.bias))

    def regime_probability(self, context: Tensor) -> Tensor:
        """p(c), the gate's probability that inputs of :meth:`context` ``(B, F)`` lie in the regime: ``(B,)``."""
        return self._regime().probability(context)

    @property
    def dtype(self) -> torch.dtype:
        return next(self.flows.parameters()).dtype

    @property
    def device(self) -> torch.device:
        return next(self.flows.parameters()).device

    def _inputs(self, x: Tensor) -> Tensor:
        x = torch.as_tensor(x)
        if self.input_shape is not None and tuple(x.shape[1:]) != self.input_shape:
            raise ValueError(
                f"x must have shape (batch, {', '.join(map(str, self.input_shape))}), got {tuple(x.shape)}"
            )
        if x.dim() < 1 or x.shape[0] == 0:
            raise ValueError(f"x must be a non-empty batch, got shape {tuple(x.shape)}")
        # torch.compile traces the training loss after train() has checked the whole data set: no per-batch check there
        if not torch.compiler.is_compiling() and x.is_floating_point() and not bool(finite_rows(x).all()):
            raise ValueError("x contains NaN or infinite values")
        return x.to(device=self.device, dtype=self.dtype)

    @torch.no_grad()
    def fit_standardization(self, x: Tensor) -> None:
        """Set ``feature_mean``/``feature_std`` to the per-element mean/std of training inputs ``x (n, *input_shape)``.

        Elements with (near) zero spread keep std 1. Does nothing when ``config.standardize`` is off. The moments are
        computed in float64 for a few hundred elements at a time: the same numbers as over the whole array (tested to the
        bit), without its float64 copy.
        """
        if not self.config.standardize:
            return
        x = self._inputs(x)
        flat = x.reshape(x.shape[0], -1)
        mean = torch.empty(flat.shape[1], dtype=torch.float64, device=x.device)
        std = torch.ones_like(mean)
        for j in range(0, flat.shape[1], _ELEMENTS_PER_MOMENT):
            block = flat[:, j : j + _ELEMENTS_PER_MOMENT].to(torch.float64)
            mean[j : j + _ELEMENTS_PER_MOMENT] = block.mean(dim=0)
            if x.shape[0] > 1:
                std[j : j + _ELEMENTS_PER_MOMENT] = block.std(dim=0, unbiased=False)
        mean, std = mean.reshape(x.shape[1:]), std.reshape(x.shape[1:])
        std = torch.where(std > 1e-8 * (1.0 + mean.abs()), std, torch.ones_like(std))
        self.feature_mean.copy_(mean.to(self.feature_mean))
        self.feature_std.copy_(std.to(self.feature_std))

    def context(self, x: Tensor) -> Tensor:
        """The flows' context ``c = context_net(embedding((x − mean)/std))``: ``(B, *input_shape) → (B,
        context_features)``."""
        x = self._inputs(x)
        if self.config.standardize:
            x = (x - self.feature_mean) / self.feature_std
        c = self.embedding(x)
        if c.dim() != 2 or c.shape != (x.shape[0], self.features):
            raise ValueError(
                f"the embedding must return (batch, features) = ({x.shape[0]}, {self.features}), got {tuple(c.shape)}"
            )
        return self.context_net(c)

    def _theta(self, theta: Tensor, batch: int) -> Tensor:
        theta = torch.as_tensor(theta)
        if theta.dim() not in (2, 3) or theta.shape[-1] != self.dim or theta.shape[0] != batch:
            raise ValueError(
                f"θ must have shape ({batch}, {self.dim}) or ({batch}, m, {self.dim}) "
                f"({', '.join(self.box.names)}), got {tuple(theta.shape)}"
            )
        theta = theta.to(device=self.device, dtype=torch.float64)
        if not torch.compiler.is_compiling() and not bool(torch.isfinite(theta).all()):
            raise ValueError("θ contains NaN or infinite values")
        return theta

    # --- densities -------------------------------------------------------------------------------------

    def log_prob_members(self, theta: Tensor, context: Tensor) -> Tensor:
        """Each flow's log qₖ(θ | x) in physical units, Jacobian included: ``(K, B)`` or ``(K, B, m)``.

        ``theta`` is ``(B, d)`` or ``(B, m, d)`` (m points per input), ``context`` is :meth:`context`'s ``(B, features)``.
        Points outside the closed box get ``-inf``. Points within ``EDGE_EPS·width`` of a face take the density at
        the clipped point (finite on the faces).
        """
        theta = self._theta(theta, context.shape[0])
        inside = self.bijection.contains(theta)
        z64 = self.bijection.to_unbounded(theta)
        ladj = self.bijection.log_abs_det_jacobian(z64)
        z = z64.to(self.dtype)
        c = context if theta.dim() == 2 else context.unsqueeze(-2)
        log_qz = torch.stack([flow(c).log_prob(z) for flow in self.flows])
        log_q = log_qz - ladj.to(self.dtype)
        return torch.where(inside, log_q, torch.full_like(log_q, -math.inf))

    def log_prob(self, theta: Tensor, x: Tensor) -> Tensor:
        """log q(θ | x) in physical units (per unit of each parameter's unit), Jacobian included.

        Arguments:
            theta: ``(B, d)`` (one θ per input) or ``(B, m, d)`` (m θ's per input), physical units.
            x: ``(B, *input_shape)``.

        Returns:
            ``(B,)`` or ``(B, m)``; exactly ``-inf`` outside the closed box (the density is zero there).
        """
        members = self.log_prob_members(theta, self.context(x))
        return torch.logsumexp(members, dim=0) - math.log(len(self.flows))

    def forward(self, theta: Tensor, x: Tensor) -> Tensor:
        """Same as :meth:`log_prob`."""
        return self.log_prob(theta, x)

    def flow(self, x: Tensor) -> Distribution:
        """The z-space distribution q(z | x), batch shape ``(B,)``, event shape ``(d,)`` (z as in :mod:`components.core.weather`).

        A zuko ``NormalizingFlow`` (its first transform is the fixed scaling by 1/:data:`Z_SCALE`), or an
        :class:`~components.posterior.mixture.EqualMixture` of them for an ensemble.
        """
        c = self.context(x)
        dists = [flow(c) for flow in self.flows]
        return dists[0] if len(dists) == 1 else EqualMixture(dists)

    # --- sampling --------------------------------------------------------------------------------------

    def _draw_z(
        self, context: Tensor, n: int, generator: torch.Generator, with_log_prob: bool
    ) -> tuple[Tensor, Tensor | None]:
        """z ``(n, B, d)`` from the (mixture) flow, and its z-space log-density ``(n, B)`` when asked."""
        b = context.shape[0]
        eps = standard_normal((n, b, self.dim), generator, like=context)
        if len(self.flows) == 1:
            dist = self.flows[0](context)
            if with_log_prob:
                z, log_qz = draw_flow(dist, eps)
                return z, log_qz
            return dist.transform.inv(eps), None
        which = torch.randint(len(self.flows), (n, b), generator=generator, device=generator.device).to(self.device)
        z = torch.empty_like(eps)
        c = context.unsqueeze(0).expand(n, b, context.shape[-1])
        for k, flow in enumerate(self.flows):
            mask = which == k
            if bool(mask.any()):
                z[mask] = flow(c[mask]).transform.inv(eps[mask])
        if not with_log_prob:
            return z, None
        parts = torch.stack([flow(context).log_prob(z) for flow in self.flows])
        return z, torch.logsumexp(parts, dim=0) - math.log(len(self.flows))

    def _check_n(self, n: int) -> None:
        whole_number("the number of posterior samples n", n, low=1)

    def sample(self, x: Tensor, n: int, *, rng: torch.Generator | int = 0) -> Tensor:
        """n draws θ ~ q(θ | x) per input, inside the closed box. No global RNG state is used; runs without autograd.

        Arguments:
            x: ``(B, *input_shape)`` inputs.
            n: draws per input, ≥ 1.
            rng: a ``torch.Generator`` (advanced by the call) or an integer seed (a fresh generator: the same seed
                gives the same draws).

        Returns:
            θ ``(B, n, d)`` in physical units, in the model's dtype.
        """
        with torch.no_grad():
            return self.sample_and_log_prob(x, n, rng=rng, with_log_prob=False)[0]

    def sample_and_log_prob(
        self, x: Tensor, n: int, *, rng: torch.Generator | int = 0, with_log_prob: bool = True
    ) -> tuple[Tensor, Tensor]:
        """n draws θ ~ q(θ | x) per input and their log q(θ | x).

        The log-density is that of the drawn z (cheaper than :meth:`log_prob` on θ). In float64 both agree to ~1e-10,
        except for draws beyond the faces' clipping (probability < 1e-6). θ is returned in the model's dtype: in
        float32, θ within ~1e-5 of a face is rounded, and :meth:`log_prob` of the rounded θ can differ by up to
        ~0.1 nat there.

        Arguments:
            x: ``(B, *input_shape)`` inputs.
            n: draws per input, ≥ 1.
            rng: a ``torch.Generator`` (advanced by the call) or an integer seed.
            with_log_prob: False skips the log-densities (the second item is then empty).

        Returns:
            θ ``(B, n, d)`` in physical units and log q(θ | x) ``(B, n)`` in nats per unit of θ.
        """
        self._check_n(n)
        generator = _generator(rng)
        context = self.context(x)
        z, log_qz = self._draw_z(context, n, generator, with_log_prob)
        z64 = z.to(torch.float64)
        theta = self.bijection.clamp_inward(self.bijection.to_physical(z64).to(self.dtype))
        theta = theta.movedim(0, 1)
        if log_qz is None:
            return theta, torch.empty(0, dtype=self.dtype, device=self.device)
        log_q = log_qz - self.bijection.log_abs_det_jacobian(z64).to(self.dtype)
        return theta, log_q.movedim(0, 1)
