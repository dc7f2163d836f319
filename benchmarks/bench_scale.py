"""What more images and a learned full-resolution backbone would buy: the scale ablation, for a machine with a GPU.

The default profile is bounded by 20 minutes on a 2-core CPU; this benchmark asks what lies beyond that bound, to tell
whether the issue's 8 nats are a matter of scale or of the images. On one machine it

1. renders the train split's first ``max(--sizes)`` images and the val and test splits of ``params.yaml`` (the same
   plan, seed and renderer as the pipeline; ``--workers`` processes);
2. computes the 273 cues of every image (``CuesBackbone``, on the device);
3. trains, in the order of ``--models``, NPEs on the cues (``cues-<size>``) with the pipeline's settings for that size
   (``components.posterior.settings``, temperature fitted on val; compiled only on a CPU) and *hybrids*
   (``hybrid-<size>[-e<epochs>][-f]``): a residual CNN on the full 128×128 image (no 2×2 reduction: rain streaks are
   one pixel wide) whose embedding is joined to the standardized cues, trained jointly with the flow (one-cycle
   schedule; ``-f``: the CNN sees each training image mirrored with probability 1/2);
4. scores each on the whole test split exactly like ``bench_levers.py`` (``score``): test NLL, information gain,
   calibration error with its band, per-parameter day errors and night coverage.

Writes one JSON per model and a summary to ``--out`` as it goes (a killed run keeps what finished). Usage (GPU)::

    python benchmarks/bench_scale.py --models cues-50000 hybrid-50000 cues-200000 hybrid-200000-e6 --out /tmp/scale

A dry run on a CPU: ``--models cues-600 hybrid-600-e1 --test 200 --samples 50 --device cpu``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing as mp
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_levers import score  # noqa: E402
from benchmarks.machine import machine_info  # noqa: E402
from components.core import weather  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.features.backbones.cues import CuesBackbone  # noqa: E402
from components.posterior import NPE, train  # noqa: E402
from components.posterior.settings import flow_config, training_config  # noqa: E402
from components.posterior.temperature import calibrate  # noqa: E402
from components.simulate import dataset  # noqa: E402
from components.simulate.procedural import ProceduralSimulator  # noqa: E402

_SIM: ProceduralSimulator | None = None


def _render_rows(job: tuple[int, int, np.ndarray, np.ndarray]) -> np.ndarray:
    """Worker: images ``(k, H, W, 3)`` uint8 of weather rows ``(k, 13)`` in scenes ``(k,)``; job (H, W, rows, scenes)."""
    global _SIM
    height, width, rows, seeds = job
    if _SIM is None or (_SIM.height, _SIM.width) != (height, width):
        _SIM = ProceduralSimulator(height, width)
    return np.stack(
        [
            _SIM.render({n: float(v) for n, v in zip(weather.ALL_NAMES, r, strict=True)}, int(s))
            for r, s in zip(rows, seeds, strict=True)
        ]
    )


def render_split(params, name: str, size: int, workers: int) -> tuple[np.ndarray, np.ndarray]:
    """The first ``size`` images ``(size, H, W, 3)`` uint8 and θ ``(size, 6)`` of split ``name``'s plan (the
    simulator's size of ``params``)."""
    sim = ProceduralSimulator(params.simulator.height, params.simulator.width)
    plan = dataset.plan_split(
        name,
        size,
        seed=params.seed,
        box=params.box,
        images_per_scene=params.data.images_per_scene,
        shard_size=params.data.shard_size,
        renderer_version=sim.version,
        resolution=(sim.height, sim.width),
    )
    chunk = 40 * params.data.images_per_scene  # whole scenes per job: the workers' scene cache is hit
    jobs = [
        (sim.height, sim.width, plan.weather[i : i + chunk], plan.scene_seed[i : i + chunk])
        for i in range(0, size, chunk)
    ]
    with mp.get_context("fork").Pool(workers) as pool:
        images = np.concatenate(list(pool.imap(_render_rows, jobs, chunksize=1)))
    return images, plan.weather[:, : len(weather.PREDICTED)].astype(np.float32)


