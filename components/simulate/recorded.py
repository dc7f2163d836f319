"""Recorded datasets: folders of labelled images imported into the dataset's shards, and the recording of such folders.

``simulator.backend: recorded`` makes the ``generate`` stage import the folders of ``simulator.recorded.folders``
(each with its labels file, :mod:`components.simulate.labels`) instead of rendering: the same shards, receipts,
manifest and content hash as rendered data (:mod:`components.simulate.dataset`), so every later stage reads them
unchanged.

- **Checks, before anything is written** (:func:`plan_import`): every labels row (:func:`~components.simulate.labels.
  read_labels`), then each folder's files: an image the labels name that is not there (*missing image*), an image file
  under the folder that no row names (*extra image*), two rows naming one file or two files of the same bytes
  (*duplicate*), sequences split across splits, and splits too small for ``data.splits`` (hence ``train.sizes``).
  Each is a :class:`~components.simulate.labels.RecordedError` of one line naming the file and the row.
- **Splits.** With a ``split`` column (in every labels file) rows go where it says, in file order, each split taking
  its first ``data.splits`` rows. Without, splits are drawn by sequence: the sequences (the ``sequence`` column, else
  an image's sub-folder; an image directly in the folder is a sequence of its own) are shuffled by the stream
  ``(seed, "recorded", "splits")`` and dealt to test, val and train in that order, each split taking whole sequences
  until it holds its ``data.splits`` count (the last one cut: its other frames are left out, never put in another
  split). Frames of one drive therefore never sit in two splits. Rows left out are counted in the manifest.
- **Images** (:func:`import_shard`) are read as RGB (:func:`components.core.images.read_image`: an unreadable or
  truncated file is an error naming it and its row) and those of another size are shrunk to ``simulator.height ×
  width`` by the exact area average (:func:`components.simulate.resized.area_resize`, as the camera-like renders
  are); an image smaller than that, or of another aspect (more than a pixel off), is an error. Each shard's receipt
  counts the source sizes and the images resized, and the manifest's ``source`` sums them (the model cards copy it).
- **Shards.** ``weather`` holds the labels' 13 values (the azimuth NaN when unknown), ``scene_id`` the sequence's
  index within the split, ``scene_seed`` is −1 (:data:`NO_SCENE_SEED`: no renderer can render a recorded scene
  again, so Task I's posterior predictive checks are skipped). A split's plan fingerprint covers its rows, the sha256
  of each image file, the resolution and the shard size: re-importing unchanged folders skips every finished shard
  (resumable, as rendering is) and writes the same bytes, hence the same content hash.

:func:`record` writes such a folder from any simulator (``pidc record``): the generate stage's plan of each split
(the same θ, azimuths and scene seeds), one PNG per image under ``<split>/scene-<j>/``, a labels CSV with every
weather column, ``sequence`` (the scene) and ``split``; resumable (finished images are kept) and the labels written
last, atomically. A CARLA user records on the server's machine and trains anywhere.

Used by the ``generate`` stage (:func:`plan_import`, :func:`import_shard`, :func:`source_entry`) and the ``pidc``
CLI (:func:`record`).
"""

from __future__ import annotations

import hashlib
import json
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from components.core import seeding, weather
from components.core.config import Params
from components.core.files import atomic_path, atomic_write_bytes, remove_stale_temps
from components.core.images import IMAGE_EXTENSIONS, ImageError, read_image
from components.simulate import dataset
from components.simulate.base import Simulator
from components.simulate.labels import IMAGE_COLUMN, SPLIT_COLUMN, Labels, RecordedError, labels_csv, read_labels
from components.simulate.resized import area_resize

__all__ = [
    "SOURCE_KIND",
    "NO_SCENE_SEED",
    "RecordedPlan",
    "RecordedRows",
    "RecordedImport",
    "plan_import",
    "import_shard",
    "source_entry",
    "split_plans",
    "record",
]

