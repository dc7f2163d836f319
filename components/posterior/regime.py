"""A base scale per regime: ε ↦ ε / τ(c), τ blended between two regimes by the probability of one given the context.

Where the image cannot show a parameter, a flow trained on every input at once can be more confident than it should
be in one regime and less in another: at night the sky's cues vanish (docs/simulators.md), and
one post-hoc τ per parameter (:mod:`components.posterior.temperature`) leaves the champion's night marginals covering
the truth 62–64 % of the time with their central 68 % intervals, and its daytime ones 69–74 % (docs/studies/night-base-scale.md). This transform gives each regime its own τ:

    log τ(c) = (1 − p(c)) · log τ_out + p(c) · log τ_in,      p(c) = σ(w · c + b),

with τ_out, τ_in ``(d,)`` and p(c) the probability, from the flow's context c, that the input lies in the regime
(e.g. θ's sun altitude < 0°): a logistic regression of the regime on the contexts of the training pairs
(:func:`fit_gate`). For every c it is an affine map of ε, so the density stays proper:
``log q(z | c) = Σ_d [log N(ε_d / τ_d(c); 0, 1) − log τ_d(c)] + log |det ∂ε/∂z|``. With ``w = 0, b → −∞`` or
``τ_in = τ_out`` it is the single τ.

Used by the ``train`` and ``export`` stages (through :mod:`components.posterior.model`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.distributions import AffineTransform
from zuko.flows import LazyTransform

__all__ = ["RegimeTemperature", "fit_gate"]


class RegimeTemperature(LazyTransform):
    """The flow's last transform ε ↦ ε / τ(c) (see the module's docstring).

    Arguments:
        dim: d, the event size.
        context: the context's size F.

    Buffers: ``log_tau (2, d)`` (rows: outside, inside the regime; zeros: τ = 1), ``weight (F,)`` and ``bias ()``
    of the gate p(c) = σ(w · c + b) (zeros: p = ½).
    """

    log_tau: Tensor
    weight: Tensor
    bias: Tensor

    def __init__(self, dim: int, context: int) -> None:
        super().__init__()
        self.register_buffer("log_tau", torch.zeros(2, dim))
        self.register_buffer("weight", torch.zeros(context))
        self.register_buffer("bias", torch.zeros(()))

    def probability(self, c: Tensor) -> Tensor:
        """p(c), the probability that an input of context ``c (..., F)`` lies in the regime: ``(...)``."""
        return torch.sigmoid(c @ self.weight + self.bias)

    def log_temperature(self, c: Tensor) -> Tensor:
        """log τ(c) ``(..., d)`` for contexts ``c (..., F)``."""
        p = self.probability(c).unsqueeze(-1)
        return self.log_tau[0] + p * (self.log_tau[1] - self.log_tau[0])

    def forward(self, c: Tensor | None = None) -> AffineTransform:
        if c is None:
            raise ValueError("RegimeTemperature needs the context c: τ depends on it")
        return AffineTransform(0.0, torch.exp(-self.log_temperature(c)))


def fit_gate(context: Tensor, inside: Tensor, l2: float = 1e-3) -> tuple[Tensor, Tensor]:
    """Logistic regression of the regime on the context: ``(weight (F,), bias ())`` maximizing the mean log-likelihood
    of ``inside (N,)`` (bool) given ``context (N, F)``, less ``l2/2 · ‖w‖²`` in units of the contexts' standard
    deviations (standardized inside, returned for the raw contexts). Deterministic: L-BFGS from zero in float64.

    Raises:
        ValueError: shapes that do not match, non-finite contexts, or a regime that holds for none or all of the pairs
            (the gate would be a constant, and one of the two τ could not be fitted).
    """
    if context.dim() != 2 or inside.shape != context.shape[:1]:
        raise ValueError(
            f"the gate needs contexts (N, F) and regime labels (N,), got {tuple(context.shape)}, {tuple(inside.shape)}"
        )
    y = inside.to(device=context.device, dtype=torch.float64)
    share = float(y.mean()) if len(y) else 0.0
    if not 0.0 < share < 1.0:
        raise ValueError(
            f"the regime holds for {100 * share:.0f} % of the {len(y)} training pairs: a base scale per regime needs "
            "pairs on both sides of it (or train.temperature_regime: null)"
        )
    c = context.detach().to(torch.float64)
    if not bool(torch.isfinite(c).all()):
        raise ValueError("the contexts are not finite: the gate of the regime's base scale cannot be fitted")
    mean, std = c.mean(0), c.std(0).clamp_min(1e-8)
    cs = (c - mean) / std
    w = torch.zeros(c.shape[1], dtype=torch.float64, device=c.device, requires_grad=True)
    b = torch.zeros((), dtype=torch.float64, device=c.device, requires_grad=True)
    opt = torch.optim.LBFGS([w, b], max_iter=200, tolerance_grad=1e-10, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        loss = F.binary_cross_entropy_with_logits(cs @ w + b, y) + 0.5 * l2 * (w * w).sum()
        loss.backward()
        return loss

    with torch.enable_grad():
        opt.step(closure)
    weight = (w / std).detach()
    return weight, (b - (mean * weight).sum()).detach()
