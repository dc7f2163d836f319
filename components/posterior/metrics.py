"""Scores of a trained posterior on a labelled split (the ``train`` stage's test metrics)."""

from __future__ import annotations

import numpy as np
import torch

from components.posterior.model import NPE

__all__ = ["mean_nll"]


@torch.no_grad()
def mean_nll(model: NPE, x: torch.Tensor, theta: np.ndarray, batch: int = 512) -> float:
    """−(1/N) Σᵢ log q(θᵢ | xᵢ) over a split of N pairs, in nats (physical units of θ).

    Arguments:
        model: the posterior q(θ | x).
        x: ``(N, …)`` model inputs (cached features or a trainable backbone's preprocessed images).
        theta: ``(N, 6)`` true weather parameters, physical units.
    """
    th = torch.from_numpy(theta).to(torch.float32)
    total = 0.0
    for s in range(0, len(th), batch):
        total += float(model.log_prob(th[s : s + batch], x[s : s + batch]).double().sum())
    return -total / len(th)
