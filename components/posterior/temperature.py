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
docs/studies/temperature.md.

A model with a regime temperature (:mod:`components.posterior.regime`) has two τ, blended per input by a gate on its
context: :func:`fit_regime_gate` fits the gate on the training pairs (the regime is known from their θ), then
:func:`calibrate` fits both τ by maximum likelihood on the held-out pairs, each pair weighted by its gate
(docs/studies/night-base-scale.md).

Used by the ``train`` stage (the grid and its variants).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from components.posterior.model import NPE
from components.posterior.regime import fit_gate

__all__ = [
    "Regime",
    "base_points",
    "tempered_nll",
    "fit_temperature",
    "fit_regime_gate",
    "calibrate",
    "calibrate_post_hoc",
]


@dataclass(frozen=True)
class Regime:
    """The inputs whose true ``θ[index] < below`` (e.g. the sun below the horizon), named ``name`` in messages."""

    index: int
    below: float
    name: str

    def holds(self, theta: Tensor) -> Tensor:
        """Whether each θ ``(N, d)`` (physical units) lies in the regime: ``(N,)`` bool."""
        return theta[:, self.index] < self.below


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
    """Mean −log q_τ over the pairs (up to the bijection's τ-free Jacobian): ``ε (K, N, d)``, ``ladj (K, N)``, τ ``(d,)``
    or one per pair ``(N, d)``."""
    d = eps.shape[-1]
    members = (-0.5 * (eps / tau) ** 2 - torch.log(tau)).sum(-1) - 0.5 * d * math.log(2 * math.pi) + ladj
    return -(torch.logsumexp(members, dim=0) - math.log(eps.shape[0])).mean()


def _checked(eps: Tensor, ladj: Tensor) -> tuple[Tensor, Tensor]:
    if eps.dim() != 3 or ladj.shape != eps.shape[:2] or eps.shape[1] < 2:
        raise ValueError(
            f"base points must be (K, N ≥ 2, d) with ladj (K, N), got {tuple(eps.shape)}, {tuple(ladj.shape)}"
        )
    if not bool(torch.isfinite(eps).all()) or not bool(torch.isfinite(ladj).all()):
        raise ValueError("the held-out base points are not finite: the flow maps a held-out θ to infinity")
    return eps.double(), ladj.double()


