"""The paper profile's scale by its parts: each stage's unit cost measured on this machine, extrapolated to the whole.

Issue #58, part 4. The paper profile (``profiles/paper.yaml``: 500 000 / 100 000 / 35 000 images at 224 × 224, the
pretrained ResNet-50, DINOv2 and CLIP, training sizes 5k / 50k / 500k at 200 epochs, 1 000 draws per test image)
cannot run here end to end: its weights cannot be downloaded on this machine, and even a tenth of it would take the
two cores most of a day. So this script measures each stage's cost per unit of work, one thread, and multiplies:

* **generate**: the renderer at the profile's size, 8 images per scene (``data.images_per_scene``), images/s;
* **features**: each pretrained backbone's real loading and extraction code (``get_backbone(name, path=...)``,
  ``extract``) on a checkpoint of the REAL architecture and size with RANDOM weights, built here in a temporary
  folder (``ResNetConfig()`` = ResNet-50; ``Dinov2Config`` of ``facebook/dinov2-small``; ``CLIPVisionConfig()`` =
  ViT-B/32) and the repositories' image processors: a dense network's time does not depend on its weights' values.
  These features mean nothing and are never written anywhere; images/s and the child process's peak memory;
* **train**: one paper model's training loop (``train``: the compiled loss where the pipeline compiles it, AdamW,
  its own validation) on synthetic inputs of the backbone's dimension, the flow the profile gives that size
  (``flow_config``), samples/s after the first epoch (the compile) — per backbone dimension and hidden width;
  an ensemble of K flows is counted as K flows' work;
* **evaluate**: from the default pipeline's measured full run (``benchmarks/bench_pipeline.py --scale 1 --cpus 0,1``,
  its JSON given by ``--pipeline``, its log beside it): each model's line gives the seconds per flow pass per
  posterior draw (an ensemble of K flows takes K + 1 passes a draw: the drawing member's and each member's density;
  the flows have the paper's widths), per test image of the rest, and the named weathers' seconds per model (which
  do not grow with the test split);
* **export, task2, task3**: the same run's flow seconds (export per model; Task II and III as they are).

The extrapolation: per stage the core-seconds of the whole profile, then its wall time on 1, 16 and 64 cores as
``max(core-seconds / cores, critical path)``: perfect scaling up to the critical path (optimistic: on 2 cores the
stages were 0.79–0.96 efficient, ``BENCHMARKS.md``), the critical path the longest single task (a model's training runs on one core:
a flow's step gains nothing from a second thread, ``bench_training.py``; a model's evaluation runs in one process).
One GPU is not measured here (no device in this session). Memory: each stage's largest resident arrays from the
profile's shapes, and the measured peak of a backbone's extraction.

    .venv/bin/python benchmarks/studies/bench_paper_scale.py --pipeline benchmarks/results/pipeline/<key>/cpus-0_1.json

Prints the tables and one JSON line. Record: docs/studies/paper-scale.md.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import dataclasses
import json
import math
import multiprocessing
import re
import resource
import sys
import tempfile
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine import machine_info  # noqa: E402

from components.core import config, seeding  # noqa: E402
from components.core.weather import sample_azimuth, weather_from_theta  # noqa: E402
from components.posterior import NPE, train  # noqa: E402
from components.posterior.settings import ensemble_for, epochs_for, flow_config, training_config  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
#: the pretrained backbones' feature dimensions at the profile's default repositories
DIMS = {"resnet50": 2048, "dinov2": 384, "clip": 768}
GIB = 2**30
#: the evaluate stage's line per model (flows/evaluate.py) in bench_pipeline's log
EVALUATED = re.compile(
    r" - (?P<model>\S+): (?P<images>\d+) images × (?P<draws>\d+) draws in [\d.]+ s, CPU [\d.]+ s \(load (?P<load>[\d.]+) s, "
    r"draws (?P<sampling>[\d.]+) s, metrics (?P<metrics>[\d.]+) s, PPC and plots (?P<ppc>[\d.]+) s, "
    r"named weathers (?P<named>[\d.]+) s\)"
)


def passes(flows: int) -> int:
    """Flow passes per posterior draw with its log-density: one for a single flow; for an ensemble of K, the drawing
    member's inverse and the density under each member (K + 1)."""
    return 1 if flows == 1 else flows + 1


