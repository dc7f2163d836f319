"""Cached backbone outputs, aligned with the dataset's shards and validated against its manifest.

Layout under the features root (``features/`` by default):

    features/<backbone>/manifest.json             # backbone fingerprint, dim, dataset content hash
    features/<backbone>/<split>/shard-00000.npy   # float32 (k, dim) features of dataset shard 0
    features/<backbone>/<split>/shard-00000.json  # receipt: dataset shard sha256, fingerprint, sha256

For a frozen backbone a shard holds its features ``f(x)``; for a backbone trained jointly with the
flow (``trainable``) it holds the backbone's model input at its ``input_size`` (uint8
``(k, h, w, 3)``), so training never re-reads and re-sizes the full images. A cached shard is reused
only when its receipt names the current dataset shard (sha256) and the current backbone
fingerprint; otherwise it is recomputed, never mixed with new data.

Used by the ``features``, ``train``, ``evaluate``, ``task2`` and ``task3`` stages and the ``pidc`` CLI.
"""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from components.core.files import atomic_write_bytes
from components.simulate.dataset import Split

__all__ = [
    "FeatureStore",
    "FeatureError",
    "open_features",
    "shard_features_done",
    "write_shard_features",
    "write_features_manifest",
    "backbone_output",
    "output_fingerprint",
]

FORMAT_VERSION = 1


class FeatureError(ValueError):
    """Cached features are missing, stale (another dataset or backbone) or damaged."""


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.ascontiguousarray(a), allow_pickle=False)
    return buf.getvalue()


@dataclass(frozen=True)
class FeatureStore:
    """Where the cached outputs of one backbone live: ``root / backbone``."""

    root: Path
    backbone: str

    @property
    def folder(self) -> Path:
        return Path(self.root) / self.backbone

    def shard_path(self, split: str, k: int) -> Path:
        return self.folder / split / f"shard-{k:05d}.npy"

    def receipt_path(self, split: str, k: int) -> Path:
        return self.folder / split / f"shard-{k:05d}.json"


def output_fingerprint(backbone) -> str:
    """What identifies a backbone's cached output: its full fingerprint when frozen; when trainable
    (its cached output is its model input, which no weight changes) only its name, version and input size."""
    if not backbone.trainable:
        return backbone.fingerprint()
    head = {
        "name": backbone.name,
        "version": backbone.version,
        "input_size": list(backbone.input_size),
        "kind": "inputs",
    }
    return hashlib.sha256(json.dumps(head, sort_keys=True).encode()).hexdigest()


def backbone_output(backbone, images: np.ndarray, batch_size: int) -> np.ndarray:
    """What is cached for ``images`` (uint8 ``(n, H, W, 3)``): features ``(n, dim)`` float32 of a frozen
    backbone, or the uint8 images at a trainable backbone's ``input_size`` ``(n, h, w, 3)``."""
    if backbone.trainable:
        from components.features.backbones.imageops import resize_area

        return images if images.shape[1:3] == tuple(backbone.input_size) else resize_area(images, backbone.input_size)
    return backbone.extract(images, batch_size=batch_size)


def _dataset_shard(split: Split, k: int) -> dict:
    return split.manifest["splits"][split.name]["shards"][k]


def shard_features_done(store: FeatureStore, split: Split, k: int, fingerprint: str) -> bool:
    """True when shard ``k`` of ``split`` has features of this backbone fingerprint for the current data."""
    try:
        receipt = json.loads(store.receipt_path(split.name, k).read_text())
    except (OSError, ValueError):
        return False
    path = store.shard_path(split.name, k)
    if not path.is_file():
        return False
    return (
        receipt.get("format") == FORMAT_VERSION
        and receipt.get("dataset_shard_sha256") == _dataset_shard(split, k)["sha256"]
        and receipt.get("fingerprint") == fingerprint
        and receipt.get("bytes") == path.stat().st_size
    )


def write_shard_features(store: FeatureStore, split: Split, k: int, values: np.ndarray, fingerprint: str) -> dict:
    """Write the cached output of dataset shard ``k`` and its receipt atomically."""
    expected = _dataset_shard(split, k)["count"]
    if values.shape[0] != expected:
        raise FeatureError(f"{store.backbone}/{split.name} shard {k}: {values.shape[0]} rows for {expected} images")
    if values.dtype.kind == "f" and not np.isfinite(values).all():
        raise FeatureError(f"{store.backbone}/{split.name} shard {k}: non-finite features (NaN or inf)")
    data = _npy_bytes(values)
    store.receipt_path(split.name, k).unlink(missing_ok=True)
    atomic_write_bytes(store.shard_path(split.name, k), data)
    receipt = {
        "format": FORMAT_VERSION,
        "dataset_shard_sha256": _dataset_shard(split, k)["sha256"],
        "fingerprint": fingerprint,
        "shape": list(values.shape),
        "dtype": str(values.dtype),
        "bytes": len(data),
        "sha256": hashlib.sha256(data).hexdigest(),
    }
    atomic_write_bytes(store.receipt_path(split.name, k), json.dumps(receipt, indent=1).encode())
    return receipt


