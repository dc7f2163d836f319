"""What more images and a learned full-resolution backbone would buy: the scale ablation, for a machine with a GPU.

The default profile is bounded by 20 minutes on a 2-core CPU; this benchmark asks what lies beyond that bound, to tell
whether the issue's 8 nats are a matter of scale or of the images. On one machine it

1. renders the train split's first ``max(--sizes)`` images and the val and test splits of ``params.yaml`` (the same
   plan, seed and renderer as the pipeline; ``--workers`` processes);
2. computes the cues of every image (``CuesBackbone``, version 4: 345 features, on the device), kept in ``--cache``;
3. trains, in the order of ``--models``, NPEs on the cues: ``cues-<size>`` with the pipeline's settings for that size
   (``components.posterior.settings``: its flows, input noise and temperature; compiled only on a CPU) or any
   ``bench_levers.py`` setting of the cues alone (``cues-v4-<size>[-ens<k>][-c…][-e<k>][-n<σ>][-t]…``), with
   ``--jobs`` > 1 in that many processes on the CPU at once (``--threads`` each) while the GPU trains the hybrids; and *hybrids*
   (``hybrid-<size>[-e<epochs>][-f][-s]``): a residual CNN on the full 128×128 image (no 2×2 reduction: rain streaks
   are one pixel wide) whose embedding is joined to the standardized cues, trained jointly with the flow (one-cycle
   schedule; ``-f``: the CNN sees each training image mirrored with probability 1/2; ``-s``: half its widths, about a
   quarter of its FLOPs); ``cnn-<size>…`` is the same CNN alone, without the cues (what one learned backbone reads).
   With ``--image-jobs`` > 1 the image models train in that many processes at once on the one GPU (the images are
   kept in ``--cache`` as ``.npy`` for them);
4. scores each on the whole test split exactly like ``bench_levers.py`` (``score``): test NLL, information gain,
   calibration error with its band, per-parameter day errors and night coverage.

It prints the sha256 of every 500 rendered images of each split (to compare one machine's images with another's
shards). Writes one JSON per model and a summary to ``--out`` as it goes (a killed run keeps what finished). Usage (GPU)::

    python benchmarks/studies/bench_scale.py --models cues-50000 hybrid-50000 cues-200000 hybrid-200000-e6 --out /tmp/scale

    # the cues models on 16 CPU cores while the GPU trains a hybrid
    python benchmarks/studies/bench_scale.py --jobs 8 --cues-device cpu --cache /tmp/scale/cache \
        --models cues-50000 cues-100000 cues-200000 cues-v4-200000-ens2-n0.066-t hybrid-200000-e6-f

A dry run on a CPU: ``--models cues-600 hybrid-600-e1 --test 200 --samples 50 --device cpu``.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import dataclasses
import hashlib
import json
import multiprocessing as mp
import re
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from benchmarks.studies.bench_levers import fit, parse_setting, score  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.features.backbones.cues import CuesBackbone  # noqa: E402
from components.posterior import NPE  # noqa: E402
from components.posterior.settings import ensemble_for, flow_config, temperature_regime, training_config  # noqa: E402
from components.posterior.temperature import calibrate_post_hoc  # noqa: E402
from components.simulate.in_memory import render_split  # noqa: E402


def cues_of(images: np.ndarray, device: str, batch: int = 2048) -> torch.Tensor:
    """The cues ``(N, 345)`` float32 (on ``device``) of uint8 images ``(N, H, W, 3)``."""
    bb = CuesBackbone().to(device).eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(images), batch):
            x = torch.from_numpy(images[i : i + batch]).to(device).permute(0, 3, 1, 2).float() / 255.0
            out.append(bb(x))
    return torch.cat(out)


WIDTHS = (32, 48, 64, 96, 128, 192)  # the CNN's channels: stem, then the five stages
SMALL_WIDTHS = (16, 24, 32, 48, 64, 96)  # ``-s``: half of them


class FullResolutionCNN(nn.Module):
    """Residual CNN on 128×128 sRGB images (+ a row channel) → ``(n, dim)``: a stem at full resolution (one-pixel rain
    streaks survive), five stages (64…4 px) of a stride-2 convolution and one residual block, global mean and max
    pooling."""

    def __init__(self, dim: int = 128, widths: tuple[int, ...] = WIDTHS) -> None:
        super().__init__()
        self.widths = tuple(widths)

        def conv(ci: int, co: int, stride: int = 1) -> nn.Sequential:
            return nn.Sequential(nn.Conv2d(ci, co, 3, stride, 1, bias=False), nn.GroupNorm(8, co), nn.SiLU())

        class Block(nn.Module):
            def __init__(self, c: int) -> None:
                super().__init__()
                self.body = nn.Sequential(conv(c, c), nn.Conv2d(c, c, 3, 1, 1, bias=False), nn.GroupNorm(8, c))

            def forward(self, x: torch.Tensor) -> torch.Tensor:
                return nn.functional.silu(x + self.body(x))

        layers: list[nn.Module] = [conv(4, widths[0])]
        for ci, co in zip(widths[:-1], widths[1:], strict=True):
            layers += [conv(ci, co, 2), Block(co)]
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(2 * widths[-1], dim)
        self.register_buffer("rows", torch.linspace(-1.0, 1.0, 128).view(1, 1, 128, 1).expand(1, 1, 128, 128).clone())

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 images ``(n, 128, 128, 3)`` → ``(n, dim)``."""
        x = (images.permute(0, 3, 1, 2).float() / 255.0 - 0.5) / 0.25
        x = torch.cat([x, self.rows.expand(len(x), -1, -1, -1)], 1).contiguous(memory_format=torch.channels_last)
        with torch.autocast(x.device.type, dtype=torch.bfloat16, enabled=x.device.type == "cuda"):
            h = self.features(x)
        h = h.float()
        return self.head(torch.cat([h.mean((2, 3)), h.amax((2, 3))], 1))


