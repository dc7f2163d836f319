"""How far the test split's figures move from one split to another: a trained model scored on fresh test-like splits.

Every figure of ``reports/task1/`` comes from one test split: 2 000 images, about 1 000 of them at night, drawn eight to
a scene. A night coverage of 62 % there is 1.5 binomial standard errors from 64 %, and the scenes make the images
fewer than they look. This benchmark tells how much of a figure is the split: it renders ``--splits`` more splits of
the test split's plan under other root seeds (``params.yaml``'s seed + 1, + 2, …: the same prior, size, scenes per
image and renderer; none of their scenes is the pipeline's), computes the model's backbone features, and scores the
model on each exactly like ``bench_levers.py`` (``score``: information gain, calibration error and its band, per
parameter the day and night median |posterior median − truth| and the night and day 68 % coverage), beside the
pipeline's own test split (its cached features, ``features/<backbone>/``; ``--pipeline-splits test val`` adds the
validation split, whose images chose the best epoch and fitted τ but none of the figures' development). It prints
one row per split and the mean and standard deviation over the fresh ones, and writes them as JSON to ``--out``. Usage::

    python benchmarks/bench_splits.py --model models/cues-50000/model.pt --splits 4 [--pipeline-splits test val]

The fresh splits' features are kept in ``--cache`` (keyed by seed, size, the renderer's version and the backbone's
fingerprint), so a second model of the same backbone costs only its draws. Models of a frozen backbone only (``cues``,
``tiny``, a pretrained one): a model that trains its backbone (``cnn``) is refused by name.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# isort: off
import components  # noqa: E402,F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks.machine import machine_info  # noqa: E402
from benchmarks.studies.bench_levers import score  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.core.files import atomic_path  # noqa: E402
from components.core.weather import PREDICTED  # noqa: E402
from components.features import cache  # noqa: E402
from components.features.backbones import get_backbone  # noqa: E402
from components.posterior.store import load_npe  # noqa: E402
from components.simulate import dataset  # noqa: E402
from components.simulate.base import make_simulator  # noqa: E402
from components.simulate.in_memory import render_split  # noqa: E402

#: the figures summarized over the fresh splits: scalars, and per-parameter blocks
SCALARS = ("info_gain_nats", "test_nll", "calibration_error")
BLOCKS = ("day_median_abs_error", "night_coverage68", "day_coverage68")


def fresh_features(params, backbone, seed: int, size: int, workers: int, folder: Path | None) -> tuple[np.ndarray, ...]:
    """Features ``(size, dim)`` float32 and θ ``(size, 6)`` of the test split's plan under root seed ``seed``, read
    from ``folder`` when it holds them for this renderer (its version: algorithm, calibration, render sizes) and this
    backbone's fingerprint, else rendered (``workers`` processes) and kept there."""
    renderer = hashlib.sha256(make_simulator(params.simulator).version.encode()).hexdigest()[:12]
    name = f"{backbone.name}-{backbone.fingerprint()[:12]}-{renderer}-{seed}-{size}.npz"
    path = folder / name if folder else None
    if path is not None and path.is_file():
        with np.load(path) as z:
            return z["x"], z["theta"]
    images, theta = render_split(params, "test", size, workers, seed=seed)
    x = backbone.extract(images, batch_size=params.backbones.batch_size)
    if path is not None:
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, x=x, theta=theta)
    return x, theta


