"""The pipeline's flow and training settings: the ``train`` section of ``params.yaml`` mapped onto the library classes.

:class:`~components.posterior.model.FlowConfig` and :class:`~components.posterior.train.TrainingConfig` keep defaults
for direct library use (benchmarks, tests); the pipeline depends on none of them: every field is set here from
``params.yaml`` (a field added to either class without a setting here is an error, not a silent default).

Used by the ``train`` stage (the grid and its variants).
"""

from __future__ import annotations

import math
from dataclasses import fields
from typing import TYPE_CHECKING, Any

from components.core.checks import whole_number
from components.posterior.model import FlowConfig
from components.posterior.temperature import Regime
from components.posterior.train import TrainingConfig

if TYPE_CHECKING:
    from components.core.config import FewFeaturesRecipeConfig, TrainConfig
    from components.core.weather import Box

__all__ = [
    "flow_config",
    "training_config",
    "temperature_regime",
    "epochs_for",
    "few_features",
    "recipe_for",
    "patience_for",
    "hidden_for",
    "input_noise_for",
    "compile_for",
    "ensemble_for",
    "small_data_scale",
]


def _every_field(cls: type, settings: dict[str, Any]) -> dict[str, Any]:
    """``settings``, checked to set every field of the dataclass ``cls`` (and nothing else)."""
    names = {f.name for f in fields(cls)}
    if set(settings) != names:
        missing, extra = sorted(names - set(settings)), sorted(set(settings) - names)
        raise TypeError(f"{cls.__name__} settings from params.yaml: missing {missing}, unknown {extra}")
    return settings


def small_data_scale(train_section: TrainConfig, size: int) -> float:
    """s = max(1, ``train.scale_to`` / size): how much smaller than ``scale_to`` the training set is.

    Below ``scale_to`` images a model trains s× more epochs with s× the patience (an epoch of few images is few
    optimizer steps) through a flow whose hidden widths shrink as 1/√s (fewer weights to fit): the rule measured on
    three SBI problems with exact posteriors (``benchmarks/bench_sbi_problems.py``, docs/studies/sbi-problems.md). At and above
    ``scale_to`` images the settings are ``train``'s as written."""
    whole_number("size", size, low=1)
    return max(1.0, train_section.scale_to / size)


def hidden_for(train_section: TrainConfig, size: int) -> tuple[int, ...]:
    """``train.flow.hidden_features`` for ``size`` training images: each width w → max(32, 16·round(w/√s/16))
    below ``scale_to`` images (never wider than w)."""
    s = small_data_scale(train_section, size)
    widths = tuple(train_section.flow.hidden_features)
    if s == 1.0:
        return widths
    return tuple(min(w, max(32, 16 * round(w / math.sqrt(s) / 16))) for w in widths)


def ensemble_for(train_section: TrainConfig, size: int) -> int:
    """The flows of a model of ``size`` training images: ``train.flow.ensemble`` from ``train.ensemble_min_size``
    images, one below. Two flows trained on the same batches from independent initializations average away part
    of each one's idiosyncratic overconfidence and sharpen the posterior where the data suffice: on the 50k cues
    (one seed, the whole test split) 6.68 → 7.08 nats with calibration error 0.019 → 0.034 without input noise
    (docs/studies/flow-ensemble.md)."""
    whole_number("size", size, low=1)
    return train_section.flow.ensemble if size >= train_section.ensemble_min_size else 1


def flow_config(train_section: TrainConfig, *, size: int, trainable: bool, ensemble: int | None = None) -> FlowConfig:
    """The conditional flow of ``train.flow`` for a model of ``size`` training images (:func:`hidden_for`,
    :func:`ensemble_for`); ``ensemble`` (a variant's) replaces that count.

    The context network (``train.flow.context_layers``) sits between frozen features and the flows; a backbone
    trained jointly with the flow (``trainable``, the ``cnn``) is itself that learned map, and gets none: measured in
    the pipeline, the network behind the cnn cost it 0.2–0.3 nats at every size, while it added 0.2–0.6 to the cues
    and tiny models (docs/studies/context-network.md)."""
    f = train_section.flow
    return FlowConfig(
        **_every_field(
            FlowConfig,
            dict(
                transforms=f.transforms,
                hidden_features=hidden_for(train_section, size),
                bins=f.bins,
                passes=f.passes,
                standardize=f.standardize,
                ensemble=ensemble_for(train_section, size) if ensemble is None else ensemble,
                context_layers=() if trainable else tuple(f.context_layers),
                regime_temperature=_regime_on(train_section),
            ),
        )
    )