def evaluation_units(log: Path, default: config.Params) -> dict[str, float]:
    """From the default pipeline's evaluate lines: seconds per flow pass per draw, per test image of the rest
    (loading, metrics, PPC, plots), and of the named weathers per model (which do not grow with the test split)."""
    try:
        text = log.read_text(errors="replace")
    except OSError as err:
        raise SystemExit(f"{log}: cannot read bench_pipeline's log ({err})") from None
    rows = [m.groupdict() for m in EVALUATED.finditer(text)]
    if not rows:
        raise SystemExit(f"{log}: no evaluate line of a model (flows/evaluate.py's 'images × draws in' line)")
    per_pass, per_image, named = [], [], []
    for r in rows:
        size = int(r["model"].rsplit("-", 1)[1])
        k = ensemble_for(default.train, size)
        n_img, n_draws = int(r["images"]), int(r["draws"])
        per_pass.append(float(r["sampling"]) / (n_img * n_draws * passes(k)))
        per_image.append((float(r["load"]) + float(r["metrics"]) + float(r["ppc"])) / n_img)
        named.append(float(r["named"]))
    return {
        "s_per_pass_draw": float(np.mean(per_pass)),
        "s_per_image": float(np.mean(per_image)),
        "named_s": float(np.mean(named)),
        "models": len(rows),
    }


def _checkpoint(name: str, folder: Path, seed: int) -> None:
    """A checkpoint of ``name``'s real architecture and image processor with random weights (timing only)."""
    import transformers
    from transformers.models.bit.image_processing_pil_bit import BitImageProcessorPil
    from transformers.models.clip.image_processing_pil_clip import CLIPImageProcessorPil
    from transformers.models.convnext.image_processing_pil_convnext import ConvNextImageProcessorPil

    torch.manual_seed(seed)
    if name == "resnet50":  # microsoft/resnet-50
        model = transformers.ResNetModel(transformers.ResNetConfig())
        processor = ConvNextImageProcessorPil(size={"shortest_edge": 224}, crop_pct=0.875)
    elif name == "dinov2":  # facebook/dinov2-small
        model = transformers.Dinov2Model(
            transformers.Dinov2Config(hidden_size=384, num_attention_heads=6, image_size=518, patch_size=14)
        )
        processor = BitImageProcessorPil(size={"shortest_edge": 256}, crop_size={"height": 224, "width": 224})
    else:  # openai/clip-vit-base-patch32's vision tower
        model = transformers.CLIPVisionModel(transformers.CLIPVisionConfig())
        processor = CLIPImageProcessorPil(size={"shortest_edge": 224}, crop_size={"height": 224, "width": 224})
    model.save_pretrained(folder)
    processor.save_pretrained(folder)


def _backbone_child(name: str, folder: str, images: np.ndarray, repeats: int) -> tuple[float, int, int]:
    """In a fresh process: (images/s, peak resident KiB, feature dim) of ``extract`` on one thread."""
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    from components.features.backbones import get_backbone

    backbone = get_backbone(name, path=folder)
    backbone.extract(images[:4])  # warm-up
    best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        out = backbone.extract(images, batch_size=len(images))
        best = min(best, time.perf_counter() - t)
    return len(images) / best, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, int(out.shape[1])


