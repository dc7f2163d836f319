"""What the model commands share: the model of ``--model``/``--registry`` (the registry, an exported folder, or the
MLflow Model Registry by URI), the images of the command line read in batches into the model's inputs (a ``note:`` or
``skipped`` line on stderr for each image converted or refused), and the checks of the common options.

Used by the ``pidc`` CLI only (:mod:`~components.cli.characterize`, :mod:`~components.cli.domain`,
:mod:`~components.cli.relate`).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from components.cli.errors import CLIError
from components.core.files import atomic_write_bytes

__all__ = [
    "READ_BATCH",
    "MIN_SAMPLES",
    "Read",
    "ReadLog",
    "load_model",
    "list_paths",
    "read_batches",
    "read_all",
    "check_samples",
    "check_seed",
    "check_folder",
    "check_figure_path",
    "figure_suffixes",
    "check_json_path",
    "write_json",
    "save_corner",
    "count",
    "none_read",
    "folder_name",
    "check_inputs",
    "say",
    "progress",
    "MIN_ESS",
    "UserPriorSetup",
    "check_prior",
    "load_prior",
    "reweighted",
    "prior_line",
    "prior_json",
]

#: Images read and turned into posterior inputs per batch (bounds memory for large folders).
READ_BATCH = 64
#: The fewest posterior draws ``--samples`` takes. The 68.27 % HDI's ends are order statistics with about 16 % of the
#: draws beyond each: at 100 draws that is ~16 draws a side, and the Monte Carlo error of a 16 % quantile,
#: √(0.16·0.84/m), is 3.7 percentage points of probability; at 10 draws 12 points, and at 1 the "interval" is one draw
#: (width 0, a posterior that looks certain). The pipeline draws 500 (``evaluate.samples``), ``pidc`` 1000 by default.
MIN_SAMPLES = 100


def _check_models_uri(uri: str) -> None:
    """A :class:`CLIError` for a malformed MLflow model URI, before MLflow runs: the forms MLflow accepts are
    ``models:/NAME/VERSION``, ``models:/NAME/STAGE`` (or ``latest``), ``models:/NAME@ALIAS`` and ``models:/MODEL_ID``."""
    path = uri[len("models:/") :]
    parts = path.split("/")
    name = parts[0].rsplit("@", 1)
    if (
        not path
        or len(parts) > 2
        or not parts[0].strip()
        or (len(parts) == 2 and not parts[1].strip())
        or (len(name) == 2 and (not name[0].strip() or not name[1].strip()))
    ):
        raise CLIError(
            f"--model {uri}: malformed models:/ URI; expected models:/NAME/VERSION, models:/NAME/STAGE, "
            "models:/NAME@ALIAS or models:/MODEL_ID (e.g. models:/pidc@champion)"
        )


def _local_store(store: str) -> tuple[Path, str] | None:
    """The file or folder a local MLflow tracking URI names, and which of the two it must be: ``sqlite:///rel.db``
    and ``sqlite:////abs.db`` a database file, ``file:///path`` or a plain path a file store's folder; None for an
    in-memory database (``sqlite://``, ``sqlite:///:memory:``, as ``Path("")``) and for other schemes (a server)."""
    from urllib.parse import unquote, urlparse

    if store.startswith("sqlite:"):
        rest = store[len("sqlite:") :].split("?", 1)[0]
        if not rest.startswith("//"):
            return None
        path = rest[2:]  # "/rel.db" or "//abs.db" (SQLAlchemy's sqlite:/// + path)
        path = path[1:] if path.startswith("/") else path
        return Path(unquote(path)) if path and path != ":memory:" else Path(""), "file"
    parsed = urlparse(store)
    if parsed.scheme == "file":
        return Path(unquote(parsed.path)), "folder"
    if not parsed.scheme or len(parsed.scheme) == 1:  # a plain path (a drive letter is not a scheme)
        return Path(store), "folder"
    return None


def _check_local_store(uri: str, store: str) -> None:
    """A :class:`CLIError` naming ``MLFLOW_TRACKING_URI`` when it names a local store that does not exist: MLflow
    would create an empty one there (a new SQLite file, a new ``mlruns`` folder) and then not find the model."""
    found = _local_store(store)
    if found is None:
        return
    path, kind = found
    if path == Path(""):
        raise CLIError(f"{uri}: MLFLOW_TRACKING_URI={store} is an in-memory store, which holds no registered model")
    if kind == "file" and not path.is_file():
        what = "a folder, not a database file" if path.is_dir() else "no such file"
        raise CLIError(
            f"{uri}: MLFLOW_TRACKING_URI={store}: {path.absolute()}: {what} (pidc does not let MLflow create an empty "
            "store there; set it to the project's store, e.g. sqlite:///mlflow.db in the project folder)"
        )
    if kind == "folder" and not path.is_dir():
        what = "not a folder" if path.exists() else "no such folder"
        raise CLIError(
            f"{uri}: MLFLOW_TRACKING_URI={store}: {path.absolute()}: {what} (pidc does not let MLflow create an empty "
            "store there)"
        )


def _download(uri: str, registry: Path, dest: Path) -> Path:
    """The exported folder of an MLflow registered model ``uri`` (e.g. ``models:/pidc@champion``), downloaded into the
    folder ``dest`` with MLflow's own command line (``mlflow artifacts download``), so that components import no
    MLflow. The tracking store is ``MLFLOW_TRACKING_URI`` or the project's ``mlflow.db`` beside ``registry``; a local
    store (SQLite file, file store folder) must exist, else MLflow would create an empty one (:func:`_check_local_store`)."""
    import os
    import subprocess

    store = os.environ.get("MLFLOW_TRACKING_URI")
    if not store:  # the project's store; MLflow would create an empty one where there is none
        db = registry.resolve().parent / "mlflow.db"
        if not db.is_file():
            raise CLIError(
                f"{uri}: no MLflow store: MLFLOW_TRACKING_URI is not set and there is no {db} beside --registry "
                f"{registry} (run pidc from the project folder, pass --registry PATH, or set MLFLOW_TRACKING_URI)"
            )
        store = f"sqlite:///{db}"
    else:
        _check_local_store(uri, store)
    cmd = [sys.executable, "-m", "mlflow", "artifacts", "download", "--artifact-uri", uri, "--dst-path", str(dest)]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "MLFLOW_TRACKING_URI": store})
    except OSError as e:
        raise CLIError(f"{uri}: could not run `mlflow artifacts download` ({e})") from None
    if r.returncode != 0:
        lines = [line for line in r.stderr.strip().splitlines() if line.strip()]
        last = lines[-1] if lines else "no message"
        if "Not a proper models:/ URI" in last:
            raise CLIError(f"--model {uri}: malformed models:/ URI ({last})")
        raise CLIError(f"{uri}: not found in the MLflow store {store}: {last}")
    folder = dest / "extra_files"
    if not (folder / "card.json").is_file():
        raise CLIError(f"{uri}: not a pidc model (no extra_files/card.json among its files)")
    return folder


