"""Typed, validated configuration: ``params.yaml`` parsed once into frozen objects.

Every setting of the pipeline is written in ``params.yaml`` and nowhere else: the models here have no
defaults, so an unknown key, a missing key or a bad value raises :class:`ConfigError` naming the file
and the dotted key. A profile (``profiles/<name>.yaml`` beside ``params.yaml``) holds only overrides of
those settings; ``params.yaml``'s ``profile`` key (or :func:`load_params`'s ``profile`` argument) picks it
and its overrides are merged over the file (mappings recursively, except the named ``train.variants``, which a
profile replaces whole; lists and scalars replace). ``default``
is ``params.yaml`` as it is.

Sections are owned by the components that use them; each is a small pydantic model here so that one
file shows every setting and its meaning: a setting's meaning is the docstring under its field (its one home;
``params.yaml`` says only the unit and the allowed values), rendered with the type and the defaults into
``docs/reference/settings.md`` by ``scripts/settings_page.py``.

Used by every stage and the ``pidc`` CLI (``pidc config check``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictBool,
    StrictInt,
    ValidationError,
    field_validator,
    model_validator,
)

from components.core import weather
from components.core.checks import whole_number
from components.core.images import RENDER_SIDES

__all__ = ["ConfigError", "Params", "load_params", "parse_params", "profile_names", "DEFAULT_PROFILE", "PROJECT_ROOT"]

#: The repository root (where ``params.yaml`` and ``dvc.yaml`` live).
PROJECT_ROOT = Path(__file__).resolve().parents[2]

#: The profile that is the params file as it is (no overrides).
DEFAULT_PROFILE = "default"


class ConfigError(ValueError):
    """A params file is unreadable, has an unknown or missing key, or a bad value."""

    def one_line(self) -> str:
        """The message on one line (its lines joined by ``; ``), for a command's error output."""
        return "; ".join(line.strip() for line in str(self).splitlines() if line.strip())


class _Section(BaseModel):
    # finite numbers only (``.inf``/``.nan`` are no setting's meaning); counts and switches strict (below). Each
    # field's docstring is its meaning, read by pydantic into ``description`` (the settings page,
    # scripts/settings_page.py, prints it beside the key)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, use_attribute_docstrings=True)


def _no_bool(v: object) -> object:
    if isinstance(v, bool):
        raise ValueError(f"must be a number, got {v!r} (YAML reads yes/no/true/false as booleans)")
    return v


#: a real number: an int or float (or a number YAML left as a string, such as ``1e-3``), never a boolean
Real = Annotated[float, BeforeValidator(_no_bool)]
# counts are strict integers (YAML's ``no`` must not become 0, nor ``"6000"`` 6000), switches strict booleans


PositiveInt = Annotated[StrictInt, Field(gt=0)]
NonNegativeInt = Annotated[StrictInt, Field(ge=0)]


def _device_form(v: str) -> str:
    import re

    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", v):
        raise ValueError(f"must be auto, cpu, cuda or cuda:N (N a device index), got {v!r}")
    return v


#: a torch device: ``auto``, ``cpu``, ``cuda`` or ``cuda:N`` (its form; what it means here: components/core/hardware.py)
Device = Annotated[str, AfterValidator(_device_form)]


