"""pidc's NPE training against the ``sbi`` package's NPE: same cached features, same flow size, same data.

What is compared (the issue: "training throughput and time to reach a given validation loss, side by side with
the ``sbi`` package's NPE on the same features and flow size, as a ratio"):

* data: the first ``--n-train`` (10 000) cached ``cues`` features (377-dim today) of the train split and their θ
  (the 6 physical weather parameters, inside the prior box of ``params.yaml``); the benchmark's validation set =
  the whole val split (6 000 today), read through pidc's API (``open_split``, ``open_features``);
* flow: a conditional zuko 1.6 NSF with 3 coupling transforms (``passes=2``), MLPs of 128×128 hidden units,
  8 spline bins — pidc: ``FlowConfig(transforms=3, hidden_features=(128, 128), bins=8, passes=2)``; sbi:
  ``posterior_nn(model="zuko_nsf", hidden_features=[128, 128], num_transforms=3, num_bins=8, passes=2)``
  (sbi 0.27 turns an integer ``hidden_features=h`` into ``[h] * num_transforms`` hidden LAYERS, i.e. three
  layers for three transforms, so the list is given). Both have 136 350 trainable parameters;
* optimisation: batch 256, learning rate 1e-3, gradient-norm clip 5, ``torch.set_num_threads(--threads)`` on
  both, ``--epochs`` epochs on both (early stopping off on both, so the epoch budgets are equal); pidc eager and
  pidc with its training loss compiled (``--pidc eager compiled``: ``TrainingConfig.compile``, what the pipeline
  turns on from ``train.compile_min_steps`` steps; its compile, from torch's on-disk cache when warm, is inside
  the timed first epoch);
* measures: (a) step throughput — samples/s of forward + backward + optimiser step alone, best of 3, fresh
  models; (b) loop throughput — samples trained per wall second of each library's own training loop (its
  own validation, data loading and bookkeeping included, the benchmark's extra evaluation excluded);
  (c) the validation NLL curve on the SAME val split after every epoch, evaluated by this script from inside
  each loop (pidc's ``train`` callback; for sbi a subclass hook on ``_summarize_epoch``), its time subtracted;
  (d) wall time until each first reaches two targets: the first pidc run's val NLL after ``--target-epoch``
  epochs, and the best val NLL that every run reaches (the worst run's best: "at equal validation NLL");
  (e) the val NLL of the model each library returns.

Units. pidc's ``log_prob`` is a density over θ in physical units (the logit bijection's Jacobian included);
sbi's flow is over raw θ with a z-score ``UnconditionalTransform`` inside the zuko flow, whose Jacobian the
flow's ``log_prob`` includes, so it is a density over θ in the same physical units. The script checks this
numerically (the "units check"): for a few val x, ``∫ q(θ|x) dθ`` over a sub-box around the posterior is
estimated twice — by uniform Monte Carlo of ``q`` (the density's value) and as the fraction of ``q``'s own
samples falling in the sub-box (its mass): a wrong Jacobian (e.g. a missing ``Σ log σ`` ≈ 21 nats) would
make them differ by orders of magnitude.

Unavoidable differences (all are sbi's defaults, what a user of sbi gets):

* θ: sbi z-scores θ (mean/std of its training part) and its flow lives on ℝ⁶, so it puts mass outside the
  prior box ("leakage"); pidc's flow is over the scaled logit of θ, exactly supported on the box. The val
  NLL of sbi is its raw estimator's (what sbi trains on); the returned model's NLL is also given after the
  leakage correction ``−log q + log P_q(θ ∈ box | x)`` (what sbi's ``DirectPosterior.log_prob`` does), with
  ``P_q`` estimated from ``--leak-samples`` draws per x. ``--sbi-theta transform_to_unconstrained`` runs
  sbi with its logit-type transform to the box instead (without pidc's scaling by 1/Z_SCALE, so near the
  box's faces sbi's logit leaves the splines' [−5, 5] domain);
* validation: sbi holds out a random ``validation_fraction = 0.1`` of the 10 000 for its own validation and
  model selection and trains on the other 9 000 (35 batches, ``drop_last=True``: 8 960 samples per epoch);
  pidc holds out the last 1 000 of them for its own (early stopping's) validation and trains on the first
  9 000 (36 batches, the last of 40). Both validate as many pairs per epoch and neither selects its returned
  model on the benchmark's val split (until 2026-12-05 pidc validated on the whole val split, 6× sbi's work
  per epoch, and picked its returned epoch there);
* optimiser: pidc AdamW (weight decay 1e-4) with a cosine schedule over ``--epochs`` (its pipeline
  defaults, ``params.yaml`` ``train``), or over ``--pidc-epochs`` when given (pidc then trains that many epochs,
  sbi still ``--epochs``: a schedule sized to the budget, as a user who wants the model sooner sets it);
  sbi Adam at a constant learning rate;
* sbi's trainer draws its train/val split, shuffling and initial weights from torch's global RNG: the script
  seeds it (from ``components.core.seeding``) inside ``torch.random.fork_rng``. sbi's TensorBoard logging is
  replaced by an in-memory tracker (sbi's ``Tracker`` protocol) so that no ``sbi-logs/`` folder is written.

Set-up (sbi lives in its own environment, never in ``.venv``; the torch pin keeps pip from fetching a CUDA
build)::

    python3 -m venv /work/main/.venv-sbi
    /work/main/.venv-sbi/bin/pip install torch==2.13.0
    echo "torch==2.13.0" > /tmp/sbi-constraints.txt
    /work/main/.venv-sbi/bin/pip install -c /tmp/sbi-constraints.txt sbi zuko numpy pyyaml pydantic \\
        opencv-python-headless tqdm
    /work/main/.venv-sbi/bin/pip install -c /tmp/sbi-constraints.txt -e /work/main --no-deps

(sbi 0.27.0, zuko 1.6.0, torch 2.13.0+cpu at the time of writing.) Needs the cached features
(``dvc repro features@cues``). Run from the repository root::

    .venv-sbi/bin/python benchmarks/bench_sbi.py [--threads 2] [--epochs 60] [--pidc-epochs N] [--target-epoch 20]
        [--sbi-theta independent transform_to_unconstrained] [--wait-load 1.5 --max-wait 600]

Prints the units check, a table (pidc, sbi, ratio sbi/pidc) and one JSON line with the settings, the
machine (load average before and after) and all figures, per-epoch curves included.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import math
import os
import platform
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from components.core import (
    config,
    seeding,
    weather,  # noqa: E402
)
from components.features import cache as features
from components.posterior import NPE, FlowConfig, TrainingConfig, npe_loss, train  # noqa: E402
from components.posterior.loss import npe_loss_terms
from components.simulate import dataset

SETUP_HINT = (
    "run this script with the sbi environment: .venv-sbi/bin/python benchmarks/bench_sbi.py "
    "(set it up with the commands in this script's docstring)"
)

try:
    import sbi
    import zuko
    from sbi.inference import NPE as SbiNPE
    from sbi.neural_nets import posterior_nn
    from sbi.utils import BoxUniform
except ImportError as err:  # the CI environment has no sbi on purpose
    raise SystemExit(f"bench_sbi: cannot import sbi ({err}); {SETUP_HINT}") from None

BATCH = 256
LR = 1e-3
CLIP = 5.0
HIDDEN = (128, 128)
TRANSFORMS = 3
BINS = 8
PASSES = 2


# --- data ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Data:
    """Train and val features ``x (n, 80)`` float32 and θ ``(n, 6)`` float64 (physical units), and the prior box."""

    x_train: Tensor
    theta_train: Tensor
    x_val: Tensor
    theta_val: Tensor
    box: weather.Box
    backbone: str


def load_data(data_root: Path, features_root: Path, backbone: str, n_train: int) -> Data:
    """The first ``n_train`` cached features of the train split and the whole val split, through pidc's API."""
    hint = f"run `dvc repro features@{backbone}` (it also generates the dataset) from the repository root"
    if not (data_root / "manifest.json").is_file():
        raise SystemExit(f"bench_sbi: no dataset at {data_root}; {hint}")
    if not (features_root / backbone / "manifest.json").is_file():
        raise SystemExit(f"bench_sbi: no cached {backbone!r} features at {features_root / backbone}; {hint}")
    try:
        train_split = dataset.open_split(data_root, "train")
        val_split = dataset.open_split(data_root, "val")
        if n_train > len(train_split):
            raise SystemExit(f"bench_sbi: --n-train {n_train} exceeds the train split's {len(train_split)} images")
        x_tr = features.open_features(features_root, backbone, train_split, stop=n_train)
        x_va = features.open_features(features_root, backbone, val_split)
    except (dataset.DatasetError, features.FeatureError) as err:
        raise SystemExit(f"bench_sbi: {err}; {hint}") from None
    box = config.load_params().box
    th_tr, th_va = train_split.theta[:n_train], val_split.theta
    box.check(th_tr, what="train θ")
    box.check(th_va, what="val θ")
    return Data(
        torch.as_tensor(x_tr, dtype=torch.float32),
        torch.as_tensor(th_tr, dtype=torch.float64),
        torch.as_tensor(x_va, dtype=torch.float32),
        torch.as_tensor(th_va, dtype=torch.float64),
        box,
        backbone,
    )


