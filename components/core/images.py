"""Image files → the uint8 RGB arrays pidc's backbones take, with one clear line for every file that cannot be used.

:func:`read_image` reads one file with Pillow (PNG, JPEG, BMP, TIFF, WebP, GIF, PPM, …) and returns an ``(H, W, 3)``
uint8 RGB array plus a *note* saying what was converted (grayscale → RGB, alpha dropped, palette expanded, 16 → 8 bits,
EXIF rotation, first frame of many, very small or not square). Files that cannot be used (missing, empty, truncated,
not an image, unsupported pixel format) raise :class:`ImageError`, whose one-line message names the file and the
reason. :func:`list_images` expands folders (image extensions only, natural sort order so ``frame_2`` comes before
``frame_10``), :func:`iter_images` reads a list and keeps going past bad files, and :func:`group_by_size` stacks
images of equal size into the ``(n, H, W, 3)`` batches a backbone takes (it resizes each batch to its input size).

Used by the ``pidc`` CLI (``characterize``, ``domain``, ``relate``), the scheduled monitoring's recorded images
(:mod:`components.monitor.recorded`) and the ``generate`` stage's import of recorded folders
(:mod:`components.simulate.recorded`); no other DVC stage reads users' images. :func:`render_shape` (the shape of a render
of another height) serves the resized renders (:mod:`components.simulate.resized`) and the model cards that name them.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

__all__ = [
    "IMAGE_EXTENSIONS",
    "SMALL_SIDE",
    "RENDER_SIDES",
    "ImageError",
    "ImageItem",
    "read_image",
    "list_images",
    "iter_images",
    "group_by_size",
    "render_shape",
    "map_by_size",
]

#: File extensions (lower case) taken from a folder; a file named explicitly is read whatever its extension.
IMAGE_EXTENSIONS: frozenset[str] = frozenset(
    {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".gif", ".ppm", ".pgm", ".pnm"}
)
_EXIF_ORIENTATION = 0x0112
#: Images with a side below this many pixels get a note (features of such images are unreliable).
SMALL_SIDE: int = 32
#: The sides (height and width, pixels) the procedural renderer draws, smallest and largest: its own check, the
#: params' ``simulator`` sizes and ``pidc render``'s options.
RENDER_SIDES: tuple[int, int] = (16, 2048)

_SIGNATURES: tuple[tuple[bytes, str], ...] = (
    (b"\x89PNG\r\n\x1a\n", "PNG"),
    (b"\xff\xd8\xff", "JPEG"),
    (b"GIF8", "GIF"),
    (b"BM", "BMP"),
    (b"II*\x00", "TIFF"),
    (b"MM\x00*", "TIFF"),
)


class ImageError(ValueError):
    """A file that cannot be used as an image; the message is one line: ``<path>: <reason>``."""


class ImageItem(NamedTuple):
    """One entry of :func:`iter_images`: ``image`` ``(H, W, 3)`` uint8 and ``note``, or ``error`` (image None)."""

    path: Path
    image: np.ndarray | None
    note: str | None
    error: ImageError | None

    @property
    def ok(self) -> bool:
        return self.error is None


def _diagnose(path: Path, reason: str) -> str:
    """A better reason for a file Pillow cannot identify: empty, or a known format with a damaged/zero-size header."""
    with open(path, "rb") as f:
        head = f.read(32)
    if not head:
        return "empty file (0 bytes)"
    for signature, name in _SIGNATURES:
        if head.startswith(signature):
            if name == "PNG" and head[12:16] == b"IHDR":
                width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
                if width == 0 or height == 0:
                    return f"zero-size PNG image ({width}×{height} pixels)"
            return f"damaged {name} file ({reason})"
    return f"not an image file, or a format Pillow cannot read ({reason})"


def _to_8bit(a: np.ndarray, mode: str, path: Path) -> np.ndarray:
    """Integer pixels of 16 (or up to 16) significant bits → uint8 by v·255/65535, rounded."""
    if a.dtype.kind == "f":
        raise ImageError(f"{path}: floating-point pixels (mode {mode}) are not supported; save it as 8-bit RGB")
    if a.size and (a.min() < 0 or a.max() > 65535):
        raise ImageError(f"{path}: {mode} pixels outside 0–65535 are not supported; save it as 8-bit RGB")
    return np.rint(a.astype(np.float64) * (255.0 / 65535.0)).astype(np.uint8)


def read_image(path: str | Path) -> tuple[np.ndarray, str | None]:
    """Read one image file as RGB.

    Returns:
        ``(image, note)``: ``image`` uint8 ``(H, W, 3)`` RGB; ``note`` a short text of the conversions done (``;``
        separated), or None when the file was plain 8-bit RGB of a usual size.

    Raises:
        ImageError: the file is missing, a folder, empty, truncated, not an image, of size zero, or has a pixel
            format pidc cannot convert (floating point); the message names the file and the reason.
    """
    from PIL import Image, ImageOps, UnidentifiedImageError

    path = Path(path)
    if not path.exists():
        raise ImageError(f"{path}: no such file")
    if path.is_dir():
        raise ImageError(f"{path}: is a folder, not an image file")
    notes: list[str] = []
    try:
        with Image.open(path) as im:
            frames = int(getattr(im, "n_frames", 1) or 1)
            rawmodes = {str(t.args) for t in (im.tile or [])}
            im.load()
            if frames > 1:
                notes.append(f"first of {frames} frames")
            if im.getexif().get(_EXIF_ORIENTATION, 1) not in (0, 1):
                im = ImageOps.exif_transpose(im)
                notes.append("rotated/flipped as its EXIF orientation says")
            image = _as_rgb(im, rawmodes, path, notes)
    except UnidentifiedImageError:
        raise ImageError(f"{path}: {_diagnose(path, 'cannot identify image file')}") from None
    except Image.DecompressionBombError as e:
        raise ImageError(f"{path}: too many pixels to read safely ({e})") from None
    except ImageError:
        raise
    except (OSError, SyntaxError, ValueError, EOFError) as e:
        reason = str(e).strip() or type(e).__name__
        raise ImageError(f"{path}: unreadable image ({reason})") from None
    h, w = image.shape[:2]
    if h == 0 or w == 0:
        raise ImageError(f"{path}: zero-size image ({w}×{h} pixels)")
    if max(h, w) < SMALL_SIDE:
        notes.append(f"very small ({w}×{h} pixels)")
    elif min(h, w) < SMALL_SIDE:
        side = "high" if h < w else "wide"
        notes.append(f"only {min(h, w)} pixels {side} ({w}×{h} pixels): the backbone stretches it to its square input")
    elif h != w:
        notes.append(f"not square ({w}×{h} pixels): the backbone resizes it to its square input")
    return image, ("; ".join(notes) or None)


def _as_rgb(im, rawmodes: set[str], path: Path, notes: list[str]) -> np.ndarray:
    """A loaded Pillow image → uint8 ``(H, W, 3)`` RGB, appending to ``notes`` what was converted."""
    mode = im.mode
    if mode == "RGB":
        if any(";16" in r for r in rawmodes):
            notes.append("16-bit RGB reduced to 8 bits")
        return np.asarray(im, dtype=np.uint8)
    if mode in ("RGBA", "RGBa", "LA", "La", "PA") or (mode == "P" and "transparency" in im.info):
        notes.append(f"alpha channel dropped ({mode} → RGB)")
        rgb = im.convert("RGBA") if mode in ("P", "PA") else im
        return np.asarray(rgb.convert("RGB"), dtype=np.uint8)
    if mode == "P":
        notes.append("palette image expanded to RGB")
        return np.asarray(im.convert("RGB"), dtype=np.uint8)
    if mode in ("L", "1"):
        notes.append("grayscale → RGB" if mode == "L" else "black-and-white → RGB")
        return np.repeat(np.asarray(im.convert("L"), dtype=np.uint8)[:, :, None], 3, axis=2)
    if mode.startswith("I") or mode == "F":
        gray = np.asarray(im)
        bits = 16 if mode.startswith("I;16") or any(";16" in r for r in rawmodes) else 32
        notes.append(f"{bits}-bit grayscale scaled to 8 bits (v·255/65535), → RGB")
        return np.repeat(_to_8bit(gray, mode, path)[:, :, None], 3, axis=2)
    notes.append(f"converted from {mode} to RGB")
    return np.asarray(im.convert("RGB"), dtype=np.uint8)


_DIGITS = re.compile(r"(\d+)")


def _natural_key(path: Path) -> list[object]:
    """Sort key comparing digit runs as numbers: ``img2`` < ``img10``; ties broken by the plain name."""
    parts = _DIGITS.split(path.name.lower())
    return [(0, int(p), "") if p.isdigit() else (1, 0, p) for p in parts] + [(2, 0, path.name)]


def list_images(paths: str | Path | Iterable[str | Path]) -> list[Path]:
    """Expand files and folders into the list of image files to read, in order.

    A folder contributes its image files (extensions :data:`IMAGE_EXTENSIONS`, any case; hidden files skipped; not
    recursive) in natural sort order; a file (or a path that does not exist) is kept as given, so reading it reports
    the problem. Raises :class:`ImageError` for a folder without image files.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = [
                f
                for f in p.iterdir()
                if f.is_file() and not f.name.startswith(".") and f.suffix.lower() in IMAGE_EXTENSIONS
            ]
            if not found:
                raise ImageError(f"{p}: no image files in this folder ({', '.join(sorted(IMAGE_EXTENSIONS))})")
            out.extend(sorted(found, key=_natural_key))
        else:
            out.append(p)
    return out