def _maximize(eps: Tensor, ladj: Tensor, start: Tensor, tau_of: Callable[[Tensor], Tensor]) -> Tensor:
    """L-BFGS on ``log τ`` from ``start``: the maximum of the tempered likelihood with τ = ``tau_of(exp(log τ))``."""
    log_tau = start.log().clone().requires_grad_(True)
    opt = torch.optim.LBFGS([log_tau], max_iter=100, tolerance_grad=1e-9, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        loss = tempered_nll(eps, ladj, tau_of(log_tau))
        loss.backward()
        return loss

    with torch.enable_grad():
        opt.step(closure)
    return log_tau.detach().exp()


def fit_temperature(eps: Tensor, ladj: Tensor, gate: Tensor | None = None) -> Tensor:
    """The maximum-likelihood τ of base points ``ε (K, N, d)`` with log-Jacobians ``ladj (K, N)``.

    Without ``gate``: τ ``(d,)``; K = 1: τ_d = √(mean ε_d²) exactly, K > 1: L-BFGS on log τ from the members' pooled
    closed form. With ``gate`` p ``(N,)`` in [0, 1], each pair's probability of lying in the regime: τ ``(2, d)``
    (rows: outside, inside the regime), pair i tempered by log τᵢ = (1 − pᵢ) log τ_out + pᵢ log τ_in; L-BFGS from the
    closed forms of the pairs on either side of p = ½ (of all pairs weighted by the gate for a side of fewer than two).
    Each side needs two pairs or their weight (Σ (1 − pᵢ) ≥ 2, Σ pᵢ ≥ 2), else ``ValueError``.
    """
    eps, ladj = _checked(eps, ladj)
    if gate is None:
        start = eps.pow(2).mean(dim=(0, 1)).sqrt()
        if eps.shape[0] == 1:
            return start
        return _maximize(eps, ladj, start, torch.exp)
    p = torch.as_tensor(gate, dtype=torch.float64, device=eps.device)
    if p.shape != eps.shape[1:2] or not bool(((p >= 0) & (p <= 1)).all()):
        raise ValueError(f"the gate must be {eps.shape[1]} probabilities in [0, 1], one per pair, got {tuple(p.shape)}")
    weights = torch.stack([1.0 - p, p])  # each pair's weight outside and inside the regime
    effective = weights.sum(dim=1)
    sides = [p < 0.5, p >= 0.5]
    if not all(bool(side.sum() >= 2) or float(e) >= 2.0 for side, e in zip(sides, effective, strict=True)):
        raise ValueError(
            f"the gate puts {int(sides[1].sum())} of the {len(p)} held-out pairs in the regime, a weight of "
            f"{float(effective[1]):.2f} (Σ of its probabilities) against {float(effective[0]):.2f}: a base scale per "
            "regime needs two pairs or a weight of two on each side (a larger validation split, or "
            "train.temperature_regime: null)"
        )
    # the closed form of each side's pairs, or of all pairs weighted by the gate where a side holds fewer than two
    start = torch.stack(
        [
            eps[:, side].pow(2).mean(dim=(0, 1)).sqrt()
            if bool(side.sum() >= 2)
            else (eps.pow(2).mean(dim=0) * w.unsqueeze(-1)).sum(dim=0).div(w.sum()).sqrt()
            for side, w in zip(sides, weights, strict=True)
        ]
    )
    w = p.unsqueeze(-1)
    return _maximize(eps, ladj, start, lambda log_tau: torch.exp((1 - w) * log_tau[0] + w * log_tau[1]))


@torch.no_grad()
def _contexts(model: NPE, x: Tensor, batch: int = 4096) -> Tensor:
    return torch.cat([model.context(x[a : a + batch]) for a in range(0, len(x), batch)])


def fit_regime_gate(model: NPE, x: Tensor, theta: Tensor, regime: Regime) -> dict[str, float]:
    """Fit the gate of ``model``'s regime temperature on training pairs ``x (N, …)``, ``θ (N, d)`` (physical units):
    a logistic regression of ``regime.holds(θ)`` on the contexts (:func:`~components.posterior.regime.fit_gate`).

    Returns ``{"regime_share": …, "regime_gate_train_accuracy": …}``.
    """
    context = _contexts(model, x)
    inside = regime.holds(theta).to(context.device)
    weight, bias = fit_gate(context, inside)
    model.set_regime_gate(weight, bias)
    accuracy = float(((model.regime_probability(context) >= 0.5) == inside).double().mean())
    return {"regime_share": float(inside.double().mean()), "regime_gate_train_accuracy": accuracy}


def calibrate(model: NPE, x: Tensor, theta: Tensor, regime: Regime | None = None) -> dict[str, float]:
    """Fit τ on held-out pairs ``x (N, …)``, ``θ (N, d)`` (physical units), set it on ``model``, and report it.

    A model with a regime temperature needs ``regime`` and its fitted gate (:func:`fit_regime_gate`): both τ are fitted,
    each pair weighted by its gate.

    Returns ``{"temperature.<name>": τ_d, …, "heldout_nll_gain": …}``: τ per parameter (the base's dimensions, in
    the order of ``model.box.names``) and the held-out NLL saved by τ (nats per pair, ≥ 0); with a regime, τ outside it
    as ``temperature.<name>``, inside it as ``temperature_<regime>.<name>``, and ``regime_gate_accuracy``, the share
    of the held-out pairs on the side of p = ½ that their θ puts them.
    """
    if model.config.regime_temperature != (regime is not None):
        raise ValueError(
            "a model with a regime temperature needs the regime (train.temperature_regime), and only such a model: "
            f"regime_temperature={model.config.regime_temperature}, regime={regime}"
        )
    eps, ladj = base_points(model, x, theta)
    gate = None
    extra: dict[str, float] = {}
    if regime is not None:
        gate = model.regime_probability(_contexts(model, x)).double()
        extra["regime_gate_accuracy"] = float(((gate >= 0.5) == regime.holds(theta).to(gate.device)).double().mean())
    tau = fit_temperature(eps, ladj, gate)
    per_pair = tau if gate is None else torch.exp((1 - gate[:, None]) * tau[0].log() + gate[:, None] * tau[1].log())
    before = float(tempered_nll(eps, ladj, torch.ones(model.dim, dtype=torch.float64, device=eps.device)))
    after = float(tempered_nll(eps, ladj, per_pair))
    model.set_temperature(tau)
    names = model.box.names
    rows = [tau] if gate is None else [tau[0], tau[1]]
    prefixes = ["temperature"] if gate is None else ["temperature", f"temperature_{regime.name}"]  # type: ignore[union-attr]
    out = {
        f"{prefix}.{name}": float(t)
        for prefix, row in zip(prefixes, rows, strict=True)
        for name, t in zip(names, row.tolist(), strict=True)
    }
    return {**out, **extra, "heldout_nll_gain": before - after}


def calibrate_post_hoc(
    model: NPE, train: tuple[Tensor, Tensor] | None, heldout: tuple[Tensor, Tensor], regime: Regime | None
) -> dict[str, float]:
    """The pipeline's post-hoc calibration of a trained ``model``: with a ``regime``, its gate on the ``train`` pairs
    ``(x, θ)`` (:func:`fit_regime_gate`; ``train`` may be None without a regime), then τ on the ``heldout`` pairs
    (:func:`calibrate`). Returns both reports, merged."""
    if regime is None:
        return calibrate(model, *heldout)
    if train is None:
        raise ValueError(f"the regime {regime.name!r} needs training pairs to fit its gate on")
    return fit_regime_gate(model, *train, regime) | calibrate(model, *heldout, regime)
