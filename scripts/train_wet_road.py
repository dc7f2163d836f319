"""Train the cues' wet-road detector from the embedded renderer and write its frozen weights and card.

    python scripts/train_wet_road.py [--images 7500] [--validation 1500] [--epochs 10] [--seed SEED]
        [--workers N] [--device cuda] [--cache DIR]

Renders ``--images`` training and ``--validation`` validation images (prior weathers, two per scene, scene seeds the
dataset splits do not use), labels their pixels with the scenes' road and wet masks, trains
:class:`components.features.backbones.wet_road.WetRoadNet` and writes ``components/features/backbones/wet_road.pt``
and ``wet_road.json`` (the data, seed, validation figures and the weights' sha256). The seed defaults to
``params.yaml``'s. The scenes' seeds come from the streams ``(seed, "scene", s, j)`` of :data:`STREAMS`, shared with
``scripts/train_weather_reader.py`` (``--cache`` lets the two learn from one rendering). The weights are identical when
retrained on one CPU (float order differs across CPUs, and GPU kernels need not be deterministic); the card names the
machine (the shipped detector: an H200, 100 000 images, 12 epochs). A new detector changes the cues: raise
``CuesBackbone.version`` so that cached features are recomputed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# isort: off
import components  # noqa: E402,F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import math  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

from components.core import seeding  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.core.files import atomic_path, sha256_file  # noqa: E402
from components.core.weather import Box, sample_azimuth, weather_from_theta  # noqa: E402
from components.features.backbones import wet_road  # noqa: E402
from components.simulate.procedural import ProceduralSimulator  # noqa: E402
from components.simulate.procedural.calibration import CALIBRATION  # noqa: E402

#: the scene streams of the cue networks' training and validation images (the splits' are "train", "val", "test")
STREAMS: tuple[str, str] = ("cue_networks_training", "cue_networks_validation")


def _render_part(args: tuple[int, int, int, str, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Images ``start..stop`` of a training set (a worker's share; its own simulator)."""
    start, stop, seed, stream, theta, azimuth = args
    sim = ProceduralSimulator(128, 128, cache_size=1)
    out = np.empty((stop - start, 128, 128, 3), np.uint8)
    labels = np.zeros((stop - start, 128 * 128), np.uint8)
    edge = CALIBRATION.puddle_edge
    for k, i in enumerate(range(start, stop)):
        scene_seed = seeding.derive_seed(seed, "scene", stream, i // 2)
        out[k] = sim.render(weather_from_theta(theta[k], azimuth[k]), scene_seed)
        sc = sim.scene(scene_seed)
        labels[k, sc.road_mask.ravel()] = 1
        refl = sc.reflections
        q = theta[k, 5] / 100.0 * (1.0 + edge)
        wet = np.clip((q - refl.quantile) / edge, 0.0, 1.0) > 0.5
        labels[k, refl.pixels[wet]] = 2
    return out, labels.reshape(-1, 128, 128)


def render_training_set(
    images: int, seed: int, stream: str, workers: int = 1, cache: Path | None = None
) -> tuple[np.ndarray, ...]:
    """``images`` rendered images ``(N, 128, 128, 3)`` uint8, their pixel classes ``(N, 128, 128)`` uint8
    (``wet_road.CLASSES``) and weathers θ ``(N, 6)``: prior weathers (the sun azimuth too), two images per scene, the
    scenes' seeds ``derive_seed(seed, "scene", stream, j)`` (the splits' are ``(seed, "scene", <split>, j)``).

    ``workers`` processes render pairs of images in parallel (the same set for any number); with ``cache`` (a
    folder) the set is kept there as ``<stream>-<images>-<seed>.npz`` and read back by later calls (the cue networks
    learn from the same images)."""
    if images < 2:
        raise ValueError(f"images must be at least 2, got {images}")
    path = cache / f"{stream}-{images}-{seed}.npz" if cache is not None else None
    if path is not None and path.is_file():
        with np.load(path) as z:
            return z["images"], z["labels"], z["theta"]
    g = seeding.rng(seed, "cue_networks", stream)
    theta = Box.full().sample(g, images)
    azimuth = sample_azimuth(g, images)
    step = max(2, 2 * math.ceil(images / (2 * 8 * max(1, workers))))  # pairs of one scene stay together
    parts = [
        (a, min(a + step, images), seed, stream, theta[a : a + step], azimuth[a : a + step])
        for a in range(0, images, step)
    ]
    if workers > 1:
        import multiprocessing

        with multiprocessing.get_context("spawn").Pool(workers) as pool:
            done = pool.map(_render_part, parts)
    else:
        done = [_render_part(p) for p in parts]
    out = np.concatenate([d[0] for d in done])
    labels = np.concatenate([d[1] for d in done])
    if path is not None:
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(f, images=out, labels=labels, theta=theta.astype(np.float32))
    return out, labels, theta.astype(np.float32)


def train_detector(
    images: np.ndarray,
    labels: np.ndarray,
    *,
    epochs: int,
    seed: int,
    batch_size: int = 32,
    lr: float = 3e-3,
    device: str = "cpu",
    log=print,
) -> wet_road.WetRoadNet:
    """Fit ``WetRoadNet`` to per-pixel classes by cross-entropy (AdamW, one-cycle learning rate), in eval mode.

    ``images`` ``(N, 128, 128, 3)`` uint8, ``labels`` ``(N, 128, 128)`` in {0, 1, 2}; the batch order and the initial
    weights come from ``seed``.
    """
    if images.ndim != 4 or images.shape[1:] != (128, 128, 3) or labels.shape != images.shape[:3]:
        raise ValueError(
            f"expected images (N, 128, 128, 3) and labels (N, 128, 128), got {images.shape} and {labels.shape}"
        )
    torch.manual_seed(seed)
    net = wet_road.WetRoadNet()
    targets = torch.from_numpy(labels[:, wet_road.ROWS[0] : wet_road.ROWS[1]])
    return fit(
        net,
        images,
        targets,
        lambda out, y: F.cross_entropy(out, y.long()),
        epochs=epochs,
        seed=seed,
        batch_size=batch_size,
        lr=lr,
        device=device,
        log=log,
        name="wet road detector",
        metric="training cross-entropy",
    )


def fit(
    net: torch.nn.Module,
    images: np.ndarray,
    targets: torch.Tensor,
    loss_fn,
    *,
    epochs: int,
    seed: int,
    batch_size: int,
    lr: float,
    weight_decay: float = 0.01,
    mirror: bool = False,
    device: str = "cpu",
    log=print,
    name: str = "network",
    metric: str = "training loss",
) -> torch.nn.Module:
    """The training loop of the cue networks: ``loss_fn(net(x), targets[batch])`` minimized by AdamW with a one-cycle
    learning rate over ``epochs`` passes in a random order; images ``(N, 128, 128, 3)`` uint8 kept once on ``device``
    and scaled to [0, 1]; with ``mirror`` each image is mirrored left-right with probability ½ (targets that a mirror
    leaves unchanged). The order and mirrors come from ``seed`` (per epoch: the order, then the mirrors). Returns the
    network in eval mode, on the CPU."""
    net = net.to(device)
    opt = torch.optim.AdamW(net.parameters(), lr, weight_decay=weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=epochs * math.ceil(len(images) / batch_size))
    g = np.random.default_rng(seed)
    x_all, y_all = torch.from_numpy(images).to(device), targets.to(device)
    net.train()
    for epoch in range(epochs):
        order = torch.from_numpy(g.permutation(len(images))).to(device)
        flips = torch.from_numpy(g.random(len(images)) < 0.5).to(device) if mirror else None
        total = torch.zeros((), device=device)
        for i in range(0, len(images), batch_size):
            idx = order[i : i + batch_size]
            x = x_all[idx].permute(0, 3, 1, 2).float() / 255.0
            if flips is not None:
                x = torch.where(flips[i : i + batch_size, None, None, None], x.flip(-1), x)
            loss = loss_fn(net(x), y_all[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.detach() * len(idx)
        log(f"{name}: epoch {epoch + 1} of {epochs}, {metric} {float(total) / len(images):.4f}")
    return net.cpu().eval()


def validation_figures(net: wet_road.WetRoadNet, images: np.ndarray, labels: np.ndarray, theta: np.ndarray) -> dict:
    """Cross-entropy on every image; by day, the wet-vs-dry AUC of road pixels and each band's correlation between the
    detector's wet share and the true one."""
    from sklearn.metrics import roc_auc_score

    with torch.no_grad():
        probs, feats = [], []
        for i in range(0, len(images), 100):
            x = torch.from_numpy(images[i : i + 100]).permute(0, 3, 1, 2).float() / 255.0
            probs.append(F.softmax(net(x), dim=1))
            feats.append(wet_road.wet_road_features(net, x))
    p, f = torch.cat(probs), torch.cat(feats).numpy()
    y = torch.from_numpy(labels[:, wet_road.ROWS[0] : wet_road.ROWS[1]]).long()
    ce = float(F.nll_loss(torch.log(p.clamp_min(1e-9)), y))
    day = theta[:, 3] > 0
    road = (y > 0).numpy() & day[:, None, None]
    wet_given_road = (p[:, 2] / (p[:, 1] + p[:, 2] + 1e-9)).numpy()
    auc = float(roc_auc_score((y.numpy() == 2)[road], wet_given_road[road]))
    bands = {}
    for k, (a, b) in enumerate(wet_road.BANDS):
        band = labels[:, a:b]
        true_road = (band > 0).sum((1, 2))
        ok = day & (true_road > 20)
        truth = (band == 2).sum((1, 2))[ok] / true_road[ok]
        r = float(np.corrcoef(f[ok, 2 * k], truth)[0, 1]) if ok.sum() > 2 else float("nan")
        bands[f"{a}-{b}"] = r if np.isfinite(r) else None  # None: too few images with road in the band, or no spread
    return {"cross_entropy": ce, "day_road_pixel_auc": auc, "day_wet_share_correlation": bands}


def arguments(
    description: str, images: int, epochs: int, batch_size: int, lr: float, out: Path
) -> argparse.ArgumentParser:
    """The command line shared by the scripts that train the cues' frozen networks."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--images", type=int, default=images, help=f"training images (default {images})")
    ap.add_argument("--validation", type=int, default=1500, help="validation images (default 1500)")
    ap.add_argument("--epochs", type=int, default=epochs, help=f"epochs (default {epochs})")
    ap.add_argument("--batch-size", type=int, default=batch_size, help=f"batch size (default {batch_size})")
    ap.add_argument("--lr", type=float, default=lr, help=f"peak learning rate (default {lr})")
    ap.add_argument("--seed", type=int, default=None, help="seed (default: params.yaml's)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    ap.add_argument("--workers", type=int, default=1, help="rendering processes (default 1; the same images for any)")
    ap.add_argument("--device", default="cpu", help="torch device to train on (default cpu; e.g. cuda)")
    ap.add_argument("--cache", type=Path, default=None, help="folder that keeps the rendered images for other runs")
    ap.add_argument("--out", type=Path, default=out, help="weights file (the card goes beside it)")
    return ap


def parse(ap: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """Parsed and checked arguments (an argparse error names the bad one); the seed filled in from params.yaml."""
    a = ap.parse_args(argv)
    for name, least in (
        ("images", 2),
        ("validation", 2),
        ("epochs", 1),
        ("batch_size", 1),
        ("threads", 1),
        ("workers", 1),
    ):
        if getattr(a, name) < least:
            ap.error(f"--{name.replace('_', '-')} must be at least {least}, got {getattr(a, name)}")
    if not a.lr > 0:
        ap.error(f"--lr must be positive, got {a.lr}")
    if a.device.startswith("cuda") and not torch.cuda.is_available():
        ap.error(f"--device {a.device}: torch sees no CUDA device here")
    a.seed = a.seed if a.seed is not None else load_params(ROOT / "params.yaml").seed
    torch.set_num_threads(a.threads)
    return a


def machine(device: str) -> str:
    """What trained the network: the GPU's name, or the CPU's."""
    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    import platform

    return platform.processor() or platform.machine()


def save(
    net: torch.nn.Module,
    a: argparse.Namespace,
    network: dict,
    figures: dict,
    t0: float,
    argv,
    script: str,
    data: dict | None = None,
) -> None:
    """Write the weights to ``a.out`` and their card beside them: ``network``'s fields (what the network is), the
    data (``data``, else the scene :data:`STREAMS`), seed, machine, ``figures`` (validation), the seconds since ``t0``,
    the command (``script`` and ``argv``) and the weights' sha256."""
    a.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), a.out)
    card = {
        **network,
        "training_images": a.images,
        "validation_images": a.validation,
        "epochs": a.epochs,
        "batch_size": a.batch_size,
        "lr": a.lr,
        "seed": a.seed,
        **({"data": data} if data is not None else {"streams": list(STREAMS)}),
        "validation": figures,
        "torch": torch.__version__,
        "machine": machine(a.device),
        "seconds": round(time.perf_counter() - t0, 1),
        "command": f"python scripts/{script} " + " ".join(argv if argv is not None else sys.argv[1:]),
        "sha256": sha256_file(a.out),
    }
    a.out.with_suffix(".json").write_text(json.dumps(card, indent=1) + "\n")
    print(json.dumps(card["validation"]))


def main(argv: list[str] | None = None) -> None:
    ap = arguments(__doc__.split("\n\n")[0], 7500, 10, 32, 3e-3, wet_road.WEIGHTS)
    a = parse(ap, argv)
    seed = a.seed
    t0 = time.perf_counter()
    images, labels, _ = render_training_set(a.images, seed, STREAMS[0], a.workers, a.cache)
    val = render_training_set(a.validation, seed, STREAMS[1], a.workers, a.cache)
    rendered = time.perf_counter() - t0
    print(f"rendered {a.images} + {a.validation} images in {rendered:.0f} s", flush=True)
    net = train_detector(
        images,
        labels,
        epochs=a.epochs,
        seed=seed,
        batch_size=a.batch_size,
        lr=a.lr,
        device=a.device,
        log=lambda m: print(m, flush=True),
    )
    save(
        net,
        a,
        {
            "detector": "wet_road",
            "channels": wet_road.CHANNELS,
            "rows": list(wet_road.ROWS),
            "classes": list(wet_road.CLASSES),
        },
        validation_figures(net, *val),
        t0,
        argv,
        "train_wet_road.py",
    )


if __name__ == "__main__":
    main()