def _regime_on(train_section: TrainConfig) -> bool:
    """Whether the flows get a second base scale τ: ``train.temperature`` on and a ``train.temperature_regime``."""
    return train_section.temperature and train_section.temperature_regime is not None


def temperature_regime(train_section: TrainConfig, box: Box) -> Regime | None:
    """The regime of the flows' second base scale τ (``train.temperature_regime``, θ's index in ``box``), or None: one
    τ (no regime given, or ``train.temperature`` off)."""
    r = train_section.temperature_regime
    if r is None or not _regime_on(train_section):
        return None
    return Regime(index=list(box.names).index(r.parameter), below=r.below, name=r.name)


def few_features(train_section: TrainConfig, features: int) -> bool:
    """Whether ``features`` frozen input features are few: fewer than ``train.input_noise_min_features``.

    A handful of informative numbers (the SBI problems' 2–10) rather than a backbone's hundreds of redundant features
    (256–2048): such an input gets no input noise (:func:`input_noise_for`) and at least ``train.few_features_epochs``
    epochs (:func:`epochs_for`). No model of the pipeline has few features."""
    whole_number("features", features, low=1)
    return features < train_section.input_noise_min_features


def epochs_for(train_section: TrainConfig, size: int, *, trainable: bool, features: int | None = None) -> int:
    """The epochs of a model trained on ``size`` images of ``features`` frozen features: ``min(⌈epochs·s⌉,
    ⌈sample_budget / size⌉)`` with s of :func:`small_data_scale`; ``embedding_epochs`` and ``embedding_sample_budget``
    (and no scaling, each epoch being costly) for a backbone trained jointly with the flow.

    With :func:`few_features` the first term is at least ``train.few_features_epochs`` (the cap stays): on the 2-D
    SBI problems the 10k models still improved at their last epoch (67 of 67), while the 1k ones, already at ⌈60·s⌉
    ≈ 667 epochs, peaked mid-run (docs/studies/sbi-small-inputs.md). ``features=None`` (not given): many."""
    t = train_section
    s = small_data_scale(t, size)
    if trainable:
        return max(1, min(t.embedding_epochs, math.ceil(t.embedding_sample_budget / size)))
    epochs = math.ceil(t.epochs * s)
    if features is not None and t.few_features_epochs is not None and few_features(t, features):
        epochs = max(epochs, t.few_features_epochs)
    return max(1, min(epochs, math.ceil(t.sample_budget / size)))


def patience_for(train_section: TrainConfig, size: int) -> int | None:
    """Early stopping's patience for ``size`` training images: ``⌈patience·s⌉`` (:func:`small_data_scale`); ``None``
    (``train.patience: null``): no early stopping."""
    if train_section.patience is None:
        return None
    return math.ceil(train_section.patience * small_data_scale(train_section, size))


def input_noise_for(train_section: TrainConfig, size: int, *, trainable: bool, features: int) -> float:
    """σ of the training-input noise for ``size`` training images of ``features`` frozen features:
    ``train.input_noise`` × √(``scale_to`` / size) up to ``train.input_noise_max_size`` images, 0 above, 0 for fewer
    than ``train.input_noise_min_features`` features and for a trainable backbone (it sees images, not features); the
    same for one flow and for an ensemble's.
    The noise a flow needs falls as 1/√n with its data: measured on the version-3 cues, σ = 0.3 at 5k and 0.15 at 20k
    brought the tempered flows from 0.104 and 0.091 to 0.065 and 0.020 at no loss of information (docs/studies/cues-3-input-noise.md,
    docs/studies/longer-training.md). With the version-6 cues (the weather reader) the
    coverage gap crosses zero near σ = 0.50 at 5k, 0.23 at 20k and 0.16–0.20 at 50k (two flows): 1/√n again, with
    no room for the 1/√K that an ensemble of K flows had before (σ/√K was measured at K = 2 only, on the version-4
    cues: docs/studies/less-noise-two-flows.md, docs/studies/cues-6.md). On a few informative features the same
    noise erases the signal instead: on the SBI problems' 2–10 inputs it took the classifier two-sample accuracy at 1k
    simulations from 0.73–0.75 to 0.86–0.96 (docs/studies/sbi-problems-defaults.md), hence the
    floor on the number of features."""
    whole_number("size", size, low=1)
    whole_number("features", features, low=1)
    if trainable or size > train_section.input_noise_max_size or few_features(train_section, features):
        return 0.0
    return float(train_section.input_noise) * math.sqrt(train_section.scale_to / size)


