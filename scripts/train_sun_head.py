"""Train the weather reader's sun head on the reader's frozen convolutions and write its weights and card.

    python scripts/train_sun_head.py [--images 100000] [--validation 4000] [--epochs 15] [--root-seed 9001]
        [--faces 0] [--face-validation 2000] [--seed SEED] [--workers N] [--cache DIR]

Renders ``--images`` training images, the plan of the dataset's ``train`` split under root seed ``--root-seed``, and
``--validation`` images of the ``val`` split's plan under ``--root-seed`` + 1 (the pipeline's splits use
``params.yaml``'s seed; the two must differ from it), with the embedded renderer as the ``generate`` stage renders
(``images_per_scene`` images a scene); ``--faces`` adds that many training images of the prior's clear-sky face
(:data:`FACE`, root seed ``--root-seed`` + 100) and scores the head on ``--face-validation`` more (+ 101) beside the
validation. Each image and its mirror go through the frozen convolutions of
:func:`components.features.backbones.weather_reader.load_reader`;
:class:`~components.features.backbones.weather_reader.SunHead` learns the sun's altitude from both maps by Gaussian
negative log likelihood (AdamW, one-cycle learning rate, batch order and initial weights from ``--seed``), and the epoch
of the lowest validation loss is kept. Writes ``components/features/backbones/weather_reader_sun.pt`` and its card
``weather_reader_sun.json`` (data, seeds, the reader's sha256, validation figures, machine, command, the weights'
sha256). With ``--cache`` the convolutions' maps are kept there (a file per 25 000 images) and read back by later runs
(a larger ``--images`` reuses a smaller run's files). The weights are identical when retrained on one CPU (float order
differs across CPUs). A new head changes the cues: raise ``CuesBackbone.version``.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

# isort: off
import components  # noqa: E402,F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import json  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from types import SimpleNamespace  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from train_wet_road import arguments, parse, save  # noqa: E402

from components.core.config import load_params  # noqa: E402
from components.core.files import atomic_path  # noqa: E402
from components.core.weather import PREDICTED, Box  # noqa: E402
from components.features.backbones import weather_reader as wr  # noqa: E402
from components.simulate.in_memory import render_split  # noqa: E402

#: the sun's altitude among the predicted parameters
SUN = PREDICTED.index("sun_altitude_angle")
#: images a call of the convolutions (with their mirrors: twice as many rows)
CHUNK = 64
#: images rendered at a time (≈ 0.8 GB of images), and per file of ``--cache``
BLOCK = 25000
#: the clear-sky face of the prior (``--faces``): CARLA's ClearNoon (cloudiness 5, fog 2, no rain or deposits) and its
#: neighbours, where the fog's airlight, the uniform images' strongest cue of the sun, is missing; wind and the sun's
#: altitude range over the whole box (docs/studies/sun-head-faces.md)
FACE: dict[str, tuple[float, float]] = {
    "cloudiness": (0.0, 20.0),
    "fog_density": (0.0, 5.0),
    "precipitation": (0.0, 5.0),
    "precipitation_deposits": (0.0, 10.0),
}
#: the face plans' root seeds: ``--root-seed`` + this (train) and + this + 1 (validation)
FACE_SEED_OFFSET = 100


def maps(net: wr.WeatherReader, images: np.ndarray) -> np.ndarray:
    """The reader's flattened convolution maps ``(N, 2, C·16)`` float32 of uint8 images ``(N, 128, 128, 3)``: the image
    (index 0) and its mirror (1), :data:`CHUNK` images a call."""
    out = None
    with torch.no_grad():
        for a in range(0, len(images), CHUNK):
            x = torch.from_numpy(np.ascontiguousarray(images[a : a + CHUNK])).permute(0, 3, 1, 2).float() / 255.0
            h = wr.reader_maps(net, x)
            if out is None:
                out = np.empty((len(images), 2, h.shape[1]), np.float32)
            b = len(x)
            out[a : a + b, 0], out[a : a + b, 1] = h[:b].numpy(), h[b:].numpy()
    assert out is not None
    return out


def rendered_maps(
    params,
    net: wr.WeatherReader,
    split: str,
    n: int,
    root_seed: int,
    workers: int,
    cache: Path | None,
    faces: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Maps ``(n, 2, C·16)`` and θ ``(n, 6)`` of the first ``n`` images of ``split``'s plan under ``root_seed``
    (θ uniform on ``params.box``, or with ``faces`` on its clear-sky face :data:`FACE`), rendered and read
    :data:`BLOCK` images at a time (only the maps are kept); a block is read from ``cache`` when it holds it for this
    reader (plans are nested prefixes: a larger ``--images`` reuses the blocks of a smaller one)."""
    reader = json.loads(wr.CARD.read_text())["sha256"][:12]
    kind = "sun_head-faces" if faces else "sun_head"
    plan = face_params(params) if faces else params
    out_m, out_theta = [], []
    for start in range(0, n, BLOCK):
        stop = min(start + BLOCK, n)
        path = cache / f"{kind}-{split}-{root_seed}-{start}-{stop}-{reader}.npz" if cache is not None else None
        cached = path is not None and path.is_file()
        if cached:
            with np.load(path) as z:
                m, theta = z["maps"], z["theta"]
        else:
            images, theta = render_split(plan, split, stop - start, workers, seed=root_seed, start=start)
            m = maps(net, images)
            del images
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                with atomic_path(path) as tmp, open(tmp, "wb") as f:
                    np.savez(f, maps=m, theta=theta)
        out_m.append(m)
        out_theta.append(theta)
        print(
            f"{split}{' (faces)' if faces else ''}: maps of images {start}–{stop - 1} ({'cache' if cached else 'rendered'})",
            flush=True,
        )
    return np.concatenate(out_m), np.concatenate(out_theta)