def _check_registry(model: str, registry: Path) -> None:
    """A :class:`CLIError` when ``--model`` needs the ``--registry`` folder (``champion`` or a model id: not an
    exported folder) and it does not exist, naming the working directory it was looked for in."""
    if Path(model).is_dir():
        return
    if not registry.exists() and ("/" in model or "\\" in model):  # meant as an exported folder
        raise CLIError(f"--model {model}: no such folder (in {Path.cwd()})")
    if not registry.exists():
        raise CLIError(
            f"--registry {registry}: no such folder (in {Path.cwd()}); run pidc from the project folder or pass "
            "--registry PATH"
        )
    if not registry.is_dir():
        raise CLIError(f"--registry {registry}: not a folder")


def load_model(args: argparse.Namespace) -> Any:
    """The model of ``--model``/``--registry`` (:class:`components.export.lookup.RegisteredPosterior`): a registry
    model (``champion``, a model id, a folder) or an MLflow registered model URI (``models:/pidc@champion``), whose
    download is removed once the model is loaded (its ONNX sessions are in memory by then)."""
    import tempfile

    from components.export.lookup import load_registered

    model = str(args.model)
    if not model.strip():
        raise CLIError("--model is empty; give champion, a model id, an exported folder or a models:/ URI")
    try:
        if model.startswith("models:/"):
            _check_models_uri(model)
            with tempfile.TemporaryDirectory(prefix="pidc-model-") as dest:
                return load_registered(_download(model, Path(args.registry), Path(dest)))
        _check_registry(model, Path(args.registry))
        return load_registered(model, args.registry)
    except (FileNotFoundError, ValueError) as e:
        raise CLIError(str(e)) from None


def list_paths(paths: Sequence[str | Path]) -> list[Path]:
    from components.core.images import ImageError, list_images

    try:
        return list_images(paths)
    except ImageError as e:
        raise CLIError(str(e)) from None