def summarize(rows: list[dict]) -> dict:
    """Mean and standard deviation (ddof 1) over ``rows`` of every figure in :data:`SCALARS` and :data:`BLOCKS`."""
    out: dict = {}
    for k in SCALARS:
        v = np.array([r[k] for r in rows])
        out[k] = {"mean": float(v.mean()), "sd": float(v.std(ddof=1)) if len(v) > 1 else None}
    for k in BLOCKS:
        v = np.array([[r[k][p] for p in PREDICTED] for r in rows])
        sd = v.std(axis=0, ddof=1) if len(v) > 1 else [None] * len(PREDICTED)
        out[k] = {
            p: {"mean": float(m), "sd": None if s is None else float(s)}
            for p, m, s in zip(PREDICTED, v.mean(0), sd, strict=True)
        }
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--model", type=Path, default=ROOT / "models" / "cues-50000" / "model.pt", help="a model.pt of the train stage"
    )
    p.add_argument("--splits", type=int, default=4, help="fresh splits (root seeds params.seed + 1 … + splits)")
    p.add_argument("--size", type=int, default=None, help="images per fresh split (default: the test split's)")
    p.add_argument("--samples", type=int, default=500, help="posterior draws per image")
    p.add_argument("--seed", type=int, default=2026, help="the draws' seed")
    p.add_argument("--workers", type=int, default=2, help="rendering processes")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument(
        "--root", type=Path, default=ROOT, help="the pipeline's project root (params.yaml, data/, features/)"
    )
    p.add_argument(
        "--pipeline-splits",
        nargs="+",
        default=["test"],
        choices=["test", "val"],
        help="the pipeline's own splits scored beside the fresh ones (their cached features)",
    )
    p.add_argument("--cache", type=Path, default=ROOT / "benchmarks" / "results" / "splits" / "cache")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "splits")
    a = p.parse_args(argv)
    if a.splits < 1:
        raise SystemExit(f"--splits must be at least 1, got {a.splits}")
    params = load_params(a.root / "params.yaml")
    size = params.data.splits["test"] if a.size is None else a.size
    if size < 2:
        raise SystemExit(f"--size must be at least 2 images, got {size}")
    model, header = load_npe(a.model)
    if header["trainable_backbone"]:
        raise SystemExit(
            f"{a.model}: its backbone {header['backbone']!r} is trained with the flow; this benchmark scores models "
            "of a frozen backbone (cues, tiny, a pretrained one)"
        )
    torch.set_num_threads(a.threads)
    backbone = get_backbone(header["backbone"], **header["backbone_options"]).eval()
    name = header["extra"].get("model_id", a.model.parent.name)
    t0 = time.perf_counter()
    splits = {}
    for split in a.pipeline_splits:
        images = dataset.open_split(a.root / params.data.root, split)
        x = cache.open_features(a.root / "features", backbone.name, images)
        splits[split] = (x, images.theta.astype(np.float32))
    for k in range(1, a.splits + 1):
        splits[f"seed+{k}"] = fresh_features(params, backbone, params.seed + k, size, a.workers, a.cache)
    rows = {}
    print(f"| {name}: split | images (night) | info gain | calibration (band) | day errors | night 68 % coverage |")
    print("|---|---|---|---|---|---|")
    for split, (x, theta) in splits.items():
        r = score(model, torch.as_tensor(x), torch.as_tensor(theta), model.box, a.samples, a.seed)
        rows[split] = r
        night = int((theta[:, PREDICTED.index("sun_altitude_angle")] <= 0).sum())
        print(
            f"| {split} | {len(x)} ({night}) | {r['info_gain_nats']:.2f} | {r['calibration_error']:.3f} "
            f"({r['calibration_band']:.3f}) | {' / '.join(f'{v:.2f}' for v in r['day_median_abs_error'].values())} | "
            f"{' / '.join(f'{100 * v:.1f}' for v in r['night_coverage68'].values())} |",
            flush=True,
        )
    fresh = summarize([r for s, r in rows.items() if s not in a.pipeline_splits])
    for k in BLOCKS:
        spread = {p: "" if v["sd"] is None else f" ± {v['sd']:.3f}" for p, v in fresh[k].items()}
        print(f"fresh splits, {k}: " + ", ".join(f"{p} {v['mean']:.3f}{spread[p]}" for p, v in fresh[k].items()))
    a.out.mkdir(parents=True, exist_ok=True)
    result = {"model": name, "path": str(a.model), "splits": rows, "fresh": fresh, "seconds": time.perf_counter() - t0}
    (a.out / f"{name}.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(machine_info(threads=a.threads)))


if __name__ == "__main__":
    main()