def face_params(params):
    """``params`` with the prior box narrowed to the clear-sky face :data:`FACE` (what :func:`render_split` reads)."""
    box = Box.from_mapping(
        {**{n: (lo, hi) for n, lo, hi in zip(params.box.names, params.box.low, params.box.high, strict=True)}, **FACE}
    )
    return SimpleNamespace(box=box, seed=params.seed, data=params.data, simulator=params.simulator)


def unit_sun(theta: np.ndarray) -> torch.Tensor:
    """The sun's altitude of θ ``(N, 6)`` on the prior box's unit scale, ``(N, 1)``."""
    box = Box.full()
    return torch.tensor((theta[:, SUN : SUN + 1] - box.low[SUN]) / (box.high[SUN] - box.low[SUN]), dtype=torch.float32)


def mirrored_guess(head: wr.SunHead, m: torch.Tensor) -> torch.Tensor:
    """The head's guess ``(N, 1, 2)`` averaged over each image's map and its mirror's (as the cues compute it)."""
    return 0.5 * (head(m[:, 0]) + head(m[:, 1]))


def train_head(
    m: np.ndarray,
    theta: np.ndarray,
    val_m: np.ndarray,
    val_theta: np.ndarray,
    *,
    epochs: int,
    seed: int,
    batch_size: int,
    lr: float,
    hidden: tuple[int, ...] = wr.SUN_HIDDEN,
    log=print,
) -> tuple[wr.SunHead, int]:
    """Fit a :class:`SunHead` to the maps ``(N, 2, F)`` (each image and its mirror one training row) and keep the epoch
    of the lowest validation loss (the mirror-averaged guess). Returns the head in eval mode and that epoch (from 1)."""
    torch.manual_seed(seed)
    head = wr.SunHead(m.shape[2], hidden)
    x = torch.from_numpy(m).reshape(-1, m.shape[2])
    y = unit_sun(theta).repeat_interleave(2, 0)
    vx, vy = torch.from_numpy(val_m), unit_sun(val_theta)
    steps = max(1, len(x) // batch_size)
    opt = torch.optim.AdamW(head.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=epochs * steps)
    best, best_state, best_epoch = math.inf, None, 0
    for epoch in range(epochs):
        head.train()
        order = torch.randperm(len(x))
        for b in range(steps):
            i = order[b * batch_size : (b + 1) * batch_size]
            loss = wr.gaussian_nll(head(x[i]), y[i])
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
        head.eval()
        with torch.no_grad():
            val = float(wr.gaussian_nll(mirrored_guess(head, vx), vy))
        if val < best:
            best, best_epoch = val, epoch + 1
            best_state = {k: v.clone() for k, v in head.state_dict().items()}
        log(f"sun head: epoch {epoch + 1} of {epochs}, validation NLL {val:.4f} (best {best:.4f} at {best_epoch})")
    assert best_state is not None
    head.load_state_dict(best_state)
    return head.eval(), best_epoch


def figures(head: wr.SunHead, net: wr.WeatherReader, m: np.ndarray, theta: np.ndarray) -> dict:
    """Validation: the head's and the reader's own Gaussian NLL (unit scale) and daytime median |μ − altitude| (°),
    overall and by true altitude in bins of 18°."""
    box = Box.full()
    scale = box.high[SUN] - box.low[SUN]
    with torch.no_grad():
        t = torch.from_numpy(m)
        own = mirrored_guess(head, t)
        reader = 0.5 * (net.head(t[:, 0]).view(-1, 6, 2) + net.head(t[:, 1]).view(-1, 6, 2))[:, SUN : SUN + 1]
    y, sun = unit_sun(theta), theta[:, SUN]
    day = sun > 0
    out = {}
    for name, g in (("sun_head", own), ("reader", reader)):
        err = np.abs(box.low[SUN] + g[:, 0, 0].numpy().astype(np.float64) * scale - sun)
        out[name] = {
            "nll": float(wr.gaussian_nll(g, y)),
            "day_median_abs_error": float(np.median(err[day])),
            "day_median_abs_error_by_18deg": {
                f"{a}-{a + 18}": float(np.median(err[day & (sun >= a) & (sun < a + 18)]))
                if np.any(day & (sun >= a) & (sun < a + 18))
                else None
                for a in range(0, 90, 18)
            },
        }
    return out


def main(argv: list[str] | None = None) -> None:
    ap = arguments(__doc__.split("\n\n")[0], 100000, 15, 512, 5e-4, wr.SUN_WEIGHTS)
    ap.set_defaults(validation=4000)
    ap.add_argument("--root-seed", type=int, default=9001, help="root seed of the training plan (+1: validation)")
    default = ",".join(map(str, wr.SUN_HIDDEN))
    ap.add_argument("--hidden", default=default, help=f"hidden units of the head's layers (default {default})")
    ap.add_argument(
        "--faces",
        type=int,
        default=0,
        help="training images of the clear-sky face added to --images (root seed --root-seed + 100; default 0)",
    )
    ap.add_argument(
        "--face-validation",
        type=int,
        default=2000,
        help="images of the clear-sky face scored beside the validation (root seed --root-seed + 101; with --faces)",
    )
    a = parse(ap, argv)
    if a.faces < 0 or (a.faces and a.face_validation < 2):
        ap.error(f"--faces must be >= 0 and --face-validation >= 2, got {a.faces} and {a.face_validation}")
    params = load_params(ROOT / "params.yaml")
    face_seed = a.root_seed + FACE_SEED_OFFSET
    if params.seed in (a.root_seed, a.root_seed + 1) or (a.faces and params.seed in (face_seed, face_seed + 1)):
        ap.error(
            f"--root-seed {a.root_seed}: its plans would be the pipeline's own images (params.yaml seed {params.seed})"
        )
    try:
        hidden = tuple(int(h) for h in a.hidden.split(","))
    except ValueError:
        ap.error(f"--hidden must be comma-separated integers, got {a.hidden!r}")
    if not hidden or min(hidden) < 1:
        ap.error(f"--hidden must be positive integers, got {a.hidden!r}")
    t0 = time.perf_counter()
    net = wr.load_reader()
    m, theta = rendered_maps(params, net, "train", a.images, a.root_seed, a.workers, a.cache)
    vm, vtheta = rendered_maps(params, net, "val", a.validation, a.root_seed + 1, a.workers, a.cache)
    if a.faces:
        fm, ftheta = rendered_maps(params, net, "train", a.faces, face_seed, a.workers, a.cache, faces=True)
        fvm, fvtheta = rendered_maps(params, net, "val", a.face_validation, face_seed + 1, a.workers, a.cache, True)
        m, theta = np.concatenate([m, fm]), np.concatenate([theta, ftheta])
        del fm
    print(f"rendered and read {len(m)} + {a.validation} images in {time.perf_counter() - t0:.0f} s", flush=True)
    head, best_epoch = train_head(
        m,
        theta,
        vm,
        vtheta,
        epochs=a.epochs,
        seed=a.seed,
        batch_size=a.batch_size,
        lr=a.lr,
        hidden=hidden,
        log=lambda s: print(s, flush=True),
    )
    network = {
        "network": "weather_reader_sun_head",
        "in_features": int(m.shape[2]),
        "hidden": list(hidden),
        "best_epoch": best_epoch,
        "reader_sha256": json.loads(wr.CARD.read_text())["sha256"],
    }
    data = {"plans": {"train": a.root_seed, "val": a.root_seed + 1}, "images_per_scene": params.data.images_per_scene}
    scores = figures(head, net, vm, vtheta)
    if a.faces:
        data["faces"] = {
            "images": a.faces,
            "validation": a.face_validation,
            "box": {k: list(v) for k, v in FACE.items()},
            "plans": {"train": face_seed, "val": face_seed + 1},
        }
        network["validation_faces"] = figures(head, net, fvm, fvtheta)
    save(head, a, network, scores, t0, argv, "train_sun_head.py", data=data)


if __name__ == "__main__":
    main()
