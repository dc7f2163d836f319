"""A drive's frames and their times, streamed in batches: from a video file or from a folder of frames.

- A **video** (any container and codec OpenCV's FFmpeg reads: ``.avi``, ``.mp4``, ``.mkv``, …): frames in stream
  order, frame k at t_k = k / fps seconds, fps the container's rate or the one given. A video whose stream ends before
  the frame count its header states is *truncated*, an error naming the file.
- A **folder of frames**: its image files in natural name order (``frame2`` before ``frame10``,
  :func:`components.core.images.list_images`), each read as :func:`components.core.images.read_image` does; times from
  its ``times.csv`` (columns ``image,time_s``, every frame listed once, strictly increasing in name order) or
  t_k = k / fps for a given fps.

Every frame must have the first frame's size, and every frame must be readable: a drive is a time series, and a frame
left out would shift every time after it; each problem is a :class:`~components.watch.errors.WatchError` naming the
file. Nothing is held but the current batch (``(b, H, W, 3)`` uint8 RGB): an hour at 10 frames/s streams in constant
memory.

Used by :mod:`components.watch.run` (the drive and the sources of ``pidc watch``).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from components.watch.errors import WatchError

__all__ = ["VIDEO_SUFFIXES", "TIMES_CSV", "FrameBatch", "Frames", "open_frames", "read_times_csv"]

#: File extensions (lower case) taken as videos; other files are refused (a folder is a folder of frames).
VIDEO_SUFFIXES: frozenset[str] = frozenset(
    {".avi", ".mp4", ".mkv", ".mov", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv", ".flv", ".ogv"}
)
#: The file of a folder of frames that gives their times.
TIMES_CSV = "times.csv"


@dataclass(frozen=True)
class FrameBatch:
    """Consecutive frames of a drive.

    Attributes:
        index: ``(b,)`` int64 frame numbers, 0 for the drive's first frame.
        time_s: ``(b,)`` float64 times, seconds (NaN for frames of a source read without times).
        names: the frames' names: file names in a folder, ``frame <k>`` in a video.
        images: ``(b, H, W, 3)`` uint8 RGB.
    """

    index: np.ndarray
    time_s: np.ndarray
    names: list[str]
    images: np.ndarray


def read_times_csv(path: Path, names: list[str]) -> np.ndarray:
    """The times (seconds, ``(n,)`` float64) of the frames ``names`` (file names, in name order) from ``times.csv``.

    Raises :class:`WatchError` naming the file (and line) for a missing column, a bad or repeated row, a frame it does
    not list or one it lists that is not in the folder, or times that do not increase in name order.
    """
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = [[c.strip() for c in row] for row in csv.reader(f)]
    except (OSError, UnicodeDecodeError) as e:
        raise WatchError(f"{path}: cannot read it as a UTF-8 CSV file ({e})") from None
    rows = [(line, r) for line, r in enumerate(rows, start=1) if any(r)]
    if not rows or rows[0][1][:2] != ["image", "time_s"]:
        raise WatchError(f"{path}: expected the header image,time_s")
    times: dict[str, float] = {}
    for line, row in rows[1:]:
        if len(row) < 2:
            raise WatchError(f"{path} line {line}: expected image,time_s, got {','.join(row)!r}")
        try:
            t = float(row[1])
        except ValueError:
            raise WatchError(f"{path} line {line}: time {row[1]!r} is not a number") from None
        if not math.isfinite(t):
            raise WatchError(f"{path} line {line}: time {row[1]!r} is not finite")
        if row[0] in times:
            raise WatchError(f"{path} line {line}: {row[0]!r} is listed twice")
        times[row[0]] = t
    missing = [n for n in names if n not in times]
    if missing:
        raise WatchError(f"{path}: no time for {len(missing)} frame(s) of the folder, e.g. {missing[0]!r}")
    extra = sorted(set(times) - set(names))
    if extra:
        raise WatchError(f"{path}: lists {len(extra)} frame(s) not in the folder, e.g. {extra[0]!r}")
    out = np.array([times[n] for n in names], dtype=np.float64)
    bad = np.flatnonzero(np.diff(out) <= 0)
    if bad.size:
        i = int(bad[0])
        raise WatchError(
            f"{path}: times must increase in the frames' name order, but {names[i + 1]!r} ({out[i + 1]:g} s) does not "
            f"come after {names[i]!r} ({out[i]:g} s)"
        )
    return out


class Frames:
    """The frames of a video or a folder (see the module docstring); open it with :func:`open_frames`.

    Attributes:
        path: the video file or the folder.
        kind: ``"video"`` or ``"folder"``.
        count: n, the number of frames (a video's as its header states it).
        size: ``(H, W)`` of the frames (a video's as its header states it; a folder's first frame's).
        fps: frames per second when the times come from a rate (a video, or ``fps`` given); None with ``times.csv`` or
            without times.
        times: ``(n,)`` seconds from ``times.csv``, or None.
        timed: whether frames have times (False for a source opened without them).
    """

    def __init__(
        self,
        path: Path,
        kind: str,
        count: int,
        size: tuple[int, int],
        fps: float | None,
        times: np.ndarray | None,
        files: list[Path] | None,
        timed: bool,
    ) -> None:
        self.path, self.kind, self.count, self.size = path, kind, count, size
        self.fps, self.times, self._files, self.timed = fps, times, files, timed

    def __repr__(self) -> str:
        return f"Frames({str(self.path)!r}, {self.kind}, {self.count} frames, {self.size[1]}×{self.size[0]})"

    @property
    def frame_seconds(self) -> float | None:
        """Δt, seconds from one frame to the next: 1/fps, or the median step of ``times.csv``; None without times or
        with one timed frame."""
        if self.fps is not None:
            return 1.0 / self.fps
        if self.times is None or self.times.size < 2:
            return None
        return float(np.median(np.diff(self.times)))

    def time_of(self, index: np.ndarray) -> np.ndarray:
        """The times (seconds) of the frames ``index`` ``(b,)``; NaN when untimed."""
        if self.times is not None:
            return self.times[index]
        if self.fps is not None:
            return index.astype(np.float64) / self.fps
        return np.full(index.shape, np.nan)

    def batches(self, size: int) -> Iterator[FrameBatch]:
        """Stream the frames in order, ``size`` at a time (the last batch may be smaller).

        Raises :class:`WatchError` naming the file for an unreadable frame, a frame of another size than the first,
        or a video that ends before its stated frame count (truncated) or holds no frame.
        """
        if size < 1:
            raise ValueError(f"a batch holds at least one frame, got {size}")
        frames = self._video() if self.kind == "video" else self._folder()
        index: list[int] = []
        names: list[str] = []
        images: list[np.ndarray] = []
        for k, (name, image) in enumerate(frames):
            if image.shape[:2] != self.size:
                raise WatchError(
                    f"{self._where(name)}: a frame of {image.shape[1]}×{image.shape[0]} pixels; the drive's frames are "
                    f"{self.size[1]}×{self.size[0]} (frames of mixed sizes)"
                )
            index.append(k)
            names.append(name)
            images.append(image)
            if len(images) == size:
                yield self._batch(index, names, images)
                index, names, images = [], [], []
        if images:
            yield self._batch(index, names, images)

    def _batch(self, index: list[int], names: list[str], images: list[np.ndarray]) -> FrameBatch:
        i = np.asarray(index, dtype=np.int64)
        return FrameBatch(i, self.time_of(i), names, np.stack(images))

    def _where(self, name: str) -> str:
        return str(self.path / name) if self.kind == "folder" else f"{self.path} ({name})"

    def _folder(self) -> Iterator[tuple[str, np.ndarray]]:
        from components.core.images import ImageError, read_image

        assert self._files is not None
        for path in self._files:
            try:
                image, _ = read_image(path)
            except ImageError as e:
                raise WatchError(f"{e} (a drive's frames must all be readable)") from None
            yield path.name, image

    def _video(self) -> Iterator[tuple[str, np.ndarray]]:
        import cv2

        capture = cv2.VideoCapture(str(self.path))
        try:
            if not capture.isOpened():
                raise WatchError(f"{self.path}: OpenCV cannot open this video (unreadable or not a video file)")
            k = 0
            while True:
                ok, frame = capture.read()
                if not ok or frame is None:
                    break
                if frame.ndim == 2:
                    frame = np.repeat(frame[:, :, None], 3, axis=2)
                yield f"frame {k}", np.ascontiguousarray(frame[:, :, 2::-1])  # OpenCV gives BGR
                k += 1
        finally:
            capture.release()
        if k == 0:
            raise WatchError(f"{self.path}: no frame could be read from this video")
        if k < self.count:
            raise WatchError(
                f"{self.path}: truncated video: its stream ends after {k} of the {self.count} frames its header states"
            )


def _open_video(path: Path, fps: float | None, timed: bool) -> Frames:
    import cv2

    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise WatchError(f"{path}: OpenCV cannot open this video (unreadable, truncated or not a video file)")
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        rate = float(capture.get(cv2.CAP_PROP_FPS))
        size = (int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)), int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)))
        if count >= 1:  # a truncated file still states its full count: its last frame tells, before any work
            capture.set(cv2.CAP_PROP_POS_FRAMES, count - 1)
            last, _ = capture.read()
    finally:
        capture.release()
    if count < 1:
        raise WatchError(f"{path}: the video states no frame count (a damaged or truncated file)")
    if not last:
        raise WatchError(
            f"{path}: truncated video: its header states {count} frames, but the last of them cannot be read"
        )
    if min(size) < 1:
        raise WatchError(f"{path}: the video states no frame size (a damaged file)")
    if fps is None and timed:
        if not (math.isfinite(rate) and rate > 0):
            raise WatchError(f"{path}: the video states no frame rate; give --fps")
        fps = rate
    return Frames(path, "video", count, size, fps if timed else None, None, None, timed)


def _check_sizes(files: list[Path], size: tuple[int, int]) -> None:
    """A :class:`WatchError` naming the first of ``files`` whose header states another size than ``size`` (H, W), or
    that is no image: before any work (a header is read in tens of microseconds; the pixels are read when streamed,
    where the size is checked again, after any EXIF rotation)."""
    from PIL import Image, ImageOps, UnidentifiedImageError

    for path in files[1:]:
        try:
            with Image.open(path) as im:
                w, h = im.size
                if (h, w) != size and im.getexif().get(0x0112, 1) not in (0, 1):
                    w, h = ImageOps.exif_transpose(im).size
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
            raise WatchError(f"{path}: unreadable image ({e}) (a drive's frames must all be readable)") from None
        if (h, w) != size:
            raise WatchError(
                f"{path}: a frame of {w}×{h} pixels; the drive's frames are {size[1]}×{size[0]} (frames of mixed sizes)"
            )


def _open_folder(path: Path, fps: float | None, timed: bool) -> Frames:
    from components.core.images import ImageError, list_images, read_image

    try:
        files = list_images([path])
    except ImageError as e:
        raise WatchError(str(e)) from None
    try:
        first, _ = read_image(files[0])
    except ImageError as e:
        raise WatchError(f"{e} (a drive's frames must all be readable)") from None
    _check_sizes(files, first.shape[:2])
    times = None
    csv_path = path / TIMES_CSV
    if timed and csv_path.is_file():
        if fps is not None:
            raise WatchError(f"--fps {fps:g}: {csv_path} gives the frames' times; leave out --fps or that file")
        times = read_times_csv(csv_path, [f.name for f in files])
    elif timed and fps is None:
        raise WatchError(f"{path}: a folder of frames without {TIMES_CSV}; give --fps (frames per second)")
    return Frames(path, "folder", len(files), first.shape[:2], fps if timed else None, times, files, timed)


def open_frames(path: str | Path, fps: float | None = None, *, timed: bool = True) -> Frames:
    """Open a drive (a video file or a folder of frames) for :meth:`Frames.batches`.

    Arguments:
        path: a video file (:data:`VIDEO_SUFFIXES`) or a folder of frames.
        fps: frames per second (> 0): a video's rate instead of the one it states; a folder's without ``times.csv``.
        timed: False for frames whose times are not needed (the sources): no rate nor ``times.csv`` is asked for.

    Raises:
        WatchError: no such file or folder, a file that is not a video, a video OpenCV cannot open or whose header
            states no frame count, size or rate (without ``fps``), a folder without image files or whose first frame
            is unreadable, a folder without ``times.csv`` and without ``fps``, a bad ``times.csv``.
    """
    path = Path(path)
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise WatchError(f"--fps must be a positive number of frames per second, got {fps:g}")
    if not path.exists():
        raise WatchError(f"{path}: no such file or folder")
    if path.is_dir():
        return _open_folder(path, fps, timed)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise WatchError(f"{path}: neither a folder of frames nor a video ({', '.join(sorted(VIDEO_SUFFIXES))})")
    return _open_video(path, fps, timed)
