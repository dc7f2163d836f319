"""The scaled-logit bijection between a parameter box and ℝᵈ, in torch.

This is the torch twin of :func:`components.core.weather.to_unbounded`, :func:`~components.core.weather.to_physical`
and :func:`~components.core.weather.log_abs_det_jacobian`: the same formulas, the same
:data:`~components.core.weather.EDGE_EPS`, so that in float64 both give the same numbers (to ~1e-12). Per parameter
``i``:

    u = (θ − low) / (high − low), clipped to [ε, 1 − ε]        (ε = EDGE_EPS)
    z = logit(u) = log u − log(1 − u)
    θ = low + (high − low)·σ(z), clamped to [low, high]
    log |∂θ/∂z| = log(high − low) + log σ(z) + log σ(−z)

so that densities convert as ``log q_θ(θ) = log q_z(z) − log|det ∂θ/∂z|``.

:class:`components.core.weather.Box` serves boxes of any dimension ``d`` (θ ∈ ℝᵈ): the 6-D weather prior, and the
1–2-D toys the posterior is tested on (``IntervalBox`` is the same class).

Used by the ``train`` and ``export`` stages.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from components.core import weather

__all__ = ["IntervalBox", "as_interval_box", "ScaledLogit", "Z_MAX"]

#: |z| of a point on a face of the box: logit(1 − EDGE_EPS) ≈ 13.8155.
Z_MAX: float = math.log1p(-weather.EDGE_EPS) - math.log(weather.EDGE_EPS)


#: The box of any dimension is :class:`components.core.weather.Box` (kept under this name for the posterior's API).
IntervalBox = weather.Box


def as_interval_box(box: weather.Box) -> weather.Box:
    """Check that ``box`` is a :class:`components.core.weather.Box` (of any dimension); anything else is a ``TypeError``."""
    if isinstance(box, weather.Box):
        return box
    raise TypeError(f"box must be a components.core.weather.Box, got {type(box).__name__}")


class ScaledLogit(nn.Module):
    """θ ∈ [low, high]ᵈ ↔ z ∈ ℝᵈ, the scaled logit of :mod:`components.core.weather`, as a torch module.

    The box is stored as float64 buffers ``low`` and ``high`` (shape ``(d,)``); every method computes in the dtype
    of its input (pass float64 for the exact numbers of the numpy version).

    Arguments:
        box: the prior box (:class:`components.core.weather.Box` or :class:`IntervalBox`).
    """

    low: Tensor
    high: Tensor

    def __init__(self, box: weather.Box) -> None:
        super().__init__()
        b = as_interval_box(box)
        self.register_buffer("low", torch.tensor(b.low, dtype=torch.float64))
        self.register_buffer("high", torch.tensor(b.high, dtype=torch.float64))

    @property
    def dim(self) -> int:
        return int(self.low.numel())

    def _bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        return self.low.to(like), self.high.to(like)

    def to_unbounded(self, theta: Tensor) -> Tensor:
        """z = logit(u), u = (θ − low)/(high − low) clipped to [ε, 1 − ε]; ``(..., d) → (..., d)``; finite on the faces."""
        low, high = self._bounds(theta)
        u = ((theta - low) / (high - low)).clamp(weather.EDGE_EPS, 1.0 - weather.EDGE_EPS)
        return torch.log(u) - torch.log1p(-u)

    def to_physical(self, z: Tensor) -> Tensor:
        """θ = low + (high − low)·σ(z), clamped to the closed box; ``(..., d) → (..., d)``."""
        low, high = self._bounds(z)
        u = 0.5 * (1.0 + torch.tanh(0.5 * z))  # the stable sigmoid of the numpy version
        return torch.minimum(torch.maximum(low + (high - low) * u, low), high)

    def log_abs_det_jacobian(self, z: Tensor) -> Tensor:
        """log |det ∂θ/∂z| at z, summed over the d parameters; ``(..., d) → (...)``.

        ``log σ(z) + log σ(−z) = −softplus(−z) − softplus(z)``, with softplus as ``logaddexp(0, ·)`` (torch's
        ``softplus`` switches to the identity above 20, which differs by ~2e-9).
        """
        low, high = self._bounds(z)
        zero = torch.zeros((), dtype=z.dtype, device=z.device)
        per = torch.log(high - low) - torch.logaddexp(zero, -z) - torch.logaddexp(zero, z)
        return per.sum(dim=-1)

    def contains(self, theta: Tensor) -> Tensor:
        """Boolean mask ``(...)``: θ ``(..., d)`` inside the closed box (compared in float64)."""
        t = theta.to(torch.float64)
        return ((t >= self.low) & (t <= self.high)).all(dim=-1)

    def clamp_inward(self, theta: Tensor) -> Tensor:
        """Clamp θ to the box with bounds rounded *inward* to θ's dtype, so that the result is inside the float64 box."""
        low, high = self._bounds(theta)
        low = torch.where(low.double() < self.low, torch.nextafter(low, torch.full_like(low, math.inf)), low)
        high = torch.where(high.double() > self.high, torch.nextafter(high, torch.full_like(high, -math.inf)), high)
        return torch.minimum(torch.maximum(theta, low), high)

    def extra_repr(self) -> str:
        pairs: Sequence[str] = [
            f"[{lo:g}, {hi:g}]" for lo, hi in zip(self.low.tolist(), self.high.tolist(), strict=False)
        ]
        return "box=" + " × ".join(pairs)