#: the manifest's ``renderer`` and ``source.kind`` of an imported dataset
SOURCE_KIND = "recorded"
#: the ``scene_seed`` of every recorded image: no renderer can render its scene again
NO_SCENE_SEED = -1
#: the import's own version: a change of how images are read or resized changes every plan fingerprint
IMPORT_VERSION = 1
#: the splits in the order they are dealt sequences (test first: Task I's images come from whole drives)
_DEAL_ORDER = ("test", "val", "train")


@dataclass(frozen=True)
class _Row:
    """One labelled image: its file (resolved), sha256, 13 weather values, sequence key, split (or None), where."""

    file: Path
    sha256: str
    weather: np.ndarray
    sequence: str
    split: str | None
    where: str


@dataclass(frozen=True)
class RecordedRows:
    """What one shard imports: the files (and their planned sha256, for a change made meanwhile), the weather
    ``(k, 13)``, the scene ids ``(k,)`` and each row's place in its labels file (for messages)."""

    spec: dataset.ShardSpec
    files: tuple[str, ...]
    sha256: tuple[str, ...]
    weather: np.ndarray
    scene_id: np.ndarray
    where: tuple[str, ...]


@dataclass(frozen=True)
class RecordedPlan:
    """A split of recorded images: the dataset's :class:`~components.simulate.dataset.SplitPlan` (weather, scene ids,
    scene seeds −1, shard size, fingerprint) and, per row, its file, sha256 and place in the labels."""

    plan: dataset.SplitPlan
    files: tuple[str, ...]
    sha256: tuple[str, ...]
    where: tuple[str, ...]

    def rows(self, spec: dataset.ShardSpec) -> RecordedRows:
        idx = slice(spec.start, spec.stop)
        return RecordedRows(
            spec,
            self.files[idx],
            self.sha256[idx],
            self.plan.weather[idx],
            self.plan.scene_id[idx],
            self.where[idx],
        )


@dataclass(frozen=True)
class RecordedImport:
    """The plans of the three splits and the manifest's ``source`` entry (without the resize counts, which the
    receipts give: :func:`source_entry`)."""

    plans: list[RecordedPlan]
    source: dict


# --- checking the folders ----------------------------------------------------------------------------------------


def _image_files(root: Path) -> list[Path]:
    """Every image file under ``root`` (any depth; hidden files and folders skipped), resolved, sorted."""
    found = []
    for path in root.rglob("*"):
        rel = path.relative_to(root).parts
        if any(part.startswith(".") for part in rel) or not path.is_file():
            continue
        if path.suffix.lower() in IMAGE_EXTENSIONS:
            found.append(path.resolve())
    return sorted(found)


def _sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _folder_rows(folder: Path, label: str, labels: Labels, seen: dict[str, str], shas: dict[str, str]) -> list[_Row]:
    """The rows of one folder, its files checked (missing, extra, duplicate); ``seen`` and ``shas`` (file → where,
    sha256 → file and where) span every folder."""
    root = folder.resolve()
    rows = []
    for i, (name, at) in enumerate(zip(labels.names, labels.rows, strict=True)):
        where = f"{labels.path}, {at}"
        path = (folder / name).resolve()
        if root not in path.parents:
            raise RecordedError(f"{where}, column {IMAGE_COLUMN}: {name!r} lies outside {folder}")
        if not path.is_file():
            raise RecordedError(f"{folder / name}: missing image (named on {at} of {labels.path})")
        if str(path) in seen:
            raise RecordedError(
                f"{where}, column {IMAGE_COLUMN}: duplicate file: {path} is also named on {seen[str(path)]}"
            )
        seen[str(path)] = where
        sha = _sha256(path)
        if sha in shas:
            raise RecordedError(
                f"{folder / name}: duplicate image: the same bytes as {shas[sha]} (named on {at} of {labels.path})"
            )
        shas[sha] = f"{path} ({where})"
        if labels.sequences is not None:
            sequence = labels.sequences[i]
        else:  # the sub-folder; an image directly in the folder is a sequence of its own
            parent = Path(name).parent
            sequence = name if str(parent) in ("", ".") else parent.as_posix()
        split = labels.splits[i] if labels.splits is not None else None
        rows.append(_Row(path, sha, labels.weather[i], f"{label}:{sequence}", split, where))
    listed = {str(r.file) for r in rows}
    extra = [p for p in _image_files(root) if str(p) not in listed]
    if extra:
        more = f" (and {len(extra) - 1} more)" if len(extra) > 1 else ""
        raise RecordedError(
            f"{extra[0]}: extra image: it lies in {folder} but no row of {labels.path} names it{more}; add its row "
            "or move it out of the folder"
        )
    return rows


