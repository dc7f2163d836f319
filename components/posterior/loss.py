"""The NPE loss and the balancing penalty of balanced NPE (Delaunoy et al., 2022; 2023).

NPE loss (here in PHYSICAL units): ``L = E_{p(θ,x)}[−log q(θ | x)]``, with log q(θ | x) of
:meth:`~components.posterior.model.NPE.log_prob` (Jacobian of the bijection included). In z-space the loss
``E[−log q_z(z | x)]`` differs by ``E[log|det ∂θ/∂z|]``, a θ-only term: same gradients, same optimum; the
physical value is the one comparable across models and bijections.

Balanced NPE views the estimator as the classifier ``d(θ, x) = σ(log q(θ | x) − log p(θ))`` between joint pairs
(θ, x) ~ p(θ, x) and marginal pairs (θ', x) ~ p(θ)p(x). The Bayes-optimal classifier satisfies the balancing
condition ``E_joint[d] + E_marginal[d] = 1``; the penalty is its squared violation, estimated on a batch, with
marginal pairs made by rolling θ by one place within the (shuffled) batch:

    L_BNPE = L + λ · (E_joint[d] + E_marginal[d] − 1)².

The square of a batch mean, as in the authors' code, is biased: E[(ā)²] = (E a)² + Var(a)/B, and the variance term's
gradient pushes every d(θᵢ, xᵢ) towards a common value, i.e. sharpens q at the joint pairs, the overconfidence
balancing is meant to remove (on the 2-D toy of the tests: coverage area −0.052 biased vs −0.039 unbiased, KL 0.12
vs 0.10 nat). pidc uses the unbiased product of the means over the two halves of the batch,
``ā₁ · ā₂ with aᵢ = d(θᵢ, xᵢ) + d(θ'ᵢ, xᵢ) − 1`` (a batch estimate that can be slightly negative; its expectation
is the squared violation).

For an ensemble (K flows), both terms are averaged over the members (each member is its own estimator).

Used by the ``train`` stage; the ``export`` stage imports it only through
:mod:`components.posterior`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from components.posterior.model import NPE

__all__ = ["LossParts", "balance_penalty", "npe_loss", "npe_loss_terms"]


@dataclass(frozen=True)
class LossParts:
    """The loss of one batch and its two terms.

    Attributes:
        loss: ``nll + balance · penalty``, a scalar tensor (differentiable).
        nll: mean −log q(θ | x) over the batch and members, physical units (float).
        penalty: the balancing penalty's batch estimate (0.0 when not computed; may be slightly negative).
    """

    loss: Tensor
    nll: float
    penalty: float


def balance_penalty(
    log_q_joint: Tensor, log_q_marginal: Tensor, log_prior_joint: Tensor, log_prior_marginal: Tensor
) -> Tensor:
    """Unbiased batch estimate of ``(E_joint[d] + E_marginal[d] − 1)²``, d = σ(log q − log p), over the last axis.

    Arguments:
        log_q_joint: log q(θᵢ | xᵢ), shape ``(..., B)``.
        log_q_marginal: log q(θ'ᵢ | xᵢ) for θ' independent of x, shape ``(..., B)``.
        log_prior_joint: log p(θᵢ) in the same units, broadcastable.
        log_prior_marginal: log p(θ'ᵢ) in the same units, broadcastable.

    Returns:
        shape ``(...)``: ``ā₁ · ā₂``, the means of ``aᵢ = d(θᵢ, xᵢ) + d(θ'ᵢ, xᵢ) − 1`` over the two halves of the
        batch (an odd last element is left out; a batch of one gives ``a₁²``). Zero in expectation for the exact
        posterior.
    """
    a = torch.sigmoid(log_q_joint - log_prior_joint) + torch.sigmoid(log_q_marginal - log_prior_marginal) - 1.0
    h = a.shape[-1] // 2
    if h == 0:
        return a.mean(dim=-1).square()
    return a[..., :h].mean(dim=-1) * a[..., h : 2 * h].mean(dim=-1)


def npe_loss_terms(model: NPE, theta: Tensor, x: Tensor, *, balance: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """The (balanced) NPE loss of a batch as scalar tensors ``(loss, nll, penalty)``, physical units.

    The tensor-only core of :func:`npe_loss` (no conversion to Python numbers), which ``torch.compile`` traces into
    one graph. Arguments as :func:`npe_loss`; ``penalty`` is a zero tensor for plain NPE (``balance`` = 0).
    """
    context = model.context(x)
    log_q = model.log_prob_members(theta, context)  # (K, B)
    nll = -log_q.mean()
    if balance == 0.0:
        return nll, nll, torch.zeros_like(nll)
    log_prior = torch.full((), -model.box.log_volume(), dtype=log_q.dtype, device=log_q.device)
    log_q_marginal = model.log_prob_members(theta.roll(1, dims=0), context)
    penalty = balance_penalty(log_q, log_q_marginal, log_prior, log_prior).mean()
    return nll + balance * penalty, nll, penalty


def npe_loss(model: NPE, theta: Tensor, x: Tensor, *, balance: float = 0.0) -> LossParts:
    """The (balanced) NPE loss of a batch, physical units.

    Arguments:
        model: the estimator; its prior is the uniform distribution on ``model.box`` (log p(θ) = −log volume).
        theta: ``(B, d)`` parameters drawn from that prior, inside the box.
        x: ``(B, *input_shape)`` the matching simulations.
        balance: λ ≥ 0; 0 = plain NPE (the penalty is not computed).
    """
    loss, nll, penalty = npe_loss_terms(model, theta, x, balance=balance)
    return LossParts(loss, float(nll.detach()), float(penalty.detach()))