# --- the two estimators --------------------------------------------------------------------------------


def pidc_model(data: Data, seed: int) -> NPE:
    cfg = FlowConfig(transforms=TRANSFORMS, hidden_features=HIDDEN, bins=BINS, passes=PASSES)
    return NPE(None, data.x_train.shape[1], data.box, cfg, seed=seeding.derive_seed(seed, "bench", "sbi", "pidc"))


def sbi_prior(box: weather.Box) -> BoxUniform:
    return BoxUniform(
        torch.tensor(np.array(box.low), dtype=torch.float32), torch.tensor(np.array(box.high), dtype=torch.float32)
    )


def sbi_builder(box: weather.Box, theta_transform: str) -> Callable[[Tensor, Tensor], Any]:
    """sbi's builder of a zuko NSF of pidc's size (``passes`` is forwarded to zuko, sbi warns it does not know it)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Unknown kwargs passed to ConditionalFlowConfig")
        return posterior_nn(
            model="zuko_nsf",
            z_score_theta=theta_transform,
            z_score_x="independent",
            hidden_features=list(HIDDEN),
            num_transforms=TRANSFORMS,
            num_bins=BINS,
            passes=PASSES,
            x_dist=sbi_prior(box),
        )


class MemoryTracker:
    """sbi's ``Tracker`` protocol, keeping the metrics in memory (instead of TensorBoard files in the cwd)."""

    def __init__(self) -> None:
        self.metrics: dict[str, list[tuple[int | None, float]]] = {}

    @property
    def log_dir(self) -> str | None:
        return None

    def log_metric(self, name: str, value: float, step: int | None = None) -> None:
        self.metrics.setdefault(name, []).append((step, float(value)))

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        for name, value in metrics.items():
            self.log_metric(name, value, step)

    def log_params(self, params: dict[str, Any]) -> None:
        return None

    def add_figure(self, name: str, figure: Any, step: int | None = None) -> None:
        return None

    def flush(self) -> None:
        return None