def progress(total: int, desc: str) -> Any:
    """A tqdm bar on stderr over ``total`` images (shown on a terminal and for more than one image)."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="image", file=sys.stderr, disable=True if total < 2 else None)


def say(bar: Any, text: str, err: bool = False) -> None:
    """Print ``text`` without breaking the progress bar."""
    bar.write(text, file=sys.stderr if err else sys.stdout)


@dataclass(frozen=True)
class Read:
    """Posterior inputs of readable images: ``paths[i]``, ``notes[i]`` and ``x[i]`` (the model's input)."""

    paths: list[Path]
    notes: list[str | None]
    x: np.ndarray


#: The kinds of the reader's notes (:func:`components.core.images.read_image`), by how a note begins: what a command
#: counts per kind when it sums up many images' notes, and the keys of ``notes`` in the ``--json`` reports.
_NOTE_KINDS: tuple[tuple[re.Pattern[str], str], ...] = (
    (re.compile(r"grayscale → RGB"), "grayscale → RGB"),
    (re.compile(r"black-and-white → RGB"), "black-and-white → RGB"),
    (re.compile(r"(\d+)-bit grayscale"), r"\1-bit grayscale → RGB"),
    (re.compile(r"16-bit RGB"), "16-bit RGB → 8 bits"),
    (re.compile(r"alpha channel dropped"), "alpha channel dropped"),
    (re.compile(r"palette image expanded"), "palette → RGB"),
    (re.compile(r"rotated/flipped"), "EXIF rotation"),
    (re.compile(r"first of \d+ frames"), "first of several frames"),
    (re.compile(r"very small"), "very small"),
    (re.compile(r"only \d+ pixels"), "a side under 32 pixels"),
    (re.compile(r"not square"), "not square"),
    (re.compile(r"squashed"), "squashed"),
    (re.compile(r"resized: "), "resized"),
    (re.compile(r"taken as a frame already shrunk"), "taken as already shrunk"),
    (re.compile(r"converted from"), "other pixel format → RGB"),
    (re.compile(r"gray in every pixel"), "gray in every pixel"),
    (re.compile(r"no colour: "), "no colour"),
)
#: The kinds of images without colour: the reader copies their gray level to red, green and blue, or the file holds
#: equal red, green and blue in every pixel (a grayscale picture stored as colour; no render of the renderer does).
COLOURLESS = re.compile(r"(\d+-bit )?grayscale → RGB|black-and-white → RGB|gray in every pixel")
#: The note of an RGB file whose every pixel is gray (:func:`_gray`).
GRAY_NOTE = "gray in every pixel (red = green = blue: a grayscale picture stored as colour)"
#: At most this many images' notes are said one line each by ``domain`` and ``relate``; more, a line per kind.
NOTE_LINES = 5
#: Files named per kind when notes are summed up (and then "and N more").
NOTE_EXAMPLES = 3


def _note_kind(text: str) -> str:
    """The kind of one note (:data:`_NOTE_KINDS`); an unknown one is its own text up to its details."""
    for pattern, kind in _NOTE_KINDS:
        if m := pattern.match(text):
            return m.expand(kind)
    return re.split(r" \(|: ", text, maxsplit=1)[0]


def _colourless_caveat(model: Any, n: int, total: int, kinds: list[str]) -> str:
    """What the posteriors of ``n`` of ``total`` images without colour (grayscale, black-and-white, gray in every
    pixel: the ``kinds``) are worth."""
    return (
        f"{n} of {count(total, 'image')} {'has' if n == 1 else 'have'} no colour ({', '.join(kinds)}: red, green and "
        f"blue equal in every pixel): {model.name} learned from colour renders, and the calibration measured in "
        "the pipeline does not cover images without colour, whose posteriors can be far off and confident (a "
        "grayscale copy of a clear-noon render of cloudiness 5 % got cloudiness 98 % [97, 100] from the default "
        "profile's cues-50000); use colour images"
    )


@dataclass
class ReadLog:
    """What reading a command's images said: the images skipped (path, reason), each image's notes by kind
    (:data:`_NOTE_KINDS`), the sizes of the images taken, and the caveats said once per command (``finished``). Shared by
    the :func:`read_batches` calls of one command (e.g. relate's folders); :meth:`finish` sums it up on stderr,
    :meth:`to_json` for ``--json``."""

    command: str
    skipped: list[tuple[str, str]] = field(default_factory=list)
    notes: dict[str, list[str]] = field(default_factory=dict)
    image_notes: dict[str, str] = field(default_factory=dict)
    sizes: set[tuple[int, int]] = field(default_factory=set)
    converted: bool = False
    taken: int = 0
    finished: bool = False
    caveats: dict[str, dict[str, Any]] = field(default_factory=dict)

    def skip(self, path: Path, reason: str) -> None:
        self.skipped.append((str(path), reason))

    def take(self, path: Path, pieces: list[str]) -> None:
        self.taken += 1
        if pieces:
            self.image_notes[str(path)] = "; ".join(pieces)
        for kind in dict.fromkeys(map(_note_kind, pieces)):
            self.notes.setdefault(kind, []).append(str(path))

    def finish(self, model: Any, each: bool) -> None:
        """The caveats of the images taken (once per command), said on stderr after the images' notes when ``each``
        (``domain`` and ``relate``, whose output names no image): one line per image for up to :data:`NOTE_LINES`
        images, else a count per kind and the first files. The resize caveat names every size outside the model's
        (:func:`_resize_caveat`); images without colour get :func:`_colourless_caveat`, naming how many."""
        if self.finished:
            return
        self.finished = True
        if each and self.image_notes:
            lines = [f"{path}: {note}" for path, note in self.image_notes.items()]
            if len(lines) > NOTE_LINES:
                lines = [
                    f"{kind}: {count(len(files), 'image')} ("
                    + ", ".join(files[:NOTE_EXAMPLES])
                    + (f" and {len(files) - NOTE_EXAMPLES} more" if len(files) > NOTE_EXAMPLES else "")
                    + ")"
                    for kind, files in self.notes.items()
                ]
            for line in lines:
                print(f"pidc {self.command}: note: {line}", file=sys.stderr)
        if self.sizes and (caveat := _resize_caveat(model, self.sizes, self.converted)):
            files = list(
                dict.fromkeys(f for k in ("resized", "taken as already shrunk") for f in self.notes.get(k, []))
            )
            self.caveats["resized"] = {"count": len(files), "images": files, "text": caveat}
        kinds = [kind for kind in self.notes if COLOURLESS.fullmatch(kind)]
        if kinds:
            files = list(dict.fromkeys(f for kind in kinds for f in self.notes[kind]))
            caveat = _colourless_caveat(model, len(files), self.taken, kinds)
            self.caveats["colourless"] = {"count": len(files), "images": files, "text": caveat}
        for item in self.caveats.values():
            print(f"pidc {self.command}: note: {item['text']}", file=sys.stderr)

    def to_json(self) -> dict[str, Any]:
        """``skipped`` (how many), ``skipped_images`` (path and reason each), ``notes`` (per kind: how many and which
        images) and ``caveats`` (per caveat: how many images, which, and its text)."""
        return {
            "skipped": len(self.skipped),
            "skipped_images": [{"image": path, "reason": reason} for path, reason in self.skipped],
            "notes": {kind: {"count": len(files), "images": files} for kind, files in self.notes.items()},
            "caveats": [{"kind": kind, **item} for kind, item in self.caveats.items()],
        }


def _outside(model: Any, sizes: set[tuple[int, int]], converted: bool) -> list[tuple[int, int]]:
    """The sizes (H, W) among ``sizes`` the model did not learn from (the card's ``training_renders``); for a card
    that does not name them (exported before pidc recorded it), those its backbone converts (another size than its
    input, or all when it does not say its input size and ``converted``)."""
    if model.training_renders:
        return sorted(s for s in sizes if not model.learned_size(s))
    size = getattr(model.backbone, "input_size", None)
    if size:
        return sorted(s for s in sizes if tuple(s) != tuple(size))
    return sorted(sizes) if converted else []


def _resize_caveat(model: Any, sizes: set[tuple[int, int]], converted: bool) -> str | None:
    """What a posterior of a resized image is worth, for images of ``sizes`` (H, W): a note when a size is not one the
    model learned from (:func:`_outside`); for a model of resized renders (``simulator.render_sizes``), also when
    images come at its input size, which it takes as frames already shrunk; None otherwise."""
    renders = model.training_renders
    other = _outside(model, sizes, converted)
    shown = ", ".join(f"{w}×{h}" for h, w in other[:3]) + (" …" if len(other) > 3 else "")
    if renders is not None and renders[2] is not None:  # a model of resized renders
        notes = [f"images of {shown} are outside them"] if other else []
        if renders[:2] in sizes:
            notes.append(
                f"images of {renders[1]}×{renders[0]} are taken as frames already shrunk to it, not as the renderer's "
                "own renders of that size"
            )
        if not notes:
            return None
        return (
            f"{model.name} learned from {model.learned_from}; {'; '.join(notes)}: the calibration measured in the "
            "pipeline covers only what it learned (docs/studies/camera-renders.md)"
        )
    if not other:
        return None
    learned = model.learned_from or "renders of a size its card does not name (re-export it)"
    return (
        f"{model.name} learned from {learned}; images of {shown} are area-resized, and the calibration measured in "
        "the pipeline does not cover them: the simulator's own renders made larger and resized gave overconfident "
        "posteriors (docs/studies/other-resolutions.md)"
    )


def _size_notes(model: Any, sizes: set[tuple[int, int]], converted: bool) -> dict[tuple[int, int], str]:
    """Each image's own part of :func:`_resize_caveat`, by size (H, W): ``resized: …`` for a size the model did not
    learn from, ``taken as a frame already shrunk …`` for the input size of a model of resized renders."""
    renders = model.training_renders
    learned = model.learned_from
    out: dict[tuple[int, int], str] = {}
    for h, w in _outside(model, sizes, converted):
        out[(h, w)] = (
            f"resized: {w}×{h} is not a size {model.name} learned from ({learned}): outside the calibration measured "
            "in the pipeline"
            if learned
            else f"resized: {w}×{h} area-resized to the backbone's input; {model.name}'s card does not name the "
            "size it learned from (re-export it)"
        )
    if renders is not None and renders[2] is not None and renders[:2] in sizes:
        h, w = renders[:2]
        out[(h, w)] = f"taken as a frame already shrunk to {w}×{h}, not as the renderer's own render of that size"
    return out


#: The backbone's one-time size note names sizes as H×W; the CLI's notes name them W×H, as image viewers and
#: :func:`components.core.images.read_image`'s notes do.
_CONVERTING = re.compile(r"converting (\d+)×(\d+) images to its input size (\d+)×(\d+)")
#: An image whose width:height differs this many times from the backbone's input's is said to be squashed: beyond the
#: 16:9 (1.8) and 2:1 of camera frames and panoramas of a few views, a resize to the input distorts what the
#: features see (a 2000×10 strip becomes 128 rows of 10 stretched ones).
SQUASH_RATIO = 3.0


def _width_first(message: str) -> str:
    """The backbone's "converting H×W images to its input size H×W" note with its sizes as width×height."""
    return _CONVERTING.sub(
        lambda m: f"converting {m[2]}×{m[1]} images (width×height) to its input size {m[4]}×{m[3]}", message
    )


def _model_inputs(model: Any, images: list[np.ndarray]) -> tuple[np.ndarray | None, dict[int, str]]:
    """The model's inputs of ``images`` (one batch per size), leaving out those no backbone takes (a side below
    :data:`~components.features.backbones.imageops.MIN_SIDE` pixels) and any size its backbone refuses: → (the inputs
    of the others, in order; None when none is left, {index: reason})."""
    from components.core.images import group_by_size
    from components.features.backbones.imageops import MIN_SIDE

    rows: dict[int, np.ndarray] = {}
    refused: dict[int, str] = {}
    for idx, batch in group_by_size(images):
        h, w = batch.shape[1:3]
        if min(h, w) < MIN_SIDE:
            refused.update(dict.fromkeys(idx, f"{w}×{h} pixels; no backbone takes images under {MIN_SIDE}×{MIN_SIDE}"))
            continue
        try:
            y = np.asarray(model.inputs(batch))
        except ValueError as e:  # the backbone's own check of the batch
            refused.update(dict.fromkeys(idx, f"{w}×{h} pixels; model {model.name} cannot take it ({e})"))
            continue
        rows.update(zip(idx, y, strict=True))
    if not rows:
        return None, refused
    return np.stack([rows[i] for i in sorted(rows)]), refused


def _inputs(
    model: Any, images: list[np.ndarray], bar: Any, command: str
) -> tuple[np.ndarray | None, dict[int, str], bool]:
    """uint8 images of any sizes → the model's inputs ``x (n, …)`` of those its backbone takes, in order, the
    reasons of those it refuses, by index (:func:`_model_inputs`), and whether the backbone said it converts them.

    The backbone's one-time "converting images" warning becomes a ``note:`` line on stderr (sizes as width×height).
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        out, refused = _model_inputs(model, images)
    for message in dict.fromkeys(str(w.message) for w in caught):
        say(bar, f"pidc {command}: note: {_width_first(message)}", err=True)
    return out, refused, bool(caught)


def _squash_note(model: Any, image: np.ndarray) -> str | None:
    """A note when the backbone's resize changes the image's aspect ratio :data:`SQUASH_RATIO` times or more."""
    size = getattr(model.backbone, "input_size", None)
    if not size:
        return None
    h, w = image.shape[:2]
    ratio = (w / h) / (size[1] / size[0])
    factor = max(ratio, 1.0 / ratio)
    if factor < SQUASH_RATIO:
        return None
    return (
        f"squashed: the resize to the backbone's {size[1]}×{size[0]} input changes its aspect ratio {factor:.0f}-fold"
    )


def _read_one(path: Path, bar: Any, command: str) -> tuple[np.ndarray, str | None]:
    """:func:`components.core.images.read_image` of ``path``, refusing what is not a regular file (a FIFO would block
    the read forever); the reader's library warnings (e.g. Pillow's DecompressionBombWarning) become ``note:`` lines.
    Raises :class:`components.core.images.ImageError`."""
    import stat

    from components.core.images import ImageError, read_image

    if path.exists() and not path.is_file() and not path.is_dir():
        kind = "a named pipe (FIFO)" if stat.S_ISFIFO(path.stat().st_mode) else "a device or socket"
        raise ImageError(f"{path}: not a regular file ({kind})")
    with warnings.catch_warnings(record=True) as caught:  # each file's own (deprecations stay filtered as usual)
        warnings.simplefilter("always", UserWarning)
        warnings.simplefilter("always", RuntimeWarning)
        out = read_image(path)
    for message in dict.fromkeys(str(w.message) for w in caught):
        say(bar, f"pidc {command}: note: {path}: {message}", err=True)
    return out


def _reason(path: Path, message: str) -> str:
    """An :class:`~components.core.images.ImageError`'s message without the path it begins with."""
    return message[len(f"{path}: ") :] if message.startswith(f"{path}: ") else message


