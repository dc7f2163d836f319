"""What each lever of the models buys: information gain and calibration of one NPE per setting, on the same images.

The ablation of docs/studies/image-models.md. Every setting trains one NPE on cached backbone
features of the pipeline (``features/<backbone>/``, so run ``dvc repro features@cues`` first) and scores it on the
test split — test NLL, information gain over the prior, calibration error (the KS distance of the HPD credibilities
from uniform, :func:`components.evaluate.diagnostics.calibration_error`) with the 95 % band of a perfectly calibrated
model on as many images, signed coverage area, and per parameter the day and night median |posterior median − truth|
and the share of truths inside the central 68 % interval —
all from ``--samples`` posterior draws per test image, seeded.

Levers (``--setting NAME``, several allowed):

* ``cues-v1-<n>``: the 80 version-1 cues (the first 80 columns of the cache), ``n`` training images;
* ``cues-v2-<n>``: the 241 version-2 cues (the first 241 columns);
* ``cues-v3-<n>``: the 273 version-3 cues (the first 273 columns);
* ``cues-v4-<n>``: the 345 cues of version 4 (the first 345 columns: version 3 and the sky's thumbnail, the
  ``tiny`` cache's columns of ``+sky3`` below to the bit);
* ``cues-v5-<n>``: the 363 cues of version 5 (the first 363 columns: version 4 and the wet road by distance);
* ``cues-v6-<n>``: the 375 cues of version 6 (the first 375 columns: version 5 and the weather reader);
* ``cues-v7-<n>``: all 377 cues of version 7 (the cache of today's ``cues``: version 6 and the reader's sun head);
* ``cues-v3+tiny-<n>``: those joined by the 256 features of the ``tiny`` backbone's cache (its 8×8 L*a*b* thumbnail
  and per-cell contrast: where the light falls, finer than the cues' 4×4 grid; ``dvc repro features@tiny``);
* ``cues-v3+sky<r>-<n>``: the cues joined by the L*a*b* of the thumbnail's upper ``r`` lattice rows only (24·r
  features of the ``tiny`` cache; ``r`` from 1 to 8; the sky and the horizon for ``r`` ≤ 3);
* ``…-e<k>``: ``k`` epochs instead of the pipeline's (``params.yaml`` ``train`` with its sample budget);
* ``…-ens<k>``: an equal-weight ensemble of ``k`` flows;
* ``…-c<w>x<w>…``: a context network of these widths before the flows (``train.flow.context_layers``), ``-c0``: none;
  without it the pipeline's (``params.yaml``; settings measured before 2026-11-26's context network had none: ``-c0``
  reproduces them);
* ``…-lr<x>``, ``…-wd<x>``: AdamW's learning rate and weight decay instead of the pipeline's (``train.lr``,
  ``train.weight_decay``);
* ``…-n<σ>``: Gaussian noise of standard deviation σ added to the standardized inputs while training
  (``TrainingConfig.input_noise``, a regularizer; off at evaluation); without it no noise, whatever ``params.yaml``
  says (``train.input_noise``);
* ``…-m``: every training input replaced by its mirror image's with probability ½ each batch
  (``TrainingConfig.mirror``: the backbones' feature permutation, no new rendering);
* ``…-t``: the base temperature τ fitted on the validation split after training (``train.temperature``,
  :mod:`components.posterior.temperature`); without it τ = 1, whatever ``params.yaml`` says.

Everything else is the pipeline's (``components.posterior.settings`` from ``params.yaml``). Usage::

    python benchmarks/studies/bench_levers.py --setting cues-v1-50000-e20 cues-v2-50000-e20 cues-v2-50000-e40 \\
        cues-v2-50000-ens3-e20 cues-v2-5000 cues-v2-20000

Prints one table row and writes one JSON file per setting (``benchmarks/results/levers/``; existing ones are reused)
and one JSON line with the machine's details.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import dataclasses
import json
import re
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.core.weather import PREDICTED  # noqa: E402
from components.evaluate import diagnostics  # noqa: E402
from components.features import cache  # noqa: E402
from components.features.backbones.cues import MIRROR  # noqa: E402
from components.features.backbones.tiny import TinyImagesBackbone  # noqa: E402
from components.posterior import NPE, train  # noqa: E402
from components.posterior.settings import flow_config, temperature_regime, training_config  # noqa: E402
from components.posterior.temperature import calibrate_post_hoc  # noqa: E402
from components.simulate import dataset  # noqa: E402

_SETTING = re.compile(
    r"^cues-(v1|v2|v3|v4|v5|v6|v7)(\+tiny|\+sky[1-8])?-(\d+)(?:-ens(\d+))?(?:-c(0|\d+(?:x\d+)*))?(?:-e(\d+))?(?:-lr(\d+(?:\.\d+)?(?:e-?\d+)?))?"
    r"(?:-wd(\d+(?:\.\d+)?(?:e-?\d+)?))?(?:-n([0-9.]+))?(-m)?(-t)?$"
)
#: the leading columns of today's cues cache that each cue version computed
COLUMNS = {"v1": 80, "v2": 241, "v3": 273, "v4": 345, "v5": 363, "v6": 375, "v7": None}


def parse_setting(name: str) -> dict:
    """``cues-v2-50000-ens3-c256x128-e20-t`` → {version, tiny, sky_rows, size, ensemble, context_layers, epochs, lr,
    weight_decay, noise, mirror, temperature} (``context_layers``, ``lr``, ``weight_decay`` None: the pipeline's);
    ``ValueError`` naming the grammar otherwise."""
    m = _SETTING.match(name)
    if not m:
        raise ValueError(
            f"setting {name!r}: expected "
            "cues-(v1|v2|v3|v4|v5|v6|v7)[+tiny|+sky<rows>]-<size>[-ens<k>][-c<w>x<w>…|-c0][-e<epochs>][-lr<lr>][-wd<decay>][-n<σ>][-m][-t]"
        )
    v, tiny, size, ens, ctx, ep, lr, wd, noise, mirror, temp = m.groups()
    return {
        "version": v,
        "tiny": tiny == "+tiny",
        "sky_rows": int(tiny[4:]) if tiny and tiny.startswith("+sky") else 0,
        "size": int(size),
        "ensemble": int(ens or 1),
        "context_layers": None if ctx is None else () if ctx == "0" else tuple(int(w) for w in ctx.split("x")),
        "epochs": int(ep) if ep else None,
        "lr": float(lr) if lr else None,
        "weight_decay": float(wd) if wd else None,
        "noise": float(noise) if noise else 0.0,
        "mirror": bool(mirror),
        "temperature": bool(temp),
    }


def run(name: str, root: Path, samples: int, seed: int) -> dict:
    s = parse_setting(name)
    params = load_params(root / "params.yaml")
    splits = {k: dataset.open_split(root / params.data.root, k) for k in dataset.SPLITS}
    cols = COLUMNS[s["version"]]

    joined = tiny_columns(s)

    def feats(split: dataset.Split, stop: int | None = None) -> np.ndarray:
        cues = cache.open_features(root / "features", "cues", split, stop=stop)[:, :cols]
        if joined is not None:
            tiny = cache.open_features(root / "features", "tiny", split, stop=stop)[:, joined]
            cues = np.concatenate([cues, tiny], axis=1)
        return cues.astype(np.float32)

    x = {"train": feats(splits["train"], s["size"]), "val": feats(splits["val"]), "test": feats(splits["test"])}
    theta = {k: splits[k].theta[: len(v)].astype(np.float32) for k, v in x.items()}
    mirror = mirror_map(s["version"], joined) if s["mirror"] else None
    return {"setting": name, **fit(s, x, theta, params, samples, seed, mirror=mirror)}


def fit(
    s: dict,
    x: dict[str, np.ndarray],
    theta: dict[str, np.ndarray],
    params,
    samples: int,
    seed: int,
    device: str = "cpu",
    mirror=None,
    compile: bool = True,
) -> dict:
    """Train one NPE of setting ``s`` (:func:`parse_setting`) on inputs ``x[split] (n, d)`` float32 with truths
    ``theta[split] (n, 6)`` (splits train, val, test; the train split's first ``s["size"]`` rows are used) and score it
    on the test split (:func:`score`); ``mirror``: the map of inputs to their mirror images' (for ``-m``); ``compile``
    False: never compile the training step (else the pipeline's rule, on a CPU only)."""
    x = {k: torch.as_tensor(v[: s["size"]] if k == "train" else v).to(device) for k, v in x.items()}
    theta = {k: torch.as_tensor(v[: s["size"]] if k == "train" else v).to(device) for k, v in theta.items()}
    if len(x["train"]) < s["size"]:
        raise ValueError(f"setting of {s['size']} training images: only {len(x['train'])} given")
    fc = flow_config(params.train, size=s["size"], trainable=False, ensemble=s["ensemble"])
    if s["context_layers"] is not None:
        fc = dataclasses.replace(fc, context_layers=s["context_layers"])
    chosen = {k: s[k] for k in ("epochs", "lr", "weight_decay") if s[k] is not None}  # else the pipeline's
    tc = dataclasses.replace(
        training_config(
            params.train,
            size=s["size"],
            trainable=False,
            features=x["train"].shape[1],
            parameters=len(params.box.names),
            seed=seed,
        ),
        input_noise=s["noise"],
        mirror=s["mirror"],
        **chosen,
    )
    if device != "cpu" or not compile:  # the pipeline's compile rule is for its CPU (inductor's C++ kernels)
        tc = dataclasses.replace(tc, compile=False)
    model = NPE(None, x["train"].shape[1], params.box, fc, parameters=len(params.box.names), seed=seed).to(device)
    t0 = time.perf_counter()
    history = train(model, (x["train"], theta["train"]), (x["val"], theta["val"]), tc, mirror=mirror)
    model.eval()
    # the pipeline's calibration: the regime's gate on the training pairs, then τ on the validation split
    regime = temperature_regime(params.train, params.box)
    pairs = {k: (x[k], theta[k]) for k in ("train", "val")}
    tempered = calibrate_post_hoc(model, pairs["train"], pairs["val"], regime) if s["temperature"] else {}
    seconds = time.perf_counter() - t0
    return {
        **s,
        "features": x["train"].shape[1],
        "epochs_run": len(history.records),
        "best_epoch": history.best_epoch,
        "train_seconds": round(seconds, 1),
        **tempered,
        **score(model, x["test"], theta["test"], params.box, samples, seed),
    }


def tiny_columns(setting: dict) -> np.ndarray | None:
    """The columns of the ``tiny`` cache joined to the cues: all of them (``+tiny``), the L*a*b* blocks' upper
    ``sky_rows`` lattice rows (``+sky<r>``), or none."""
    if setting["tiny"]:
        return np.arange(TinyImagesBackbone().dim)
    if setting["sky_rows"]:
        g = TinyImagesBackbone().grid
        return np.arange(4 * g * g).reshape(4, g, g)[:3, : setting["sky_rows"]].ravel()  # L*, a*, b*; not contrast
    return None


def mirror_map(version: str, tiny: np.ndarray | None):
    """The inputs of the mirrored images as a map of a batch of inputs: the cues' permutation
    (:data:`components.features.backbones.cues.MIRROR`) on the version's columns, joined by the ``tiny`` one's on its
    columns ``tiny`` (:func:`tiny_columns`; a lattice row mirrors onto itself)."""
    cols = COLUMNS[version] or len(MIRROR)
    index = list(MIRROR[:cols])
    if max(index) >= cols:
        raise ValueError(f"cues-{version}: the mirror permutation leaves its {cols} columns")
    if tiny is not None:
        position = {int(c): k for k, c in enumerate(tiny)}
        mirrored = TinyImagesBackbone().mirror_index()
        index += [cols + position[mirrored[int(c)]] for c in tiny]
    perm = torch.tensor(index)
    return lambda x: x[:, perm]


def score(model: NPE, xt: torch.Tensor, tt: torch.Tensor, box, samples: int, seed: int) -> dict:
    """The scores of a trained ``model`` on test inputs ``xt (N, …)`` with truths ``tt (N, 6)`` (on the model's
    device): test NLL, information gain over the prior ``box``, calibration error and its 95 % band, coverage gap, and
    per parameter the day and night median |posterior median − truth| and central-68 % coverage, from ``samples``
    draws per image seeded by ``seed``."""
    with torch.no_grad():
        lp_truth = torch.cat([model.log_prob(tt[i : i + 500], xt[i : i + 500]) for i in range(0, len(xt), 500)])
        draws, lps = [], []
        for i in range(0, len(xt), 100):
            d, lp = model.sample_and_log_prob(xt[i : i + 100], samples, rng=seed + i)
            draws.append(d.cpu().numpy())
            lps.append(lp.cpu().numpy())
    draws, lp = np.concatenate(draws), np.concatenate(lps)  # (N, samples, 6), (N, samples)
    theta = tt.cpu().numpy()
    cred = diagnostics.hpd_credibility(lp, lp_truth.cpu().numpy())
    levels = diagnostics.DEFAULT_LEVELS
    coverage = diagnostics.expected_coverage(cred, levels)
    nll = float(-lp_truth.mean())
    day = theta[:, PREDICTED.index("sun_altitude_angle")] > 0
    err = np.abs(np.median(draws, axis=1) - theta)
    low, high = np.quantile(draws, [0.15865, 0.84135], axis=1)  # (N, 6) each
    inside = (theta >= low) & (theta <= high)
    return {
        "test_images": len(xt),
        "test_nll": nll,
        "info_gain_nats": box.log_volume() - nll,
        "calibration_error": diagnostics.calibration_error(cred),
        "calibration_band": diagnostics.calibration_band(
            len(xt), samples, None, np.random.default_rng(seed), quantile=0.95, replicates=1000
        ),
        "coverage_auc_gap": float(np.trapezoid(coverage - levels, levels)),
        "day_median_abs_error": dict(zip(PREDICTED, np.median(err[day], axis=0).round(2).tolist(), strict=True)),
        "night_median_abs_error": dict(zip(PREDICTED, np.median(err[~day], axis=0).round(2).tolist(), strict=True)),
        # share of the truths inside each marginal's central 68 % interval (#13's target for night images: 63–73 %)
        "day_coverage68": dict(zip(PREDICTED, inside[day].mean(axis=0).round(3).tolist(), strict=True)),
        "night_coverage68": dict(zip(PREDICTED, inside[~day].mean(axis=0).round(3).tolist(), strict=True)),
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--setting", nargs="+", required=True, type=str)
    p.add_argument("--root", type=Path, default=ROOT, help="the pipeline's project root (params.yaml, features/)")
    p.add_argument("--samples", type=int, default=500, help="posterior draws per test image")
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "levers")
    a = p.parse_args(argv)
    for name in a.setting:
        parse_setting(name)  # every name checked before any work
    torch.set_num_threads(a.threads)
    a.out.mkdir(parents=True, exist_ok=True)
    print("| setting | features | epochs | train s | info gain | calibration error (band) | coverage gap |")
    print("|---|---|---|---|---|---|---|")
    for name in a.setting:
        path = a.out / f"{name}.json"
        r = json.loads(path.read_text()) if path.is_file() else run(name, a.root, a.samples, a.seed)
        path.write_text(json.dumps(r, indent=1))
        print(
            f"| {name} | {r['features']} | {r['epochs_run']} | {r['train_seconds']} | {r['info_gain_nats']:.2f} | "
            f"{r['calibration_error']:.3f} ({r['calibration_band']:.3f}) | {r['coverage_auc_gap']:+.3f} |",
            flush=True,
        )
    print(json.dumps(machine_info(threads=a.threads)))


if __name__ == "__main__":
    main()
