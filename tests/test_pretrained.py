"""Pretrained backbones: tiny random checkpoints of each architecture, loaded through the real code path."""

from __future__ import annotations

import shutil
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import transformers

from components.core import seeding
from components.features.backbones import PRETRAINED, MissingWeightsError, get_backbone

SEED = 2026
DIMS = {"resnet50": 16, "dinov2": 32, "clip": 32}


@pytest.fixture(scope="module")
def weights(tmp_path_factory: pytest.TempPathFactory, tiny_checkpoint) -> Path:
    """``pretrained_dir`` with one tiny checkpoint per pretrained backbone."""
    root = tmp_path_factory.mktemp("pretrained")
    for i, name in enumerate(PRETRAINED):
        tiny_checkpoint(name, root / name, seeding.derive_seed(SEED, "test", "checkpoint", i))
    return root


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    return seeding.rng(SEED, "test", "pretrained", "images").integers(0, 256, (5, 128, 128, 3), dtype=np.uint8)


def _load(name: str, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return get_backbone(name, **options)


def _extract(b, images: np.ndarray) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return b.extract(images, batch_size=2)


@pytest.mark.parametrize("name", PRETRAINED)
def test_features_shape_determinism_and_frozen(name: str, weights: Path, images: np.ndarray) -> None:
    a = _load(name, pretrained_dir=weights)
    b = _load(name, path=weights / name)
    assert not a.trainable and a.dim == DIMS[name] and a.input_size == (32, 32)
    assert not any(p.requires_grad for p in a.parameters())
    fa, fb = _extract(a, images), _extract(b, images)
    assert fa.shape == (5, DIMS[name]) and fa.dtype == np.float32 and np.isfinite(fa).all()
    np.testing.assert_array_equal(fa, fb)
    np.testing.assert_array_equal(fa, _extract(a, images))
    assert a.fingerprint() == b.fingerprint()
    assert fa.std(0).max() > 0  # features differ between images


@pytest.mark.parametrize("name", PRETRAINED)
def test_matches_transformers_processor_and_model(name: str, weights: Path, images: np.ndarray) -> None:
    """Our batched torch preprocessing equals the model's own image processor to one grey level,
    and the features equal the model's pooled output on the processor's tensors."""
    b = _load(name, pretrained_dir=weights)
    processor = transformers.AutoImageProcessor.from_pretrained(weights / name, backend="pil", local_files_only=True)
    reference = processor(list(images), return_tensors="pt")["pixel_values"]
    with pytest.warns(UserWarning, match=f"'{name}'.*128×128.*32×32.*bicubic"):
        ours = b.preprocess(images)
    assert ours.shape == reference.shape
    one_level = 1.0 / 255.0 / min(processor.image_std)
    assert (ours - reference).abs().max().item() <= one_level * 1.01
    with torch.inference_mode():
        expected = b.model(pixel_values=reference).pooler_output.reshape(len(images), -1).numpy()
    np.testing.assert_allclose(_extract(b, images), expected, atol=0.05 * np.abs(expected).max())


def test_fingerprint_changes_with_weights(weights: Path, tmp_path: Path) -> None:
    original = _load("dinov2", pretrained_dir=weights)
    moved = tmp_path / "moved"
    shutil.copytree(weights / "dinov2", moved)
    assert _load("dinov2", path=moved).fingerprint() == original.fingerprint()  # location is not identity
    model = transformers.Dinov2Model.from_pretrained(moved, local_files_only=True)
    with torch.no_grad():
        model.layernorm.bias[0] += 1e-3
    changed = tmp_path / "changed"
    model.save_pretrained(changed)
    shutil.copy(moved / "preprocessor_config.json", changed)
    assert _load("dinov2", path=changed).fingerprint() != original.fingerprint()


def test_hub_cache_is_used_offline(weights: Path, tmp_path: Path, images: np.ndarray) -> None:
    """A repo laid out as in the Hugging Face cache loads by repo id with local_files_only."""
    snapshot = tmp_path / "models--openai--clip-vit-base-patch32" / "snapshots" / ("0" * 40)
    shutil.copytree(weights / "clip", snapshot)
    (tmp_path / "models--openai--clip-vit-base-patch32" / "refs").mkdir()
    (tmp_path / "models--openai--clip-vit-base-patch32" / "refs" / "main").write_text("0" * 40)
    b = _load("clip", cache_dir=tmp_path)
    assert b.source.kind == "hub" and b.source.local_files_only
    np.testing.assert_array_equal(_extract(b, images), _extract(_load("clip", pretrained_dir=weights), images))


@pytest.mark.parametrize("name", PRETRAINED)
def test_missing_weights_fail_fast_and_clearly(name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)  # even online, never the hub's retry loop
    empty_cache = tmp_path / "hub"
    empty_cache.mkdir()
    for options, where in (
        ({"pretrained_dir": tmp_path / "none"}, str(tmp_path / "none" / name)),
        ({"path": tmp_path / "nowhere"}, str(tmp_path / "nowhere")),
        ({"cache_dir": empty_cache}, str(empty_cache)),
    ):
        start = time.perf_counter()
        with pytest.raises(MissingWeightsError) as err:
            get_backbone(name, **options)
        assert time.perf_counter() - start < 5.0
        message = str(err.value)
        assert f"'{name}'" in message and where in message and "hf download" in message
        assert isinstance(err.value, ValueError)


def test_incomplete_folder_names_the_missing_file(weights: Path, tmp_path: Path) -> None:
    folder = tmp_path / "resnet50"
    shutil.copytree(weights / "resnet50", folder)
    (folder / "model.safetensors").unlink()
    with pytest.raises(MissingWeightsError, match="lacks model.safetensors or"):
        get_backbone("resnet50", path=folder)
    shutil.copy(weights / "resnet50" / "model.safetensors", folder)
    (folder / "preprocessor_config.json").unlink()
    with pytest.raises(MissingWeightsError, match="lacks preprocessor_config.json"):
        get_backbone("resnet50", path=folder)


def test_offline_env_forbids_download(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(MissingWeightsError, match="HF_HUB_OFFLINE is set"):
        get_backbone("dinov2", download=True, cache_dir=tmp_path)


def test_wrong_architecture_is_rejected(weights: Path) -> None:
    with pytest.raises(ValueError, match="holds a 'resnet' model.*CLIPVisionModel"):
        get_backbone("clip", path=weights / "resnet50")


def test_bad_images_are_rejected(weights: Path) -> None:
    b = _load("resnet50", pretrained_dir=weights)
    with pytest.raises(ValueError, match="dtype uint8"):
        b.preprocess(np.zeros((1, 128, 128, 3), np.float64))
    with pytest.raises(ValueError, match=r"\(n, H, W, 3\)"):
        b.preprocess(np.zeros((1, 128, 128), np.uint8))


def test_hub_offline_env_is_read_at_call_time(monkeypatch: pytest.MonkeyPatch) -> None:
    from components.features.backbones.weights import hub_offline

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    assert hub_offline()
    monkeypatch.setenv("HF_HUB_OFFLINE", "0")
    assert not hub_offline()