def _read_folders(folders: Sequence[Path], labels_name: str, box: weather.Box) -> tuple[list[_Row], list[Labels]]:
    """Every folder's checked rows, in folder then file order, and their labels."""
    seen: dict[str, str] = {}
    shas: dict[str, str] = {}
    rows: list[_Row] = []
    all_labels = []
    for k, folder in enumerate(folders):
        labels = read_labels(folder, box, name=labels_name)
        all_labels.append(labels)
        rows.extend(_folder_rows(folder, f"{k}", labels, seen, shas))
    with_split = [lab for lab in all_labels if lab.splits is not None]
    if with_split and len(with_split) != len(all_labels):
        without = next(lab for lab in all_labels if lab.splits is None)
        raise RecordedError(
            f"{without.path}: no {SPLIT_COLUMN} column, but {with_split[0].path} has one: give it in every labels "
            "file (rows go where it says) or in none (splits drawn by sequence)"
        )
    return rows, all_labels


# --- the splits --------------------------------------------------------------------------------------------------


def _too_small(name: str, need: int, have: str, train_max: int, where: str) -> RecordedError:
    for_train = (
        f" (train.sizes go up to {train_max}: the train split must cover the largest training size)"
        if name == "train"
        else ""
    )
    return RecordedError(
        f"{where}: split {name} too small: data.splits.{name} is {need} images{for_train}, but {have}; record "
        "more images or lower data.splits"
    )


def _by_column(rows: list[_Row], sizes: dict[str, int], train_max: int, where: str) -> dict[str, list[_Row]]:
    """The rows of each split as the split column says (the first ``sizes[split]`` of each, file order)."""
    first: dict[str, _Row] = {}
    for r in rows:
        other = first.setdefault(r.sequence, r)
        if other.split != r.split:
            raise RecordedError(
                f"{r.where}, column {SPLIT_COLUMN}: sequence {r.sequence.split(':', 1)[1]!r} is in split {r.split} "
                f"here and in split {other.split} on {other.where}: frames of one sequence must sit in one split"
            )
    out = {}
    for name in dataset.SPLITS:
        mine = [r for r in rows if r.split == name]
        if len(mine) < sizes[name]:
            raise _too_small(name, sizes[name], f"the {SPLIT_COLUMN} column gives it {len(mine)}", train_max, where)
        out[name] = mine[: sizes[name]]
    return out


def _by_sequence(
    rows: list[_Row], sizes: dict[str, int], seed: int, train_max: int, where: str
) -> dict[str, list[_Row]]:
    """Whole sequences, shuffled from ``seed``, dealt to test, val and train; each split's last one cut to its size."""
    sequences: dict[str, list[_Row]] = {}
    for r in rows:
        sequences.setdefault(r.sequence, []).append(r)
    keys = list(sequences)
    order = [keys[i] for i in seeding.rng(seed, "recorded", "splits").permutation(len(keys))]
    out: dict[str, list[_Row]] = {}
    taken = 0
    for name in _DEAL_ORDER:
        mine: list[_Row] = []
        while len(mine) < sizes[name] and taken < len(order):
            mine.extend(sequences[order[taken]])
            taken += 1
        if len(mine) < sizes[name]:
            dealt = ", ".join(f"{n} {len(out[n])}" for n in out) or "nothing"
            have = (
                f"only {len(mine)} images in whole sequences are left for it ({len(rows)} images in {len(keys)} "
                f"sequences, after {dealt})"
            )
            raise _too_small(name, sizes[name], have, train_max, where)
        out[name] = mine[: sizes[name]]
    return out


