"""Train the cues' weather reader from the embedded renderer and write its frozen weights and card.

    python scripts/train_weather_reader.py [--images 20000] [--validation 1500] [--epochs 20] [--seed SEED]
        [--workers N] [--device cuda] [--cache DIR]

Renders ``--images`` training and ``--validation`` validation images (prior weathers, two per scene, from the scene
streams of ``scripts/train_wet_road.py``, which the dataset splits do not use), trains
:class:`components.features.backbones.weather_reader.WeatherReader` to guess each weather parameter by a Gaussian
(negative log likelihood, every batch randomly mirrored, AdamW with a one-cycle learning rate) and writes
``components/features/backbones/weather_reader.pt`` and ``weather_reader.json`` (the data, seed, machine, validation
figures and the weights' sha256). The seed defaults to ``params.yaml``'s. The weights are identical when retrained on
one CPU (float order differs across CPUs, and GPU kernels need not be deterministic). The shipped reader was trained on
a GPU (its card says which and how: 100 000 images, 80 epochs, ~4 minutes with the rendering); the defaults are for a
CPU. A new reader changes the cues: raise ``CuesBackbone.version``.
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
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from train_wet_road import STREAMS, arguments, fit, parse, render_training_set, save  # noqa: E402

from components.core.weather import SHORT_NAMES, Box  # noqa: E402
from components.features.backbones import weather_reader  # noqa: E402


def unit_scale(theta: np.ndarray) -> np.ndarray:
    """θ ``(N, 6)`` in physical units → the prior box's unit scale ``[0, 1]``."""
    box = Box.full()
    return ((theta - box.low) / (box.high - box.low)).astype(np.float32)


def train_reader(
    images: np.ndarray,
    theta: np.ndarray,
    *,
    epochs: int,
    seed: int,
    batch_size: int = 256,
    lr: float = 2e-3,
    device: str = "cpu",
    widths: tuple[int, ...] = weather_reader.WIDTHS,
    hidden: int = weather_reader.HIDDEN,
    log=print,
) -> weather_reader.WeatherReader:
    """Fit the reader to θ ``(N, 6)`` (physical units) of images ``(N, 128, 128, 3)`` uint8 by Gaussian negative log
    likelihood, each image mirrored with probability ½; in eval mode, on the CPU. Batch order, mirrors and initial
    weights come from ``seed``."""
    if images.ndim != 4 or images.shape[1:] != (128, 128, 3) or theta.shape != (len(images), 6):
        raise ValueError(f"expected images (N, 128, 128, 3) and θ (N, 6), got {images.shape} and {theta.shape}")
    torch.manual_seed(seed)
    net = weather_reader.WeatherReader(widths, hidden)
    return fit(
        net,
        images,
        torch.from_numpy(unit_scale(theta)),
        weather_reader.gaussian_nll,
        epochs=epochs,
        seed=seed,
        batch_size=batch_size,
        lr=lr,
        weight_decay=1e-4,
        mirror=True,
        device=device,
        log=log,
        name="weather reader",
        metric="training NLL",
    )


def validation_figures(net: weather_reader.WeatherReader, images: np.ndarray, theta: np.ndarray) -> dict:
    """Per parameter, the median |μ − θ| in physical units by day (sun altitude > 0) and night, and the Gaussian
    negative log likelihood (unit scale) over all images."""
    with torch.no_grad():
        f = torch.cat(
            [
                weather_reader.reader_features(
                    net, torch.from_numpy(images[i : i + 200]).permute(0, 3, 1, 2).float() / 255.0
                )
                for i in range(0, len(images), 200)
            ]
        ).view(-1, 6, 2)
    nll = float(weather_reader.gaussian_nll(f, torch.from_numpy(unit_scale(theta))))
    box = Box.full()
    guess = box.low + f[..., 0].numpy().astype(np.float64) * (box.high - box.low)
    err = np.abs(guess - theta)
    day = theta[:, 3] > 0
    median = {}
    for part, rows in (("day", day), ("night", ~day)):
        median[part] = {k: float(np.median(err[rows, j])) if rows.any() else None for j, k in enumerate(SHORT_NAMES)}
    return {"nll": nll, "median_abs_error": median}


def main(argv: list[str] | None = None) -> None:
    ap = arguments(__doc__.split("\n\n")[0], 20000, 20, 256, 2e-3, weather_reader.WEIGHTS)
    default = ",".join(map(str, weather_reader.WIDTHS))
    ap.add_argument("--widths", default=default, help=f"channels of the five convolutions (default {default})")
    ap.add_argument("--hidden", type=int, default=weather_reader.HIDDEN, help="hidden units (default %(default)s)")
    a = parse(ap, argv)
    try:
        widths = tuple(int(w) for w in a.widths.split(","))
    except ValueError:
        ap.error(f"--widths must be five comma-separated integers, got {a.widths!r}")
    if len(widths) != 5 or min(widths) < 1 or a.hidden < 1:
        ap.error(f"--widths must be five positive integers and --hidden positive, got {a.widths!r} and {a.hidden}")
    t0 = time.perf_counter()
    images, _, theta = render_training_set(a.images, a.seed, STREAMS[0], a.workers, a.cache)
    val_images, _, val_theta = render_training_set(a.validation, a.seed, STREAMS[1], a.workers, a.cache)
    print(f"rendered {a.images} + {a.validation} images in {time.perf_counter() - t0:.0f} s", flush=True)
    net = train_reader(
        images,
        theta,
        epochs=a.epochs,
        seed=a.seed,
        batch_size=a.batch_size,
        lr=a.lr,
        device=a.device,
        widths=widths,
        hidden=a.hidden,
        log=lambda m: print(m, flush=True),
    )
    network = {"network": "weather_reader", "widths": list(widths), "hidden": a.hidden}
    save(net, a, network, validation_figures(net, val_images, val_theta), t0, argv, "train_weather_reader.py")


if __name__ == "__main__":
    main()
