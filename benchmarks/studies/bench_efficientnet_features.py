"""Which features of ``efficientnet_lite0`` to give the flow: pooled last stage or several stages, at which input size.

The study of docs/studies/efficientnet-features.md. Candidates (``--candidates``), each ``<pooling>-<size>``:

* ``head-128``: the global mean of the 1280 head channels at the renders' native 128×128 (dim 1280);
* ``head-224``: the same at EfficientNet-Lite0's training size, 224×224 (the render enlarged; dim 1280);
* ``stages-128`` / ``stages-224``: the global means of the blocks' outputs at strides 8, 16, 32 (dim 472);
* ``stages+head-128`` / ``stages+head-224``: both (dim 1752);

and, for reference, the pipeline's cached ``cues`` and ``tiny`` features (``features/<name>/``, read only; skipped
when absent). For each: the features stage's cost (seconds per image through ``Backbone.extract`` in batches of
``backbones.batch_size``, ``--threads`` torch threads, the median of ``--repeats`` rounds that alternate the
candidates), then one flow trained with the pipeline's settings for ``--train`` images (``params.yaml`` through
:mod:`components.posterior.settings`: epochs, widths, input noise, base temperature τ; the same for every candidate,
:func:`benchmarks.studies.bench_levers.fit`) on the train split's first images, its best epoch and τ chosen on the
first ``--val`` images of the val split, and scored on the next ``--held-out`` val images: NLL, information gain over
the prior, calibration error (with the 95 % band of a calibrated model on as many images) and per parameter the
median |posterior median − truth|.

    .venv/bin/python benchmarks/studies/bench_efficientnet_features.py --threads 1

Writes the candidates' features (``.npy``) and one JSON per candidate under ``--out`` (reused when present: delete
them to measure again); prints a table and one JSON line with the machine's details.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from benchmarks.studies.bench_levers import fit  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.core.weather import PREDICTED  # noqa: E402
from components.features import cache  # noqa: E402
from components.features.backbones import get_backbone  # noqa: E402
from components.posterior.settings import input_noise_for  # noqa: E402
from components.simulate import dataset  # noqa: E402

CANDIDATES = ("head-128", "stages-128", "stages+head-128", "head-224", "stages-224", "stages+head-224")
REFERENCES = ("cues", "tiny")
HEAD = 1280  # the head's channels: the last columns of the "stages+head" features, the stages' the first


def _backbone(candidate: str):
    pooling, size = candidate.rsplit("-", 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return get_backbone("efficientnet_lite0", pooling=pooling, size=int(size))


def _extract(backbone, images: np.ndarray, batch_size: int) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the size conversion is announced once
        return backbone.extract(images, batch_size=batch_size)


def seconds_per_image(names: list[str], images: np.ndarray, batch_size: int, repeats: int) -> dict[str, float]:
    """Median seconds per image of each backbone (candidate or reference name) on ``images``, rounds alternated."""
    built = {n: _backbone(n) if n in CANDIDATES else get_backbone(n) for n in names}
    for b in built.values():
        _extract(b, images[:8], batch_size)  # warm-up
    times: dict[str, list[float]] = {n: [] for n in names}
    for _ in range(repeats):
        for n, b in built.items():
            t0 = time.perf_counter()
            _extract(b, images, batch_size)
            times[n].append((time.perf_counter() - t0) / len(images))
    return {n: statistics.median(t) for n, t in times.items()}


def features(candidate: str, splits: dict, counts: dict[str, int], out: Path, batch_size: int) -> dict:
    """The candidate's features of the first ``counts[split]`` images of each split (``stages+head`` computed once
    per size; ``head`` its last 1280 columns, ``stages`` the others: the same numbers); cached as ``.npy`` under
    ``out``."""
    pooling, size = candidate.rsplit("-", 1)
    result = {}
    for name, n in counts.items():
        path = out / f"stages-{size}-{name}-{n}.npy"
        if not path.is_file():
            backbone = _backbone(f"stages+head-{size}")
            values = np.concatenate([_extract(backbone, imgs, batch_size) for _, imgs in splits[name].iter_shards(n)])
            np.save(path, values)
        values = np.load(path)
        result[name] = {"head": values[:, -HEAD:], "stages": values[:, :-HEAD], "stages+head": values}[pooling]
    return result


def study(candidate: str, args: argparse.Namespace, params, splits: dict) -> dict:
    counts = {"train": args.train, "val": args.val + args.held_out}
    if candidate in REFERENCES:
        x = {k: cache.open_features(args.root / "features", candidate, splits[k], stop=n) for k, n in counts.items()}
    else:
        x = features(candidate, splits, counts, args.out, params.backbones.batch_size)
    x = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in x.items()}
    theta = {k: splits[k].theta[:n].astype(np.float32) for k, n in counts.items()}
    v = args.val
    inputs = {"train": x["train"], "val": x["val"][:v], "test": x["val"][v:]}  # "test": the held-out val images
    truths = {"train": theta["train"], "val": theta["val"][:v], "test": theta["val"][v:]}
    setting = {
        "size": args.train,
        "ensemble": 1,
        "context_layers": None,  # the pipeline's, and every other None below
        "epochs": None,
        "lr": None,
        "weight_decay": None,
        "noise": input_noise_for(params.train, args.train, trainable=False, features=x["train"].shape[1]),
        "mirror": False,
        "temperature": bool(params.train.temperature),
    }
    return {"candidate": candidate, **fit(setting, inputs, truths, params, args.samples, args.seed, compile=False)}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--candidates", nargs="+", default=[*CANDIDATES, *REFERENCES], choices=[*CANDIDATES, *REFERENCES])
    p.add_argument("--root", type=Path, default=ROOT, help="the project root (params.yaml, data/, features/)")
    p.add_argument("--train", type=int, default=5000, help="training images (the train split's first)")
    p.add_argument("--val", type=int, default=2000, help="val images choosing the best epoch and τ")
    p.add_argument("--held-out", type=int, default=2000, help="the next val images, scored")
    p.add_argument("--timing-images", type=int, default=256)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--samples", type=int, default=300, help="posterior draws per scored image")
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--threads", type=int, default=1, help="torch threads (the features stage uses 1 per worker)")
    p.add_argument("--out", type=Path, default=Path("/tmp/efficientnet-features"))
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    a.out.mkdir(parents=True, exist_ok=True)
    params = load_params(a.root / "params.yaml")
    splits = {k: dataset.open_split(a.root / params.data.root, k) for k in ("train", "val")}
    names = [c for c in a.candidates if c in CANDIDATES or (a.root / "features" / c / "manifest.json").is_file()]

    timing_path = a.out / "timing.json"  # measured together, so that the rounds alternate; delete it to re-measure
    timing = json.loads(timing_path.read_text()) if timing_path.is_file() else {}
    if set(names) - set(timing):
        images = splits["val"].images(a.timing_images)
        timing = seconds_per_image(names, images, params.backbones.batch_size, a.repeats)
        timing_path.write_text(json.dumps(timing, indent=1))
    print(
        "| candidate | dim | s / image | epochs | val NLL | info gain | calibration error (band) | "
        + " | ".join(f"day {k}" for k in PREDICTED)
        + " |"
    )
    print("|---" * (7 + len(PREDICTED)) + "|")
    for name in names:
        path = a.out / f"{name}-{a.train}-seed{a.seed}.json"
        r = json.loads(path.read_text()) if path.is_file() else study(name, a, params, splits)
        path.write_text(json.dumps(r, indent=1))
        errors = r["day_median_abs_error"]  # sun above the horizon: every parameter can show
        print(
            f"| {name} | {r['features']} | {timing.get(name, float('nan')):.4f} | {r['epochs_run']} | "
            f"{r['test_nll']:.2f} | {r['info_gain_nats']:.2f} | {r['calibration_error']:.3f} "
            f"({r['calibration_band']:.3f}) | " + " | ".join(f"{errors[k]:.1f}" for k in PREDICTED) + " |",
            flush=True,
        )
    print(json.dumps({"benchmark": "efficientnet-features", **machine_info(threads=a.threads)}))


if __name__ == "__main__":
    main()