class HookedNPE(SbiNPE):
    """sbi's NPE whose training loop calls ``on_epoch(estimator)`` at the end of every epoch (after its validation)."""

    def __init__(self, on_epoch: Callable[[Any], None], **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._on_epoch = on_epoch

    def _summarize_epoch(self, *args: Any, **kwargs: Any) -> None:
        super()._summarize_epoch(*args, **kwargs)
        self._on_epoch(self._neural_net)


# --- evaluation ----------------------------------------------------------------------------------------


@torch.no_grad()
@torch.no_grad()
def pidc_nll(model: NPE, x: Tensor, theta: Tensor) -> float:
    """Mean −log q(θ | x) over the set, nats, physical units."""
    model.eval()
    return float(
        -torch.cat([model.log_prob(t, xb) for xb, t in zip(x.split(2048), theta.split(2048), strict=False)])
        .double()
        .mean()
    )


@torch.no_grad()
def sbi_log_prob(net: Any, x: Tensor, theta: Tensor) -> Tensor:
    """log q(θ | x) of sbi's density estimator, ``(n,)``; θ ``(n, d)`` or ``(m, n, d)`` → ``(n,)`` or ``(m, n)``."""
    was_training = net.training
    net.eval()
    t = theta.to(torch.float32)
    out = net.log_prob(t if t.dim() == 3 else t.unsqueeze(0), x)
    net.train(was_training)
    return out if theta.dim() == 3 else out[0]


def sbi_nll(net: Any, x: Tensor, theta: Tensor) -> float:
    lp = torch.cat([sbi_log_prob(net, xb, t) for xb, t in zip(x.split(2048), theta.split(2048), strict=False)])
    return float(-lp.double().mean())


@torch.no_grad()
def sbi_samples(net: Any, x: Tensor, n: int, seed: int) -> Tensor:
    """n draws per x from sbi's estimator: ``(B, n, d)`` (sbi samples with torch's global RNG: seeded in a fork)."""
    net.eval()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return net.sample(torch.Size((n,)), condition=x).transpose(0, 1).double()


def in_box(theta: Tensor, low: Tensor, high: Tensor) -> Tensor:
    return ((theta >= low) & (theta <= high)).all(dim=-1)


def sbi_log_mass_in_box(net: Any, x: Tensor, box: weather.Box, n: int, seed: int) -> Tensor:
    """log P_q(θ ∈ box | x) per x, ``(B,)``, from n draws each (floored at 1/(n+1))."""
    low, high = torch.tensor(np.array(box.low)), torch.tensor(np.array(box.high))
    frac = []
    for k, xb in enumerate(x.split(256)):
        draws = sbi_samples(net, xb, n, seeding.derive_seed(seed, "bench", "sbi", "leak", k))
        frac.append(in_box(draws, low, high).double().mean(dim=1))
    return torch.log(torch.cat(frac).clamp_min(1.0 / (n + 1)))


@torch.no_grad()
def units_check(
    log_prob: Callable[[Tensor], Tensor], draws: Tensor, box: weather.Box, n_uniform: int, seed: int
) -> tuple[float, float]:
    """``∫_S q(θ|x) dθ`` over a sub-box S around the posterior, as (uniform MC of the density, fraction of draws in S).

    Arguments:
        log_prob: θ ``(m, d)`` → log q(θ | x) ``(m,)`` for one fixed x, physical units.
        draws: ``(n, d)`` draws from q(· | x).
        box: the prior box (S is clipped to it).
    """
    lo = torch.quantile(draws, 0.01, dim=0)
    hi = torch.quantile(draws, 0.99, dim=0)
    pad = 0.1 * (hi - lo)
    lo = torch.maximum(lo - pad, torch.tensor(np.array(box.low)))
    hi = torch.minimum(hi + pad, torch.tensor(np.array(box.high)))
    u = torch.as_tensor(seeding.rng(seed, "bench", "sbi", "units").uniform(size=(n_uniform, box.dim)))
    theta = lo + u * (hi - lo)
    lq = torch.cat([log_prob(t) for t in theta.split(20_000)]).double()
    log_vol = float(torch.log(hi - lo).sum())
    integral = float(torch.exp(torch.logsumexp(lq, 0) - math.log(n_uniform) + log_vol))
    mass = float(in_box(draws, lo, hi).double().mean())
    return integral, mass


# --- runs ----------------------------------------------------------------------------------------------


@dataclass
class Run:
    """One library's training run: per-epoch wall times (s, since the training call) and val NLLs (nats)."""

    name: str
    samples_per_epoch: int
    times: list[float] = field(default_factory=list)
    val_nll: list[float] = field(default_factory=list)
    final_nll: float = math.nan
    final_nll_leak_corrected: float = math.nan
    mean_log_mass_in_box: float = 0.0
    step_samples_per_s: float = math.nan
    returned_epoch: int = -1

    @property
    def median_epoch_s(self) -> float:
        """Median wall seconds of one epoch (robust to load spikes from other processes)."""
        return float(np.median(np.diff([0.0, *self.times])))

    @property
    def loop_samples_per_s(self) -> float:
        return self.samples_per_epoch * len(self.times) / self.times[-1]

    def time_to(self, target: float) -> tuple[float | None, int | None]:
        """Wall seconds and epochs (1-based) until the val NLL first is ≤ target; ``(None, None)`` if never."""
        for k, (t, v) in enumerate(zip(self.times, self.val_nll, strict=False)):
            if v <= target:
                return t, k + 1
        return None, None


def run_pidc(data: Data, args: argparse.Namespace, compiled: bool) -> tuple[Run, NPE]:
    """pidc's ``train`` as the pipeline runs it; ``compiled``: its training loss compiled by ``torch.compile`` (what
    ``train.compile_min_steps`` turns on for long trainings), the cold compile inside the measured wall time."""
    p = config.load_params().train
    model = pidc_model(data, args.seed)
    tc = TrainingConfig(
        epochs=args.pidc_epochs,
        batch_size=BATCH,
        lr=LR,
        weight_decay=p.weight_decay,
        schedule=p.schedule,
        patience=args.pidc_epochs,
        clip_norm=CLIP,
        seed=args.seed,
        compile=compiled,
    )
    # pidc's own validation (early stopping's and the returned epoch's) is the last share of the training pairs, as
    # large as sbi's random held-out share: both libraries train on the same number of pairs and validate as many
    n_own = int(round(args.sbi_validation_fraction * len(data.x_train)))
    x_fit, th_fit = data.x_train[:-n_own], data.theta_train[:-n_own]
    x_own, th_own = data.x_train[-n_own:], data.theta_train[-n_own:]
    run = Run(f"pidc ({'compiled' if compiled else 'eager'})", samples_per_epoch=len(x_fit))
    excluded = 0.0
    t0 = time.perf_counter()

    def record(rec: Any) -> None:
        nonlocal excluded
        t_end = time.perf_counter()
        run.times.append(t_end - t0 - excluded)
        run.val_nll.append(pidc_nll(model, data.x_val, data.theta_val))  # the benchmark's curve: not timed
        excluded += time.perf_counter() - t_end

    history = train(model, (x_fit, th_fit), (x_own, th_own), tc, progress=False, callback=record)
    run.returned_epoch = history.best_epoch + 1
    run.final_nll = run.final_nll_leak_corrected = pidc_nll(model, data.x_val, data.theta_val)
    return run, model


def run_sbi(data: Data, theta_transform: str, args: argparse.Namespace) -> tuple[Run, Any]:
    n = len(data.x_train)
    n_fit = int((1 - args.sbi_validation_fraction) * n)
    run = Run(f"sbi ({theta_transform})", samples_per_epoch=(n_fit // BATCH) * BATCH)
    excluded = 0.0
    t0 = 0.0

    def on_epoch(net: Any) -> None:
        nonlocal excluded
        t_end = time.perf_counter()
        run.times.append(t_end - t0 - excluded)
        run.val_nll.append(sbi_nll(net, data.x_val, data.theta_val))
        excluded += time.perf_counter() - t_end

    tracker = MemoryTracker()
    with torch.random.fork_rng(devices=[]), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Maximum number of epochs")
        torch.manual_seed(seeding.derive_seed(args.seed, "bench", "sbi", "sbi", theta_transform))
        inference = HookedNPE(
            on_epoch,
            prior=sbi_prior(data.box),
            density_estimator=sbi_builder(data.box, theta_transform),
            tracker=tracker,
            show_progress_bars=False,
        )
        t0 = time.perf_counter()
        inference.append_simulations(data.theta_train.to(torch.float32), data.x_train)
        # sbi's loop runs while epoch <= max_num_epochs: max_num_epochs = E − 1 gives E epochs
        net = inference.train(
            training_batch_size=BATCH,
            learning_rate=LR,
            validation_fraction=args.sbi_validation_fraction,
            stop_after_epochs=args.epochs + 1,
            max_num_epochs=args.epochs - 1,
            clip_max_norm=CLIP,
        )
    print()
    if len(run.times) != args.epochs:
        raise RuntimeError(f"sbi ran {len(run.times)} epochs, expected {args.epochs}")
    own_val = inference._summary["validation_loss"]
    run.returned_epoch = int(np.argmin(own_val)) + 1
    run.final_nll = sbi_nll(net, data.x_val, data.theta_val)
    log_mass = sbi_log_mass_in_box(net, data.x_val, data.box, args.leak_samples, args.seed)
    run.mean_log_mass_in_box = float(log_mass.mean())
    run.final_nll_leak_corrected = run.final_nll + run.mean_log_mass_in_box
    return run, net


def step_throughput(data: Data, theta_transform: str, args: argparse.Namespace) -> dict[str, float]:
    """Samples/s of forward + backward + clip + optimiser step on batches of 256 (best of 3, interleaved, fresh
    models): pidc eager, pidc with its loss compiled and AdamW fused (as ``train`` with ``compile``; compiled
    before the timing), and sbi."""
    n = args.step_batches * BATCH
    xs, ths = data.x_train[:n].split(BATCH), data.theta_train[:n].split(BATCH)
    passes: dict[str, Callable[[], None]] = {}
    for compiled in (False, True):
        model = pidc_model(data, args.seed + 1)
        model.fit_standardization(data.x_train)
        opt = torch.optim.AdamW(model.parameters(), lr=LR, weight_decay=1e-4, fused=compiled or None)
        if compiled:
            terms = torch.compile(lambda th, x, model=model: npe_loss_terms(model, th, x)[0], dynamic=False)
        else:
            terms = lambda th, x, model=model: npe_loss(model, th, x).loss  # noqa: E731

        def pidc_pass(model: NPE = model, opt: torch.optim.Optimizer = opt, terms: Callable = terms) -> None:
            model.train()
            for xb, tb in zip(xs, ths, strict=False):
                loss = terms(tb, xb)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.parameters(), CLIP)
                opt.step()

        passes[f"pidc ({'compiled' if compiled else 'eager'})"] = pidc_pass
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seeding.derive_seed(args.seed, "bench", "sbi", "step"))
        net = sbi_builder(data.box, theta_transform)(data.theta_train.to(torch.float32), data.x_train)
    sopt = torch.optim.Adam(net.parameters(), lr=LR)
    ths32 = [t.to(torch.float32) for t in ths]

    def sbi_pass() -> None:
        net.train()
        for xb, tb in zip(xs, ths32, strict=False):
            loss = net.loss(tb, xb).mean()
            sopt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), CLIP)
            sopt.step()

    passes["sbi"] = sbi_pass
    best = dict.fromkeys(passes, math.inf)
    for fn in passes.values():
        fn()  # warm-up (and the compile)
    for _ in range(3):  # interleaved, so that a load change hits all
        for key, fn in passes.items():
            t = time.perf_counter()
            fn()
            best[key] = min(best[key], time.perf_counter() - t)
    return {key: n / b for key, b in best.items()}