def _split_plan(name: str, rows: list[_Row], shard_size: int, resolution: tuple[int, int]) -> RecordedPlan:
    """The plan of one split: the rows' weather, their sequences' index in the split, scene seeds −1."""
    index: dict[str, int] = {}
    scene_id = np.array([index.setdefault(r.sequence, len(index)) for r in rows], dtype=np.int64)
    table = np.stack([r.weather for r in rows]) if rows else np.zeros((0, len(weather.ALL_NAMES)))
    sha = tuple(r.sha256 for r in rows)
    head = {
        "format": dataset.FORMAT_VERSION,
        "source": SOURCE_KIND,
        "import": IMPORT_VERSION,
        "split": name,
        "resolution": list(resolution),
        "shard_size": shard_size,
    }
    fp = hashlib.sha256(
        json.dumps(head, sort_keys=True).encode() + table.tobytes() + scene_id.tobytes() + "\n".join(sha).encode()
    ).hexdigest()[:16]
    seeds = np.full(len(rows), NO_SCENE_SEED, dtype=np.int64)
    plan = dataset.SplitPlan(name, table, scene_id, seeds, shard_size, fp)
    return RecordedPlan(plan, tuple(str(r.file) for r in rows), sha, tuple(r.where for r in rows))


def plan_import(params: Params, root: str | Path) -> RecordedImport:
    """Check the recorded folders of ``params.simulator.recorded`` (relative to the project ``root``) and plan the
    three splits (the module's description); nothing is read but the labels and the files' bytes (hashed).

    Arguments:
        params: the project's settings (``simulator``, ``data.splits``, ``data.shard_size``, ``seed``, the prior box,
            ``train.sizes``).
        root: the project root, against which relative folders are resolved.

    Returns:
        The plans and the manifest's ``source`` entry (:class:`RecordedImport`).

    Raises:
        RecordedError: one line naming the file and row of the first problem found.
    """
    rec = params.simulator.recorded
    folders = [Path(f) if Path(f).is_absolute() else Path(root) / f for f in rec.folders]
    rows, all_labels = _read_folders(folders, rec.labels, params.box)
    sizes = {name: params.data.splits[name] for name in dataset.SPLITS}
    where = ", ".join(str(lab.path) for lab in all_labels)
    train_max = max(params.train.sizes)
    by_column = all_labels[0].splits is not None
    splits = (
        _by_column(rows, sizes, train_max, where)
        if by_column
        else _by_sequence(rows, sizes, params.seed, train_max, where)
    )
    resolution = (params.simulator.height, params.simulator.width)
    plans = [_split_plan(name, splits[name], params.data.shard_size, resolution) for name in dataset.SPLITS]
    used = sum(len(p.plan) for p in plans)
    source = {
        "kind": SOURCE_KIND,
        "folders": list(rec.folders),
        "labels": [
            {
                "file": str(lab.path.relative_to(Path(root)) if lab.path.is_relative_to(Path(root)) else lab.path),
                "sha256": _sha256(lab.path),
                "rows": len(lab),
            }
            for lab in all_labels
        ],
        "images": len(rows),
        "used": used,
        "left_out": len(rows) - used,
        "sequences": len({r.sequence for r in rows}),
        "splits_from": "the split column" if by_column else "whole sequences drawn from the seed",
        "sequence_from": "the sequence column"
        if all(lab.sequences is not None for lab in all_labels)
        else "the sequence column, else each image's sub-folder",
        "azimuth_known": bool(all(np.all(np.isfinite(p.plan.weather[:, 6])) for p in plans)),
        "scene_seed": f"{NO_SCENE_SEED}: no renderer can render a recorded scene again",
    }
    return RecordedImport(plans, source)


