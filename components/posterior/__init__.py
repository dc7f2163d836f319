"""Neural posterior estimation (NPE) of the weather parameters θ from image features x.

* :mod:`~components.posterior.bijection` — the box ↔ ℝᵈ scaled logit in torch, and a box of any dimension;
* :mod:`~components.posterior.model` — :class:`NPE` (embedding → context → conditional NSF over z, ensembles);
* :mod:`~components.posterior.mixture` — seeded sampling of zuko flows, the equal-weight mixture of an ensemble;
* :mod:`~components.posterior.loss` — the NPE loss (physical units) and balanced NPE's penalty;
* :mod:`~components.posterior.checkpoint` — atomic checkpoint files;
* :mod:`~components.posterior.train` — :func:`train` with :class:`TrainingConfig`, returning a :class:`History`;
* :mod:`~components.posterior.temperature` — post-hoc calibration: the flows' base scale τ fitted on held-out pairs;
* :mod:`~components.posterior.regime` — a base scale per regime (day and night), blended by a gate on the context.

Used by the ``train`` and ``export`` stages (``metrics``, ``settings`` and ``temperature`` by
``train`` only).
"""

from components.posterior.bijection import IntervalBox, ScaledLogit, as_interval_box
from components.posterior.loss import balance_penalty, npe_loss
from components.posterior.model import NPE, FlowConfig
from components.posterior.train import EpochRecord, History, TrainingConfig, train

__all__ = [
    "IntervalBox",
    "ScaledLogit",
    "as_interval_box",
    "NPE",
    "FlowConfig",
    "npe_loss",
    "balance_penalty",
    "TrainingConfig",
    "EpochRecord",
    "History",
    "train",
]