def iter_images(paths: str | Path | Iterable[str | Path]) -> Iterator[ImageItem]:
    """Read the images of :func:`list_images` one by one, yielding an :class:`ImageItem` per file, bad ones included.

    Folders are expanded up front (an empty folder raises :class:`ImageError` before anything is read).
    """
    for path in list_images(paths):
        try:
            image, note = read_image(path)
        except ImageError as e:
            yield ImageItem(path, None, None, e)
        else:
            yield ImageItem(path, image, note, None)


def group_by_size(images: Sequence[np.ndarray]) -> list[tuple[list[int], np.ndarray]]:
    """Stack images of equal size: → ``[(indices, batch (n, H, W, 3) uint8), …]`` in order of first appearance.

    ``indices`` are the positions in ``images`` of the batch's rows, so results can be put back in order.
    """
    groups: dict[tuple[int, ...], list[int]] = {}
    for i, image in enumerate(images):
        a = np.asarray(image)
        if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
            raise ValueError(f"images[{i}] must be a uint8 (H, W, 3) RGB array, got {a.dtype} {a.shape}")
        groups.setdefault(a.shape, []).append(i)
    return [(idx, np.stack([images[i] for i in idx])) for idx in groups.values()]


def map_by_size(images: Sequence[np.ndarray], fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """``fn`` applied to every batch of equal-size images (:func:`group_by_size`), its rows put back in the order of
    ``images``: e.g. ``map_by_size(images, model.inputs)`` → the posterior inputs ``(n, …)`` of images of any sizes."""
    out: np.ndarray | None = None
    for idx, batch in group_by_size(images):
        y = np.asarray(fn(batch))
        if out is None:
            out = np.empty((len(images), *y.shape[1:]), dtype=y.dtype)
        out[idx] = y
    if out is None:
        raise ValueError("no images")
    return out


def render_shape(height: int, width: int, render: int) -> tuple[int, int]:
    """The ``(height, width)`` of a render ``render`` pixels high for images of ``height × width``: the same aspect,
    the width rounded to whole pixels (``simulator.render_sizes``; a model card's ``training_renders``)."""
    return render, max(width, round(render * width / height))