def _gray(image: np.ndarray) -> bool:
    """Whether ``image`` ``(H, W, 3)`` has red = green = blue in every pixel. Exact equality: the renders' darkest,
    foggiest nights still differ by 2–3 levels somewhere (measured on the default profile's 8 000 test and validation
    images), and a gray picture stays exactly gray through JPEG."""
    return np.array_equal(image[..., 0], image[..., 1]) and np.array_equal(image[..., 1], image[..., 2])


def _colour_note(model: Any) -> str:
    return f"no colour: outside the calibration ({model.name} learned from colour renders)"


def read_batches(
    model: Any, paths: list[Path], command: str, desc: str, log: ReadLog | None = None
) -> Iterator[tuple[Read, Any]]:
    """Read ``paths`` in batches of :data:`READ_BATCH`: yields the readable ones' inputs (and the progress bar).

    Bad files (unreadable, not a regular file, or of a size the model's backbone refuses) are reported on stderr
    (``pidc <command>: skipped <path>: <reason>``) and left out. Each image's notes (the reader's conversions, a
    squash, a size the model did not learn, no colour) are in :attr:`Read.notes`; the skips, the notes and the sizes
    are recorded in ``log`` (shared by the calls of one command; a new one when None), which
    :meth:`ReadLog.finish` sums up.
    """
    from components.core.images import ImageError

    log = ReadLog(command) if log is None else log

    with progress(len(paths), desc) as bar:
        for start in range(0, len(paths), READ_BATCH):
            good: list[Path] = []
            notes: list[list[str]] = []
            images: list[np.ndarray] = []
            for path in paths[start : start + READ_BATCH]:
                try:
                    image, note = _read_one(path, bar, command)
                except ImageError as e:
                    say(bar, f"pidc {command}: skipped {e}", err=True)
                    log.skip(path, _reason(path, str(e)))
                else:
                    pieces = note.split("; ") if note else []
                    colourless = any(COLOURLESS.fullmatch(_note_kind(p)) for p in pieces)
                    if not colourless and _gray(image):  # a grayscale picture stored as colour
                        pieces.append(GRAY_NOTE)
                        colourless = True
                    if colourless:
                        pieces.append(_colour_note(model))
                    if squash := _squash_note(model, image):
                        pieces.append(squash)
                    good.append(path)
                    notes.append(pieces)
                    images.append(image)
                bar.update(1)
            if not good:
                continue
            x, refused, converted = _inputs(model, images, bar, command)
            for i, reason in refused.items():
                say(bar, f"pidc {command}: skipped {good[i]}: {reason}", err=True)
                log.skip(good[i], reason)
            if x is not None:
                keep = [i for i in range(len(good)) if i not in refused]
                sizes = {images[i].shape[:2] for i in keep}
                by_size = _size_notes(model, sizes, converted)
                for i in keep:
                    if size_note := by_size.get(images[i].shape[:2]):
                        notes[i].append(size_note)
                    log.take(good[i], notes[i])
                log.sizes |= sizes
                log.converted |= converted
                yield Read([good[i] for i in keep], ["; ".join(notes[i]) or None for i in keep], x), bar


