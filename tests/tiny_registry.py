"""A tiny registry for the CLI tests: one small NPE on the cues of 32×32 renders, exported with the fast torchscript
exporter, and the champion pointer naming it; and folders of renders at weathers uniform in a box.

The NPE is trained for a few epochs with input noise, as the pipeline trains its frozen-feature models (without it,
256 images of the cues gave posteriors so sharp that `relate`'s verdict on an in-ODD mix turned on the float order of
one thread or two). Used by tests/test_cli_registry.py and tests/test_prior.py; each names its own random streams.
tests/test_watch.py builds a larger one with :func:`build_registry`'s keywords (more renders, epochs and width, and
the cheap ``tiny`` backbone: a watch reads every source frame, which the cues would make minutes).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from components.core import seeding, weather
from components.export.lookup import CHAMPION_POINTER

BOX = weather.Box.full()
#: the card the export flow writes for such a model
CARD = {
    "model_id": "cues-tiny",
    "backbone": "cues",
    "backbone_options": {},
    "size": 256,
    "training_renders": {"simulator": "procedural", "height": 32, "width": 32},
}


def render_folder(
    folder: Path, box: tuple[list[float], list[float]], n: int, seed: int, prefix: str = "", stream: str = "cli-folder"
) -> Path:
    """``n`` PNGs of 32×32 at weathers uniform in ``box`` (distinct scenes), named ``<prefix><i>.png``."""
    from components.simulate.procedural import ProceduralSimulator

    sim = ProceduralSimulator(32, 32)
    folder.mkdir(parents=True, exist_ok=True)
    r = seeding.rng(seed, "test", stream)
    for i in range(n):
        image = sim.render(weather.weather_from_theta(r.uniform(box[0], box[1]), 100.0), 1000 * seed + i)
        Image.fromarray(image).save(folder / f"{prefix}{i:03d}.png")
    return folder


def build_registry(
    root: Path,
    stream: str,
    champion: dict | None = None,
    *,
    n: int = 288,
    size: int = 32,
    backbone: str = "cues",
    epochs: int = 12,
    width: int = 64,
    batch_size: int = 32,
    model_id: str = "cues-tiny",
) -> Path:
    """``root/registry`` holding ``model_id`` (an NPE on ``backbone``'s features of ``n`` renders of ``size × size``
    pixels at weathers uniform in the full box, stream ``("test", stream)``), and the champion pointer
    ``root/reports/task1/champion.json`` (``champion``, default ``{"model": model_id}``).

    The flow is one spline transform (6 bins) with one hidden layer of ``width``; it is trained for ``epochs`` in
    batches of ``batch_size`` on the first ``n − n // 9`` renders, validated on the other ``n // 9``. The defaults are
    the CLI tests' ``cues-tiny``: 256 renders to train on, 32 to validate.
    """
    from components.export.onnx import export_posterior
    from components.features.backbones import get_backbone
    from components.features.cache import posterior_inputs
    from components.posterior import NPE, FlowConfig, TrainingConfig, train
    from components.simulate.procedural import ProceduralSimulator

    r = seeding.rng(0, "test", stream)
    theta, azimuth = BOX.sample(r, n), weather.sample_azimuth(r, n)
    sim = ProceduralSimulator(size, size)
    images = np.stack(
        [sim.render(weather.weather_from_theta(t, a), i) for i, (t, a) in enumerate(zip(theta, azimuth, strict=True))]
    )
    with pytest.warns(UserWarning, match=f"converting {size}×{size} images to its input size"):
        x = posterior_inputs(get_backbone(backbone), images)
    model = NPE(None, x.shape[1], BOX, FlowConfig(transforms=1, hidden_features=(width,), bins=6), seed=0)
    fit = n - n // 9
    train(
        model,
        (x[:fit], theta[:fit]),
        (x[fit:], theta[fit:]),
        TrainingConfig(epochs=epochs, batch_size=batch_size, lr=3e-3, input_noise=0.5),
        progress=False,
    )
    registry = root / "registry"
    renders = CARD["training_renders"] | {"height": size, "width": size}
    card = CARD | {"model_id": model_id, "backbone": backbone, "size": fit, "training_renders": renders}
    export_posterior(model, registry / model_id, exporter="torchscript", card=card)
    pointer = registry.parent / CHAMPION_POINTER  # <project>/reports/task1/champion.json
    pointer.parent.mkdir(parents=True)
    pointer.write_text(json.dumps(champion or {"model": model_id}))
    return registry