# --- importing a shard -------------------------------------------------------------------------------------------


def fit_image(image: np.ndarray, size: tuple[int, int], file: str, where: str) -> np.ndarray:
    """``image`` area-resized to ``size`` (h, w); an error naming the file for a smaller image or another aspect."""
    h, w = size
    height, width = image.shape[:2]
    if (height, width) == (h, w):
        return image
    if height < h or width < w:
        raise RecordedError(
            f"{file}: {width}×{height} pixels is smaller than the dataset's {w}×{h} (simulator.width × height); area "
            f"resizing only shrinks (named on {where})"
        )
    if abs(width * h - height * w) > h:  # the width more than a pixel off the dataset's aspect
        raise RecordedError(
            f"{file}: {width}×{height} pixels has another aspect than the dataset's {w}×{h}; set simulator.height and "
            f"width to the camera's aspect (named on {where})"
        )
    return area_resize(image, (h, w))


def import_shard(rows: RecordedRows, resolution: tuple[int, int], root: str | Path) -> dict:
    """Read, check and resize the images of one shard and write it with its receipt (atomically, as
    :func:`~components.simulate.dataset.render_shard`); the receipt also counts the images resized and their source
    sizes (``"<width>x<height>"``). :class:`~components.simulate.labels.RecordedError` naming the file and row of an
    image that is unreadable, truncated, changed since the plan, too small or of another aspect."""
    spec = rows.spec
    h, w = resolution
    images = np.empty((spec.stop - spec.start, h, w, 3), dtype=np.uint8)
    sizes: Counter[str] = Counter()
    for j, (file, sha, where) in enumerate(zip(rows.files, rows.sha256, rows.where, strict=True)):
        path = Path(file)
        try:
            if _sha256(path) != sha:
                raise RecordedError(f"{file}: changed since the import was planned (named on {where}); run it again")
            image, _ = read_image(path)
        except ImageError as e:
            raise RecordedError(f"{e} (named on {where})") from None
        except OSError as e:
            raise RecordedError(f"{file}: unreadable ({e.strerror or e}) (named on {where})") from None
        sizes[f"{image.shape[1]}x{image.shape[0]}"] += 1
        images[j] = fit_image(image, (h, w), file, where)
    resized = sum(n for size, n in sizes.items() if size != f"{w}x{h}")
    extra = {"resized": resized, "source_sizes": dict(sorted(sizes.items()))}
    seeds = np.full(len(images), NO_SCENE_SEED, dtype=np.int64)
    return dataset.write_shard(spec, images, rows.weather, seeds, rows.scene_id, root, extra)


def source_entry(imported: RecordedImport, root: str | Path) -> dict:
    """The manifest's ``source`` entry: the plan's description and the resize counts summed over the finished shards'
    receipts (``resized``, ``source_sizes``)."""
    sizes: Counter[str] = Counter()
    resized = 0
    for p in imported.plans:
        for spec in p.plan.shards():
            receipt = json.loads(spec.receipt_path(root).read_text())
            resized += int(receipt.get("resized", 0))
            sizes.update(receipt.get("source_sizes", {}))
    return {**imported.source, "resized": resized, "source_sizes": dict(sorted(sizes.items()))}


# --- recording a folder ------------------------------------------------------------------------------------------


def split_plans(
    params: Params, splits: Sequence[str], count: int | None, renderer_version: str
) -> list[dataset.SplitPlan]:
    """The generate stage's plans of ``splits`` (the same θ, azimuths and scene seeds), each cut to its first
    ``count`` images when given (a split's rows do not depend on its size)."""
    sim = params.simulator
    return [
        dataset.plan_split(
            name,
            params.data.splits[name] if count is None else count,
            seed=params.seed,
            box=params.box,
            images_per_scene=params.data.images_per_scene,
            shard_size=params.data.shard_size,
            renderer_version=renderer_version,
            resolution=(sim.height, sim.width),
        )
        for name in splits
    ]


