"""The pipeline's flow and training settings: the ``train`` section of ``params.yaml`` mapped onto the library classes.

:class:`~components.posterior.model.FlowConfig` and :class:`~components.posterior.train.TrainingConfig` keep defaults
for direct library use (benchmarks, tests); the pipeline depends on none of them: every field is set here from
``params.yaml`` (a field added to either class without a setting here is an error, not a silent default).

Used by the ``train`` and ``variant`` stages.
"""

from __future__ import annotations

from dataclasses import fields
from typing import TYPE_CHECKING, Any

from components.posterior.model import FlowConfig
from components.posterior.train import TrainingConfig

if TYPE_CHECKING:
    from components.core.config import TrainConfig

__all__ = ["flow_config", "training_config"]


def _every_field(cls: type, settings: dict[str, Any]) -> dict[str, Any]:
    """``settings``, checked to set every field of the dataclass ``cls`` (and nothing else)."""
    names = {f.name for f in fields(cls)}
    if set(settings) != names:
        missing, extra = sorted(names - set(settings)), sorted(set(settings) - names)
        raise TypeError(f"{cls.__name__} settings from params.yaml: missing {missing}, unknown {extra}")
    return settings


def flow_config(train_section: TrainConfig, ensemble: int | None = None) -> FlowConfig:
    """The conditional flow of ``train.flow``; ``ensemble`` (a variant's) replaces ``train.flow.ensemble``."""
    f = train_section.flow
    return FlowConfig(
        **_every_field(
            FlowConfig,
            dict(
                transforms=f.transforms,
                hidden_features=tuple(f.hidden_features),
                bins=f.bins,
                passes=f.passes,
                standardize=f.standardize,
                ensemble=f.ensemble if ensemble is None else ensemble,
            ),
        )
    )


def training_config(
    train_section: TrainConfig, *, trainable: bool, seed: int, balance: float | None = None
) -> TrainingConfig:
    """The training settings of ``train``: ``embedding_epochs`` epochs for a backbone trained jointly with the flow
    (``trainable``), else ``epochs``; ``seed`` is the caller's; ``balance`` (a variant's) replaces ``train.balance``."""
    t = train_section
    return TrainingConfig(
        **_every_field(
            TrainingConfig,
            dict(
                epochs=t.embedding_epochs if trainable else t.epochs,
                batch_size=t.batch_size,
                lr=t.lr,
                weight_decay=t.weight_decay,
                schedule=t.schedule,
                min_lr=t.min_lr,
                plateau_factor=t.plateau_factor,
                plateau_patience=t.plateau_patience,
                patience=t.patience,
                min_delta=t.min_delta,
                clip_norm=t.clip_norm,
                seed=seed,
                balance=t.balance if balance is None else balance,
            ),
        )
    )