# --- report --------------------------------------------------------------------------------------------


def wait_for_load(limit: float, max_wait: float) -> float:
    """Wait (up to max_wait s) for the 1-min load average to fall below limit; return the load when starting."""
    t0 = time.monotonic()
    while os.getloadavg()[0] >= limit and time.monotonic() - t0 < max_wait:
        time.sleep(15)
    return os.getloadavg()[0]


def fmt(v: float | None, spec: str) -> str:
    return "—" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b == 0 else a / b


def print_table(pidcs: list[Run], sbis: list[Run], targets: dict[str, float]) -> list[dict[str, Any]]:
    """Print one row per run and the ratios sbi / pidc for each pair; return the rows (ratios inside sbi's rows).

    ``targets``: name → val NLL (nats); each run's wall time and epochs until it first reaches each."""
    rows = []
    for r in [*pidcs, *sbis]:
        rows.append(
            {
                "library": r.name,
                "step_samples_per_s": r.step_samples_per_s,
                "loop_samples_per_s": r.loop_samples_per_s,
                "epoch_s": r.times[-1] / len(r.times),
                "median_epoch_s": r.median_epoch_s,
                "time_to_target_s": {k: r.time_to(v)[0] for k, v in targets.items()},
                "epochs_to_target": {k: r.time_to(v)[1] for k, v in targets.items()},
                "best_epoch_val_nll": min(r.val_nll),
                "last_epoch_val_nll": r.val_nll[-1],
                "returned_epoch": r.returned_epoch,
                "final_val_nll": r.final_nll,
                "final_val_nll_leak_corrected": r.final_nll_leak_corrected,
                "mean_log_mass_in_box": r.mean_log_mass_in_box,
                "total_s": r.times[-1],
            }
        )
    for k, v in targets.items():
        print(f"\ntarget {k!r}: val NLL {v:.3f} nats")
    print("val NLL in nats, physical units; t→target: wall seconds (epochs) until the val NLL first reaches it")
    head = (
        f"{'library':<32} {'step smp/s':>10} {'loop smp/s':>10} {'s/epoch':>8} {'med s/ep':>8} "
        + "".join(f"{'t→' + k:>16}" for k in targets)
        + f" {'best NLL':>9} {'last NLL':>9} {'ret ep':>6} {'final NLL':>9} {'final+leak':>10}"
    )
    print(head)
    for d in rows:
        reach = "".join(
            f"{fmt(d['time_to_target_s'][k], '.1f') + ' (' + fmt(d['epochs_to_target'][k], 'd') + ')':>16}"
            for k in targets
        )
        print(
            f"{d['library']:<32} {fmt(d['step_samples_per_s'], ',.0f'):>10} {fmt(d['loop_samples_per_s'], ',.0f'):>10} "
            f"{d['epoch_s']:>8.2f} {d['median_epoch_s']:>8.2f} {reach} "
            f"{d['best_epoch_val_nll']:>9.3f} {d['last_epoch_val_nll']:>9.3f} {d['returned_epoch']:>6d} "
            f"{d['final_val_nll']:>9.3f} {d['final_val_nll_leak_corrected']:>10.3f}"
        )
    bases = rows[: len(pidcs)]
    for d in rows[len(pidcs) :]:
        d["ratios_sbi_over_pidc"] = {}
        for base in bases:
            q = {
                "step_samples_per_s": ratio(d["step_samples_per_s"], base["step_samples_per_s"]),
                "loop_samples_per_s": ratio(d["loop_samples_per_s"], base["loop_samples_per_s"]),
                "epoch_s": ratio(d["epoch_s"], base["epoch_s"]),
                "median_epoch_s": ratio(d["median_epoch_s"], base["median_epoch_s"]),
                "time_to_target_s": {k: ratio(d["time_to_target_s"][k], base["time_to_target_s"][k]) for k in targets},
            }
            d["ratios_sbi_over_pidc"][base["library"]] = q
            print(
                f"{'ratio ' + d['library'] + ' / ' + base['library']:<32} {fmt(q['step_samples_per_s'], '.2f'):>10} "
                f"{fmt(q['loop_samples_per_s'], '.2f'):>10} {fmt(q['epoch_s'], '.2f'):>8} {fmt(q['median_epoch_s'], '.2f'):>8} "
                + "".join(f"{fmt(q['time_to_target_s'][k], '.2f'):>16}" for k in targets)
                + "   (samples/s: >1 = sbi faster; times: >1 = sbi slower)"
            )
        d["final_val_nll_difference_sbi_minus_pidc"] = {
            base["library"]: d["final_val_nll_leak_corrected"] - base["final_val_nll"] for base in bases
        }
    return rows