def compile_for(
    train_section: TrainConfig,
    size: int,
    *,
    trainable: bool,
    features: int | None = None,
    batch_size: int | None = None,
) -> bool:
    """Whether a model of ``size`` training images (of ``features`` frozen features, as :func:`epochs_for`) compiles
    its training loss (``TrainingConfig.compile``): when it
    takes at least ``train.compile_min_steps`` optimizer steps (:func:`epochs_for` × ⌈size / batch_size⌉;
    ``batch_size``: the model's, ``train.batch_size`` when not given). The
    compilation costs 35–50 s once per model shape (later processes reuse inductor's disk cache) and takes a
    256-sample step of the cues flow from 18.6 to 11.0 ms on one thread: it pays from a few thousand steps
    (``benchmarks/bench_compile.py``, docs/studies/compiled-training.md)."""
    t = train_section
    batch_size = t.batch_size if batch_size is None else batch_size
    if t.compile_min_steps is None:
        return False
    steps = epochs_for(t, size, trainable=trainable, features=features) * math.ceil(size / batch_size)
    return steps >= t.compile_min_steps


def recipe_for(
    train_section: TrainConfig, size: int, *, trainable: bool, features: int, parameters: int
) -> FewFeaturesRecipeConfig | None:
    """``train.few_features_recipe`` when it applies to a model of ``size`` training images, ``features`` frozen
    features and ``parameters`` dimensions of θ: :func:`few_features`, frozen, and fewer than
    ``size_per_parameter`` × ``parameters`` images; else None (``train``'s own batch, rate, weight decay, schedule and
    patience).

    Few images of a few informative numbers, measured on sbibm's problems: the defaults' long cosine schedule with
    weight decay peaks early (the 10-D Gaussian's 900 simulations: its best epoch 23 of 667) and loses to sbi's NPE
    (C2ST +0.027 ± 0.014 over 10 observations), while sbi's recipe on the same flow is level (−0.002 ± 0.014); with
    more images per parameter (two_moons' 450 at 1k, any problem at 10k) the defaults win, by up to 0.146
    (docs/studies/few-features-recipe.md)."""
    whole_number("size", size, low=1)
    whole_number("parameters", parameters, low=1)
    r = train_section.few_features_recipe
    if r is None or trainable or not few_features(train_section, features):
        return None
    return r if size < r.size_per_parameter * parameters else None


def training_config(
    train_section: TrainConfig,
    *,
    size: int,
    trainable: bool,
    features: int,
    parameters: int,
    seed: int,
    balance: float | None = None,
    ensemble: int | None = None,
    spared: tuple[int, ...] = (),
) -> TrainingConfig:
    """The training settings of ``train`` for a model of ``size`` training images of ``features`` input features
    (the backbone's dimension) predicting ``parameters`` dimensions of θ: :func:`epochs_for` epochs,
    :func:`input_noise_for` noise (both depend on :func:`few_features`), the batch, rate, weight decay, schedule and
    patience of :func:`recipe_for` where it applies; ``seed`` is the caller's;
    ``balance`` and ``ensemble`` (a variant's) replace ``train.balance`` and the flows of :func:`ensemble_for`;
    ``spared``: the features whose noise is ``train.input_noise_spared`` of the others' (the backbone's
    ``spared_index()``; none for inputs that are not a backbone's)."""
    t = train_section
    r = recipe_for(t, size, trainable=trainable, features=features, parameters=parameters)
    rule = t if r is None else r  # where batch, rate, weight decay and schedule come from
    return TrainingConfig(
        **_every_field(
            TrainingConfig,
            dict(
                epochs=epochs_for(t, size, trainable=trainable, features=features),
                batch_size=rule.batch_size,
                lr=rule.lr,
                weight_decay=rule.weight_decay,
                schedule=rule.schedule,
                min_lr=min(t.min_lr, rule.lr),
                plateau_factor=t.plateau_factor,
                plateau_patience=t.plateau_patience,
                patience=patience_for(t, size) if r is None else r.patience,
                min_delta=t.min_delta,
                clip_norm=t.clip_norm,
                seed=seed,
                balance=t.balance if balance is None else balance,
                input_noise=input_noise_for(t, size, trainable=trainable, features=features),
                spared=() if trainable else tuple(spared),
                spared_noise=float(t.input_noise_spared),
                mirror=t.mirror,
                compile=compile_for(t, size, trainable=trainable, features=features, batch_size=rule.batch_size),
            ),
        )
    )
