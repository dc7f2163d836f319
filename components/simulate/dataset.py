"""The simulated dataset: a deterministic plan, sharded files, atomic writes and validated reading.

Layout under the data root (``data/`` by default):

    data/manifest.json                 # counts, ranges, resolution, renderer version, content hash
    data/<split>/shard-00000.npz       # images uint8 (k, H, W, 3) RGB, weather float64 (k, 13),
    data/<split>/shard-00000.json      #   scene_seed int64 (k,), scene_id int64 (k,), index int64 (k,)
                                       # + a receipt: sha256, count, plan fingerprint

A shard counts as done only when its receipt exists, names the current plan's fingerprint and the
file's sha256 matches; anything else (missing, truncated, stale) is re-rendered. Files are written
to a temporary name and renamed, so a killed run never leaves a file that reads as valid.

The plan is a pure function of the params: split sizes, seed, prior box, images per scene. θ and the
azimuth of image ``i`` do not depend on the split's size (prefix property), so smaller training sets
are nested prefixes of the train split. Image ``i`` is rendered in scene ``i // images_per_scene``
(a map/spawn point under several weathers, as data are collected in CARLA).

Used by every stage but ``export``, by the scheduled monitoring (new draws planned as the
test split) and by the ``pidc`` CLI.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from components.core import seeding, weather
from components.core.checks import whole_number
from components.core.files import atomic_write_bytes, sha256_file

__all__ = [
    "SPLITS",
    "FORMAT_VERSION",
    "SplitPlan",
    "ShardSpec",
    "ShardRows",
    "remove_orphans",
    "DatasetError",
    "plan_split",
    "render_shard",
    "write_shard",
    "shard_is_done",
    "write_manifest",
    "Split",
    "open_split",
]

SPLITS = ("train", "val", "test")
FORMAT_VERSION = 1
_ARRAYS = ("images", "weather", "scene_seed", "scene_id", "index")


class DatasetError(ValueError):
    """A dataset file is missing, truncated, stale or inconsistent with its manifest."""


# --- atomic, deterministic writing ------------------------------------------------------------


def _npz_bytes(arrays: Mapping[str, np.ndarray]) -> bytes:
    """An uncompressed ``.npz`` with fixed zip metadata: same arrays → same bytes (np.savez stamps the time)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            payload = io.BytesIO()
            np.lib.format.write_array(payload, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            zf.writestr(info, payload.getvalue())
    return buf.getvalue()


# --- the plan ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class SplitPlan:
    """What split ``name`` holds: per image, its weather (13 values, ``weather.ALL_NAMES`` order)
    and its scene. Shapes: ``weather (n, 13)``, ``scene_id (n,)``, ``scene_seed (n,)``."""

    name: str
    weather: np.ndarray
    scene_id: np.ndarray
    scene_seed: np.ndarray
    shard_size: int
    fingerprint: str

    def __len__(self) -> int:
        return int(self.weather.shape[0])

    @property
    def n_shards(self) -> int:
        return -(-len(self) // self.shard_size)

    def shard(self, k: int) -> ShardSpec:
        if not 0 <= k < self.n_shards:
            raise IndexError(f"split {self.name!r} has {self.n_shards} shards, asked for shard {k}")
        start, stop = k * self.shard_size, min((k + 1) * self.shard_size, len(self))
        return ShardSpec(self.name, k, start, stop, self.fingerprint)

    def shards(self) -> list[ShardSpec]:
        return [self.shard(k) for k in range(self.n_shards)]

    def rows(self, spec: ShardSpec) -> ShardRows:
        """The plan's rows for one shard (small enough to send to a worker process)."""
        idx = slice(spec.start, spec.stop)
        return ShardRows(spec, self.weather[idx], self.scene_seed[idx], self.scene_id[idx])


@dataclass(frozen=True)
class ShardSpec:
    """Images ``[start, stop)`` of a split, stored as ``<split>/shard-<k>.npz``."""

    split: str
    k: int
    start: int
    stop: int
    plan_fingerprint: str

    @property
    def stem(self) -> str:
        return f"shard-{self.k:05d}"

    def path(self, root: str | Path) -> Path:
        return Path(root) / self.split / f"{self.stem}.npz"

    def receipt_path(self, root: str | Path) -> Path:
        return Path(root) / self.split / f"{self.stem}.json"


@dataclass(frozen=True)
class ShardRows:
    """What one shard renders: ``weather (k, 13)``, ``scene_seed (k,)``, ``scene_id (k,)``."""

    spec: ShardSpec
    weather: np.ndarray
    scene_seed: np.ndarray
    scene_id: np.ndarray


def plan_split(
    name: str,
    size: int,
    *,
    seed: int,
    box: weather.Box,
    images_per_scene: int,
    shard_size: int,
    renderer_version: str,
    resolution: tuple[int, int],
) -> SplitPlan:
    """The deterministic plan of one split (no rendering).

    θ ~ U(box), azimuth ~ U[0, 360) from streams named by ``(seed, "data", name, …)``; scene ``j``
    of the split has seed ``derive_seed(seed, "scene", name, j)``. Row ``i`` is the same for every
    ``size > i`` (nested prefixes).
    """
    if name not in SPLITS:
        raise ValueError(f"unknown split {name!r}; splits are {', '.join(SPLITS)}")
    for label, v in (("size", size), ("images_per_scene", images_per_scene), ("shard_size", shard_size)):
        whole_number(f"split {name!r}: {label}", v, low=1)
    theta = box.sample(seeding.rng(seed, "data", name, "theta"), size)
    azimuth = weather.sample_azimuth(seeding.rng(seed, "data", name, "azimuth"), size)
    rows = np.empty((size, len(weather.ALL_NAMES)), dtype=np.float64)
    rows[:, : len(weather.PREDICTED)] = theta
    rows[:, len(weather.PREDICTED)] = azimuth
    for j, n in enumerate(weather.ALL_NAMES[len(weather.PREDICTED) + 1 :], start=len(weather.PREDICTED) + 1):
        rows[:, j] = weather.FIXED[n]
    scene_id = np.arange(size, dtype=np.int64) // images_per_scene
    n_scenes = int(scene_id[-1]) + 1 if size else 0
    scene_seeds = np.array([seeding.derive_seed(seed, "scene", name, j) for j in range(n_scenes)], dtype=np.int64)
    scene_seed = scene_seeds[scene_id]
    fp = hashlib.sha256(
        json.dumps(
            {
                "format": FORMAT_VERSION,
                "split": name,
                "renderer": renderer_version,
                "resolution": list(resolution),
                "shard_size": shard_size,
            },
            sort_keys=True,
        ).encode()
        + rows.tobytes()
        + scene_seed.tobytes()
    ).hexdigest()[:16]
    return SplitPlan(name, rows, scene_id, scene_seed, shard_size, fp)


# --- rendering and checking shards ------------------------------------------------------------


def _read_receipt(spec: ShardSpec, root: Path) -> dict | None:
    try:
        return json.loads(spec.receipt_path(root).read_text())
    except (OSError, ValueError):
        return None


def shard_is_done(spec: ShardSpec, root: str | Path, *, verify_hash: bool = True) -> bool:
    """True when the shard file and its receipt exist, the receipt names this plan and the file matches it."""
    root = Path(root)
    receipt = _read_receipt(spec, root)
    path = spec.path(root)
    if receipt is None or not path.is_file():
        return False
    if receipt.get("plan") != spec.plan_fingerprint or receipt.get("count") != spec.stop - spec.start:
        return False
    if receipt.get("bytes") != path.stat().st_size:
        return False
    return not verify_hash or receipt.get("sha256") == sha256_file(path)


def render_shard(rows: ShardRows, simulator, root: str | Path) -> dict:
    """Render the images of one shard with ``simulator`` and write the shard and its receipt atomically.

    Images of the same scene are consecutive, so the simulator's per-scene geometry cache is hit.
    Returns the receipt (sha256, count, bytes, plan).
    """
    root = Path(root)
    spec = rows.spec
    h, w = simulator.height, simulator.width
    images = np.empty((spec.stop - spec.start, h, w, 3), dtype=np.uint8)
    for j, (row, scene_seed) in enumerate(zip(rows.weather, rows.scene_seed, strict=False)):
        wdict = {n: float(v) for n, v in zip(weather.ALL_NAMES, row, strict=False)}
        img = simulator.render(wdict, int(scene_seed))
        if img.shape != (h, w, 3) or img.dtype != np.uint8:
            raise DatasetError(f"simulator returned {img.dtype} {img.shape}, expected uint8 {(h, w, 3)}")
        images[j] = img
    return write_shard(spec, images, rows.weather, rows.scene_seed, rows.scene_id, root)


def write_shard(
    spec: ShardSpec,
    images: np.ndarray,
    weather_rows: np.ndarray,
    scene_seed: np.ndarray,
    scene_id: np.ndarray,
    root: str | Path,
    extra: Mapping[str, object] | None = None,
) -> dict:
    """Write shard ``spec`` (``images (k, H, W, 3)`` uint8, ``weather_rows (k, 13)``, ``scene_seed``/``scene_id``
    ``(k,)``) and then its receipt, each atomically; ``extra`` entries join the receipt (and the manifest's shard
    entry). Returns the receipt (sha256, count, bytes, plan)."""
    root = Path(root)
    arrays = {
        "images": images,
        "weather": weather_rows,
        "scene_seed": scene_seed,
        "scene_id": scene_id,
        "index": np.arange(spec.start, spec.stop, dtype=np.int64),
    }
    data = _npz_bytes(arrays)
    path = spec.path(root)
    # drop a stale receipt first: a crash between the two writes then reads as "not done"
    spec.receipt_path(root).unlink(missing_ok=True)
    atomic_write_bytes(path, data)
    receipt = {
        "plan": spec.plan_fingerprint,
        "count": spec.stop - spec.start,
        "start": spec.start,
        "stop": spec.stop,
        "bytes": len(data),
        "sha256": hashlib.sha256(data).hexdigest(),
        **(extra or {}),
    }
    atomic_write_bytes(spec.receipt_path(root), json.dumps(receipt, indent=1).encode())
    return receipt


def remove_orphans(root: str | Path, plan: SplitPlan) -> list[Path]:
    """Delete shard files and receipts of ``plan.name`` that the plan does not have (e.g. a shrunk split)."""
    folder = Path(root) / plan.name
    keep = {f"{s.stem}{ext}" for s in plan.shards() for ext in (".npz", ".json")}
    removed = []
    if folder.is_dir():
        for f in sorted(folder.iterdir()):
            if f.is_file() and f.name not in keep and (f.name.startswith("shard-") or f.name.startswith(".shard-")):
                f.unlink()
                removed.append(f)
    return removed


def write_manifest(
    root: str | Path,
    plans: Sequence[SplitPlan],
    *,
    renderer_version: str,
    resolution: tuple[int, int],
    seed: int,
    box: weather.Box,
    images_per_scene: int | None,
    source: Mapping[str, object] | None = None,
) -> dict:
    """Write ``manifest.json`` from the receipts of finished shards (all must be done); ``source`` (a recorded
    dataset's description, :mod:`components.simulate.recorded`) becomes its ``source`` entry, and
    ``images_per_scene`` is None for recorded data."""
    root = Path(root)
    splits: dict[str, dict] = {}
    content = hashlib.sha256()
    for plan in plans:
        shards = []
        for spec in plan.shards():
            receipt = _read_receipt(spec, root)
            if receipt is None or receipt.get("plan") != plan.fingerprint:
                raise DatasetError(f"{spec.path(root)}: shard not finished; cannot write the manifest")
            shards.append({"file": f"{plan.name}/{spec.stem}.npz", **receipt})
            content.update(receipt["sha256"].encode())
        theta = weather.theta_from_weather(plan.weather)
        splits[plan.name] = {
            "count": len(plan),
            "scenes": int(plan.scene_id[-1]) + 1 if len(plan) else 0,
            "plan": plan.fingerprint,
            "theta_min": dict(zip(weather.PREDICTED, theta.min(0).tolist(), strict=False)),
            "theta_max": dict(zip(weather.PREDICTED, theta.max(0).tolist(), strict=False)),
            "shards": shards,
        }
    manifest = {
        "format": FORMAT_VERSION,
        "renderer": renderer_version,
        "resolution": {"height": resolution[0], "width": resolution[1]},
        "seed": seed,
        "images_per_scene": images_per_scene,
        "weather_columns": list(weather.ALL_NAMES),
        "theta_columns": list(weather.PREDICTED),
        "prior_box": {
            n: [float(lo), float(hi)] for n, lo, hi in zip(weather.PREDICTED, box.low, box.high, strict=False)
        },
        "splits": splits,
        "content_hash": content.hexdigest(),
    }
    if source is not None:
        manifest["source"] = dict(source)
    atomic_write_bytes(root / "manifest.json", json.dumps(manifest, indent=1).encode())
    return manifest


# --- reading ----------------------------------------------------------------------------------


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in _ARRAYS}
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as e:
        raise DatasetError(f"{path}: unreadable shard ({type(e).__name__}: {e}); re-run the generate stage") from None
    return out


class Split:
    """A read-only view of one split: θ and metadata in memory, images loaded per shard on demand.

    Attributes: ``weather (n, 13)``, ``theta (n, 6)``, ``scene_id (n,)``, ``scene_seed (n,)``,
    ``manifest`` (the dataset manifest), ``name``.
    """

    def __init__(self, root: Path, name: str, manifest: dict, *, verify: bool):
        self.root, self.name, self.manifest = root, name, manifest
        info = manifest["splits"][name]
        self.shard_files = [root / s["file"] for s in info["shards"]]
        self._shard_info = info["shards"]
        for path, s in zip(self.shard_files, self._shard_info, strict=False):
            if not path.is_file():
                raise DatasetError(
                    f"{path}: shard listed in {root / 'manifest.json'} is missing; re-run the generate stage"
                )
            if path.stat().st_size != s["bytes"] or (verify and sha256_file(path) != s["sha256"]):
                raise DatasetError(
                    f"{path}: shard does not match the manifest (truncated or changed); re-run the generate stage"
                )
        meta = [self._load_meta(p) for p in self.shard_files]
        self.weather = np.concatenate([m["weather"] for m in meta]) if meta else np.zeros((0, 13))
        self.scene_id = np.concatenate([m["scene_id"] for m in meta]) if meta else np.zeros(0, np.int64)
        self.scene_seed = np.concatenate([m["scene_seed"] for m in meta]) if meta else np.zeros(0, np.int64)
        if len(self.weather) != info["count"]:
            raise DatasetError(f"{root / name}: {len(self.weather)} images on disk, manifest says {info['count']}")
        self.theta = weather.theta_from_weather(self.weather)
        self._bounds = np.cumsum([0] + [s["count"] for s in self._shard_info])

    @staticmethod
    def _load_meta(path: Path) -> dict[str, np.ndarray]:
        try:
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in ("weather", "scene_id", "scene_seed")}
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as e:
            raise DatasetError(
                f"{path}: unreadable shard ({type(e).__name__}: {e}); re-run the generate stage"
            ) from None

    def __len__(self) -> int:
        return len(self.weather)

    @property
    def resolution(self) -> tuple[int, int]:
        r = self.manifest["resolution"]
        return int(r["height"]), int(r["width"])

    @property
    def content_hash(self) -> str:
        return self.manifest["content_hash"]

    def iter_shards(self, stop: int | None = None) -> Iterator[tuple[slice, np.ndarray]]:
        """Yield ``(rows, images)`` per shard for the first ``stop`` images (all by default)."""
        stop = len(self) if stop is None else stop
        if not 0 <= stop <= len(self):
            raise ValueError(f"split {self.name!r} has {len(self)} images, asked for the first {stop}")
        for k, path in enumerate(self.shard_files):
            a, b = int(self._bounds[k]), int(self._bounds[k + 1])
            if a >= stop:
                break
            images = _load_npz(path)["images"]
            yield slice(a, min(b, stop)), images[: min(b, stop) - a]

    def shard_images(self, k: int) -> np.ndarray:
        """The images of shard ``k``: uint8 ``(count_k, H, W, 3)``."""
        if not 0 <= k < len(self.shard_files):
            raise IndexError(f"split {self.name!r} has {len(self.shard_files)} shards, asked for shard {k}")
        return _load_npz(self.shard_files[k])["images"]

    def images(self, stop: int | None = None) -> np.ndarray:
        """The first ``stop`` images as one array ``(stop, H, W, 3)`` uint8."""
        parts = [imgs for _, imgs in self.iter_shards(stop)]
        h, w = self.resolution
        return np.concatenate(parts) if parts else np.zeros((0, h, w, 3), np.uint8)


def open_split(root: str | Path, name: str, *, verify: bool = False) -> Split:
    """Open split ``name`` of the dataset at ``root`` (checks presence and sizes; ``verify`` also hashes)."""
    root = Path(root)
    mpath = root / "manifest.json"
    try:
        manifest = json.loads(mpath.read_text())
    except OSError:
        raise DatasetError(f"{mpath}: no dataset manifest; run the generate stage (`dvc repro generate`)") from None
    except ValueError as e:
        raise DatasetError(f"{mpath}: corrupt manifest ({e}); re-run the generate stage") from None
    if manifest.get("format") != FORMAT_VERSION:
        raise DatasetError(f"{mpath}: dataset format {manifest.get('format')}, this pidc reads {FORMAT_VERSION}")
    if name not in manifest.get("splits", {}):
        raise DatasetError(f"{mpath}: no split {name!r}; it has {sorted(manifest.get('splits', {}))}")
    return Split(root, name, manifest, verify=verify)