def none_read(n: int, whose: str = "the") -> str:
    """``none of the 3 images could be read``; for one image ``the only image could not be read``."""
    return f"{whose} only image could not be read" if n == 1 else f"none of {whose} {n} images could be read"


def read_all(model: Any, paths: list[Path], command: str, desc: str, folder: Path, log: ReadLog | None = None) -> Read:
    """All readable images' inputs at once (the bag of a domain); CLIError naming ``folder`` when none is readable."""
    parts = [read for read, _ in read_batches(model, paths, command, desc, log)]
    if not parts:
        raise CLIError(f"{folder}: {none_read(len(paths), 'its')}")
    return Read(
        [p for r in parts for p in r.paths], [n for r in parts for n in r.notes], np.concatenate([r.x for r in parts])
    )


def count(n: int, word: str) -> str:
    """``n`` and ``word``, plural unless n is 1: ``1 image``, ``3 images``."""
    return f"{n} {word}{'' if n == 1 else 's'}"


#: Figure types matplotlib writes that pidc does not offer: PGF is LaTeX source that matplotlib typesets with a LaTeX
#: engine (xelatex) to measure the text, which fails, after all the work, where none is installed.
_FIGURE_TYPES_LEFT_OUT = frozenset({"pgf"})


def figure_suffixes() -> list[str]:
    """The figure file suffixes the commands write (matplotlib's Agg types but :data:`_FIGURE_TYPES_LEFT_OUT`)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    return [f".{t}" for t in FigureCanvasAgg.get_supported_filetypes() if t not in _FIGURE_TYPES_LEFT_OUT]


def check_figure_path(path: Path | None, option: str = "--corner") -> None:
    """A figure file name whose type pidc writes (:func:`figure_suffixes`: PNG, PDF, SVG, …), else a one-line error
    naming ``option`` and the suffixes it takes."""
    if path is None:
        return
    suffixes = figure_suffixes()
    if path.suffix.lower() in suffixes:
        return
    known = ", ".join(suffixes)
    if path.suffix.lstrip(".").lower() in _FIGURE_TYPES_LEFT_OUT:
        raise CLIError(
            f"{option} {path}: {path.suffix} (PGF, LaTeX source) needs a LaTeX engine, which pidc does not use; "
            f"use one of {known}"
        )
    raise CLIError(f"{option} {path}: unknown image type {path.suffix!r}; use one of {known}")


def save_corner(draws: np.ndarray, box: Any, title: str, path: Path) -> None:
    from components.plots import corner_plot, save_figure

    save_figure(corner_plot(draws, box=box, title=title), path)


def check_samples(value: int) -> int:
    """``--samples``, at least :data:`MIN_SAMPLES`."""
    if value < MIN_SAMPLES:
        raise CLIError(
            f"--samples must be at least {MIN_SAMPLES} for a 68.27 % HDI that rests on more than a handful of draws, "
            f"got {value}"
        )
    return value


def check_json_path(path: Path | None) -> None:
    if path is not None and path.suffix.lower() != ".json":
        raise CLIError(f"--json {path}: expected a .json file name")


def write_json(path: Path, report: dict) -> None:
    """``report`` as indented JSON at ``path`` (atomically; its folder made), and a line on stderr saying so."""
    atomic_write_bytes(path, (json.dumps(report, indent=1) + "\n").encode())
    print(f"wrote {path}", file=sys.stderr)


def check_seed(value: int) -> int:
    if value < 0:
        raise CLIError(f"--seed must be a non-negative integer, got {value}")
    return value


def check_folder(path: Path, command: str) -> Path:
    """``path`` when it is a folder, else a :class:`CLIError` saying whether it is missing or not a folder."""
    if not path.exists():
        raise CLIError(f"{path}: no such folder")
    if not path.is_dir():
        raise CLIError(f"{path}: not a folder (pidc {command} reads the images of a folder)")
    return path


def folder_name(path: Path) -> str:
    """The name of the folder ``path``, also when it is given as ``.`` or ``..`` (the resolved folder's name; the
    path itself for the root)."""
    if path.name not in ("", ".", ".."):
        return path.name
    resolved = path.resolve()
    return resolved.name or str(resolved)


def check_inputs(paths: Sequence[str | Path]) -> None:
    """A :class:`CLIError` naming the first of ``paths`` (files or folders given on the command line) that does not
    exist, before any work (a broken link said as such)."""
    for given in paths:
        path = Path(given)
        if path.exists():
            continue
        if path.is_symlink():
            raise CLIError(f"{given}: a broken link (its target {path.readlink()} does not exist)")
        what = "folder" if str(given).endswith(("/", "\\")) else "file or folder"
        raise CLIError(f"{given}: no such {what}")


#: ``--min-ess``'s default: the fewest effective draws an image's reweighted posterior may rest on, as
#: :data:`MIN_SAMPLES` is for plain draws (a 68.27 % HDI's ends are ~16 effective draws a side at 100).
MIN_ESS = 100


def check_prior(args: argparse.Namespace, proposals: int, option: str) -> float | None:
    """``--min-ess`` (default :data:`MIN_ESS`; positive and at most the ``proposals`` draws per image that ``option``
    sets, since the ESS of m draws is at most m) once ``--prior`` is checked to be a file, before any work; None
    without ``--prior`` (and then ``--min-ess`` or ``--prior-draws`` is an error)."""
    if args.prior is None:
        for name, value in (("--min-ess", args.min_ess), ("--prior-draws", getattr(args, "prior_draws", None))):
            if value is not None:
                raise CLIError(f"{name} applies with --prior FILE only")
        return None
    path = Path(args.prior)
    if not path.is_file():
        raise CLIError(f"--prior {path}: {'not a file' if path.exists() else 'no such file'}")
    min_ess = float(MIN_ESS if args.min_ess is None else args.min_ess)
    if not (0 < min_ess <= proposals):
        raise CLIError(
            f"--min-ess must be in (0, {proposals}] (the effective sample size of {proposals} draws per image, "
            f"{option}, is at most {proposals}), got {min_ess:g}"
        )
    return min_ess


@dataclass(frozen=True)
class UserPriorSetup:
    """A command's ``--prior``: the user's prior (:class:`components.domains.prior.UserPrior`) on the model's
    training box ``train``, and ``option``, the option that sets the draws per image (for the ESS error)."""

    path: Path
    prior: Any
    train: Any
    min_ess: float
    option: str


def load_prior(args: argparse.Namespace, model: Any, min_ess: float | None, option: str) -> UserPriorSetup | None:
    """The ``--prior`` file read on ``model``'s training prior (its card's box; :func:`components.domains.prior.
    training_prior`), None without ``--prior``: a one-line :class:`CLIError` naming the file, the parameter and the
    problem."""
    if args.prior is None or min_ess is None:
        return None
    from components.domains.prior import PriorError, read_prior, training_prior

    try:
        train = training_prior(model.posterior.card, str(model.folder / "card.json"))
        prior = read_prior(args.prior, train)
    except PriorError as e:
        raise CLIError(f"--prior {e}") from None
    return UserPriorSetup(Path(args.prior), prior, train, min_ess, option)


def reweighted(
    setup: UserPriorSetup,
    posterior: Any,
    reads: Sequence[tuple[Sequence[Path], np.ndarray]],
    proposals: int,
    seed: int,
    desc: str,
) -> tuple[Any, np.ndarray]:
    """The posterior under the user's prior (:class:`components.domains.prior.ReweightedPosterior`) prepared on the
    images of ``reads`` (their paths and inputs), and each image's ESS; every command reweights here. A
    :class:`CLIError` names the image of lowest ESS when it is below ``--min-ess``."""
    from components.domains.prior import ReweightedPosterior

    found = ReweightedPosterior(posterior, setup.prior, setup.train, proposals)
    paths = [p for ps, _ in reads for p in ps]
    parts = []
    with progress(len(paths), f"{desc}: reweighting to {setup.path.name}") as bar:
        for _, x in reads:
            for start in range(0, len(x), READ_BATCH):
                chunk = x[start : start + READ_BATCH]
                parts.append(found.prepare(chunk, seed))
                bar.update(len(chunk))
    ess = np.concatenate(parts)
    below = np.flatnonzero(ess < setup.min_ess)
    if below.size:
        worst = int(below[np.argmin(ess[below])])
        others = (
            f" ({below.size} of {count(len(ess), 'image')} are below it; this is the lowest)" if below.size > 1 else ""
        )
        if ess[worst] == 0:
            raise CLIError(
                f"{paths[worst]}: no posterior draw of this image has a positive density under --prior {setup.path} "
                f"(effective sample size 0 of {proposals} draws){others}: the prior rules out the weather the image "
                "shows; widen the prior"
            )
        need = math.ceil(proposals * setup.min_ess / ess[worst])
        raise CLIError(
            f"{paths[worst]}: effective sample size {ess[worst]:.1f} of {proposals} draws under --prior {setup.path} "
            f"is below --min-ess {setup.min_ess:g}{others}: the prior puts its weight on few of the image's posterior "
            f"draws; use more {setup.option} (about {need}) or a prior that agrees with the image"
        )
    return found, ess


def prior_line(setup: UserPriorSetup, ess: np.ndarray, proposals: int) -> str:
    """``prior FILE: ESS per image min …, median … of m draws`` (the line every command prints)."""
    return (
        f"prior {setup.path} (importance weights from the training prior, uniform on the model's box): effective "
        f"sample size per image min {np.min(ess):.1f}, median {np.median(ess):.1f} of {proposals} draws"
    )


def prior_json(setup: UserPriorSetup, ess: np.ndarray, proposals: int) -> dict[str, Any]:
    """The ``prior`` entry of ``--json``: the file, its densities, the draws per image, ``--min-ess`` and the ESS."""
    from components.domains.prior import ess_summary

    return {
        "prior": {
            "file": str(setup.path),
            "parameters": setup.prior.describe(),
            "training_prior": "uniform on the model's box: "
            + ", ".join(
                f"{n} [{lo:g}, {hi:g}]"
                for n, lo, hi in zip(setup.train.names, setup.train.low, setup.train.high, strict=True)
            ),
            "draws_per_image": proposals,
            "min_ess": setup.min_ess,
            "ess": {"images": len(ess), **ess_summary(ess)},
        }
    }
