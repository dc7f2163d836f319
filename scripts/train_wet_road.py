"""Train the cues' wet-road detector from the embedded renderer and write its frozen weights and card.

    python scripts/train_wet_road.py [--images 7500] [--validation 1500] [--epochs 10] [--seed SEED]

Renders ``--images`` training and ``--validation`` validation images (prior weathers, two per scene, scene seeds the
dataset splits do not use), labels their pixels with the scenes' road and wet masks, trains
:class:`components.features.backbones.wet_road.WetRoadNet` and writes ``components/features/backbones/wet_road.pt``
and ``wet_road.json`` (the data, seed, validation figures and the weights' sha256). The seed defaults to
``params.yaml``'s. The scenes' seeds come from the streams ``(seed, "scene", "wet_road_training" | "wet_road_validation", j)``. The weights are identical when retrained on one machine (float order differs across CPUs). A new
detector changes the cues: raise ``CuesBackbone.version`` so that cached features are recomputed.
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
from components.core.files import sha256_file  # noqa: E402
from components.core.weather import Box, sample_azimuth, weather_from_theta  # noqa: E402
from components.features.backbones import wet_road  # noqa: E402
from components.simulate.procedural import ProceduralSimulator  # noqa: E402
from components.simulate.procedural.calibration import CALIBRATION  # noqa: E402


def render_training_set(images: int, seed: int, stream: str) -> tuple[np.ndarray, ...]:
    """``images`` rendered images ``(N, 128, 128, 3)`` uint8, their pixel classes ``(N, 128, 128)`` uint8
    (``wet_road.CLASSES``) and weathers θ ``(N, 6)``: prior weathers (the sun azimuth too), two images per scene, the
    scenes' seeds ``derive_seed(seed, "scene", stream, j)`` (the splits' are ``(seed, "scene", <split>, j)``)."""
    height = width = 128
    if images < 2:
        raise ValueError(f"images must be at least 2, got {images}")
    sim = ProceduralSimulator(height, width, cache_size=1)
    g = seeding.rng(seed, "wet_road", stream)
    theta = Box.full().sample(g, images)
    azimuth = sample_azimuth(g, images)
    out = np.empty((images, height, width, 3), np.uint8)
    labels = np.zeros((images, height * width), np.uint8)
    edge = CALIBRATION.puddle_edge
    for i in range(images):
        scene_seed = seeding.derive_seed(seed, "scene", stream, i // 2)
        out[i] = sim.render(weather_from_theta(theta[i], azimuth[i]), scene_seed)
        sc = sim.scene(scene_seed)
        labels[i, sc.road_mask.ravel()] = 1
        refl = sc.reflections
        q = theta[i, 5] / 100.0 * (1.0 + edge)
        wet = np.clip((q - refl.quantile) / edge, 0.0, 1.0) > 0.5
        labels[i, refl.pixels[wet]] = 2
    return out, labels.reshape(images, height, width), theta.astype(np.float32)


def _batches(images: np.ndarray, labels: np.ndarray, idx: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    x = torch.from_numpy(images[idx]).permute(0, 3, 1, 2).float() / 255.0
    y = torch.from_numpy(labels[idx, wet_road.ROWS[0] : wet_road.ROWS[1]]).long()
    return x, y


def train_detector(
    images: np.ndarray,
    labels: np.ndarray,
    *,
    epochs: int,
    seed: int,
    batch_size: int = 32,
    lr: float = 3e-3,
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
    opt = torch.optim.AdamW(net.parameters(), lr)
    per_epoch = math.ceil(len(images) / batch_size)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=epochs * per_epoch)
    g = np.random.default_rng(seed)
    net.train()
    for epoch in range(epochs):
        order = g.permutation(len(images))
        total = 0.0
        for i in range(0, len(images), batch_size):
            x, y = _batches(images, labels, order[i : i + batch_size])
            loss = F.cross_entropy(net(x), y)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss.detach()) * len(y)
        log(f"wet road detector: epoch {epoch + 1} of {epochs}, training cross-entropy {total / len(images):.4f}")
    return net.eval()


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


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=7500, help="training images (default 7500)")
    ap.add_argument("--validation", type=int, default=1500, help="validation images (default 1500)")
    ap.add_argument("--epochs", type=int, default=10, help="epochs (default 10)")
    ap.add_argument("--seed", type=int, default=None, help="seed (default: params.yaml's)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    ap.add_argument("--out", type=Path, default=wet_road.WEIGHTS, help="weights file (the card goes beside it)")
    a = ap.parse_args(argv)
    for name, least in (("images", 2), ("validation", 2), ("epochs", 1), ("threads", 1)):
        if getattr(a, name) < least:
            ap.error(f"--{name} must be at least {least}, got {getattr(a, name)}")
    seed = a.seed if a.seed is not None else load_params(ROOT / "params.yaml").seed
    torch.set_num_threads(a.threads)
    t0 = time.perf_counter()
    images, labels, _ = render_training_set(a.images, seed, "wet_road_training")
    val = render_training_set(a.validation, seed, "wet_road_validation")
    rendered = time.perf_counter() - t0
    print(f"rendered {a.images} + {a.validation} images in {rendered:.0f} s", flush=True)
    net = train_detector(images, labels, epochs=a.epochs, seed=seed, log=lambda m: print(m, flush=True))
    figures = validation_figures(net, *val)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), a.out)
    card = {
        "detector": "wet_road",
        "channels": wet_road.CHANNELS,
        "rows": list(wet_road.ROWS),
        "classes": list(wet_road.CLASSES),
        "training_images": a.images,
        "validation_images": a.validation,
        "epochs": a.epochs,
        "seed": seed,
        "validation": figures,
        "torch": torch.__version__,
        "seconds": round(time.perf_counter() - t0, 1),
        "command": "python scripts/train_wet_road.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "sha256": sha256_file(a.out),
    }
    a.out.with_suffix(".json").write_text(json.dumps(card, indent=1) + "\n")
    print(json.dumps(card["validation"]))


if __name__ == "__main__":
    main()