def train_hybrid(
    params,
    images,
    cues,
    theta,
    val,
    epochs: int,
    seed: int,
    device: str,
    flip: bool = False,
    with_cues: bool = True,
    widths: tuple[int, ...] | None = None,
) -> tuple[NPE, Callable[[np.ndarray, torch.Tensor], torch.Tensor], dict]:
    """Train the hybrid (CNN embedding ⊕ standardized cues → flow) jointly; returns the flow, the map (images, cues) ↦
    its contexts (the trained CNN, in eval mode) and the training's figures. ``flip``: the
    CNN sees each training image mirrored left-right with probability 1/2 (the weather is mirror-invariant);
    ``with_cues=False``: the CNN's embedding alone is the context; ``widths``: the CNN's (default: its own)."""
    torch.manual_seed(seed)
    mean, std = cues.mean(0), cues.std(0).clamp_min(1e-6)
    cnn = FullResolutionCNN(widths=widths or WIDTHS).to(device)
    fc = dataclasses.replace(flow_config(params.train, size=len(images), trainable=True), standardize=False)
    width = cnn.head.out_features + (cues.shape[1] if with_cues else 0)
    flow = NPE(None, width, params.box, fc, parameters=len(params.box.names), seed=seed).to(device)
    parameters = [*cnn.parameters(), *flow.parameters()]
    opt = torch.optim.AdamW(parameters, lr=params.train.lr, weight_decay=params.train.weight_decay)
    batch = params.train.batch_size
    steps = epochs * (len(images) // batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, params.train.lr, total_steps=steps, pct_start=0.05)
    gpu_images = torch.from_numpy(images).to(device)
    th = theta.to(device)

    def context(imgs: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return torch.cat([cnn(imgs), (c - mean) / std], 1) if with_cues else cnn(imgs)

    t0, gen = time.perf_counter(), torch.Generator(device="cpu").manual_seed(seed)
    for epoch in range(epochs):
        cnn.train()
        perm = torch.randperm(len(images), generator=gen).to(device)
        total = 0.0
        for i in range(len(images) // batch):
            idx = perm[i * batch : (i + 1) * batch]
            imgs = gpu_images[idx]
            if flip:
                mirror = torch.rand(len(idx), generator=gen).to(device) < 0.5
                imgs = torch.where(mirror[:, None, None, None], imgs.flip(2), imgs)
            loss = -flow.log_prob(th[idx], context(imgs, cues[idx])).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(parameters, params.train.clip_norm)
            opt.step()
            sched.step()
            total += float(loss.detach())
        print(
            f"  {'hybrid' if with_cues else 'cnn'}-{len(images)} epoch {epoch + 1}/{epochs}: train NLL {total / (i + 1):.3f}",
            flush=True,
        )
    cnn.eval()

    def contexts(imgs: np.ndarray, c: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return torch.cat(
                [
                    context(torch.from_numpy(imgs[j : j + 1024]).to(device), c[j : j + 1024])
                    for j in range(0, len(imgs), 1024)
                ]
            )

    flow.eval()
    regime = temperature_regime(params.train, params.box)  # the pipeline's: a gate on the training pairs, then τ
    train_pairs = (contexts(images, cues), th) if regime is not None else None
    tempered = calibrate_post_hoc(flow, train_pairs, (contexts(val[0], val[1]), val[2].to(device)), regime)
    return (
        flow,
        contexts,
        {
            "epochs_run": epochs,
            "flip": flip,
            "with_cues": with_cues,
            "widths": list(cnn.widths),
            "train_seconds": round(time.perf_counter() - t0, 1),
            **tempered,
        },
    )


def _parse(name: str, epochs: int, params) -> tuple[str, int, int, bool, dict | None]:
    """A model's name → (kind, size, epochs, flip, setting): ``cues-<size>`` (the pipeline's settings for the size, as
    a :func:`~benchmarks.studies.bench_levers.parse_setting` dict), ``cues-v4-<size>…`` (a ``bench_levers.py`` setting on the
    cues alone) or an image model ``hybrid-<size>[-e<epochs>][-f][-s]`` / ``cnn-<size>[-e<epochs>][-f][-s]`` (its
    setting ``{"with_cues": …, "widths": …}``); ``ValueError`` naming the grammar otherwise."""
    if name.startswith("cues-v"):
        s = parse_setting(name)
        if s["version"] != "v4" or s["tiny"] or s["sky_rows"] or s["mirror"]:
            raise ValueError(
                f"model {name!r}: this benchmark computes the version-4 cues alone (cues-v4-<size>…, no -m)"
            )
        return "cues", s["size"], 0, False, s
    m = re.fullmatch(r"(cues|hybrid|cnn)-(\d+)(?:-e(\d+))?(-f)?(-s)?", name)
    if not m or (m[1] == "cues" and (m[3] or m[4] or m[5])):
        raise ValueError(
            f"model {name!r}: expected cues-<size>, a bench_levers setting cues-v4-<size>…, "
            "hybrid-<size>[-e<epochs>][-f][-s] or cnn-<size>[-e<epochs>][-f][-s]"
        )
    size = int(m[2])
    if m[1] == "cues":
        return "cues", size, 0, False, pipeline_setting(params, size)
    image = {"with_cues": m[1] == "hybrid", "widths": SMALL_WIDTHS if m[5] else WIDTHS}
    return "image", size, int(m[3] or epochs), bool(m[4]), image


def pipeline_setting(params, size: int) -> dict:
    """The pipeline's settings of a cues model of ``size`` images (``components.posterior.settings``: its flows, input
    noise and temperature) as a ``bench_levers.py`` setting."""
    noise = training_config(
        params.train, size=size, trainable=False, features=CuesBackbone.dim, parameters=len(params.box.names), seed=0
    ).input_noise
    s = parse_setting(f"cues-v4-{size}-ens{ensemble_for(params.train, size)}")
    return {**s, "noise": noise, "temperature": params.train.temperature}


def prepare(
    params, n_train: int, n_test: int, workers: int, device: str, cache: Path | None, keep_images: bool = False
):
    """Images (``{split: (n, H, W, 3) uint8}``, or None when read from a ``cache`` that holds none), cues
    ``{split: (n, 345)}`` float32 and θ ``{split: (n, 6)}`` float32 of the train split's first ``n_train`` images, val
    and the first ``n_test`` test images; the cues and θ (and with ``keep_images`` the images) are kept in ``cache``
    (``.npy``) when given, and read from there when it holds them (the images memory-mapped)."""
    sizes = {"train": n_train, "val": params.data.splits["val"], "test": n_test}
    if cache is not None and all((cache / f"cues_{k}.npy").is_file() for k in sizes):
        cues = {k: np.load(cache / f"cues_{k}.npy", mmap_mode="r") for k in sizes}
        theta = {k: np.load(cache / f"theta_{k}.npy") for k in sizes}
        short = [k for k, n in sizes.items() if len(cues[k]) < n]
        if short:
            raise ValueError(f"cache {cache}: splits {short} hold fewer images than asked ({sizes})")
        images = None
        if all((cache / f"images_{k}.npy").is_file() for k in sizes):
            images = {k: np.load(cache / f"images_{k}.npy", mmap_mode="r")[:n] for k, n in sizes.items()}
        cues_n = {k: np.asarray(cues[k][:n]) for k, n in sizes.items()}
        return images, cues_n, {k: theta[k][:n] for k, n in sizes.items()}
    t0 = time.perf_counter()
    split = {k: render_split(params, k, n, workers) for k, n in sizes.items()}
    print(f"rendered {n_train} + val + test images in {time.perf_counter() - t0:.0f} s", flush=True)
    for k, (images, _) in split.items():  # to compare one machine's images with another's (the data shards')
        digests = [hashlib.sha256(images[i : i + 500].tobytes()).hexdigest() for i in range(0, len(images), 500)]
        print(f"sha256 of the {k} images, by 500: {json.dumps(digests)}", flush=True)
    t1 = time.perf_counter()
    cues = {k: cues_of(v[0], device).cpu().numpy() for k, v in split.items()}
    theta = {k: v[1] for k, v in split.items()}
    print(f"cues in {time.perf_counter() - t1:.0f} s", flush=True)
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        for k in sizes:
            if keep_images:
                np.save(cache / f"images_{k}.npy", split[k][0])
            np.save(cache / f"theta_{k}.npy", theta[k])
            np.save(cache / f"cues_{k}.npy", cues[k])  # last: its presence says the split is whole
    return {k: v[0] for k, v in split.items()}, cues, theta


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--models",
        nargs="+",
        default=["cues-50000", "hybrid-50000", "cues-200000", "hybrid-200000"],
        help="cues-<size> (the pipeline's flow on the cues), a bench_levers setting cues-v4-<size>… or "
        "hybrid-<size>[-e<epochs>][-f] (-f: mirrored images half the time), in this order",
    )
    p.add_argument("--hybrid-epochs", type=int, default=12, help="the hybrids' epochs unless a name gives them")
    p.add_argument("--test", type=int, default=None, help="test images (default: the whole test split)")
    p.add_argument("--samples", type=int, default=500, help="posterior draws per test image")
    p.add_argument("--seed", type=int, default=2026, help="the flows' seed (the data follow params.yaml)")
    p.add_argument("--workers", type=int, default=mp.cpu_count(), help="rendering processes")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument(
        "--cues-device", default=None, help="where the cues models train (default: --device); cpu with --jobs > 1"
    )
    p.add_argument("--jobs", type=int, default=1, help="cues models trained at once, each in its own process")
    p.add_argument(
        "--image-jobs", type=int, default=1, help="image models (hybrid, cnn) trained at once on --device, in processes"
    )
    p.add_argument("--threads", type=int, default=1, help="torch threads of each cues model's process")
    p.add_argument("--no-compile", action="store_true", help="never compile the cues models' training step")
    p.add_argument("--cache", type=Path, default=None, help="keep (or read) the cues and θ here (.npy)")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "scale")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)  # one model of a --jobs run: no summary
    a = p.parse_args(argv)
    params = load_params(ROOT / "params.yaml")
    a.out.mkdir(parents=True, exist_ok=True)
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    torch.backends.cudnn.benchmark = True  # the fastest convolution algorithms for the image models' fixed shapes
    cues_device = a.cues_device or a.device
    if a.jobs > 1 and (cues_device != "cpu" or a.cache is None):
        raise ValueError(
            "--jobs > 1 trains the cues models in processes on the CPU: give --cues-device cpu and --cache"
        )
    if a.image_jobs > 1 and a.cache is None:
        raise ValueError("--image-jobs > 1 trains the image models in processes that read the images: give --cache")
    t0 = time.perf_counter()
    models = [_parse(m, a.hybrid_epochs, params) for m in a.models]  # every name checked before any work
    n_train = max(size for _, size, *_ in models)
    n_test = a.test or params.data.splits["test"]
    images, cues, theta = prepare(params, n_train, n_test, a.workers, a.device, a.cache, keep_images=a.image_jobs > 1)
    summary = {
        "machine": machine_info(threads=a.threads),
        "device": torch.cuda.get_device_name() if a.device == "cuda" else "cpu",
        "models": {},
    }

    def record(name: str, r: dict) -> None:
        summary["models"][name] = r
        (a.out / f"{name}.json").write_text(json.dumps(r, indent=1))
        if not a.child:
            (a.out / "summary.json").write_text(json.dumps(summary, indent=1))
        day = r["day_median_abs_error"]
        print(
            f"{name}: info gain {r['info_gain_nats']:.2f} nats, test NLL {r['test_nll']:.2f}, calibration "
            f"{r['calibration_error']:.3f} (band {r['calibration_band']:.3f}), day errors {day}, night coverage "
            f"{r['night_coverage68']}, trained in {r['train_seconds']} s, {time.perf_counter() - t0:.0f} s since the start",
            flush=True,
        )

    children: dict[str, subprocess.Popen] = {}

    def spawn(name: str, device: str, jobs: int, kind: str) -> None:
        """Train model ``name`` in a process of its own (at most ``jobs`` of this kind at once); it writes its JSON."""
        while sum(c.poll() is None for n, c in children.items() if kinds[n] == kind) >= jobs:
            time.sleep(2)
        argv_child = [sys.executable, __file__, "--models", name, "--cache", str(a.cache), "--out", str(a.out)]
        argv_child += ["--device", device, "--threads", str(a.threads), "--seed", str(a.seed)]
        argv_child += ["--samples", str(a.samples), "--test", str(n_test), "--child"]
        argv_child += ["--no-compile"] if a.no_compile else []
        log = (a.out / f"{name}.log").open("w")
        children[name] = subprocess.Popen(argv_child, stdout=log, stderr=subprocess.STDOUT)
        print(f"{name}: training in process {children[name].pid} (log {a.out / name}.log)", flush=True)

    kinds = {name: kind for name, (kind, *_) in zip(a.models, models, strict=True)}
    for name, (kind, size, epochs, flip, setting) in zip(a.models, models, strict=True):
        if kind == "cues" and a.jobs > 1:
            spawn(name, "cpu", a.jobs, kind)
        elif kind == "image" and a.image_jobs > 1:
            spawn(name, a.device, a.image_jobs, kind)
        elif kind == "cues":
            torch.set_num_threads(a.threads)
            r = fit(setting, cues, theta, params, a.samples, a.seed, device=cues_device, compile=not a.no_compile)
            record(name, {"setting": name, **r})
        else:
            if images is None:
                raise ValueError(f"model {name!r}: an image model needs the images; the cache holds only the cues")
            val = (images["val"], torch.from_numpy(cues["val"]).to(a.device), torch.from_numpy(theta["val"]))
            flow, contexts, info = train_hybrid(
                params,
                images["train"][:size],
                torch.from_numpy(cues["train"][:size]).to(a.device),
                torch.from_numpy(theta["train"][:size]),
                val,
                epochs,
                a.seed,
                a.device,
                flip,
                **setting,
            )
            r = score(
                flow,
                contexts(images["test"], torch.from_numpy(cues["test"]).to(a.device)),
                torch.from_numpy(theta["test"]).to(a.device),
                params.box,
                a.samples,
                a.seed,
            )
            record(name, {"size": size, **info, **r})
    for name, child in children.items():
        if child.wait() != 0:
            print(f"{name}: its process failed (exit {child.returncode}); see {a.out / name}.log", flush=True)
            continue
        record(name, json.loads((a.out / f"{name}.json").read_text()))
    print(f"done in {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