def backbone_rates(size: int, n: int, repeats: int, seed: int) -> dict[str, dict]:
    from components.simulate.procedural import ProceduralSimulator

    sim = ProceduralSimulator(size, size, cache_size=4)
    images = np.stack([sim.render(w, 100 + i // 8) for i, w in enumerate(_weathers(n, seed))])
    out = {}
    ctx = multiprocessing.get_context("spawn")
    with tempfile.TemporaryDirectory(prefix="pidc-paper-") as tmp:
        for name in DIMS:
            folder = Path(tmp) / name
            _checkpoint(name, folder, seeding.derive_seed(seed, "paper-scale", name))
            with ctx.Pool(1) as pool:
                rate, peak_kib, dim = pool.apply(_backbone_child, (name, str(folder), images, repeats))
            if dim != DIMS[name]:
                raise SystemExit(f"{name}: features of dimension {dim}, expected {DIMS[name]}")
            out[name] = {"images_per_s": rate, "peak_gib": peak_kib / 2**20, "dim": dim}
            print(f"  features {name:<9} {rate:7.2f} images/s, peak {peak_kib / 2**20:.2f} GiB", flush=True)
    return out


def _weathers(n: int, seed: int) -> list[dict[str, float]]:
    rng = seeding.rng(seed, "paper-scale", "weathers")
    box = config.load_params().box
    theta = box.sample(rng, n)
    return [weather_from_theta(t, a) for t, a in zip(theta, sample_azimuth(rng, n), strict=True)]


def render_rate(size: int, n: int, seed: int) -> float:
    from components.simulate.procedural import ProceduralSimulator

    cv2.setNumThreads(1)
    sim = ProceduralSimulator(size, size, cache_size=4)
    ws = _weathers(n, seed)
    sim.render(ws[0], 0)
    t = time.perf_counter()
    for i, w in enumerate(ws):
        sim.render(w, 1000 + i // 8)
    return n / (time.perf_counter() - t)


def train_rate(params: config.Params, dim: int, size: int, batches: int, epochs: int, seed: int) -> float:
    """Samples/s of the paper's training loop for a model of ``size`` images of ``dim`` features, one flow, one
    thread, after its first epoch (the compile), on synthetic pairs."""
    t = params.train
    flow = flow_config(t, size=size, trainable=False, ensemble=1)
    cfg = training_config(
        t, size=size, trainable=False, features=dim, parameters=len(params.box.names), seed=seed, ensemble=1
    )
    cfg = dataclasses.replace(cfg, epochs=epochs, patience=None)
    g = seeding.rng(seed, "paper-scale", "train", dim, size)
    n = batches * cfg.batch_size
    x = g.normal(size=(n, dim)).astype(np.float32)
    theta = params.box.sample(g, n).astype(np.float32)
    n_val = max(cfg.batch_size, n // 5)
    model = NPE(None, dim, params.box, flow, seed=seed)
    times: list[float] = []
    t0 = time.perf_counter()

    def record(rec) -> None:
        times.append(time.perf_counter() - t0)

    train(model, (x[n_val:], theta[n_val:]), (x[:n_val], theta[:n_val]), cfg, progress=False, callback=record)
    per_epoch = float(np.median(np.diff(times)))
    return (n - n_val) / per_epoch


def paper_models(params: config.Params) -> list[dict]:
    """The profile's models: id, backbone, size, flows, epochs, samples trained (all flows), compiled."""
    t = params.train
    grid = [(f"{b}-{s}", b, s, ensemble_for(t, s)) for b in params.backbones.names for s in t.sizes]
    grid += [
        (f"{v.backbone}-{v.size}-{name}", v.backbone, v.size, v.ensemble or ensemble_for(t, v.size))
        for name, v in t.variants.items()
    ]
    out = []
    for model_id, backbone, size, flows in grid:
        epochs = epochs_for(t, size, trainable=False, features=DIMS[backbone])
        cfg = training_config(
            t,
            size=size,
            trainable=False,
            features=DIMS[backbone],
            parameters=len(params.box.names),
            seed=0,
            ensemble=flows,
        )
        out.append(
            {
                "model": model_id,
                "backbone": backbone,
                "size": size,
                "flows": flows,
                "epochs": epochs,
                "samples": epochs * size,
                "hidden": flow_config(t, size=size, trainable=False, ensemble=flows).hidden_features,
                "compiled": cfg.compile,
            }
        )
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pipeline", type=Path, required=True, help="bench_pipeline.py's JSON of a full-scale run")
    ap.add_argument("--images", type=int, default=24, help="images per backbone measure")
    ap.add_argument("--renders", type=int, default=64, help="images rendered for the render rate")
    ap.add_argument("--batches", type=int, default=12, help="training batches per epoch of the train measure")
    ap.add_argument("--epochs", type=int, default=3, help="epochs of the train measure (the first compiles; ≥ 3)")
    ap.add_argument("--seed", type=int, default=2026)
    args = ap.parse_args(argv)
    for name, low in (("images", 1), ("renders", 1), ("batches", 1), ("epochs", 3)):
        if getattr(args, name) < low:
            ap.error(f"--{name} must be >= {low}, got {getattr(args, name)}")
    torch.set_num_threads(1)
    params = config.load_params(profile="paper")
    default = config.load_params()
    try:
        pipe = json.loads(args.pipeline.read_text())
    except (OSError, ValueError) as err:
        raise SystemExit(f"--pipeline {args.pipeline}: cannot read bench_pipeline's JSON ({err})") from None
    try:
        cores, stages = len(pipe["cpus"]), {st["stage"]: st for st in pipe["stages"]}
        log = Path(pipe["log"])
    except (KeyError, TypeError):
        raise SystemExit(
            f"--pipeline {args.pipeline}: not a run of bench_pipeline.py (no cpus, stages or log)"
        ) from None

    size = params.simulator.height
    splits = params.data.splits
    n_images = sum(splits.values())
    print(f"paper profile: {n_images:,} images at {size} px; measuring (one thread each) …", flush=True)
    render = render_rate(size, args.renders, args.seed)
    print(f"  render {render:.1f} images/s", flush=True)
    backbones = backbone_rates(size, args.images, 2, args.seed)
    models = paper_models(params)
    rates: dict[tuple[int, tuple[int, ...]], float] = {}
    for m in models:
        key = (DIMS[m["backbone"]], m["hidden"])
        if key not in rates:
            rates[key] = train_rate(params, key[0], m["size"], args.batches, args.epochs, args.seed)
            print(f"  train dim {key[0]:>4}, hidden {key[1]}: {rates[key]:,.0f} samples/s (one flow)", flush=True)
        m["core_s"] = m["samples"] * m["flows"] / rates[key]

    # the default pipeline's measured full run: its units
    d_models = len(default.backbones.names) * len(default.train.sizes) + len(default.train.variants)
    units = evaluation_units(log, default)
    for m in models:
        m["evaluate_s"] = (
            units["s_per_pass_draw"] * passes(m["flows"]) * splits["test"] * params.evaluate.samples
            + units["s_per_image"] * splits["test"]
            + units["named_s"]
        )
    work = {
        "generate": {"core_s": n_images / render, "critical_s": params.data.shard_size / render},
        **{
            f"features@{b}": {
                "core_s": n_images / r["images_per_s"],
                "critical_s": params.data.shard_size / r["images_per_s"],
            }
            for b, r in backbones.items()
        },
        "train": {"core_s": sum(m["core_s"] for m in models), "critical_s": max(m["core_s"] for m in models)},
        "export": {
            "core_s": cores * stages["export"]["flow_seconds"] * len(models) / d_models,
            "critical_s": cores * stages["export"]["flow_seconds"] / d_models,
        },
        "evaluate": {
            "core_s": sum(m["evaluate_s"] for m in models),
            "critical_s": max(m["evaluate_s"] for m in models),
        },
        "task2": {"core_s": cores * stages["task2"]["flow_seconds"], "critical_s": stages["task2"]["flow_seconds"]},
        "task3": {"core_s": cores * stages["task3"]["flow_seconds"], "critical_s": stages["task3"]["flow_seconds"]},
    }
    for w in work.values():
        w["wall_s"] = {c: max(w["core_s"] / c, w["critical_s"]) for c in (1, 16, 64)}
    print(
        f"\n{'stage':<22}{'core-hours':>12}{'longest task h':>16}{'1 core h':>10}{'16 cores h':>12}{'64 cores h':>12}"
    )
    for name, w in work.items():
        print(
            f"{name:<22}{w['core_s'] / 3600:>12.1f}{w['critical_s'] / 3600:>16.2f}"
            + "".join(f"{w['wall_s'][c] / 3600:>{10 if c == 1 else 12}.1f}" for c in (1, 16, 64))
        )
    total = {c: sum(w["wall_s"][c] for w in work.values()) for c in (1, 16, 64)}
    print(
        f"{'whole (stages in turn)':<22}{'':>28}"
        + "".join(f"{total[c] / 3600:>{10 if c == 1 else 12}.1f}" for c in (1, 16, 64))
    )
    print(f"\n{'model':<28}{'flows':>6}{'epochs':>8}{'samples':>14}{'core-hours':>12}")
    for m in models:
        print(f"{m['model']:<28}{m['flows']:>6}{m['epochs']:>8}{m['samples']:>14,}{m['core_s'] / 3600:>12.1f}")

    # sizes and memory from the shapes (float32 features, uint8 images)
    data_dir = ROOT / "data"
    default_n = sum(default.data.splits.values())
    bytes_per_image_now = sum(f.stat().st_size for f in data_dir.rglob("*.npz")) / default_n
    scale = (size / default.simulator.height) * (size / default.simulator.width)
    sizes = {
        "data_gib": bytes_per_image_now * scale * n_images / GIB,
        "features_gib": {b: n_images * d * 4 / GIB for b, d in DIMS.items()},
    }
    per_model = {
        m["model"]: (m["size"] + splits["val"]) * DIMS[m["backbone"]] * 4 / GIB for m in models
    }  # the train prefix and the val split, each held once (open_features joins its shards in place)
    memory = {
        "train_per_model_gib": per_model,
        "train_all_models_at_once_gib": sum(per_model.values()),
        "features_worker_peak_gib": {b: r["peak_gib"] for b, r in backbones.items()},
        "generate_shard_gib": params.data.shard_size * size * size * 3 / GIB,
        "evaluate_per_model_gib": {b: splits["test"] * d * 4 / GIB for b, d in DIMS.items()},
    }
    print(
        f"\ndata/ ≈ {sizes['data_gib']:.0f} GiB (today's bytes per image × {scale:.2f}); features/ "
        + ", ".join(f"{b} {g:.1f}" for b, g in sizes["features_gib"].items())
        + " GiB"
    )
    big = max(per_model, key=per_model.get)
    print(
        f"memory: train {big} {per_model[big]:.1f} GiB; all {len(models)} models at once "
        f"{memory['train_all_models_at_once_gib']:.1f} GiB; a features worker "
        + ", ".join(f"{b} {g:.2f}" for b, g in memory["features_worker_peak_gib"].items())
        + " GiB"
    )
    result = {
        "benchmark": "paper_scale",
        "settings": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        "machine": machine_info(),
        "render_images_per_s": render,
        "backbones": backbones,
        "train_samples_per_s": {f"{k[0]}:{'x'.join(map(str, k[1]))}": v for k, v in rates.items()},
        "evaluate_units": units,
        "models": [{k: v for k, v in m.items() if k != "hidden"} | {"hidden": list(m["hidden"])} for m in models],
        "stages": work,
        "total_wall_s": total,
        "sizes": sizes,
        "memory": memory,
    }
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
