"""Drawing from zuko flows with an explicit ``torch.Generator``, and the equal-weight mixture of an ensemble.

zuko's ``NormalizingFlow.sample`` draws its base noise from torch's global RNG. pidc draws every random number
from an explicit seed, so sampling here pushes noise ``ε ~ N(0, I)`` drawn from a caller's generator through the
inverse transform: ``z = f⁻¹(ε | c)``, ``log q(z | c) = log N(ε; 0, I) − log|det ∂f⁻¹/∂ε|``. This relies on the
flow's base being the standard normal, which is how :func:`zuko.flows.NSF` builds it (fixed buffers).

Used by the ``train`` and ``export`` stages.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Size, Tensor
from torch.distributions import Distribution
from zuko.distributions import NormalizingFlow

__all__ = ["standard_normal", "draw_flow", "EqualMixture"]


def standard_normal(shape: Sequence[int], generator: torch.Generator, *, like: Tensor) -> Tensor:
    """ε ~ N(0, I) of ``shape`` drawn on the generator's device, then moved to ``like``'s device and dtype."""
    eps = torch.randn(tuple(shape), generator=generator, dtype=torch.float64, device=generator.device)
    return eps.to(device=like.device, dtype=like.dtype)


def draw_flow(dist: NormalizingFlow, eps: Tensor) -> tuple[Tensor, Tensor]:
    """Push base noise through a conditional flow: ``eps (..., d) → (z (..., d), log q(z) (...))``.

    ``eps`` must broadcast against the flow's batch shape (e.g. ``(n, B, d)`` for a flow conditioned on ``B``
    contexts).
    """
    z, ladj = dist.transform.inv.call_and_ladj(eps)
    return z, dist.base.log_prob(eps) - ladj


class EqualMixture(Distribution):
    """The equal-weight mixture of K flows (an ensemble), ``q(z) = (1/K) Σₖ qₖ(z)``.

    Arguments:
        components: K conditional flows with the same batch and event shapes (zuko ``NormalizingFlow``).
    """

    arg_constraints: dict = {}
    has_rsample = False

    def __init__(self, components: Sequence[NormalizingFlow]) -> None:
        if len(components) == 0:
            raise ValueError("a mixture needs at least one component")
        self.components = list(components)
        first = self.components[0]
        super().__init__(first.batch_shape, first.event_shape, validate_args=False)

    def log_prob(self, value: Tensor) -> Tensor:
        """log q(z) = logsumexp_k log qₖ(z) − log K; shape ``value.shape[:-1]``."""
        parts = torch.stack([c.log_prob(value) for c in self.components])
        return torch.logsumexp(parts, dim=0) - math.log(len(self.components))

    def sample_and_log_prob(self, shape: Sequence[int], generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """``shape + batch_shape`` draws (component chosen uniformly per draw) and their mixture log-density."""
        full = Size(shape) + self.batch_shape
        d = self.event_shape
        like = self.components[0].base.base_dist.loc
        eps = standard_normal(full + d, generator, like=like)
        which = torch.randint(len(self.components), tuple(full), generator=generator, device=generator.device)
        which = which.to(like.device)
        z = torch.zeros_like(eps)
        for k, comp in enumerate(self.components):
            zk, _ = draw_flow(comp, eps)
            z = torch.where((which == k).unsqueeze(-1), zk, z)
        return z, self.log_prob(z)

    def sample(self, sample_shape: Sequence[int] = Size(), generator: torch.Generator | None = None) -> Tensor:
        """Draws of shape ``sample_shape + batch_shape + event_shape``; ``generator`` is required (no global RNG)."""
        if generator is None:
            raise ValueError("EqualMixture.sample needs an explicit torch.Generator (pidc uses no global RNG state)")
        with torch.no_grad():
            return self.sample_and_log_prob(sample_shape, generator)[0]
