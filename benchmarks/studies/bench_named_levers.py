"""Levers for honesty at named weathers: the champion's cell against changed models, on the evaluate stage's protocol.

Each lever makes a model of the champion's cell (``cues-50000``, the pipeline's data and cached features), exports it
to ONNX in a scratch project beside the pipeline's (``--out``: its ``data/`` and ``features/`` link to the project's)
and runs the ``evaluate`` stage's own evaluation on it (:func:`components.evaluate.evaluation.evaluate_exported`):
the 2 000 test images (information gain, calibration error and band), and the named weathers of ``params.yaml``
(each weather × parameter's 68 % HDI coverage against a correct model's range, the L-C2ST at the named images and at
test images, the sun at ClearNoon) — the same images, draws and seeds for every lever. Levers (``--levers``):

- ``base`` — the pipeline's champion as it is (``registry/cues-50000``, copied);
- ``tau-head`` — the champion with its base scale τ a function of the image: ``log τ(c) = b + W ĉ`` per parameter on
  the standardized context ĉ (:class:`ContextTemperature`, the day/night gate generalized), fitted by maximum
  likelihood on the validation split with a ridge penalty chosen by two-fold cross-validation on it
  (:func:`fit_context_temperature`);
- ``ensemble-4`` — four flows instead of two, trained as the pipeline trains a variant (``flows.train``'s settings,
  the same data, seeds and calibration);
- ``ensemble-4-tau-head`` — the two together;
- ``boundary`` — more training images near the box's faces: the 50 000 images of the train split and ``--extra``
  (20 000) images rendered with θ from a boundary-heavy law B (each parameter independently in its lowest
  :data:`SLAB` of the range with probability :data:`FACE`, in its highest with probability :data:`FACE`, uniform
  otherwise; azimuth uniform; 8 images per new scene), every training pair's loss weighted by the importance weight
  U(θ) / q̃(θ) of the training law q̃ = (1 − s)·U + s·B (s the extra images' share, :func:`boundary_weight`), so
  that the posterior stays relative to the uniform prior; the same sample budget as the champion (3 M pairs: 43 epochs
  of 70 000), its input noise and validation;
- ``more-uniform`` — the control of ``boundary``: the same with the extra images drawn from U (unweighted);
- ``estimate-noise-S`` — the champion's cell trained as the pipeline trains it (its model seed and draws), with the
  input noise on every estimate of θ among the cues (the weather reader's and its sun head's μ and log σ: the fourteen
  ``reader_*`` columns) S times the other features' (S in [0, 1]), theirs unchanged;
- ``sun-noise-S`` — the same with the share on the sun head's two columns alone (the reader's twelve keep the noise:
  :meth:`~components.features.backbones.base.Backbone.spared_index`; ``train.input_noise_spared`` is S).

Beside each row, the sun at ClearNoon on ``--clear-noon-scenes`` (96) of the named weathers' scenes, split by whether
the sun head is sure of itself there (:func:`clear_noon`): 24 scenes move the figure by 3–4° between trainings.

A lever's model and its evaluation are kept under ``--out`` (a rerun reuses them). Prints the ablation table and one
JSON line with every figure and the machine.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/studies/bench_named_levers.py --levers base tau-head ensemble-4
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import copy
import dataclasses
import json
import logging
import math
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from torch.distributions import AffineTransform
from zuko.flows import LazyTransform

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from components.core.config import VariantConfig, load_params  # noqa: E402
from components.core.paths import ProjectPaths  # noqa: E402
from components.posterior.model import NPE  # noqa: E402
from components.posterior.temperature import base_points  # noqa: E402

#: the champion's cell
CELL = ("cues", 50000)
#: ridge penalties tried for the τ head (per pair, on the standardized context)
RIDGE = (1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0)
#: the boundary law B: each parameter lies in the lowest (highest) SLAB of its range with probability FACE each
FACE, SLAB = 0.25, 0.10
#: the levers this script knows
LEVERS = (
    "base",
    "tau-head",
    "ensemble-4",
    "ensemble-4-tau-head",
    "boundary",
    "more-uniform",
    "estimate-noise-S",
    "sun-noise-S",
)
#: the noise levers: their prefix → the estimates whose noise they share out (all of them, or the sun head's)
NOISE_LEVERS = {"estimate-noise-": "all", "sun-noise-": "sun"}


def boundary_draws(g: np.random.Generator, box, n: int) -> np.ndarray:
    """``n`` draws ``(n, d)`` of the boundary law B on ``box`` (see the module's docstring)."""
    u = g.random((n, box.dim))
    side = g.random((n, box.dim))
    low, high, inside = side < FACE, side >= 1 - FACE, (side >= FACE) & (side < 1 - FACE)
    unit = np.where(low, SLAB * u, np.where(high, 1 - SLAB * u, u))
    assert bool((low | high | inside).all())
    return box.low + unit * box.width


def boundary_weight(theta: Tensor, low: Tensor, width: Tensor, share: float) -> Tensor:
    """The importance weight U(θ) / q̃(θ), q̃ = (1 − share)·U + share·B, for θ ``(N, d)``: ``(N,)``; its mean under q̃
    is 1. B/U is the product over parameters of r = (1 − 2·FACE) + FACE/SLAB in a face's slab, 1 − 2·FACE inside."""
    u = (theta - low) / width
    slab = (u < SLAB) | (u > 1 - SLAB)
    r = torch.where(slab, (1 - 2 * FACE) + FACE / SLAB, torch.full_like(u, 1 - 2 * FACE))
    return 1.0 / ((1 - share) + share * r.prod(dim=-1))


class ContextTemperature(LazyTransform):
    """The flow's last transform ε ↦ ε / τ(c) with ``log τ(c) = bias + weight · c`` per parameter.

    Buffers ``weight (d, F)`` and ``bias (d,)`` (for the raw context; fitted on standardized contexts and folded back).
    For every c it is an affine map of ε, so the density stays proper.
    """

    weight: Tensor
    bias: Tensor

    def __init__(self, weight: Tensor, bias: Tensor) -> None:
        super().__init__()
        self.register_buffer("weight", weight.to(torch.float32))
        self.register_buffer("bias", bias.to(torch.float32))

    def log_temperature(self, c: Tensor) -> Tensor:
        return c @ self.weight.T + self.bias

    def forward(self, c: Tensor | None = None) -> AffineTransform:
        if c is None:
            raise ValueError("ContextTemperature needs the context c")
        return AffineTransform(0.0, torch.exp(-self.log_temperature(c)))


def _nll(eps: Tensor, ladj: Tensor, log_tau: Tensor) -> Tensor:
    """Mean −log q of held-out pairs with per-pair log τ ``(N, d)``; ``ε (K, N, d)``, ``ladj (K, N)``."""
    members = (-0.5 * (eps * torch.exp(-log_tau)) ** 2 - log_tau).sum(-1) + ladj
    return -(torch.logsumexp(members, dim=0) - math.log(eps.shape[0])).mean() + 0.5 * eps.shape[-1] * math.log(
        2 * math.pi
    )


def _fit(eps: Tensor, ladj: Tensor, c: Tensor, ridge: float, start: Tensor) -> tuple[Tensor, Tensor]:
    """L-BFGS on (W, b) of log τ = b + W ĉ: the mean NLL of the pairs + ridge/2 ‖W‖² (ĉ standardized)."""
    w = torch.zeros(eps.shape[-1], c.shape[1], dtype=torch.float64, requires_grad=True)
    b = start.clone().requires_grad_(True)
    opt = torch.optim.LBFGS([w, b], max_iter=300, tolerance_grad=1e-9, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        loss = _nll(eps, ladj, c @ w.T + b) + 0.5 * ridge * (w * w).sum()
        loss.backward()
        return loss

    with torch.enable_grad():
        opt.step(closure)
    return w.detach(), b.detach()


@torch.no_grad()
def fit_context_temperature(model: NPE, x: Tensor, theta: Tensor) -> tuple[NPE, dict]:
    """A copy of ``model`` whose base scale is :class:`ContextTemperature`, fitted on held-out pairs ``(x, θ)``.

    The untempered base points of the pairs (the model's τ set to 1) and their contexts, standardized; the ridge
    penalty of :data:`RIDGE` with the best held-out NLL over two folds (the first and second half of the pairs),
    then the fit on all pairs. Returns the copy and a report (the penalty, each fold's NLL, the NLL of the model's
    own τ and of the head on the held-out folds).
    """
    eps, ladj = base_points(model, x, theta)
    c = torch.cat([model.context(x[a : a + 4096]) for a in range(0, len(x), 4096)]).double()
    mean, std = c.mean(0), c.std(0).clamp_min(1e-8)
    cs = (c - mean) / std
    own = model.temperature.double()
    with torch.no_grad():
        c_own = model.flows[0].transform.transforms[-1]
        own_log_tau = (
            c_own.log_temperature(c.float()).double()
            if hasattr(c_own, "log_temperature")
            else own.log().expand(len(c), -1)
        )
    start = own_log_tau.mean(0)
    half = len(x) // 2
    folds = [(slice(0, half), slice(half, None)), (slice(half, None), slice(0, half))]
    scores = {}
    for ridge in RIDGE:
        held = []
        for fit_rows, test_rows in folds:
            w, b = _fit(eps[:, fit_rows], ladj[:, fit_rows], cs[fit_rows], ridge, start)
            held.append(float(_nll(eps[:, test_rows], ladj[:, test_rows], cs[test_rows] @ w.T + b)))
        scores[ridge] = float(np.mean(held))
    ridge = min(scores, key=scores.get)
    w, b = _fit(eps, ladj, cs, ridge, start)
    weight, bias = w / std, b - (w / std) @ mean
    out = copy.deepcopy(model)
    for flow in out.flows:
        flow.transform.transforms[-1] = ContextTemperature(weight, bias)
    report = {
        "ridge": ridge,
        "heldout_nll_by_ridge": {str(k): v for k, v in scores.items()},
        "own_tau_nll": float(_nll(eps, ladj, own_log_tau)),
        "head_nll_in_sample": float(_nll(eps, ladj, cs @ w.T + b)),
        "log_tau_spread": (cs @ w.T + b).std(0).tolist(),
    }
    return out, report


def estimates(backbone) -> tuple[int, ...]:
    """Every estimate of θ among the cues: the indices of the weather reader's and its sun head's columns."""
    from components.features.backbones.cues import FEATURE_NAMES

    if backbone.name != "cues":
        raise ValueError(f"the estimate-noise levers need the cues, not {backbone.name!r}")
    return tuple(i for i, name in enumerate(FEATURE_NAMES) if name.startswith("reader_"))


def estimate_share(lever: str) -> tuple[str, float]:
    """(which estimates, S) of the lever ``estimate-noise-S`` or ``sun-noise-S``; ``ValueError`` naming the lever
    unless it is one with 0 ≤ S ≤ 1."""
    for prefix, which in NOISE_LEVERS.items():
        if lever.startswith(prefix):
            try:
                share = float(lever.removeprefix(prefix))
            except ValueError:
                break
            if 0 <= share <= 1:
                return which, share
    raise ValueError(f"lever {lever!r}: expected estimate-noise-S or sun-noise-S with S in [0, 1], e.g. sun-noise-0")


def _scratch(out: Path) -> tuple[Path, ProjectPaths]:
    """The scratch project: ``params.yaml`` copied, ``data`` and ``features`` linked to the project's."""
    root = out / "project"
    root.mkdir(parents=True, exist_ok=True)
    shutil.copy(ROOT / "params.yaml", root / "params.yaml")
    for name in ("data", "features"):
        link = root / name
        if not link.exists():
            link.symlink_to(ROOT / name, target_is_directory=True)
    params = load_params(root / "params.yaml")
    return root / "params.yaml", ProjectPaths.of(params, root / "params.yaml")


def _card(model_id: str) -> dict:
    card = json.loads((ROOT / "registry" / f"{CELL[0]}-{CELL[1]}" / "card.json").read_text())
    keep = ("backbone", "backbone_options", "backbone_fingerprint", "size", "training_renders", "data_hash")
    return {"model_id": model_id, **{k: card[k] for k in keep}, "metrics": {}, "registered_model": None}


def _export(model: NPE, paths: ProjectPaths, model_id: str) -> None:
    from components.export.onnx import export_posterior

    if not (paths.registry / model_id / "card.json").is_file():
        export_posterior(model.cpu().eval(), paths.registry / model_id, card=_card(model_id))


def _train_ensemble(
    params_file: Path,
    paths: ProjectPaths,
    flows: int | None,
    logger: logging.Logger,
    *,
    share: tuple[str, float] | None = None,
) -> NPE:
    """The champion's cell with ``flows`` flows, trained as ``flows.train`` trains a variant (checkpoint kept), or as
    it trains the cell itself (``flows`` None); ``share``: (which estimates of θ, all or the sun head's; their input
    noise as a share of the others') (None: as params say)."""
    from components.posterior.store import load_npe, save_npe
    from components.posterior.train import train
    from flows.train import _calibrate_and_test, _inputs, _new_model, _run_key

    name = f"ensemble{flows}" + (
        "" if share is None else f"-{share[0]}-noise-{share[1]:g}".replace("-all-", "-estimate-")
    )
    done = paths.models / name / "model.pt"
    if done.is_file():
        return load_npe(done)[0]
    params = load_params(params_file)
    variant = (
        VariantConfig(backbone=CELL[0], size=CELL[1], balance=params.train.balance, ensemble=flows) if flows else None
    )
    splits, options, backbone, x, theta = _inputs(params, paths, *CELL)
    # a noise lever keeps the champion's model seed (its initial weights) and draws: the noise mask is the difference
    model_id = f"{CELL[0]}-{CELL[1]}" + (f"-{name}" if share is None else "")
    model, flow_cfg, cfg, seed = _new_model(params, backbone, x, CELL[1], variant, model_id)
    if share is not None:
        spared = estimates(backbone) if share[0] == "all" else backbone.spared_index()
        cfg = dataclasses.replace(cfg, spared=spared, spared_noise=share[1])
    key = _run_key(cfg, flow_cfg, seed, splits["train"].content_hash, options, backbone)
    done.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    history = train(
        model,
        (x["train"], theta["train"]),
        (x["val"], theta["val"]),
        cfg,
        checkpoint=done.parent / f"checkpoint-{key}.pt",
        progress=True,
    )
    metrics = _calibrate_and_test(params, model, x, theta, history, t0)
    logger.info("%s: %s", name, json.dumps(metrics))
    save_npe(done, model, backbone=CELL[0], backbone_options=options, extra={"metrics": metrics})
    return model


def _extra_set(kind: str, n: int, params_file: Path, paths: ProjectPaths, out: Path) -> tuple[np.ndarray, np.ndarray]:
    """``n`` new training pairs ``(x (n, F) float32, θ (n, 6) float32)`` of ``kind`` (``boundary``: θ ~ B;
    ``uniform``: θ ~ U), rendered 8 to a new scene (scene seeds ``derive_seed(seed, "scene", "named-levers", kind,
    j)``, azimuth uniform) and read by the cues; kept in ``out/extra-<kind>-<n>-<fingerprint>.npz`` (another version
    of the cues reads them again)."""
    from components.core import seeding, weather
    from components.features.backbones import get_backbone
    from components.features.cache import posterior_inputs
    from components.features.options import backbone_options
    from components.simulate.base import make_simulator

    params = load_params(params_file)
    backbone = get_backbone(CELL[0], **backbone_options(CELL[0], params, paths.root))
    kept = out / f"extra-{kind}-{n}-{backbone.fingerprint()[:12]}.npz"
    if kept.is_file():
        z = np.load(kept)
        return z["x"], z["theta"]
    box, seed = params.box, params.seed
    g = seeding.rng(seed, "named-levers", kind, "theta")
    theta = boundary_draws(g, box, n) if kind == "boundary" else box.sample(g, n)
    azimuth = weather.sample_azimuth(seeding.rng(seed, "named-levers", kind, "azimuth"), n)
    simulator = make_simulator(params.simulator)
    x = np.empty((n, backbone.dim), dtype=np.float32)
    from tqdm import tqdm

    for a in tqdm(range(0, n, 256), desc=f"extra {kind}", unit="batch"):
        rows = range(a, min(a + 256, n))
        images = np.stack(
            [
                simulator.render(
                    weather.complete_weather(
                        {
                            **{name: float(v) for name, v in zip(box.names, theta[i], strict=True)},
                            "sun_azimuth_angle": float(azimuth[i]),
                        }
                    ),
                    seeding.derive_seed(seed, "scene", "named-levers", kind, i // 8),
                )
                for i in rows
            ]
        )
        x[a : a + len(rows)] = posterior_inputs(backbone, images)
    theta = theta.astype(np.float32)
    np.savez(kept, x=x, theta=theta)
    return x, theta


def _train_extra(kind: str, n: int, params_file: Path, paths: ProjectPaths, logger: logging.Logger) -> NPE:
    """The champion's cell trained on its 50 000 images and ``n`` more of ``kind`` (:func:`_extra_set`), the
    ``boundary`` pairs' losses weighted by :func:`boundary_weight`; the champion's settings but for the epochs, which
    keep its sample budget. The validation split stays the uniform one (unweighted)."""
    import importlib
    from dataclasses import replace

    training = importlib.import_module("components.posterior.train")  # the module (the package names its function)
    from components.posterior.store import load_npe, save_npe
    from flows.train import _calibrate_and_test, _inputs, _new_model, _run_key

    name = f"{kind}{n}"
    done = paths.models / name / "model.pt"
    if done.is_file():
        return load_npe(done)[0]
    params = load_params(params_file)
    splits, options, backbone, x, theta = _inputs(params, paths, *CELL)
    model, flow_cfg, cfg, seed = _new_model(params, backbone, x, CELL[1], None, f"{CELL[0]}-{CELL[1]}-{name}")
    xe, te = _extra_set("boundary" if kind == "boundary" else "uniform", n, params_file, paths, paths.root.parent)
    x_train = torch.cat([x["train"], torch.from_numpy(xe)])
    theta_train = np.concatenate([theta["train"], te])
    cfg = replace(cfg, epochs=math.ceil(params.train.sample_budget / len(x_train)))
    share = n / len(x_train)
    low = torch.tensor(params.box.low, dtype=torch.float64)
    width = torch.tensor(params.box.width, dtype=torch.float64)
    plain = training.npe_loss_terms

    def weighted(model: NPE, theta: Tensor, x: Tensor, *, balance: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
        log_q = model.log_prob_members(theta, model.context(x))  # (K, B)
        w = boundary_weight(theta.to(torch.float64), low, width, share).to(log_q.dtype)
        nll = -(log_q.mean(dim=0) * w).mean()
        return nll, nll, torch.zeros_like(nll)

    key = _run_key(cfg, flow_cfg, seed, splits["train"].content_hash + name, options, backbone)
    done.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if kind == "boundary":
        training.npe_loss_terms = weighted  # the training batches only: the validation loss is train._evaluate's
    try:
        history = training.train(
            model,
            (x_train, theta_train),
            (x["val"], theta["val"]),
            cfg,
            checkpoint=done.parent / f"checkpoint-{key}.pt",
            progress=True,
        )
    finally:
        training.npe_loss_terms = plain
    metrics = _calibrate_and_test(params, model, x, theta, history, t0)
    logger.info("%s: %s", name, json.dumps(metrics))
    save_npe(done, model, backbone=CELL[0], backbone_options=options, extra={"metrics": metrics})
    return model


def _val_pairs(params_file: Path, paths: ProjectPaths) -> tuple[Tensor, Tensor]:
    from flows.train import _inputs

    _, _, _, x, theta = _inputs(load_params(params_file), paths, *CELL)
    return x["val"], torch.from_numpy(theta["val"]).double()


def build(lever: str, params_file: Path, paths: ProjectPaths, logger: logging.Logger, extra: int) -> dict:
    """Make, export and describe the model of ``lever``; its notes (fits, training)."""
    from components.posterior.store import load_npe

    model_id = f"{CELL[0]}-{CELL[1]}-{lever}" if lever != "base" else f"{CELL[0]}-{CELL[1]}"
    notes_file = paths.registry / model_id / "lever.json"
    if notes_file.is_file():
        return json.loads(notes_file.read_text())
    notes: dict = {"model": model_id}
    if lever == "base":
        shutil.copytree(ROOT / "registry" / model_id, paths.registry / model_id, dirs_exist_ok=True)
    elif lever in ("boundary", "more-uniform"):
        model = _train_extra(lever, extra, params_file, paths, logger)
        _export(model, paths, model_id)
    elif lever.startswith(tuple(NOISE_LEVERS)):
        model = _train_ensemble(params_file, paths, None, logger, share=estimate_share(lever))
        _export(model, paths, model_id)
    else:
        flows = 4 if lever.startswith("ensemble-4") else None
        model = (
            _train_ensemble(params_file, paths, flows, logger)
            if flows
            else load_npe(ROOT / "models" / f"{CELL[0]}-{CELL[1]}" / "model.pt")[0]
        )
        if lever.endswith("tau-head"):
            model, notes["tau_head"] = fit_context_temperature(model.eval(), *_val_pairs(params_file, paths))
        _export(model, paths, model_id)
    notes_file.write_text(json.dumps(notes, indent=1))
    return notes


def evaluate(model_id: str, params_file: Path, paths: ProjectPaths, logger: logging.Logger) -> dict:
    """The evaluate stage's result for ``model_id`` (kept in ``result.json`` beside its graphs)."""
    from components.evaluate import task1
    from components.evaluate.evaluation import evaluate_exported
    from components.simulate import dataset

    kept = paths.registry / model_id / "result.json"
    if kept.is_file():
        return json.loads(kept.read_text())
    params = load_params(params_file)
    ev = params.evaluate
    n = task1.images_evaluated(ev.images, len(dataset.open_split(paths.data, "test")))
    band = task1.calibration_band(n, ev.samples, ev.band_level, ev.band_replicates, params.seed)
    result = evaluate_exported(params, paths, model_id, band, paths.root / "plots" / model_id, logger)
    kept.write_text(json.dumps(result))
    return result


def clear_noon(model_id: str, params_file: Path, paths: ProjectPaths, scenes: int) -> dict:
    """The sun at ClearNoon on ``scenes`` of the named weathers' scenes (the first 24 are the evaluate stage's), 500
    draws an image: the median |posterior median − 45°| over all and over the scenes where the sun head is sure of
    itself (its σ below 3.3°, log σ < −4 in its units) and where it is not, the posterior's median sd there, the
    central 68 % interval's coverage with its Clopper–Pearson interval, and the head's own error and σ (sure, unsure). Kept in ``clear_noon-<scenes>.json``."""
    from components.core import presets, seeding
    from components.evaluate.local import clopper_pearson
    from components.evaluate.named import scene_seeds
    from components.export.lookup import load_registered
    from components.features.cache import posterior_inputs
    from components.simulate.base import make_simulator

    kept = paths.registry / model_id / f"clear_noon-{scenes}.json"
    if kept.is_file():
        return json.loads(kept.read_text())
    params = load_params(params_file)
    model = load_registered(model_id, paths.registry)
    images_file = paths.root / f"clear_noon-{scenes}.npz"
    if not images_file.is_file():
        simulator = make_simulator(params.simulator)
        seeds = scene_seeds(params.seed, "ClearNoon", scenes)
        images = np.stack([simulator.render(presets.preset_weather("ClearNoon"), s) for s in seeds])
        np.savez(images_file, images=images)
    x = posterior_inputs(model.backbone, np.load(images_file)["images"])
    draws = model.posterior.sample(x, 500, seeding.derive_seed(params.seed, "clear-noon", scenes))[:, :, 3]
    error, sd = np.abs(np.median(draws, axis=1) - 45.0), draws.std(axis=1)
    lo, hi = np.percentile(draws, [15.865, 84.135], axis=1)
    covered = int(((lo <= 45.0) & (45.0 <= hi)).sum())
    sure = x[:, model.backbone.dim - 1] < -4.0  # the sun head's log σ (last cue; units of the altitude's range)
    ci = clopper_pearson(np.array([covered]), scenes)
    # the head's own guess and σ in degrees (its units: the altitude's range, 180°, from −90°)
    head, head_sd = x[:, -2] * 180.0 - 90.0, np.exp(x[:, -1]) * 180.0
    out = {
        "head_median_abs_error": [float(np.median(np.abs(head[m] - 45.0))) for m in (sure, ~sure)],
        "head_median_sd": [float(np.median(head_sd[m])) for m in (sure, ~sure)],
        "scenes": scenes,
        "median_abs_error": float(np.median(error)),
        "sure": int(sure.sum()),
        "median_abs_error_sure": float(np.median(error[sure])),
        "median_sd_sure": float(np.median(sd[sure])),
        "median_abs_error_unsure": float(np.median(error[~sure])),
        "coverage68": covered / scenes,
        "ci68": [float(ci[0][0]), float(ci[1][0])],
    }
    kept.write_text(json.dumps(out))
    return out


def row(lever: str, result: dict) -> dict:
    """One line of the ablation: the average figures and the named weathers'."""
    m, local = result["metrics"], result["local"]
    weathers = {r["weather"]: r for r in local["weathers"]}
    cells = [c for r in local["weathers"] for c in r["parameters"].values()]
    pooled = local["pooled"]["all"]["parameters"]
    lc = local["lc2st"]
    return {
        "lever": lever,
        "info_gain_nats": m["info_gain_nats"],
        "test_nll_se": m["test_nll_se"],
        "calibration_error": m["calibration_error"],
        "calibration_band": m["calibration_band"],
        "cells_below": sum(c["below"] for c in cells),
        "cells_above": sum(c["above"] for c in cells),
        "cells": len(cells),
        "pooled68": {k: v["coverage68"] for k, v in pooled.items()},
        "toy68": {k: v["toy68"] for k, v in pooled.items()},
        "lc2st_named": {k: [v["rate"], v["p_value"]] for k, v in lc["named"].items()},
        "lc2st_test": {k: [v["rate"], v["p_value"]] for k, v in lc["test"].items()},
        "clear_noon_sun": weathers["ClearNoon"]["parameters"]["sun_altitude_angle"]["median_abs_error"],
        "noon_sun": {
            w: r["parameters"]["sun_altitude_angle"]["median_abs_error"] for w, r in weathers.items() if "Noon" in w
        },
    }


def report(rows: list[dict]) -> None:
    short = ("cloud", "fog", "rain", "sun", "wind", "dep")
    print(
        "| lever | nats | calibration (band) | cells − · + | pooled 68 % coverage "
        + "/".join(short)
        + " | joint L-C2ST named (p) | test (p) | params p ≤ 0.05 at named | ClearNoon sun | the same, more scenes: "
        + "all · head sure (posterior sd) · unsure | its 68 % coverage [95 % CP] |"
    )
    print("|---|---:|---:|---:|---|---:|---:|---|---:|---|---|")
    for r in rows:
        cov = " ".join(f"{v:.2f}" for v in r["pooled68"].values())
        rejected = [s for s, (k, v) in zip(short, list(r["lc2st_named"].items())[1:], strict=True) if v[1] <= 0.05]
        jn, jt = r["lc2st_named"]["joint"], r["lc2st_test"]["joint"]
        print(
            f"| {r['lever']} | {r['info_gain_nats']:.2f} ± {r['test_nll_se']:.2f} | {r['calibration_error']:.3f} "
            f"({r['calibration_band']:.3f}) | {r['cells_below']} · {r['cells_above']} of {r['cells']} | {cov} | "
            f"{jn[0]:.3f} ({jn[1]:.3f}) | {jt[0]:.3f} ({jt[1]:.3f}) | {', '.join(rejected) or '—'} | "
            f"{r['clear_noon_sun']:.2f}° | {more_scenes(r)} |"
        )


def more_scenes(r: dict) -> str:
    """The cells of :func:`clear_noon`'s figures in the table (empty where not measured)."""
    c = r.get("clear_noon_more")
    if c is None:
        return " |"
    return (
        f"{c['median_abs_error']:.2f}° ({c['scenes']}) · {c['median_abs_error_sure']:.2f}° ({c['median_sd_sure']:.1f}°; "
        f"{c['sure']}) · {c['median_abs_error_unsure']:.2f}° | {c['coverage68']:.2f} [{c['ci68'][0]:.2f}, "
        f"{c['ci68'][1]:.2f}]"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    default = [x for x in LEVERS if not x.endswith("-noise-S")]
    parser.add_argument("--levers", nargs="+", default=default, metavar="LEVER", help="*-noise-S: S in [0, 1]")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "named_levers"))
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--extra", type=int, default=20000, help="extra training images of boundary, more-uniform")
    parser.add_argument("--clear-noon-scenes", type=int, default=96, help="ClearNoon's scenes for the sun (0: none)")
    args = parser.parse_args()
    if args.clear_noon_scenes < 0:
        parser.error(f"--clear-noon-scenes must be ≥ 0, got {args.clear_noon_scenes}")
    unknown = sorted(x for x in set(args.levers) - set(LEVERS) if not x.startswith(tuple(NOISE_LEVERS)))
    if unknown:
        parser.error(f"unknown levers {unknown}; choose from {', '.join(LEVERS)}")
    for lever in args.levers:
        if lever.startswith(tuple(NOISE_LEVERS)):
            try:
                estimate_share(lever)
            except ValueError as e:
                parser.error(str(e))
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(message)s")
    logger = logging.getLogger("named-levers")
    logger.setLevel(logging.INFO)
    params_file, paths = _scratch(Path(args.out))
    start = time.perf_counter()
    rows, notes = [], {}
    for lever in args.levers:
        notes[lever] = build(lever, params_file, paths, logger, args.extra)
        rows.append(row(lever, evaluate(notes[lever]["model"], params_file, paths, logger)))
        if args.clear_noon_scenes:
            rows[-1]["clear_noon_more"] = clear_noon(notes[lever]["model"], params_file, paths, args.clear_noon_scenes)
    report(rows)
    from benchmarks.machine import machine_info

    print(json.dumps({"rows": rows, "notes": notes, "seconds": time.perf_counter() - start, **machine_info()}))


if __name__ == "__main__":
    main()
