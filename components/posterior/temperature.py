"""Post-hoc calibration of a trained posterior: the base distribution's scale τ, fitted on held-out simulations.

Each flow maps z to base noise ε = f(z | x), with ε ~ N(0, I) during training. An overconfident flow puts held-out
truths too far out in the base space (E‖ε‖² > d). Tempering widens the base to N(0, diag τ²):

    log q_τ(z | x) = Σ_d [log N(ε_d / τ_d; 0, 1) − log τ_d] + log |det ∂f/∂z|,

a proper density for every τ > 0 (a change of variables of N(0, diag τ²)), so the support and the flow's shape
are kept and only the spread changes. It is the flow's last transform, ``ε ↦ ε / τ``
(:meth:`~components.posterior.model.NPE.set_temperature`), so sampling, densities and the ONNX graphs need nothing
else. τ (one per dimension, shared by an ensemble's members) maximizes the mean log q_τ(θᵢ | xᵢ) of the held-out
pairs (the validation split): for one flow the optimum is τ_d² = mean εᵢ_d²; for an ensemble's mixture it is found
by L-BFGS over log τ. This is temperature scaling (Guo et al. 2017) moved to the flow's base; measured in
BENCHMARKS.md ("Calibration levers").

Used by the ``train`` and ``variant`` stages.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from components.posterior.model import NPE

__all__ = ["base_points", "tempered_nll", "fit_temperature", "calibrate"]


@torch.no_grad()
def base_points(model: NPE, x: Tensor, theta: Tensor, batch: int = 512) -> tuple[Tensor, Tensor]:
    """The untempered base points of held-out pairs: ``ε (K, N, d)`` and ``log|det ∂ε/∂z| (K, N)`` per member.

    ``log q(θ | x) = logsumexp_k [log N(εₖ; 0, I) + ladjₖ] − log K − log|det ∂θ/∂z|``; the last term does not depend
    on τ and is left out. The model's temperature is set to 1 for the call and restored after it.
    """
    saved = model.temperature.clone()
    model.set_temperature(torch.ones_like(saved))
    try:
        eps, ladj = [], []
        for a in range(0, len(theta), batch):
            c = model.context(x[a : a + batch])
            th = model._theta(theta[a : a + batch], c.shape[0])
            z = model.bijection.to_unbounded(th).to(model.dtype)
            parts = [flow(c).transform.call_and_ladj(z) for flow in model.flows]
            eps.append(torch.stack([p[0] for p in parts]).double())
            ladj.append(torch.stack([p[1] for p in parts]).double())
    finally:
        model.set_temperature(saved)
    return torch.cat(eps, dim=1), torch.cat(ladj, dim=1)


def tempered_nll(eps: Tensor, ladj: Tensor, tau: Tensor) -> Tensor:
    """Mean −log q_τ over the pairs (up to the bijection's τ-free Jacobian): ``ε (K, N, d)``, ``ladj (K, N)``, τ (d,)."""
    d = eps.shape[-1]
    members = (-0.5 * (eps / tau) ** 2 - torch.log(tau)).sum(-1) - 0.5 * d * math.log(2 * math.pi) + ladj
    return -(torch.logsumexp(members, dim=0) - math.log(eps.shape[0])).mean()


def fit_temperature(eps: Tensor, ladj: Tensor) -> Tensor:
    """The maximum-likelihood τ ``(d,)`` of base points ``ε (K, N, d)`` with log-Jacobians ``ladj (K, N)``.

    K = 1: τ_d = √(mean ε_d²) exactly. K > 1: L-BFGS on log τ from the members' pooled closed form.
    """
    if eps.dim() != 3 or ladj.shape != eps.shape[:2] or eps.shape[1] < 2:
        raise ValueError(
            f"base points must be (K, N ≥ 2, d) with ladj (K, N), got {tuple(eps.shape)}, {tuple(ladj.shape)}"
        )
    if not bool(torch.isfinite(eps).all()) or not bool(torch.isfinite(ladj).all()):
        raise ValueError("the held-out base points are not finite: the flow maps a held-out θ to infinity")
    eps, ladj = eps.double(), ladj.double()
    start = eps.pow(2).mean(dim=(0, 1)).sqrt()
    if eps.shape[0] == 1:
        return start
    log_tau = start.log().clone().requires_grad_(True)
    opt = torch.optim.LBFGS([log_tau], max_iter=100, tolerance_grad=1e-9, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        loss = tempered_nll(eps, ladj, log_tau.exp())
        loss.backward()
        return loss

    with torch.enable_grad():
        opt.step(closure)
    return log_tau.detach().exp()


def calibrate(model: NPE, x: Tensor, theta: Tensor) -> dict[str, float]:
    """Fit τ on held-out pairs ``x (N, …)``, ``θ (N, d)`` (physical units), set it on ``model``, and report it.

    Returns ``{"temperature.<name>": τ_d, …, "heldout_nll_gain": …}``: τ per parameter (the base's dimensions, in
    the order of ``model.box.names``) and the held-out NLL saved by τ (nats per pair, ≥ 0).
    """
    eps, ladj = base_points(model, x, theta)
    tau = fit_temperature(eps, ladj)
    before = float(tempered_nll(eps, ladj, torch.ones_like(tau)))
    after = float(tempered_nll(eps, ladj, tau))
    model.set_temperature(tau)
    out = {f"temperature.{name}": float(t) for name, t in zip(model.box.names, tau.tolist(), strict=True)}
    return {**out, "heldout_nll_gain": before - after}