def _workers_form(v: object) -> object:
    if v == "auto" or (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
        return v
    raise ValueError(f"must be auto or a whole number ≥ 1, got {v!r}")


#: a runner's workers: ``auto`` (the usable cores, resolved at a stage's start) or a whole number ≥ 1
Workers = Annotated[PositiveInt | Literal["auto"], BeforeValidator(_workers_form)]


#: the backbones of ``components.features.backbones`` (``available()``; tests/test_config.py keeps the two equal)
BackboneName = Literal["cues", "tiny", "cnn", "efficientnet_lite0", "resnet50", "dinov2", "clip"]


def _each_once(v: tuple) -> tuple:
    repeated = sorted({str(x) for x in v if v.count(x) > 1})
    if repeated:
        raise ValueError(f"each value at most once, got {', '.join(repeated)} more than once in {list(v)}")
    return v


class CarlaConfig(_Section):
    """Connection and scene settings of the CARLA backend (``simulator.backend: carla``)."""

    host: str
    """host name or address of the CARLA server"""
    port: Annotated[StrictInt, Field(gt=0, lt=65536)]
    """the CARLA server's RPC port"""
    timeout_s: Annotated[Real, Field(gt=0)]
    """seconds the client waits for the server to answer before it fails"""
    maps: Annotated[tuple[str, ...], AfterValidator(_each_once)]
    """the towns a scene seed draws from, by name (uniformly); each must be on the server. A town is ``Town`` +
    digits with an optional ``HD`` and ``_Opt`` (the layered variant): Town01 … Town07, Town10HD, Town10HD_Opt. Other
    maps are refused by name: CARLA's non-town maps (no vehicle spawns there, e.g. AnnotationColorLandscape) and its
    large maps Town11, Town12, Town13 and Town15 (streamed tiles, no pedestrian navigation). Town06 and Town07 come
    with CARLA's AdditionalMaps package"""

    @field_validator("maps")
    @classmethod
    def _towns(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        if not v:
            raise ValueError("empty: list the towns a scene seed draws from (the default: Town01 … Town07, Town10HD)")
        bad = [f"{name!r} {problem}" for name in v if (problem := CarlaConfig.town_problem(name))]
        if bad:
            raise ValueError("; ".join(bad))
        return v

    @staticmethod
    def town_problem(name: object) -> str | None:
        """Why ``name`` is no town the CARLA backend draws from (a phrase), or ``None`` for a town such as Town10HD."""
        import re

        match = re.fullmatch(r"Town(\d+)(HD)?(_Opt)?", name) if isinstance(name, str) else None
        if match is None and isinstance(name, str) and "/" in name:
            return f"is a path: give the map's name ({name.rstrip('/').rsplit('/', 1)[-1]!r})"
        if match is None:
            return (
                "is not a CARLA town (Town + digits, optional HD and _Opt: Town01 … Town07, Town10HD, Town10HD_Opt); "
                "no vehicle spawns on CARLA's other maps"
            )
        if int(match.group(1)) in (11, 12, 13, 15):
            return "is one of CARLA's large maps (streamed tiles, no pedestrian navigation), which pidc does not use"
        return None

    fixed_delta_seconds: Annotated[Real, Field(gt=0, le=0.1)]
    """simulated seconds per tick: the world runs in synchronous mode, one tick per step of the client"""
    settle_ticks: PositiveInt
    """ticks between setting the weather and capturing (auto-exposure settles)"""
    traffic_manager_port: Annotated[StrictInt, Field(gt=0, lt=65536)]
    """the port of CARLA's traffic manager, which drives the spawned vehicles"""
    max_vehicles: NonNegativeInt
    """a scene's vehicles besides the camera's: uniform on 0 … max_vehicles (from the scene seed), capped by the
    map's spawn points"""
    max_pedestrians: NonNegativeInt
    """a scene's pedestrians: uniform on 0 … max_pedestrians (from the scene seed)"""
    fov: Annotated[Real, Field(gt=0, lt=180)]
    """horizontal field of view of the RGB camera, degrees"""


class RecordedConfig(_Section):
    """Recorded datasets (``simulator.backend: recorded``): folders of images with a labels file, imported by the
    generate stage into the same shards and manifest as rendered data (docs/simulators.md, "Recorded datasets")."""

    folders: tuple[Annotated[str, Field(min_length=1)], ...]
    """the recorded folders, relative to the project unless absolute, each holding its images and the labels file
    (columns ``image`` and the six predicted parameters; optional ``sun_azimuth_angle``, fixed ones, ``sequence``,
    ``split``; written by ``pidc record``). DVC cannot list them as deps of the generate stage: after changing a
    folder's files, run ``dvc repro -f generate`` (the stage re-imports only the splits whose files changed)"""
    labels: Annotated[str, Field(min_length=1)]
    """the labels file's name in each folder: a ``.csv`` or ``.parquet`` file"""
    renderer: Literal["procedural", "carla"] | None
    """the simulator that renders Task II's bag (fresh scenes of a known weather distribution) beside recorded data:
    ``procedural``, ``carla`` (``simulator.carla``) or null (none at hand: Task II is skipped and its report says
    why). Task I's posterior predictive checks are skipped with recorded data whatever it is: no simulator
    re-renders a recorded scene"""

    @field_validator("folders")
    @classmethod
    def _folders(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        for folder in v:
            if folder != folder.strip():
                raise ValueError(f"a folder path without surrounding spaces, got {folder!r}")
        return _each_once(v)

    @field_validator("labels")
    @classmethod
    def _labels(cls, v: str) -> str:
        if "/" in v or "\\" in v or not v.lower().endswith((".csv", ".parquet")):
            raise ValueError(f"a file name ending in .csv or .parquet (no folder), got {v!r}")
        return v


class SimulatorConfig(_Section):
    """Which simulator renders the data, and at what resolution (pixels)."""

    backend: Literal["procedural", "carla", "recorded"]
    """the renderer: ``procedural`` (embedded in pidc, no server), ``carla`` (a running CARLA server,
    ``simulator.carla``), or ``recorded`` (no renderer: the folders of ``simulator.recorded`` are imported,
    their images area-resized to ``height × width``)"""
    height: Annotated[StrictInt, Field(ge=RENDER_SIDES[0], le=RENDER_SIDES[1])]
    """the images' height in pixels, within the renderer's range (``images.RENDER_SIDES``: 16..2048)"""
    width: Annotated[StrictInt, Field(ge=RENDER_SIDES[0], le=RENDER_SIDES[1])]
    """the images' width in pixels, within the renderer's range"""
    render_sizes: tuple[PositiveInt, PositiveInt] | None
    """null: the renderer's own ``height × width`` images; ``[low, high]``: each scene rendered ``low..high`` pixels
    high (drawn from its seed; the width in proportion) and area-resized to ``height × width``, as a camera's
    images are (components/simulate/resized.py), so the models cover resized images; the procedural backend only
    (study: docs/studies/camera-renders.md)"""
    carla: CarlaConfig
    """the CARLA backend's connection and scenes (read only with ``backend: carla``)"""
    recorded: RecordedConfig
    """the recorded folders (read only with ``backend: recorded``)"""

    @model_validator(mode="after")
    def _recorded_folders(self) -> SimulatorConfig:
        if self.backend == "recorded" and not self.recorded.folders:
            raise ValueError(
                "recorded.folders is empty but backend is recorded: name the folders of recorded images to import "
                "(simulator.recorded.folders, relative to the project)"
            )
        return self

    @model_validator(mode="after")
    def _render_sizes(self) -> SimulatorConfig:
        if self.render_sizes is None:
            return self
        low, high = self.render_sizes
        if self.backend != "procedural":
            raise ValueError(
                f"render_sizes {list(self.render_sizes)} needs backend: procedural (a CARLA camera renders at "
                "height × width); set render_sizes: null"
            )
        if not self.height <= low <= high <= RENDER_SIDES[1]:
            raise ValueError(
                f"render_sizes [{low}, {high}] must satisfy height ({self.height}) ≤ low ≤ high ≤ {RENDER_SIDES[1]}: each render "
                "is shrunk to height × width"
            )
        return self


class RunnerConfig(_Section):
    """The Prefect task runner of fan-out flows: threads, processes, or a Dask cluster."""

    kind: Literal["threads", "processes", "dask"]
    """``threads`` (one process), ``processes`` (local worker processes) or ``dask`` (a Dask cluster)"""
    workers: Workers
    """tasks run at a time (threads, processes, or the workers of a local Dask cluster); ``auto``: the cores this
    process may use (its CPU affinity, capped by a cgroup CPU quota: components/core/hardware.py), resolved at the
    stage's start; a number above them is an error naming the key"""
    dask_address: str | None
    """address of an existing Dask scheduler (``tcp://host:8786``); null = a local cluster (kind: dask only)"""

    @model_validator(mode="after")
    def _dask_address(self) -> RunnerConfig:
        if self.dask_address is not None and self.kind != "dask":
            raise ValueError(
                f"dask_address {self.dask_address!r} is set but kind is {self.kind!r}: it names a Dask scheduler, "
                "so set kind: dask, or dask_address: null"
            )
        return self


class DataConfig(_Section):
    """The simulated dataset: split sizes, sharding and scene reuse."""

    root: Annotated[str, Field(min_length=1)]
    """the folder of the simulated dataset's shards, relative to the project unless absolute (a DVC output)"""
    splits: dict[Literal["train", "val", "test"], PositiveInt]
    """number of images per split. The train split must cover the largest training size; the val split picks the
    best epoch, fits the base scales τ (and the night regime's) and stops early where ``train.patience`` is set;
    the test split is Task I's; study: docs/studies/validation-split.md"""
    shard_size: PositiveInt
    """images per shard file"""
    images_per_scene: PositiveInt
    """consecutive images rendered in the same scene (a map and spawn point under many weathers)"""
    shards_per_task: PositiveInt
    """shards one Prefect task renders (generate) or passes through a backbone (features); each task run costs
    0.1–0.3 s of bookkeeping, and a task still writes its shards one by one
    (study: docs/studies/fewer-larger-tasks.md)"""
    runner: RunnerConfig
    """the task runner of the generate and features stages"""

    @field_validator("splits")
    @classmethod
    def _all_splits(cls, v: dict[str, int]) -> dict[str, int]:
        missing = {"train", "val", "test"} - set(v)
        if missing:
            raise ValueError(f"missing split(s) {sorted(missing)}; need train, val and test")
        return v


class ContactSheetConfig(_Section):
    """The generate stage's contact sheet: each row sweeps one parameter from low to high."""

    steps: Annotated[StrictInt, Field(ge=2)]
    """tiles per row: the parameter's values from its low to its high end"""
    scenes: PositiveInt
    """scenes shown, one block of rows (one per predicted parameter) each"""
    path: Annotated[str, Field(min_length=1)]
    """the sheet's PNG file, relative to the project (a DVC output)"""


class BackbonesConfig(_Section):
    """The image backbones of the grid and where pretrained weights are found."""

    names: tuple[BackboneName, ...] = Field(min_length=1)
    """the grid's backbones, each once (components/features/backbones: ``available()``)"""
    pretrained_dir: str | None
    """a local directory holding one sub-folder of Hugging Face weights per pretrained backbone
    (``<dir>/<backbone>/``, ``save_pretrained`` folders); null = the Hugging Face cache"""
    batch_size: PositiveInt
    """images per batch through a frozen backbone in the features stage"""
    device: Device
    """where the features stage runs the frozen backbones (the cues' networks, the pretrained ones): ``auto`` (CUDA
    when torch sees it, else the CPU), ``cpu``, ``cuda`` or ``cuda:N``; resolved at the stage's start (``cuda`` without
    one is an error naming the key). Not part of the features' fingerprint: features cached on another device are
    kept"""

    @field_validator("names")
    @classmethod
    def _each_once(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        return _each_once(v)


class FlowParams(_Section):
    """The conditional neural spline flow (``components.posterior.FlowConfig``)."""

    transforms: PositiveInt
    """rational-quadratic spline transforms stacked in the flow"""
    hidden_features: tuple[PositiveInt, ...]
    """widths of each transform's conditioner MLP at ``train.scale_to`` training images or more (divided by √s
    below it, components/posterior/settings.py)"""
    bins: Annotated[StrictInt, Field(ge=2)]
    """spline bins per transform and parameter"""
    passes: Annotated[StrictInt, Field(ge=2, le=len(weather.PREDICTED))] | None
    """2 = coupling flow (fast sampling), up to 6 (one pass per parameter); null = fully autoregressive (1 would make
    the parameters independent given the image)"""
    ensemble: PositiveInt
    """flows in an equal-weight ensemble for models of at least ``train.ensemble_min_size`` training images (fewer
    images: one flow); calibration and sharpness beyond the paper; 1 = a single flow everywhere
    (studies: docs/studies/sky-thumbnail-two-flows.md, docs/studies/flow-ensemble.md)"""
    standardize: StrictBool
    """standardize the flow's inputs with a mean/std fitted on the training set"""
    context_layers: tuple[PositiveInt, ...]
    """widths of the context network (an MLP, SiLU between its layers) from the backbone's features to the flows'
    context, shared by an ensemble's flows; the last width is the context size; [] = the features are the context.
    A backbone trained jointly with the flow (``cnn``) has none; study: docs/studies/context-network.md"""


class VariantConfig(_Section):
    """A model beside the grid: one backbone and size trained with other calibration settings.

    Variants are keyed by name in ``train.variants``; the model id is ``<backbone>-<size>-<name>``."""

    backbone: str
    """the variant's backbone, one of ``backbones.names``"""
    size: PositiveInt
    """the variant's training images, one of ``train.sizes``"""
    balance: Annotated[Real, Field(ge=0)]
    """λ of balanced NPE for this model (0 = plain NPE)"""
    ensemble: PositiveInt
    """flows in this model's equal-weight ensemble"""


class TemperatureRegimeConfig(_Section):
    """A second base scale τ for the inputs whose θ[parameter] < below (components/posterior/regime.py)."""

    name: Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]*$")]
    """the regime's name in the models' metrics (``temperature_<name>.<parameter>``)"""
    parameter: str
    """the predicted parameter that defines the regime"""
    below: Real
    """an input lies in the regime when its ``parameter`` is below this value (physical units, inside the prior)"""


class FewFeaturesRecipeConfig(_Section):
    """How a model of few features and few training images per parameter trains: sbi's NPE recipe, a constant rate
    and early stopping (components/posterior/settings.py; study: docs/studies/few-features-recipe.md)."""

    size_per_parameter: PositiveInt
    """the recipe applies below this many training images per dimension of θ (and below
    ``input_noise_min_features`` features); at and above it, ``train``'s own settings"""
    batch_size: PositiveInt
    """training examples per optimizer step"""
    lr: Annotated[Real, Field(gt=0)]
    """the learning rate of AdamW"""
    weight_decay: Annotated[Real, Field(ge=0)]
    """AdamW's decoupled weight decay"""
    schedule: Literal["cosine", "plateau", "constant"]
    """the learning-rate schedule (``train.schedule``'s choices)"""
    patience: PositiveInt
    """early stopping after this many epochs without improvement of the validation loss (not scaled by s; the epochs
    of :func:`~components.posterior.settings.epochs_for` stay the cap)"""


class TrainConfig(_Section):
    """The grid of models (backbone × training size) and how each is trained."""

    sizes: tuple[PositiveInt, ...] = Field(min_length=1)
    """training-set sizes: nested prefixes of the train split"""
    experiment: Annotated[str, Field(min_length=1)]
    """the MLflow experiment of the grid (the store is ``sqlite:///mlflow.db`` unless ``MLFLOW_TRACKING_URI`` is
    set)"""
    flow: FlowParams
    """the conditional neural spline flow of every model (zuko's NSF)"""
    epochs: PositiveInt
    """epochs at ``scale_to`` training images or more (× s below, capped by ``sample_budget``)
    (study: docs/studies/longer-training.md)"""
    embedding_epochs: PositiveInt
    """maximum epochs for a backbone trained jointly with the flow (``cnn``; costly on a CPU)"""
    sample_budget: PositiveInt
    """training samples seen at most (epochs × size): a model of ``size`` images trains
    min(⌈epochs·s⌉, ⌈sample_budget / size⌉) epochs (s of ``scale_to``), so large training sets cost a bounded time"""
    embedding_sample_budget: PositiveInt
    """the same for a backbone trained jointly with the flow (with ``embedding_epochs``, no scaling by s)"""
    scale_to: PositiveInt
    """below this many training images, s = scale_to / size: s× epochs and patience, hidden widths / √s
    (study: docs/studies/sbi-problems.md)"""
    batch_size: PositiveInt
    """training examples per optimizer step"""
    lr: Annotated[Real, Field(gt=0)]
    """the learning rate of AdamW (the schedule's start)"""
    weight_decay: Annotated[Real, Field(ge=0)]
    """AdamW's decoupled weight decay"""
    schedule: Literal["cosine", "plateau", "constant"]
    """the learning-rate schedule: ``cosine`` (from ``lr`` down to ``min_lr`` over the epochs), ``plateau``
    (× ``plateau_factor`` when the validation loss stalls) or ``constant``"""
    min_lr: Annotated[Real, Field(ge=0)]
    """the schedule's floor (where cosine ends; the plateau schedule's minimum)"""
    plateau_factor: Annotated[Real, Field(gt=0, lt=1)]
    """the plateau schedule: lr × plateau_factor after plateau_patience epochs without improvement"""
    plateau_patience: PositiveInt
    """the plateau schedule's epochs without improvement of the validation loss before the rate drops"""
    patience: PositiveInt | None
    """early stopping: stop after this many epochs without improvement of the validation loss (× s below scale_to);
    null: none, every epoch of the schedule runs (the weights of the best validation epoch are kept either way)
    (study: docs/studies/early-stopping.md)"""
    min_delta: Annotated[Real, Field(ge=0)]
    """the improvement of the validation loss that counts (nats)"""
    clip_norm: Annotated[Real, Field(gt=0)] | None
    """the gradients' global L2 norm is clipped to this; null = no clipping"""
    balance: Annotated[Real, Field(ge=0)]
    """λ of balanced NPE (calibration beyond the paper; 0 = plain NPE)"""
    input_noise: Annotated[Real, Field(ge=0)]
    """σ of Gaussian noise added to the frozen features while training (units of their standard deviation) at
    ``scale_to`` images, × √(scale_to / size) for other sizes, none above ``input_noise_max_size`` images
    (components/posterior/settings.py); 0 = none. It regularizes the frozen features of few training images; with
    τ fitted on the validation split the default leaves the coverage gap near zero (docs/training.md)
    (studies: docs/studies/validation-split.md, docs/studies/cues-3-input-noise.md)"""
    input_noise_max_size: PositiveInt
    """no input noise for models of more training images than this"""
    input_noise_min_features: PositiveInt
    """no input noise for a model of fewer input features: noise regularizes many redundant features (cues 377, tiny
    256) and erases the signal of a few informative ones (the SBI problems' 2–10)
    (study: docs/studies/sbi-problems-defaults.md); such "few features" also train ``few_features_epochs``"""
    input_noise_spared: Annotated[Real, Field(ge=0, le=1)]
    """the input noise on the features a backbone spares (``Backbone.spared_index``: the cues' sun head, μ and log σ),
    as a share of ``input_noise``: 1 the same as on every feature, 0 none. The sun head reads a clear sky's sun to
    1.7° (its own σ), finer than the 5.8° of the default noise at 50 000 images, which capped the champion there;
    sparing all fourteen of the reader's estimates instead overfits (calibration error 0.043)
    (study: docs/studies/estimate-noise.md)"""
    few_features_epochs: PositiveInt | None
    """a model of fewer than ``input_noise_min_features`` frozen features trains at least this many epochs (still
    capped by ``sample_budget``): a few informative inputs keep improving long after the image models' ``epochs``;
    null: the images' rule for every input (components/posterior/settings.py; study: docs/studies/sbi-small-inputs.md)"""
    few_features_recipe: FewFeaturesRecipeConfig | None
    """a model of few features (below ``input_noise_min_features``) and fewer than ``size_per_parameter`` training
    images per parameter trains with this recipe instead (its batch, rate, weight decay, schedule and patience); null:
    ``train``'s settings for every model. No model of the pipeline has few features
    (study: docs/studies/few-features-recipe.md)"""
    mirror: StrictBool
    """train on each input or its mirror image's with probability ½ (a left-right mirror leaves the weather and the
    sun and wind azimuths unchanged in law, the scenes nearly; components/posterior/train.py); the backbones'
    features permute under it; a pretrained backbone's features cannot (an error names it)
    (study: docs/studies/mirrored-inputs.md)"""
    ensemble_min_size: PositiveInt
    """models of at least this many training images are ensembles of ``train.flow.ensemble`` flows, the others one
    flow (components/posterior/settings.py)"""
    temperature: StrictBool
    """after training, fit the flows' base scale τ (one per parameter) on the validation split by maximum
    likelihood (post-hoc calibration, components/posterior/temperature.py); false: τ = 1
    (study: docs/studies/temperature.md)"""
    temperature_regime: TemperatureRegimeConfig | None
    """with ``temperature``: one τ outside and one inside this regime, blended per input by a logistic gate on the
    flows' context fitted on the training split (components/posterior/regime.py); null: one τ for every input
    (study: docs/studies/night-base-scale.md)"""
    compile_min_steps: NonNegativeInt | None
    """a model trained for at least this many optimizer steps compiles its training loss with torch.compile (35–50 s
    once per model shape, then 1.7–1.9× faster steps); null: never (components/posterior/settings.py)
    (study: docs/studies/compiled-training.md)"""
    variants: dict[Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]*$")], VariantConfig]
    """calibrated variants trained and evaluated beside the grid, keyed by a name of your choice (model id
    ``<backbone>-<size>-<name>``), e.g. ``ensemble: {backbone: cues, size: 50000, balance: 0.0, ensemble: 3}``;
    empty: the grid alone"""
    runner: RunnerConfig
    """the task runner training the models in parallel, the largest first (processes: ``cores // workers`` torch
    threads each, of the cores this process may use); study: docs/studies/parallel-grid.md"""
    device: Device
    """where the models train (the flows, a jointly trained ``cnn``): ``auto`` (CUDA when torch sees it, else the
    CPU), ``cpu``, ``cuda`` or ``cuda:N``; resolved at the stage's start (``cuda`` without one is an error naming the
    key). Several models train on one GPU at once, one process each (``runner.workers``), each with its own CUDA
    context; calibration and the test NLL are computed on the CPU. The same seeds: weights differ from the CPU's in
    float rounding, the figures within their standard errors. Not part of a checkpoint's key"""

    @field_validator("sizes")
    @classmethod
    def _sizes_once(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        return _each_once(v)

    @model_validator(mode="after")
    def _min_lr(self) -> TrainConfig:
        if self.min_lr > self.lr:
            raise ValueError(f"min_lr ({self.min_lr:g}) must not exceed lr ({self.lr:g})")
        return self


class LocalTestConfig(_Section):
    """The local test of the posterior, L-C2ST (:class:`components.evaluate.local.LocalTest`): classifiers trained on
    validation images tell a model's draws from the truths; its p-value at an image is exact under H₀ (labels
    swapped within pairs)."""

    level: Annotated[Real, Field(gt=0, lt=1)]
    """α: H₀(x) (the model's posterior is the true one at image x) is rejected when the p-value is ≤ α; a set of
    images is judged by its rejection rate against the rates of the null classifiers (its own exact p-value)"""
    calibration_images: Annotated[StrictInt, Field(ge=10)] | Literal["all"]
    """the first validation images the classifiers learn from (their cached features and labels, one draw of the
    model each); ≤ ``data.splits.val``, or ``all`` of them"""
    summary_draws: Annotated[StrictInt, Field(ge=4)]
    """posterior draws per image summarizing x for the classifiers (each parameter's median and log IQR)"""
    test_draws: Annotated[StrictInt, Field(ge=50)]
    """posterior draws per image in the statistic T(x) at an image; ≤ ``evaluate.named.draws``"""
    steps: PositiveInt
    """full-batch Adam steps of each classifier"""
    null_trials: Annotated[StrictInt, Field(ge=19)]
    """H, the classifiers trained on swapped labels: p-values take the values k / (H + 1)"""
    test_images: PositiveInt | Literal["all"]
    """the first test images tested beside the named weathers (the control: an average image of the prior);
    ≤ ``data.splits.test``, or ``all`` of them"""


class NamedConfig(_Section):
    """Named weathers: the conditions users name (CARLA's presets, one's own, recorded folders), each on images of
    new scenes, with each parameter's interval coverage beside an exact posterior's on a toy of the same faces, and
    the local test (``reports/task1/local.json``, ``plots/<model>/named.png``)."""

    presets: Literal["carla", "none"]
    """``carla``: CARLA's 15 presets that keep the paper's fixed parameters (``pidc weather``), by CARLA's names and
    values; ``none``: only ``weathers`` and ``folders``"""
    weathers: dict[Annotated[str, Field(pattern=r"^[A-Za-z0-9_.:-]+$")], dict[str, Real]]
    """one's own named weathers: name → the six predicted parameters in physical units inside ``prior`` (sun azimuth
    0° as the presets'); a name must differ from the presets'"""
    folders: dict[Annotated[str, Field(pattern=r"^[A-Za-z0-9_.:-]+$")], str]
    """recorded named weathers: name → a folder of images with ``labels.csv`` (the recorded format,
    docs/simulators.md), relative to the project; images larger than ``simulator.height × width`` at its aspect are
    area-resized"""
    scenes: Annotated[StrictInt, Field(ge=2)]
    """new scenes per rendered weather (scene seeds no split of the dataset uses; checked)"""
    draws: Annotated[StrictInt, Field(ge=400)]
    """posterior draws per image (the 68.27 % and 95 % HDIs)"""
    tolerance: Annotated[Real, Field(ge=0)]
    """θ's units: a truth on a face of the box (no rain) is covered when the interval reaches within this of it"""
    toy_images: Annotated[StrictInt, Field(ge=24)]
    """images per weather of the exact toy (θ uniform on the box, x = θ + σ·ε, σ from the model's own intervals
    there): what a correct model's coverage is at that weather"""
    local_test: LocalTestConfig
    """the L-C2ST's settings"""

    @model_validator(mode="after")
    def _names(self) -> NamedConfig:
        from components.core import presets

        taken = set(presets.USABLE) if self.presets == "carla" else set()
        for name, values in self.weathers.items():
            if name in taken:
                raise ValueError(f"weathers.{name}: the name of a CARLA preset; name one's own weather otherwise")
            missing = [p for p in weather.PREDICTED if p not in values]
            extra = sorted(set(values) - set(weather.PREDICTED))
            if missing or extra:
                raise ValueError(
                    f"weathers.{name}: needs exactly the six predicted parameters ({', '.join(weather.PREDICTED)}); "
                    f"missing {missing}, unknown {extra}"
                )
        clash = sorted((taken | set(self.weathers)) & set(self.folders))
        if clash:
            raise ValueError(f"folders: {', '.join(clash)} already name a weather")
        if self.local_test.test_draws > self.draws:
            raise ValueError(f"local_test.test_draws ({self.local_test.test_draws}) exceeds draws ({self.draws})")
        return self


class EvaluateConfig(_Section):
    """Task I evaluation of every model of the grid on the test split."""

    images: PositiveInt | Literal["all"]
    """test images evaluated: ``all`` (the whole test split) or a count ≤ ``data.splits.test`` (the first ones)"""
    samples: Annotated[StrictInt, Field(ge=400)]
    """posterior samples per image (HPD credibility, coverage, π); the 99.73 % HDR of the plots needs ≥ 371"""
    ppc_images: PositiveInt
    """test images given a posterior predictive check"""
    ppc_renders: Annotated[StrictInt, Field(ge=2)]
    """re-renders per check, from the posterior and from the prior each"""
    example_images: NonNegativeInt
    """test images shown as histograms and corner plots per model"""
    profile_bins: Annotated[StrictInt, Field(ge=1, le=100)]
    """equal-width bins of each parameter's prior range: the errors and the 68 % coverage by true value
    (``reports/task1/profiles.json``, ``plots/<model>/profile.png``)"""
    band_level: Annotated[Real, Field(gt=0, lt=1)]
    """``calibration_band``: this quantile of the calibration error of a perfectly calibrated model on the same
    images and samples, simulated ``band_replicates`` times (seeded); ``within_band``: the error is ≤ the band"""
    band_replicates: Annotated[StrictInt, Field(ge=100)]
    """simulated evaluations of a perfectly calibrated model behind the band (seeded)"""
    named: NamedConfig
    """named weathers and the local test, for every model"""
    runner: RunnerConfig
    """the task runner evaluating models in parallel (processes: one onnxruntime thread each)"""

    @field_validator("images", mode="before")
    @classmethod
    def _images(cls, v: object) -> object:
        if v == "all":
            return v
        return whole_number("the number of test images", v, low=1, hint=" or 'all' (the whole test split)")


class ExportConfig(_Section):
    """ONNX export of every model into ``registry/`` and its registration in the MLflow Model Registry."""

    exporter: Literal["torchscript", "dynamo"]
    """torch → ONNX exporter: ``torchscript`` (~5 s a model here; deprecated by torch but checked against torch at
    export time) or ``dynamo`` (torch.export, torch's maintained route; 50–130 s a model here)"""
    registered_model: Annotated[str, Field(pattern=r"^[A-Za-z0-9_.-]+$")]
    """the one registered model whose versions are the exported models (each tagged ``pidc.model``); the aliases
    ``champion`` and ``challenger`` move between its versions, so ``models:/<name>@champion`` is the current best"""
    champion_max_calibration_error: Annotated[Real, Field(gt=0, le=1)]
    """the champion (alias ``champion``, ``reports/task1/champion.json``) is the lowest test NLL among the models whose
    calibration error lies within the band of a perfectly calibrated model (``evaluate.band_level``); when none
    does, the lowest test NLL among those with a calibration error ≤ this ceiling (the choice is recorded);
    when none is below it either, the evaluation fails"""
    runner: RunnerConfig
    """models exported at a time (their registrations follow one by one, in the grid's order); in processes only:
    torch's ONNX exporter keeps global state, so two exports in one process would corrupt each other"""

    @field_validator("runner")
    @classmethod
    def _exports_in_processes(cls, v: RunnerConfig) -> RunnerConfig:
        if v.workers != 1 and v.kind != "processes":  # auto may mean several
            raise ValueError(
                f"kind {v.kind!r} with {v.workers} workers: parallel exports need kind: processes (torch's ONNX "
                "exporter keeps global state, two exports in one process corrupt each other), or workers: 1"
            )
        return v


def _model_name(v: str) -> str:
    if v != v.strip():
        raise ValueError(
            f"must be champion, challenger, a models:/ URI or a model id, without surrounding spaces, got {v!r}"
        )
    return v


#: the model a task characterizes with: ``champion``/``challenger``, a ``models:/`` URI, or a model id of ``registry/``
ModelName = Annotated[str, Field(min_length=1), AfterValidator(_model_name)]


class GaussianMode(_Section):
    """One component of Task II's Gaussian mixture over (fog_density, precipitation), physical units."""

    weight: Annotated[Real, Field(gt=0)]
    """its share of the mixture; the modes' weights are relative (divided by their sum)"""
    mean: tuple[Real, Real]
    """the mode's centre, ``[fog_density, precipitation]``, inside the prior"""
    std: tuple[Annotated[Real, Field(gt=0)], Annotated[Real, Field(gt=0)]]
    """the mode's standard deviations, ``[fog_density, precipitation]`` (independent)"""


class DeconvolutionConfig(_Section):
    """Task II's deconvolved estimate (:mod:`components.domains.deconvolution`)."""

    draws_per_image: PositiveInt
    """posterior draws per bag image forming the support of the estimate (support size = images × draws)"""
    max_steps: PositiveInt
    """EM steps tried from the prior (1 = the mixture of posteriors); the number used is chosen by held-out
    likelihood (the one-standard-error rule)"""
    folds: Annotated[StrictInt, Field(ge=2)]
    """folds of the cross-validation over the bag's images"""


class WidthFloorConfig(_Section):
    """Task II's width floor (:func:`components.domains.task2.width_floor`): the mixture with each image's posterior
    moved onto the image's true θ, and the mixture of calibrated posteriors of the same shape, their spread scaled by
    each of ``scales``; for the varying parameters, the two mixtures' difference with its bootstrap interval."""

    draws: Annotated[StrictInt, Field(ge=2)]
    """posterior draws per bag image behind both mixtures"""
    bootstrap: Annotated[StrictInt, Field(ge=40)]
    """bootstrap replicates (resampled bag images) behind the 95 % interval of the mixture's ratio minus the calibrated"""
    scales: tuple[Annotated[Real, Field(gt=0)], ...] = Field(min_length=1)
    """the spread's scale factors s (1 = the posteriors' own widths, required: the report and its plot show it)"""

    @field_validator("scales")
    @classmethod
    def _own_widths(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if 1.0 not in v:
            raise ValueError(f"must include 1 (the posteriors' own widths), got {list(v)}")
        return v


class Task2Config(_Section):
    """Task II: a bag of rendered images whose weather follows a known distribution → its characterization."""

    model: ModelName
    """the model characterizing the bag: ``champion``/``challenger`` (the registered model's alias, e.g.
    ``models:/pidc@champion``; the evaluate stage sets it), a ``models:/`` URI, or a model id of ``registry/``"""
    images: PositiveInt
    """images in the bag (all equally weighted), rendered in fresh scenes"""
    images_per_scene: PositiveInt
    """consecutive images of the bag rendered in the same scene"""
    fixed: dict[str, Real]
    """the fixed predicted parameters (every one but fog_density and precipitation), physical units"""
    sun_azimuth_angle: Annotated[Real, Field(ge=0, lt=360)]
    """the sun azimuth of every image of the bag, degrees (the paper fixes every parameter but the two that vary)"""
    modes: tuple[GaussianMode, ...] = Field(min_length=1)
    """the bag's weather: a Gaussian mixture over (fog_density, precipitation), truncated to the prior box"""
    samples: Annotated[StrictInt, Field(ge=100)]
    """draws from the estimate and from the true distribution (metrics and plots)"""
    hdr_level: Annotated[Real, Field(gt=0, lt=1)]
    """the estimate's highest-density region whose share of the true mass is reported"""
    estimate: Literal["mixture", "deconvolved"]
    """the estimate scored: ``mixture`` = Σᵢ wᵢ q(θ | xᵢ) (the paper's), ``deconvolved`` = the maximum-likelihood
    weather distribution of the bag, by EM from the prior whose first step is the mixture (the mixture's figures
    are then reported beside it); study: docs/studies/task2-deconvolution.md"""
    deconvolution: DeconvolutionConfig
    """the deconvolved estimate's settings (read with ``estimate: deconvolved``)"""
    width_floor: WidthFloorConfig
    """what the posteriors' widths alone allow (``reports/task2/metrics.json``, ``width_floor``)
    (study: docs/studies/task2-width-floor.md)"""

    @model_validator(mode="after")
    def _folds_fit(self) -> Task2Config:
        if self.estimate == "deconvolved" and self.deconvolution.folds > self.images:
            raise ValueError(
                f"deconvolution.folds = {self.deconvolution.folds} exceeds images = {self.images}: "
                "each fold of the cross-validation needs an image of the bag"
            )
        return self

    @field_validator("fixed")
    @classmethod
    def _fixed_params(cls, v: dict[str, float]) -> dict[str, float]:
        expected = set(weather.PREDICTED) - {"fog_density", "precipitation"}
        if set(v) != expected:
            raise ValueError(
                f"must give exactly {sorted(expected)} (fog_density and precipitation follow the "
                f"mixture), got {sorted(v)}"
            )
        return v


class BagConfig(_Section):
    """A Task III bag: the test images whose weather lies in a sub-box of the prior (uniform on it)."""

    box: dict[str, tuple[Real, Real]]
    """the sub-box, per predicted parameter (omitted ones span the prior), physical units"""
    max_images: PositiveInt
    """at most this many images (the first ones of the test split inside the sub-box)"""


class Task3Config(_Section):
    """Task III: targets mixing three source bags and an out-of-ODD bag b0 at noise level η (the paper's sweep)."""

    model: ModelName
    """the model characterizing every bag: as ``task2.model``"""
    bags: dict[Annotated[str, Field(pattern=r"^b[0-9]+$")], BagConfig]
    """b0 (out of the ODD; disjoint from the others), then the sources b1, b2, b3; an image in two source sub-boxes
    belongs to the first (b1 before b2 …), so bags and fresh pools share no image"""
    weights: tuple[Annotated[Real, Field(ge=0)], ...]
    """the true mixture weights λ of the sources b1, b2, … (on the simplex)"""
    etas: tuple[Annotated[Real, Field(ge=0, le=1)], ...]
    """noise levels η: the share of b0 in the target"""
    repetitions: PositiveInt
    """targets per η and kind: with 50, a perfect separation's 95 % interval of the AUC against η = 0 (Newcombe)
    starts at 0.961; study: docs/studies/task3-auc-intervals.md"""
    n_points: PositiveInt
    """n_W, points drawn from the target's characterization where the densities are compared (the paper: 16)
    (study: docs/studies/task3-characterization.md)"""
    false_alarm_rate: Annotated[Real, Field(gt=0, lt=1)]
    """the ODD decision's false-alarm rate α"""
    calibration_targets: PositiveInt
    """in-ODD (η = 0) targets of their own seeds calibrating the decision's threshold; the threshold's spread makes
    a healthy detector fail the binomial check on 200 targets 20 % of the time at 100, 8 % at 400"""
    false_alarm_targets: PositiveInt
    """in-ODD (η = 0) targets of new seeds (neither the calibration's nor the sweep's) on which the false-alarm rate
    is measured, with its Clopper–Pearson interval"""
    fresh_targets: StrictBool
    """beyond the paper: also run fresh targets (their in-ODD part from other test images of the sources' sub-boxes);
    the ODD decision is then calibrated and judged on them (see components.domains.sweep)"""
    smoothing: Literal["scott", "none"]
    """how a bag's weather is characterized: ``scott``, the kernel density of ``draws_per_image`` posterior draws per
    image with the sources' Scott bandwidth (components.domains.kernel); ``none``, the exact mixture of posteriors
    (the paper's: isolated peaks when the posteriors are sharp and the bags small)
    (study: docs/studies/task3-characterization.md)"""
    draws_per_image: Annotated[StrictInt, Field(ge=2)]
    """posterior draws per image behind the kernel density (smoothing: scott)"""
    bandwidth_scale: Annotated[Real, Field(gt=0)]
    """the kernel's bandwidth in units of Scott's rule, one for all bags (smoothing: scott)
    (study: docs/studies/task3-characterization.md)"""

    @model_validator(mode="after")
    def _consistent(self) -> Task3Config:
        names = sorted(self.bags, key=lambda n: int(n[1:]))
        if names != [f"b{i}" for i in range(len(names))] or len(names) < 3:
            raise ValueError(f"bags must be b0 (out of the ODD), b1, b2, … with at least two sources, got {names}")
        if len(self.weights) != len(names) - 1:
            raise ValueError(f"weights has {len(self.weights)} entries for {len(names) - 1} sources (b1…)")
        if abs(sum(self.weights) - 1.0) > 1e-9:
            raise ValueError(f"task3.weights must sum to 1 (λ on the simplex), got {list(self.weights)}")
        if 0.0 not in self.etas:
            raise ValueError("etas must contain 0 (in-ODD targets: the reference of the ROC curves)")
        labels = [f"{eta:g}" for eta in self.etas]  # the metrics' keys (components/domains/sweep.py)
        if len(set(labels)) < len(labels):
            repeated = sorted({x for x in labels if labels.count(x) > 1})
            raise ValueError(
                f"etas repeats {', '.join(repeated)} (as the metrics name them, {list(self.etas)}): the sweep of "
                "one η is deterministic, a repeat only duplicates its targets"
            )
        alpha = self.false_alarm_rate
        need = math.ceil((1.0 - alpha) / alpha - 1e-9)  # OddDetector.calibrate: ⌈(n+1)(1−α)⌉ ≤ n
        if self.calibration_targets < need:
            raise ValueError(
                f"calibration_targets = {self.calibration_targets} is too few for false_alarm_rate = "
                f"{alpha:g}: the threshold, the ⌈(n+1)(1−α)⌉-th smallest in-ODD gap, needs n ≥ {need}"
            )
        if self.n_points < len(names) - 1:
            raise ValueError(f"n_points = {self.n_points} cannot determine {len(names) - 1} weights")
        boxes = {}
        for name, bag in self.bags.items():
            try:
                boxes[name] = weather.Box.from_mapping(bag.box)
            except ValueError as e:
                raise ValueError(f"bags.{name}.box: {e}") from None
        for name in names[1:]:  # b0 must be out of the ODD: disjoint from every source's box
            a, b = boxes["b0"], boxes[name]
            if not np.any((a.high < b.low) | (b.high < a.low)):
                raise ValueError(f"bags.b0.box overlaps bags.{name}.box: b0 must be disjoint from every source")
        return self

    @property
    def sources(self) -> list[str]:
        """The source bags b1, b2, … in order."""
        return sorted((n for n in self.bags if n != "b0"), key=lambda n: int(n[1:]))


class MonitorConfig(_Section):
    """Scheduled monitoring (``flows/monitor.py``, the deployments of ``prefect.yaml``): the registered models judged
    on new labelled images every run, never a DVC output (``reports/monitoring/<date>/``, an MLflow experiment)."""

    experiment: Annotated[str, Field(min_length=1)]
    """the MLflow experiment of the monitoring runs (one run ``monitor-<date>`` per scheduled run: a time series)"""
    models: Literal["champion", "all"]
    """``champion`` (``models:/<export.registered_model>@champion``) or ``all`` (every registered model's newest
    version); a flow parameter overrides it"""
    source: Annotated[str, Field(min_length=1)]
    """``simulator`` (new images rendered from seeds of ``seed`` and the run's date) or the path of a folder of
    recorded images with their labels (``labels.csv``: ``image`` and the six parameters; relative to the project)"""
    images: PositiveInt
    """Task I images per run (simulator: rendered; a folder: its first ones in ``labels.csv``, all if it holds fewer)"""
    samples: Annotated[StrictInt, Field(ge=100)]
    """posterior draws per image (credibility of the truth, coverage, the calibration band at the same count)"""
    alarm_level: Annotated[Real, Field(gt=0.5, lt=1)]
    """the level of both alarms: the calibration band is this quantile of a perfectly calibrated model's calibration
    error on as many images and draws, and the false-alarm interval holds this probability of the ODD decision's
    false-alarm count; a model that is fine raises each alarm with probability ≤ 1 − level. With k models judged
    the band's quantile is 1 − (1 − level)/k (Bonferroni): 0.99 fails at most ~2 % of healthy runs, 0.95 up to ~10 %"""
    false_alarm_targets: NonNegativeInt
    """Task III: in-ODD targets of new seeds (and, from the simulator, new images) on which the ODD decision's
    false-alarm rate is measured with the threshold of ``reports/task3/metrics.json``; 0: no ODD check"""

    @field_validator("source")
    @classmethod
    def _source(cls, v: str) -> str:
        if v != v.strip():
            raise ValueError(f"must be 'simulator' or a folder path without surrounding spaces, got {v!r}")
        return v


class Params(_Section):
    """The whole ``params.yaml``, resolved: the default settings with the chosen profile's overrides merged over them."""

    profile: str
    """the profile whose overrides are merged over the file's settings: ``default`` (none: the file as it is) or
    the name of a file of ``profiles/`` (``paper`` for ``profiles/paper.yaml``)"""
    seed: NonNegativeInt
    """the root of every random draw in the pipeline (components/core/seeding.py)"""
    simulator: SimulatorConfig
    prior: dict[str, tuple[Real, Real]]
    """the uniform training prior: ``[low, high]`` in physical units for each of the six predicted parameters (the
    paper's Table 1 ranges by default)"""
    data: DataConfig
    contact_sheet: ContactSheetConfig
    backbones: BackbonesConfig
    train: TrainConfig
    evaluate: EvaluateConfig
    export: ExportConfig
    task2: Task2Config
    task3: Task3Config
    monitor: MonitorConfig

    @field_validator("prior")
    @classmethod
    def _prior_box(cls, v: dict[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
        weather.Box.from_mapping(v)  # raises ValueError naming the parameter
        missing = [name for name in weather.PREDICTED if name not in v]
        if missing:  # Box.from_mapping would give them their physical range: the prior is never implicit
            raise ValueError(
                f"missing {', '.join(missing)}: the prior needs [low, high] for each of the six parameters"
            )
        return v

    @model_validator(mode="after")
    def _train_fits(self) -> Params:
        largest = max(self.train.sizes)
        if largest > self.data.splits["train"]:
            raise ValueError(
                f"train.sizes has {largest} but data.splits.train is only {self.data.splits['train']}: "
                "the train split must cover the largest training size"
            )
        for name, v in self.train.variants.items():
            if v.backbone not in self.backbones.names or v.size not in self.train.sizes:
                raise ValueError(
                    f"train.variants.{name} needs a backbone in backbones.names and a size in "
                    f"train.sizes, got {v.backbone!r} and {v.size}"
                )
        regime = self.train.temperature_regime
        if regime is not None:
            box = self.box
            if regime.parameter not in box.names:
                raise ValueError(
                    f"train.temperature_regime.parameter is {regime.parameter!r}, not one of the prior's parameters "
                    f"({', '.join(box.names)})"
                )
            i = box.names.index(regime.parameter)
            if not box.low[i] < regime.below < box.high[i]:
                raise ValueError(
                    f"train.temperature_regime.below = {regime.below:g} must lie inside the prior of "
                    f"{regime.parameter}, ({box.low[i]:g}, {box.high[i]:g}): both regimes need inputs"
                )
        if self.evaluate.images != "all" and self.evaluate.images > self.data.splits["test"]:
            raise ValueError(
                f"evaluate.images is {self.evaluate.images} but the test split has only "
                f"{self.data.splits['test']} images"
            )
        lt = self.evaluate.named.local_test
        for key, n, split in (
            ("calibration_images", lt.calibration_images, "val"),
            ("test_images", lt.test_images, "test"),
        ):
            if n != "all" and n > self.data.splits[split]:
                raise ValueError(
                    f"evaluate.named.local_test.{key} is {n} but the {split} split has only {self.data.splits[split]} "
                    "images"
                )
        return self

    @model_validator(mode="after")
    def _domains_inside_prior(self) -> Params:
        """Every fixed, named or bag weather lies inside the prior; all that do not are named in one error."""
        box = self.box
        errors: list[str] = []
        for name, value in self.task2.fixed.items():
            i = box.names.index(name)
            if not box.low[i] <= value <= box.high[i]:
                errors.append(
                    f"task2.fixed.{name} = {value:g} lies outside the prior [{box.low[i]:g}, {box.high[i]:g}]"
                )
        varying = [box.names.index(name) for name in ("fog_density", "precipitation")]
        for k, mode in enumerate(self.task2.modes):
            for name, i, value in zip(("fog_density", "precipitation"), varying, mode.mean, strict=True):
                if not box.low[i] <= value <= box.high[i]:
                    errors.append(
                        f"task2.modes.{k}.mean: {name} = {value:g} lies outside the prior [{box.low[i]:g}, "
                        f"{box.high[i]:g}]: the bag's weather is the mixture truncated to the prior"
                    )
        named = dict(self.evaluate.named.weathers)
        if self.evaluate.named.presets == "carla":
            from components.core import presets

            named |= {n: {k: presets.preset_weather(n)[k] for k in weather.PREDICTED} for n in presets.USABLE}
        for name, values in named.items():
            where = (
                f"evaluate.named.weathers.{name}.{{}}"
                if name in self.evaluate.named.weathers
                else f"evaluate.named.presets: CARLA's {name} has {{}}"
            )
            for parameter, value in values.items():
                i = box.names.index(parameter)
                if not box.low[i] <= value <= box.high[i]:
                    hint = "" if name in self.evaluate.named.weathers else " (set evaluate.named.presets: none)"
                    errors.append(
                        f"{where.format(parameter)} = {value:g}, outside the prior [{box.low[i]:g}, {box.high[i]:g}]"
                        f"{hint}"
                    )
        for bag, cfg in self.task3.bags.items():
            for name, (low, high) in cfg.box.items():
                i = box.names.index(name)
                if low < box.low[i] or high > box.high[i]:
                    errors.append(
                        f"task3.bags.{bag}.box.{name} = [{low:g}, {high:g}] lies outside the prior "
                        f"[{box.low[i]:g}, {box.high[i]:g}]: a bag's sub-box must lie inside the prior"
                    )
        if errors:
            # Every misplaced value at once: a prior edit moves several of them together.
            raise ValueError("\n  ".join(errors))
        return self

    @property
    def box(self) -> weather.Box:
        """The uniform prior's support in θ-space."""
        return weather.Box.from_mapping(self.prior)

    def _model_cells(self) -> dict[str, tuple[str, int, str | None]]:
        grid = {f"{b}-{s}": (b, s, None) for b in self.backbones.names for s in self.train.sizes}
        return grid | {
            f"{v.backbone}-{v.size}-{name}": (v.backbone, v.size, name) for name, v in self.train.variants.items()
        }

    def model_ids(self) -> list[str]:
        """The grid's models (``<backbone>-<size>``), then the calibrated variants (``<backbone>-<size>-<name>``)."""
        return list(self._model_cells())

    def model_cell(self, model_id: str) -> tuple[str, int, str | None]:
        """``(backbone, size, variant name or None)`` of a model of the grid or its variants; a ``ValueError`` naming
        the known model ids otherwise."""
        cells = self._model_cells()
        if model_id not in cells:
            raise ValueError(f"no model {model_id!r} in the grid or train.variants (known: {', '.join(cells)})")
        return cells[model_id]


def _format_error(path: Path, err: ValidationError) -> str:
    lines = [f"{path}: invalid params"]
    for e in err.errors():
        loc = list(e["loc"])
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            msg = "unknown key"
        elif e["type"] == "missing" and loc and isinstance(loc[-1], int):  # a fixed-length list that is too short
            msg = f"too few items (item {loc.pop()} missing)"
        elif e["type"] == "missing":
            msg = "missing key"
        key = ".".join(str(p) for p in loc)
        lines.append(f"  {key}: {msg}" if key else f"  {msg}")  # a check across sections names its keys itself
    return "\n".join(lines)


def parse_params(data: object, *, source: str | Path = "<params>") -> Params:
    """Validate an already-loaded mapping (e.g. from YAML) into :class:`Params`."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the top level must be a mapping, got {type(data).__name__}")
    try:
        return Params.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_error(Path(source), err)) from None


class _DuplicateKey(yaml.YAMLError):
    """A key written twice in one mapping."""


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, but a key written twice in one mapping is an error (PyYAML keeps the last silently;
    DVC refuses such a params file)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[object, yaml.Mark] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, list | dict):
                continue  # unhashable: PyYAML's own error follows
            if key in seen:
                raise _DuplicateKey(
                    f"line {key_node.start_mark.line + 1}: {key} appears twice in one mapping (first "
                    f"at line {seen[key].line + 1}); PyYAML would keep the last silently"
                )
            seen[key] = key_node.start_mark
        return super().construct_mapping(node, deep=deep)


def _read_yaml(p: Path, what: str) -> object:
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"{p}: cannot read {what} ({e.strerror})") from None
    except UnicodeDecodeError as e:
        raise ConfigError(
            f"{p}: cannot read {what}: not UTF-8 text (byte {e.object[e.start]:#04x} at {e.start})"
        ) from None
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader)
    except _DuplicateKey as e:
        raise ConfigError(f"{p}: {e}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{p}: not valid YAML: {e}") from None


def profile_names(params_path: str | Path) -> list[str]:
    """The profiles a params file can use: ``default`` and every ``profiles/<name>.yaml`` beside it."""
    folder = Path(params_path).parent / "profiles"
    found = sorted(f.stem for f in folder.glob("*.yaml")) if folder.is_dir() else []
    return [DEFAULT_PROFILE, *(n for n in found if n != DEFAULT_PROFILE)]


#: mappings keyed by the user's names, not by settings: a profile's value replaces params.yaml's as a whole
NAMED_MAPPINGS: frozenset[str] = frozenset({"train.variants", "evaluate.named.weathers", "evaluate.named.folders"})


def _merge(base: dict, override: dict, where: str, unknown: list[str]) -> dict:
    """``override`` merged over ``base``: mappings recursively (but :data:`NAMED_MAPPINGS` replaced), anything else
    replaced; keys not in ``base`` are collected (dotted) in ``unknown``."""
    out = dict(base)
    for k, v in override.items():
        key = f"{where}.{k}" if where else str(k)
        if key in NAMED_MAPPINGS and k in base:
            out[k] = v
        elif k not in base:
            unknown.append(key)
        elif isinstance(base[k], dict) and isinstance(v, dict):
            out[k] = _merge(base[k], v, key, unknown)
        else:
            out[k] = v
    return out


def _apply_profile(data: dict, p: Path, name: object) -> tuple[dict, str]:
    """The params ``data`` of file ``p`` with profile ``name``'s overrides merged in, and the source to name."""
    names = profile_names(p)
    if not isinstance(name, str) or name not in names:
        raise ConfigError(
            f"{p}: profile: unknown profile {name!r}; profiles found: {', '.join(names)} "
            f"(default, or profiles/<name>.yaml beside {p.name})"
        )
    if name == DEFAULT_PROFILE:
        return {**data, "profile": name} if "profile" in data else data, str(p)
    pp = p.parent / "profiles" / f"{name}.yaml"
    overrides = _read_yaml(pp, "profile")
    if overrides is None:
        overrides = {}
    if not isinstance(overrides, dict):
        raise ConfigError(f"{pp}: the top level must be a mapping of overrides, got {type(overrides).__name__}")
    if "profile" in overrides:
        raise ConfigError(f"{pp}: profile: unknown key (a profile's name is its file name; it cannot set one)")
    unknown: list[str] = []
    merged = _merge(data, overrides, "", unknown)
    if unknown:
        raise ConfigError("\n".join(f"{pp}: {key}: unknown key (not a setting of {p})" for key in unknown))
    if "profile" in data:
        merged["profile"] = name
    return merged, f"{p} with {pp}"


def load_params(path: str | Path | None = None, profile: str | None = None) -> Params:
    """Read, resolve and validate a params file (default: ``params.yaml`` at the project root).

    The profile is ``profile`` if given, else the file's ``profile`` key; unless it is ``default``, the overrides of
    ``<params dir>/profiles/<profile>.yaml`` are merged over the file's settings before validation."""
    p = Path(path) if path is not None else PROJECT_ROOT / "params.yaml"
    data = _read_yaml(p, "params file")
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: the top level must be a mapping, got {type(data).__name__}")
    source = str(p)
    name = profile if profile is not None else data.get("profile")
    if name is not None or "profile" in data:
        data, source = _apply_profile(data, p, name)
    return parse_params(data, source=source)