def write_features_manifest(
    store: FeatureStore, splits: list[Split], *, fingerprint: str, kind: str, config: dict
) -> dict:
    """Write ``manifest.json`` once every shard of every split is done."""
    out = {
        "format": FORMAT_VERSION,
        "backbone": store.backbone,
        "fingerprint": fingerprint,
        "kind": kind,
        "config": config,
        "dataset_content_hash": splits[0].content_hash,
        "splits": {},
    }
    for split in splits:
        n = len(split.shard_files)
        if not all(shard_features_done(store, split, k, fingerprint) for k in range(n)):
            raise FeatureError(f"{store.folder / split.name}: unfinished shards; cannot write the manifest")
        first = json.loads(store.receipt_path(split.name, 0).read_text()) if n else {"shape": [0], "dtype": "float32"}
        out["splits"][split.name] = {
            "count": len(split),
            "shards": n,
            "shape": first["shape"][1:],
            "dtype": first["dtype"],
        }
    atomic_write_bytes(store.folder / "manifest.json", json.dumps(out, indent=1).encode())
    # drop shards of splits or sizes that are no longer in the dataset
    for split in splits:
        folder = store.folder / split.name
        keep = {f"shard-{k:05d}{e}" for k in range(len(split.shard_files)) for e in (".npy", ".json")}
        for f in folder.iterdir():
            if f.name not in keep:
                f.unlink()
    return out


def open_features(root: str | Path, backbone: str, split: Split, *, stop: int | None = None) -> np.ndarray:
    """The cached output of ``backbone`` for the first ``stop`` images of ``split``.

    Raises :class:`FeatureError` when the cache is missing, was made from another dataset (its
    content hash differs) or a shard is damaged.
    """
    store = FeatureStore(Path(root), backbone)
    mpath = store.folder / "manifest.json"
    try:
        manifest = json.loads(mpath.read_text())
    except OSError:
        raise FeatureError(
            f"{mpath}: no cached features for backbone {backbone!r}; run `dvc repro features@{backbone}`"
        ) from None
    except ValueError as e:
        raise FeatureError(f"{mpath}: corrupt features manifest ({e})") from None
    if manifest.get("dataset_content_hash") != split.content_hash:
        raise FeatureError(
            f"{mpath}: features of backbone {backbone!r} were computed on another dataset "
            f"({str(manifest.get('dataset_content_hash'))[:12]} ≠ {split.content_hash[:12]}); run `dvc repro features@{backbone}`"
        )
    stop = len(split) if stop is None else stop
    if not 0 <= stop <= len(split):
        raise FeatureError(f"split {split.name!r} has {len(split)} images, asked for the first {stop}")
    # each shard is mapped, not read, and copied into one array of the final size: the features are in memory once
    # (a join by concatenation held them twice for a moment; docs/studies/paper-scale.md)
    out: np.ndarray | None = None
    have = 0
    for k in range(len(split.shard_files)):
        if have >= stop:
            break
        path = store.shard_path(split.name, k)
        if not shard_features_done(store, split, k, manifest["fingerprint"]):
            raise FeatureError(f"{path}: missing or stale; run `dvc repro features@{backbone}`")
        try:
            shard = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError, EOFError) as e:
            raise FeatureError(f"{path}: unreadable ({e})") from None
        if out is None:
            out = np.empty((stop, *shard.shape[1:]), shard.dtype)
        elif shard.shape[1:] != out.shape[1:] or shard.dtype != out.dtype:
            raise FeatureError(
                f"{path}: rows of shape {shard.shape[1:]} {shard.dtype}, where the split's first shard has "
                f"{out.shape[1:]} {out.dtype}; run `dvc repro features@{backbone}`"
            )
        take = min(len(shard), stop - have)
        out[have : have + take] = shard[:take]
        del shard  # closes the map
        have += take
    if out is None:
        return np.zeros((0, *manifest["splits"][split.name]["shape"]), np.float32)
    if have < stop:
        raise FeatureError(
            f"{store.folder / split.name}: the shards hold {have} rows, the split {split.name!r} {stop} images; "
            f"run `dvc repro features@{backbone}`"
        )
    return out


def posterior_inputs(backbone, images: np.ndarray, batch_size: int = 256) -> np.ndarray:
    """The posterior's input ``x`` for uint8 images ``(n, H, W, 3)``: frozen features ``(n, dim)``, or a trainable
    backbone's preprocessed tensor ``(n, C, h, w)``; float32 numpy (what :class:`components.export.runtime.OnnxPosterior`
    takes)."""
    return inputs_from_cached(backbone, backbone_output(backbone, images, batch_size))


def inputs_from_cached(backbone, cached: np.ndarray) -> np.ndarray:
    """The posterior's input ``x`` (float32 numpy) from what :func:`backbone_output` cached: the features themselves,
    or a trainable backbone's preprocessed tensor of its cached images."""
    if backbone.trainable:
        return backbone.preprocess(cached).detach().numpy().astype(np.float32, copy=False)
    return np.ascontiguousarray(cached, dtype=np.float32)