_MARKER = ".pidc-record.json"


def _png(image: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(np.asarray(image)[:, :, ::-1]))
    if not ok:
        raise ValueError("could not encode a PNG")
    return buf.tobytes()


def _claim(out: Path, meta: dict) -> None:
    """Make ``out`` this recording's folder, or check that it already is (resuming): an error for a folder holding
    another recording or other files."""
    marker = out / _MARKER
    if marker.is_file():
        try:
            before = json.loads(marker.read_text())
        except ValueError:
            before = None
        if before != meta:
            raise RecordedError(
                f"{out}: holds a recording of another plan ({marker}: another simulator, size, split or count); record "
                "into a new folder or remove this one"
            )
        return
    if out.exists() and any(not p.name.startswith(".") for p in out.iterdir()):
        raise RecordedError(f"{out}: not empty and not a folder pidc record wrote; record into a new folder")
    atomic_write_bytes(marker, json.dumps(meta, indent=1, sort_keys=True).encode())


def record(
    simulator: Simulator,
    plans: Sequence[dataset.SplitPlan],
    out: str | Path,
    *,
    labels: str = "labels.csv",
    progress: Callable[[int], object] | None = None,
) -> dict:
    """Render ``plans`` with ``simulator`` into the recorded folder ``out`` (the module's description): image ``i`` of
    split ``s`` in scene ``j`` at ``<s>/scene-<j>/<i>.png``, then the labels file ``labels``.

    Resumable: a finished image (written atomically) is kept; the folder is claimed by a marker naming the simulator,
    size and plans, so resuming with another plan is an error rather than a mix.

    Arguments:
        simulator: any :class:`~components.simulate.base.Simulator` (procedural, resized renders, CARLA).
        plans: the splits' plans (:func:`split_plans`).
        out: the folder to write.
        labels: the labels file's name (``.csv``).
        progress: called with the number of images done after each (a progress bar's ``update``).

    Returns:
        ``{"images", "rendered", "kept", "labels"}``: the counts and the labels file's path.
    """
    out = Path(out)
    meta = {
        "format": 1,
        "renderer": simulator.version,
        "resolution": [simulator.height, simulator.width],
        "plans": {p.name: {"fingerprint": p.fingerprint, "count": len(p)} for p in plans},
    }
    _claim(out, meta)
    names, rows, sequences, splits = [], [], [], []
    rendered = kept = 0
    for plan in plans:
        for j in np.unique(plan.scene_id):
            folder = out / plan.name / f"scene-{int(j):06d}"
            if folder.is_dir():
                remove_stale_temps(folder)  # an image cut short by a kill
        for i in range(len(plan)):
            sequence = f"{plan.name}/scene-{int(plan.scene_id[i]):06d}"
            name = f"{sequence}/{i:06d}.png"
            path = out / name
            if path.is_file():
                kept += 1
            else:
                row = {n: float(v) for n, v in zip(weather.ALL_NAMES, plan.weather[i], strict=True)}
                image = simulator.render(row, int(plan.scene_seed[i]))
                with atomic_path(path, fsync=False) as tmp:
                    tmp.write_bytes(_png(image))
                rendered += 1
            names.append(name)
            rows.append(plan.weather[i])
            sequences.append(sequence)
            splits.append(plan.name)
            if progress is not None:
                progress(1)
    table = np.stack(rows) if rows else np.zeros((0, len(weather.ALL_NAMES)))
    atomic_write_bytes(out / labels, labels_csv(names, table, sequences, splits))
    return {"images": len(names), "rendered": rendered, "kept": kept, "labels": str(out / labels)}