def main() -> None:
    root = config.PROJECT_ROOT
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--n-train", type=int, default=10_000)
    p.add_argument("--epochs", type=int, default=60, help="fixed epoch budget of both libraries")
    p.add_argument(
        "--pidc-epochs",
        type=int,
        default=None,
        help="pidc's epochs and the length of its cosine schedule (default: --epochs); sbi keeps --epochs",
    )
    p.add_argument("--target-epoch", type=int, default=20, help="target NLL = pidc's val NLL after this many epochs")
    p.add_argument(
        "--sbi-theta",
        nargs="+",
        default=["independent"],
        choices=["independent", "transform_to_unconstrained"],
        help="sbi's z_score_theta variants to run",
    )
    p.add_argument(
        "--pidc",
        nargs="+",
        default=["eager", "compiled"],
        choices=["eager", "compiled"],
        help="pidc's training loss eager and/or compiled by torch.compile (the cold compile counted)",
    )
    p.add_argument("--sbi-validation-fraction", type=float, default=0.1)
    p.add_argument("--leak-samples", type=int, default=128, help="draws per val x for sbi's leakage correction")
    p.add_argument("--step-batches", type=int, default=20, help="batches per pass of the step-throughput measure")
    p.add_argument("--units-x", type=int, default=3, help="val inputs of the units check")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--backbone", default="cues")
    p.add_argument("--data", type=Path, default=root / "data")
    p.add_argument("--features", type=Path, default=root / "features")
    p.add_argument("--wait-load", type=float, default=1.5, help="start when the 1-min load average is below this")
    p.add_argument("--max-wait", type=float, default=0.0, help="seconds to wait for --wait-load (0 = start at once)")
    args = p.parse_args()
    if args.threads < 1:
        p.error(f"--threads must be >= 1, got {args.threads}")
    if args.epochs < 1:
        p.error(f"--epochs must be >= 1, got {args.epochs}")
    if args.pidc_epochs is None:
        args.pidc_epochs = args.epochs
    if args.pidc_epochs < 1:
        p.error(f"--pidc-epochs must be >= 1, got {args.pidc_epochs}")
    if not 1 <= args.target_epoch <= args.pidc_epochs:
        p.error(f"--target-epoch must be in [1, --pidc-epochs={args.pidc_epochs}], got {args.target_epoch}")
    if args.n_train < 2 * BATCH:
        p.error(f"--n-train must be >= {2 * BATCH}, got {args.n_train}")
    if not 0 < args.sbi_validation_fraction < 0.5:
        p.error(f"--sbi-validation-fraction must be in (0, 0.5), got {args.sbi_validation_fraction}")
    for name in ("leak_samples", "step_batches", "units_x"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    torch.set_num_threads(args.threads)

    data = load_data(args.data, args.features, args.backbone, args.n_train)
    if args.step_batches * BATCH > len(data.x_train):
        p.error(f"--step-batches × {BATCH} must not exceed --n-train ({args.n_train})")
    load_start = wait_for_load(args.wait_load, args.max_wait)
    print(
        f"data: {len(data.x_train)} train, {len(data.x_val)} val, {data.x_train.shape[1]}-dim {args.backbone!r} "
        f"features; load {load_start:.2f}"
    )
    wall0 = time.perf_counter()

    step = {v: step_throughput(data, v, args) for v in args.sbi_theta}
    print(f"step throughput (samples/s): {step}; load {os.getloadavg()[0]:.2f}", flush=True)
    pidcs, models = [], []
    for variant in args.pidc:
        r, model = run_pidc(data, args, compiled=variant == "compiled")
        r.step_samples_per_s = float(np.mean([s[r.name] for s in step.values()]))
        print(f"{r.name}: {len(r.times)} epochs in {r.times[-1]:.1f} s; load {os.getloadavg()[0]:.2f}", flush=True)
        pidcs.append(r)
        models.append(model)
    model = models[0]
    sbis, nets = [], []
    for v in args.sbi_theta:
        r, net = run_sbi(data, v, args)
        r.step_samples_per_s = step[v]["sbi"]
        print(f"{r.name}: {len(r.times)} epochs in {r.times[-1]:.1f} s; load {os.getloadavg()[0]:.2f}", flush=True)
        sbis.append(r)
        nets.append(net)
    # two targets: the first pidc run's val NLL after --target-epoch epochs (the historical one), and the best val
    # NLL that EVERY run reaches (the worst run's best epoch): the quality a user gets from either library
    targets = {
        f"{pidcs[0].name} ep {args.target_epoch}": pidcs[0].val_nll[args.target_epoch - 1],
        "reached by all": max(min(r.val_nll) for r in [*pidcs, *sbis]),
    }

    print("units check: ∫_S q dθ by uniform MC of the density vs the fraction of q's draws in S (should agree)")
    checks = []
    for i in range(args.units_x):
        x1 = data.x_val[i : i + 1]
        draws = model.sample(x1, 4000, rng=seeding.derive_seed(args.seed, "bench", "sbi", "draws", i))[0]
        got = units_check(
            lambda t, x1=x1: model.log_prob(t.unsqueeze(0), x1)[0], draws, data.box, 50_000, args.seed + i
        )
        checks.append({"library": "pidc", "x": i, "density_integral": got[0], "sample_mass": got[1]})
        for r, net in zip(sbis, nets, strict=False):
            d = sbi_samples(net, x1, 4000, seeding.derive_seed(args.seed, "bench", "sbi", "draws", i))[0]
            got = units_check(
                lambda t, net=net, x1=x1: sbi_log_prob(net, x1.expand(len(t), -1), t),
                d,
                data.box,
                50_000,
                args.seed + i,
            )
            checks.append({"library": r.name, "x": i, "density_integral": got[0], "sample_mass": got[1]})
    for c in checks:
        print(
            f"  {c['library']:<32} x#{c['x']}: density ∫ {c['density_integral']:.3f}   draws' mass {c['sample_mass']:.3f}"
        )

    rows = print_table(pidcs, sbis, targets)
    machine = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "sbi": sbi.__version__,
        "zuko": zuko.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "threads": torch.get_num_threads(),
        "load_avg_1m_start": round(load_start, 2),
        "load_avg_1m_end": round(os.getloadavg()[0], 2),
        "wall_s": round(time.perf_counter() - wall0, 1),
    }
    curves = {
        r.name: {"time_s": [round(t, 3) for t in r.times], "val_nll": [round(v, 4) for v in r.val_nll]}
        for r in [*pidcs, *sbis]
    }
    print(
        json.dumps(
            {
                "benchmark": "npe_vs_sbi",
                "settings": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
                "machine": machine,
                "target_val_nll": targets,
                "results": rows,
                "units_check": checks,
                "curves": curves,
            }
        )
    )


if __name__ == "__main__":
    main()