def cues_of(images: np.ndarray, device: str, batch: int = 2048) -> torch.Tensor:
    """The 273 cues ``(N, 273)`` float32 (on ``device``) of uint8 images ``(N, H, W, 3)``."""
    bb = CuesBackbone().to(device).eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(images), batch):
            x = torch.from_numpy(images[i : i + batch]).to(device).permute(0, 3, 1, 2).float() / 255.0
            out.append(bb(x))
    return torch.cat(out)


class FullResolutionCNN(nn.Module):
    """Residual CNN on 128×128 sRGB images (+ a row channel) → ``(n, dim)``: a stem at full resolution (one-pixel rain
    streaks survive), five stages (64…4 px) of a stride-2 convolution and one residual block, global mean and max
    pooling."""

    def __init__(self, dim: int = 128, widths: tuple[int, ...] = (32, 48, 64, 96, 128, 192)) -> None:
        super().__init__()

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
    params, images, cues, theta, val, epochs: int, seed: int, device: str, flip: bool = False
) -> tuple[NPE, Callable[[np.ndarray, torch.Tensor], torch.Tensor], dict]:
    """Train the hybrid (CNN embedding ⊕ standardized cues → flow) jointly; returns the flow, the map (images, cues) ↦
    its contexts (the trained CNN, in eval mode) and the training's figures. ``flip``: the
    CNN sees each training image mirrored left-right with probability 1/2 (the weather is mirror-invariant)."""
    torch.manual_seed(seed)
    mean, std = cues.mean(0), cues.std(0).clamp_min(1e-6)
    cnn = FullResolutionCNN().to(device)
    fc = dataclasses.replace(flow_config(params.train, size=len(images), trainable=True), standardize=False)
    flow = NPE(None, cnn.head.out_features + cues.shape[1], params.box, fc, seed=seed).to(device)
    parameters = [*cnn.parameters(), *flow.parameters()]
    opt = torch.optim.AdamW(parameters, lr=params.train.lr, weight_decay=params.train.weight_decay)
    batch = params.train.batch_size
    steps = epochs * (len(images) // batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, params.train.lr, total_steps=steps, pct_start=0.05)
    gpu_images = torch.from_numpy(images).to(device)
    th = theta.to(device)

    def context(imgs: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return torch.cat([cnn(imgs), (c - mean) / std], 1)

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
        print(f"  hybrid-{len(images)} epoch {epoch + 1}/{epochs}: train NLL {total / (i + 1):.3f}", flush=True)
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
    tempered = calibrate(flow, contexts(val[0], val[1]), val[2].to(device))
    return (
        flow,
        contexts,
        {"epochs_run": epochs, "flip": flip, "train_seconds": round(time.perf_counter() - t0, 1), **tempered},
    )


def _parse(name: str, epochs: int) -> tuple[str, int, int, bool]:
    """``cues-50000`` / ``hybrid-50000[-e6][-f]`` → (kind, size, epochs, flip); ``ValueError`` naming the grammar
    otherwise."""
    m = re.fullmatch(r"(cues|hybrid)-(\d+)(?:-e(\d+))?(-f)?", name)
    if not m or (m[1] == "cues" and (m[3] or m[4])):
        raise ValueError(f"model {name!r}: expected cues-<size> or hybrid-<size>[-e<epochs>][-f]")
    return m[1], int(m[2]), int(m[3] or epochs), bool(m[4])


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--models",
        nargs="+",
        default=["cues-50000", "hybrid-50000", "cues-200000", "hybrid-200000"],
        help="cues-<size> (the pipeline's flow on the cues) or hybrid-<size>[-e<epochs>][-f] (-f: mirrored images half the time), in this order",
    )
    p.add_argument("--hybrid-epochs", type=int, default=12, help="the hybrids' epochs unless a name gives them")
    p.add_argument("--test", type=int, default=None, help="test images (default: the whole test split)")
    p.add_argument("--samples", type=int, default=500, help="posterior draws per test image")
    p.add_argument("--seed", type=int, default=2026, help="the flows' seed (the data follow params.yaml)")
    p.add_argument("--workers", type=int, default=mp.cpu_count())
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "scale")
    a = p.parse_args(argv)
    params = load_params(ROOT / "params.yaml")
    a.out.mkdir(parents=True, exist_ok=True)
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    t0 = time.perf_counter()
    models = [_parse(m, a.hybrid_epochs) for m in a.models]  # every name checked before any work
    n_train = max(size for _, size, _, _ in models)
    n_test = a.test or params.data.splits["test"]
    split = {
        "train": render_split(params, "train", n_train, a.workers),
        "val": render_split(params, "val", params.data.splits["val"], a.workers),
        "test": render_split(params, "test", n_test, a.workers),
    }
    render_s = time.perf_counter() - t0
    print(f"rendered {n_train} + val + test images in {render_s:.0f} s", flush=True)
    cues = {k: cues_of(v[0], a.device) for k, v in split.items()}
    theta = {k: torch.from_numpy(v[1]) for k, v in split.items()}
    print(f"cues in {time.perf_counter() - t0 - render_s:.0f} s", flush=True)
    summary = {
        "machine": machine_info(threads=torch.get_num_threads()),
        "render_seconds": round(render_s, 1),
        "device": torch.cuda.get_device_name() if a.device == "cuda" else "cpu",
        "models": {},
    }

    def record(name: str, r: dict) -> None:
        summary["models"][name] = r
        (a.out / f"{name}.json").write_text(json.dumps(r, indent=1))
        (a.out / "summary.json").write_text(json.dumps(summary, indent=1))
        day = r["day_median_abs_error"]
        print(
            f"{name}: info gain {r['info_gain_nats']:.2f} nats, calibration {r['calibration_error']:.3f} "
            f"(band {r['calibration_band']:.3f}), day errors {day}, night coverage {r['night_coverage68']}, "
            f"trained in {r['train_seconds']} s, {time.perf_counter() - t0:.0f} s since the start",
            flush=True,
        )

    for name, (kind, size, epochs, flip) in zip(a.models, models, strict=True):
        if kind == "cues":
            tc = training_config(params.train, size=size, trainable=False, features=cues["train"].shape[1], seed=a.seed)
            if a.device != "cpu":  # the pipeline's compile rule is for its CPU (inductor's C++ kernels)
                tc = dataclasses.replace(tc, compile=False)
            model = NPE(
                None,
                cues["train"].shape[1],
                params.box,
                flow_config(params.train, size=size, trainable=False),
                seed=a.seed,
            )
            model.to(a.device)
            t1 = time.perf_counter()
            history = train(
                model,
                (cues["train"][:size], theta["train"][:size].to(a.device)),
                (cues["val"], theta["val"].to(a.device)),
                tc,
            )
            model.eval()
            tempered = calibrate(model, cues["val"], theta["val"].to(a.device))
            seconds = round(time.perf_counter() - t1, 1)
            r = score(model, cues["test"], theta["test"].to(a.device), params.box, a.samples, a.seed)
            info = {
                "epochs_run": len(history.records),
                "best_epoch": history.best_epoch,
                "input_noise": tc.input_noise,
                "train_seconds": seconds,
                **tempered,
            }
        else:
            val = (split["val"][0], cues["val"], theta["val"])
            flow, contexts, info = train_hybrid(
                params,
                split["train"][0][:size],
                cues["train"][:size],
                theta["train"][:size],
                val,
                epochs,
                a.seed,
                a.device,
                flip,
            )
            r = score(
                flow,
                contexts(split["test"][0], cues["test"]),
                theta["test"].to(a.device),
                params.box,
                a.samples,
                a.seed,
            )
        record(name, {"size": size, **info, **r})
    print(f"done in {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
