"""Training loop of the neural posterior estimator: AdamW, LR schedule, early stopping, resumable checkpoints.

The loss is :func:`~components.posterior.loss.npe_loss`: ``−log q(θ | x)`` in PHYSICAL units (Jacobian of the
bijection included), plus ``balance · penalty`` for balanced NPE. Early stopping watches the validation loss (the
same objective) and the returned model holds the weights of the best epoch.

Randomness, all from ``TrainingConfig.seed`` (no global RNG state leaks):

* shuffling: epoch ``e`` permutes the training set with a ``torch.Generator`` seeded by
  ``seeding.derive_seed(seed, "train", "shuffle", e)``, so epoch ``e``'s order does not depend on earlier epochs;
* any global-RNG use inside the model (e.g. dropout in a caller's embedding) runs in ``torch.random.fork_rng``
  seeded by ``derive_seed(seed, "train", "torch", e)``;
* the flows' initial weights come from :class:`~components.posterior.model.NPE`'s own ``seed``;
* balanced NPE's marginal pairs roll θ by one place within the shuffled batch (no extra draws).

Hence a run killed after epoch ``e`` resumes from its checkpoint (model, AdamW and schedule state, best weights,
early-stopping counters, history) and ends bit-for-bit like an uninterrupted run (same thread count and device).

Used by the ``train`` stage; the ``export`` stage imports it only through
:mod:`components.posterior`.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from components.core import seeding
from components.core.checks import whole_number
from components.posterior.checkpoint import load_checkpoint, save_checkpoint
from components.posterior.loss import npe_loss, npe_loss_terms
from components.posterior.model import NPE, finite_rows

__all__ = ["TrainingConfig", "EpochRecord", "History", "train", "check_split"]

CHECKPOINT_FORMAT = 1


@dataclass(frozen=True)
class TrainingConfig:
    """Settings of :func:`train`.

    Attributes:
        epochs: maximum number of passes over the training set.
        batch_size: simulations per step (validation uses the same batches size).
        lr: AdamW's initial learning rate.
        weight_decay: AdamW's decoupled weight decay.
        schedule: ``"cosine"`` (annealed from ``lr`` to ``min_lr`` over ``epochs``), ``"plateau"`` (× ``plateau_factor``
            after ``plateau_patience`` epochs without improvement, floored at ``min_lr``) or ``"constant"``.
        min_lr: the schedule's floor.
        plateau_factor: the ``"plateau"`` schedule's factor on the learning rate.
        plateau_patience: the ``"plateau"`` schedule's epochs without improvement before it cuts the rate.
        patience: early stopping: stop after this many epochs without a validation loss below best − ``min_delta``;
            ``None``: every epoch runs. Either way the model ends with the weights of its best validation epoch.
        min_delta: the improvement that counts (nats).
        clip_norm: the gradients' global L2 norm is clipped to this; ``None`` = no clipping.
        seed: the root of the training's random draws (shuffling, global-RNG use in the model).
        balance: λ of balanced NPE (0 = plain NPE; Delaunoy et al. use 100).
        input_noise: σ of Gaussian noise added to each training input, in units of the input's training-set
            standard deviation (the model's ``feature_std``): x + σ·std·ε, ε ~ 𝒩(0, I), drawn anew every batch; a
            regularizer that keeps a flow trained on few simulations from trusting every feature to its last digit
            (0 = none; never at validation or inference).
        spared: the input features (indices into the last axis, increasing) whose noise is ``spared_noise`` of
            ``input_noise``: a backbone's estimates of θ sharper than the noise
            (:meth:`~components.features.backbones.base.Backbone.spared_index`), whose precision the noise would cap
            (docs/studies/estimate-noise.md).
        spared_noise: the input noise on ``spared``, as a share of ``input_noise`` (1: the same as on every feature;
            0: none).
        mirror: replace each training input by its mirror image's with probability ½, drawn anew every batch
            (``train``'s ``mirror`` maps a batch of inputs to those of the left-right mirrored images): the weather
            and the sun and wind azimuths (uniform) keep their law when the image is mirrored, the scenes nearly (the
            traffic keeps to one side, which the mirrored inputs teach the flow to ignore); twice the distinct
            training inputs at no rendering cost (never at validation or inference).
        compile: compile the training loss (forward and backward) with ``torch.compile`` (inductor: generated C++
            kernels) and use AdamW's fused kernel; full batches only, the last, smaller batch of an epoch runs
            eagerly. 1.7–1.9× faster steps on a 2-core CPU after a compilation of 35–50 s per model shape (cached on disk
            for later processes); the kernels add floats in another order than eager torch, so the weights differ
            from an eager run's in the last digits (and are, like those, reproducible on one machine and thread
            count).
    """

    epochs: int = 200
    batch_size: int = 256
    lr: float = 1e-3
    weight_decay: float = 1e-4
    schedule: Literal["cosine", "plateau", "constant"] = "cosine"
    min_lr: float = 1e-6
    plateau_factor: float = 0.5
    plateau_patience: int = 5
    patience: int | None = 20
    min_delta: float = 0.0
    clip_norm: float | None = 5.0
    seed: int = 0
    balance: float = 0.0
    input_noise: float = 0.0
    spared: tuple[int, ...] = ()
    spared_noise: float = 1.0
    mirror: bool = False
    compile: bool = False

    def __post_init__(self) -> None:
        for name, low in (("epochs", 1), ("batch_size", 1), ("plateau_patience", 1), ("seed", 0)):
            object.__setattr__(self, name, whole_number(f"TrainingConfig.{name}", getattr(self, name), low=low))
        if self.patience is not None:
            hint = " or None (no early stopping)"
            object.__setattr__(
                self, "patience", whole_number("TrainingConfig.patience", self.patience, low=1, hint=hint)
            )
        for name, low_ok in (
            ("lr", False),
            ("weight_decay", True),
            ("min_lr", True),
            ("min_delta", True),
            ("balance", True),
            ("input_noise", True),
            ("spared_noise", True),
        ):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0 or (v == 0 and not low_ok):
                raise ValueError(
                    f"TrainingConfig.{name} must be a finite number {'>=' if low_ok else '>'} 0, got {v!r}"
                )
        if self.min_lr > self.lr:
            raise ValueError(f"TrainingConfig.min_lr ({self.min_lr:g}) must not exceed lr ({self.lr:g})")
        if not 0 < self.plateau_factor < 1:
            raise ValueError(f"TrainingConfig.plateau_factor must be in (0, 1), got {self.plateau_factor!r}")
        if self.schedule not in ("cosine", "plateau", "constant"):
            raise ValueError(
                f"TrainingConfig.schedule must be 'cosine', 'plateau' or 'constant', got {self.schedule!r}"
            )
        if self.clip_norm is not None and not (isinstance(self.clip_norm, (int, float)) and self.clip_norm > 0):
            raise ValueError(f"TrainingConfig.clip_norm must be > 0 or None, got {self.clip_norm!r}")
        free = self.spared
        if (
            not isinstance(free, tuple)
            or any(isinstance(i, bool) or not isinstance(i, int) or i < 0 for i in free)
            or list(free) != sorted(set(free))
        ):
            raise ValueError(
                f"TrainingConfig.spared must be a tuple of distinct feature indices ≥ 0 in increasing order, got {free!r}"
            )
        for name in ("mirror", "compile"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"TrainingConfig.{name} must be true or false, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class EpochRecord:
    """One epoch of training, as handed to the callback (e.g. to log metrics).

    Attributes:
        epoch: 0-based epoch index.
        train_loss: mean training loss (nats, physical units; ``nll + balance·penalty``).
        val_loss: mean validation loss (the same).
        train_nll: mean −log q(θ | x) on the training pairs (nats, physical units).
        val_nll: the same on the validation pairs.
        train_penalty: mean balancing penalty on the training pairs (0 for plain NPE).
        val_penalty: the same on the validation pairs.
        lr: the learning rate used during the epoch.
        wall_time: seconds spent on the epoch (training + validation).
        best_epoch: the best epoch so far (lowest ``val_loss``).
        improved: whether this epoch is the new best.
    """

    epoch: int
    train_loss: float
    val_loss: float
    train_nll: float
    val_nll: float
    train_penalty: float
    val_penalty: float
    lr: float
    wall_time: float
    best_epoch: int
    improved: bool


@dataclass
class History:
    """What :func:`train` returns: one :class:`EpochRecord` per epoch run, and the outcome.

    Attributes:
        records: per-epoch records, in order.
        best_epoch: the epoch whose weights the model holds after training (-1 before any epoch).
        best_val_loss: its validation loss.
        stopped_early: whether early stopping ended the run before ``epochs``.
    """

    records: list[EpochRecord] = field(default_factory=list)
    best_epoch: int = -1
    best_val_loss: float = math.inf
    stopped_early: bool = False

    def column(self, name: str) -> list[float]:
        """One field over epochs, e.g. ``history.column("val_loss")``."""
        return [getattr(r, name) for r in self.records]

    @property
    def train_loss(self) -> list[float]:
        return self.column("train_loss")

    @property
    def val_loss(self) -> list[float]:
        return self.column("val_loss")

    @property
    def lr(self) -> list[float]:
        return self.column("lr")

    @property
    def wall_time(self) -> list[float]:
        return self.column("wall_time")

    def to_dict(self) -> dict[str, Any]:
        """Plain Python (JSON-serializable) form."""
        return {
            "records": [asdict(r) for r in self.records],
            "best_epoch": self.best_epoch,
            "best_val_loss": self.best_val_loss,
            "stopped_early": self.stopped_early,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> History:
        return cls(
            [EpochRecord(**r) for r in d["records"]],
            int(d["best_epoch"]),
            float(d["best_val_loss"]),
            bool(d["stopped_early"]),
        )


# --- input validation -----------------------------------------------------------------------------------


def _as_tensor(a: object, what: str) -> Tensor:
    if isinstance(a, Tensor):
        return a.detach().cpu()
    try:
        return torch.as_tensor(np.asarray(a))
    except (TypeError, ValueError) as err:
        raise TypeError(f"{what} must be an array or tensor, got {type(a).__name__} ({err})") from None


def check_split(name: str, data: tuple[object, object], model: NPE) -> tuple[Tensor, Tensor]:
    """Validate one split ``(x, θ)`` for ``model`` and return ``(x float32, θ float64)`` CPU tensors.

    Raises ``ValueError`` naming the split for: not a pair, empty, different lengths, x of the wrong shape or with
    NaN/inf, θ of the wrong shape, non-finite or outside the prior box (naming the parameter and its range).
    """
    if not isinstance(data, (tuple, list)) or len(data) != 2:
        raise ValueError(f"{name} split must be a pair (x, θ), got {type(data).__name__}")
    x = _as_tensor(data[0], f"{name} x")
    theta = _as_tensor(data[1], f"{name} θ")
    if x.dim() == 0 or theta.dim() == 0:
        raise ValueError(
            f"{name} split: x and θ need a leading sample axis, got shapes {tuple(x.shape)} and {tuple(theta.shape)}"
        )
    if x.shape[0] == 0 or theta.shape[0] == 0:
        raise ValueError(f"{name} split is empty (x has {x.shape[0]} rows, θ has {theta.shape[0]})")
    if x.shape[0] != theta.shape[0]:
        raise ValueError(f"{name} split: x has {x.shape[0]} rows but θ has {theta.shape[0]}")
    if model.input_shape is not None and tuple(x.shape[1:]) != model.input_shape:
        raise ValueError(
            f"{name} x must have shape (n, {', '.join(map(str, model.input_shape))}), got {tuple(x.shape)}"
        )
    if not x.is_floating_point():
        x = x.to(torch.float32)
    finite = finite_rows(x)
    if not bool(finite.all()):
        row = int((~finite).nonzero()[0])
        raise ValueError(f"{name} x contains NaN or infinite values ({int((~finite).sum())} rows, first at row {row})")
    if theta.dim() != 2 or theta.shape[1] != model.dim:
        raise ValueError(
            f"{name} θ must have shape (n, {model.dim}) ({', '.join(model.box.names)}), got {tuple(theta.shape)}"
        )
    theta = theta.to(torch.float64)
    model.box.check(theta.numpy(), what=f"{name} θ")
    return x.to(torch.float32), theta


def _fingerprint(x: Tensor, theta: Tensor) -> str:
    h = hashlib.sha256()
    h.update(str(tuple(x.shape)).encode())
    h.update(theta.numpy().tobytes())
    h.update(np.float64(torch.sum(x, dtype=torch.float64)).tobytes())  # = x.double().sum(), without the copy
    return h.hexdigest()


# --- the loop ---------------------------------------------------------------------------------------------


def _scheduler(opt: torch.optim.Optimizer, config: TrainingConfig) -> Any:
    if config.schedule == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=config.epochs, eta_min=config.min_lr)
    if config.schedule == "plateau":
        return torch.optim.lr_scheduler.ReduceLROnPlateau(
            opt, mode="min", factor=config.plateau_factor, patience=config.plateau_patience, min_lr=config.min_lr
        )
    return torch.optim.lr_scheduler.LambdaLR(opt, lambda _: 1.0)


def _batches(n: int, size: int, order: Tensor | None = None) -> list[Tensor]:
    idx = order if order is not None else torch.arange(n)
    return list(torch.split(idx, size))


def _evaluate(model: NPE, x: Tensor, theta: Tensor, config: TrainingConfig) -> tuple[float, float, float]:
    """Mean (loss, nll, penalty) over fixed batches of the validation set, weighted by batch size."""
    model.eval()
    totals = np.zeros(3)
    with torch.no_grad():
        for idx in _batches(x.shape[0], config.batch_size):
            parts = npe_loss(model, theta[idx], x[idx], balance=config.balance)
            totals += len(idx) * np.array([float(parts.loss.detach()), parts.nll, parts.penalty])
    return tuple(float(v) for v in totals / x.shape[0])  # type: ignore[return-value]


def _loss_terms(model: NPE, config: TrainingConfig) -> Callable[[Tensor, Tensor], tuple[Tensor, Tensor, Tensor]]:
    """``(θ, x) ↦ (loss, nll, penalty)`` of a training batch: :func:`npe_loss_terms`, compiled when ``config.compile``
    (one graph for the full batch size; other sizes run eagerly, so a ragged last batch causes no recompilation)."""

    def terms(theta: Tensor, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return npe_loss_terms(model, theta, x, balance=config.balance)

    if not config.compile:
        return terms
    compiled = torch.compile(terms, dynamic=False)
    compiled_once = False

    def full_batches_compiled(theta: Tensor, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        nonlocal compiled_once
        if theta.shape[0] != config.batch_size:
            return terms(theta, x)
        if compiled_once:
            return compiled(theta, x)
        try:  # the first call compiles: inductor needs a working C++ compiler
            out = compiled(theta, x)
        except Exception as err:
            first_line = next((line for line in str(err).splitlines() if line.strip()), "")
            raise RuntimeError(
                f"TrainingConfig.compile: torch.compile could not compile the training loss ({type(err).__name__}: "
                f"{first_line}). Compiling needs a C++ compiler (g++; scripts/setup.sh installs one where it can): "
                "install one, or set train.compile_min_steps: null in params.yaml to train eagerly"
            ) from err
        compiled_once = True
        return out

    return full_batches_compiled


def _fork_devices(model: NPE) -> list[int]:
    dev = model.device
    return [dev.index or 0] if dev.type == "cuda" else []


def _clone_state(model: NPE) -> dict[str, Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def train(
    model: NPE,
    train_set: tuple[object, object],
    val_set: tuple[object, object],
    config: TrainingConfig = TrainingConfig(),
    *,
    checkpoint: str | Path | None = None,
    callback: Callable[[EpochRecord], None] | None = None,
    progress: bool = True,
    mirror: Callable[[Tensor], Tensor] | None = None,
) -> History:
    """Fit ``model`` to simulations by (balanced) NPE; the model ends with its best epoch's weights.

    One function on purpose (over 80 lines): the epoch loop, its checkpoint and its resume share one state, in one
    order of random draws; split, a resumed run could draw its batches in another order than an uninterrupted one.

    Arguments:
        model: the estimator; its standardization is fitted here on the training x (unless resuming).
        train_set: ``(x (n, *input_shape), θ (n, d))`` arrays or tensors, θ in physical units inside
            ``model.box`` (drawn from the uniform prior on it). Validated before any training.
        val_set: the validation pairs, in the same form (early stopping and the best epoch are judged on them).
        config: the settings.
        checkpoint: a file path; after every epoch the full training state is written there atomically. If the
            file exists, training resumes from it (same config and data required; a finished run just restores
            the best weights and returns its history).
        callback: called after each epoch (after the checkpoint is written) with its :class:`EpochRecord`.
        progress: show a tqdm progress bar over epochs.
        mirror: with ``config.mirror``, the inputs ``(B, *input_shape)`` of the left-right mirrored images of a batch's
            inputs (e.g. :meth:`components.features.backbones.base.Backbone.mirror_inputs`); required then, unused otherwise.

    Returns:
        the :class:`History`; the model is left in eval mode.
    """
    if not isinstance(model, NPE):
        raise TypeError(f"model must be an NPE, got {type(model).__name__}")
    if not isinstance(config, TrainingConfig):
        raise TypeError(f"config must be a TrainingConfig, got {type(config).__name__}")
    x_tr, th_tr = check_split("train", train_set, model)
    x_va, th_va = check_split("val", val_set, model)
    fingerprint = _fingerprint(x_tr, th_tr) + _fingerprint(x_va, th_va)
    device = model.device

    # compiled training also takes AdamW's fused kernel (one loop over all parameters: ~15 % of a compiled step)
    opt = torch.optim.AdamW(
        model.parameters(), lr=config.lr, weight_decay=config.weight_decay, fused=config.compile or None
    )
    sched = _scheduler(opt, config)
    history = History()
    best_state: dict[str, Tensor] | None = None
    bad_epochs = 0
    start = 0

    state = load_checkpoint(checkpoint) if checkpoint is not None else None
    if state is not None:
        if state.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(
                f"checkpoint {checkpoint} has format {state.get('format')!r}, expected {CHECKPOINT_FORMAT}"
            )
        saved = state["config"]
        diff = [f.name for f in fields(config) if saved.get(f.name) != getattr(config, f.name)]
        if diff:
            raise ValueError(
                f"checkpoint {checkpoint} was written with other training settings ({', '.join(diff)}); "
                "delete it or use another path"
            )
        if state["data"] != fingerprint:
            raise ValueError(
                f"checkpoint {checkpoint} was written for other training/validation data; delete it or use another path"
            )
        try:
            model.load_state_dict(state["model"])
        except RuntimeError as err:
            raise ValueError(f"checkpoint {checkpoint} does not fit this model's architecture: {err}") from None
        history = History.from_dict(state["history"])
        best_state = state["best_model"]
        if state["finished"]:
            model.load_state_dict(best_state)
            model.eval()
            return history
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        bad_epochs = int(state["bad_epochs"])
        # killed between the early stop's checkpoint and the final write: nothing left to train
        start = config.epochs if history.stopped_early else int(state["epoch"]) + 1
    else:
        model.fit_standardization(x_tr)

    def write(epoch: int, finished: bool) -> None:
        if checkpoint is None:
            return
        save_checkpoint(
            {
                "format": CHECKPOINT_FORMAT,
                "epoch": epoch,
                "finished": finished,
                "config": asdict(config),
                "data": fingerprint,
                "model": model.state_dict(),
                "best_model": best_state,
                "optimizer": opt.state_dict(),
                "scheduler": sched.state_dict(),
                "bad_epochs": bad_epochs,
                "history": history.to_dict(),
            },
            checkpoint,
        )

    n = x_tr.shape[0]
    noise_scale = getattr(model, "feature_std", None)
    if config.input_noise > 0 and noise_scale is None:
        raise ValueError(
            "TrainingConfig.input_noise needs a model with standardization buffers (an NPE with input_shape)"
        )
    if config.input_noise > 0 and config.spared and config.spared_noise != 1:
        if noise_scale.ndim != 1 or config.spared[-1] >= noise_scale.shape[0]:
            raise ValueError(
                f"TrainingConfig.spared names feature {config.spared[-1]}, but the inputs have "
                f"{noise_scale.shape[-1] if noise_scale.ndim else 0} features in one axis"
            )
        noise_scale = noise_scale.clone()
        noise_scale[list(config.spared)] *= config.spared_noise
    if config.mirror:
        if mirror is None:
            raise ValueError("TrainingConfig.mirror needs train(..., mirror=<the inputs of the mirrored images>)")
        probe = mirror(x_tr[:2].to(device))  # before any epoch: an input that cannot mirror fails here, named
        if probe.shape != x_tr[:2].shape:
            raise ValueError(f"mirror maps inputs {tuple(x_tr[:2].shape)} to {tuple(probe.shape)}, not to their shape")
    loss_terms = _loss_terms(model, config)
    bar = tqdm(total=config.epochs, initial=start, desc="train NPE", unit="epoch", disable=not progress, leave=False)
    try:
        for epoch in range(start, config.epochs):
            t0 = time.perf_counter()
            lr = float(opt.param_groups[0]["lr"])
            shuffle = torch.Generator().manual_seed(seeding.derive_seed(config.seed, "train", "shuffle", epoch))
            order = torch.randperm(n, generator=shuffle)
            sums = np.zeros(3)
            model.train()
            with torch.random.fork_rng(devices=_fork_devices(model)):
                torch.manual_seed(seeding.derive_seed(config.seed, "train", "torch", epoch))
                for b, idx in enumerate(_batches(n, config.batch_size, order)):
                    xb = x_tr[idx].to(device)
                    if config.mirror:
                        flip = (torch.rand(len(idx)) < 0.5).to(device).view(-1, *(1,) * (xb.ndim - 1))
                        xb = torch.where(flip, mirror(xb), xb)
                    if config.input_noise > 0:
                        xb = xb + config.input_noise * noise_scale * torch.randn_like(xb)
                    loss, nll, penalty = loss_terms(th_tr[idx].to(device), xb)
                    values = np.array([float(loss.detach()), float(nll.detach()), float(penalty.detach())])
                    if not math.isfinite(values[0]):
                        raise FloatingPointError(
                            f"non-finite training loss at epoch {epoch}, batch {b} (nll {values[1]}, penalty {values[2]}); "
                            "lower TrainingConfig.lr or set clip_norm"
                        )
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    if config.clip_norm is not None:
                        torch.nn.utils.clip_grad_norm_(model.parameters(), config.clip_norm)
                    opt.step()
                    sums += len(idx) * values
            train_loss, train_nll, train_pen = (float(v) for v in sums / n)
            val_loss, val_nll, val_pen = _evaluate(model, x_va, th_va, config)
            if not math.isfinite(val_loss):
                raise FloatingPointError(f"non-finite validation loss at epoch {epoch}; lower TrainingConfig.lr")
            if config.schedule == "plateau":
                sched.step(val_loss)
            else:
                sched.step()
            improved = val_loss < history.best_val_loss - config.min_delta
            if improved:
                history.best_epoch, history.best_val_loss = epoch, val_loss
                best_state = _clone_state(model)
                bad_epochs = 0
            else:
                bad_epochs += 1
            record = EpochRecord(
                epoch,
                train_loss,
                val_loss,
                train_nll,
                val_nll,
                train_pen,
                val_pen,
                lr,
                time.perf_counter() - t0,
                history.best_epoch,
                improved,
            )
            history.records.append(record)
            stop = config.patience is not None and bad_epochs >= config.patience and epoch + 1 < config.epochs
            history.stopped_early = stop
            write(epoch, finished=False)
            if callback is not None:
                callback(record)
            bar.update(1)
            bar.set_postfix(train=f"{train_loss:.3f}", val=f"{val_loss:.3f}", best=history.best_epoch)
            if stop:
                break
    finally:
        bar.close()
    if best_state is not None:
        model.load_state_dict(best_state)
    model.eval()
    write(history.records[-1].epoch if history.records else -1, finished=True)
    return history
