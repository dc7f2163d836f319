"""The watch of a drive: its frames' posteriors, its windows related to the sources, the rule's alarms, their causes.

1. **Sources.** Each source's frames (:mod:`components.watch.frames`) → m fixed posterior draws each
   (:func:`components.watch.draws.frame_draws`, stream ``source-<k>``), cut into blocks
   (:mod:`components.watch.calibration`): the density blocks make the sources' kernel densities
   (:class:`components.watch.relation.SourceDensities`), the held-out blocks calibrate the threshold and the in-ODD
   levels and give the rule's stated false alarms per hour (:mod:`components.watch.sequential`).
2. **Drive.** Streamed in batches: each frame's n draws (stream ``drive``, seeded by the frame's number) → its median
   and 68.27 % HDI; the last L frames' draws are kept (:class:`components.watch.timeline.RecentFrames`), and each
   window ending at a frame gets its domain's median and HDI (Task II), its relation to the sources (Task III: λ̂, the
   relative gap, W₁ per parameter) and its flag (relative gap > threshold), with the parameters beyond their in-ODD
   level.
3. **Rule.** Alarm segments over the drive's windows (:class:`components.watch.sequential.ConsecutiveRule`), each
   with its cause: the parameters beyond their in-ODD level in at least half of its windows, largest W₁/level first.
4. **Truth**, when the drive and the sources carry their known weather (:mod:`components.watch.truth`): the
   false alarms and the detection delay on this drive.

Memory is one batch of frames, one window of draws, and the per-frame and per-window rows (a few dozen numbers
each): a one-hour drive at 10 frames/s is 36 000 rows.

Used by the ``pidc watch`` command.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from components.core.seeding import derive_seed
from components.domains.relative import SimplexLeastSquares
from components.watch.calibration import Calibration, calibrate, check_sources, density_draws
from components.watch.draws import frame_draws, frame_summaries
from components.watch.errors import WatchError
from components.watch.frames import Frames
from components.watch.relation import SourceDensities, relate_window
from components.watch.sequential import ConsecutiveRule, Segment, StatedRate, stated_rate
from components.watch.settings import FEATURE_GROUP, WatchOptions
from components.watch.timeline import RecentFrames, WindowShape, domain_summary
from components.watch.truth import against_truth, read_truth, sources_range

__all__ = ["Alarm", "PreparedSources", "WatchResult", "prepare_sources", "read_source", "watch"]

#: A parameter names an alarm's cause when it is beyond its in-ODD level in at least this share of the alarm's windows.
CAUSE_SHARE = 0.5
#: The quantiles of a source's pooled draws drawn as its range in the timeline figure.
RANGE_QUANTILES = (0.005, 0.995)


@dataclass(frozen=True)
class Alarm:
    """One alarm segment of the drive.

    Attributes:
        segment: the :class:`~components.watch.sequential.Segment` (window indices).
        first_s: the end time of its first flagged window, seconds.
        fired_s: when the rule fired (the end of its k-th flagged window), seconds.
        end_s: the end of its last flagged window, seconds.
        cause: the parameters beyond their in-ODD level in ≥ :data:`CAUSE_SHARE` of its windows, largest mean
            W₁/level first (empty: no single parameter; the windows differ jointly).
        share: per parameter (box order) the share of its windows beyond the level ``(d,)``.
        ratio: per parameter the mean W₁/level over its windows ``(d,)``.
    """

    segment: Segment
    first_s: float
    fired_s: float
    end_s: float
    cause: list[str]
    share: np.ndarray
    ratio: np.ndarray


@dataclass
class WatchResult:
    """Everything a watch found (see the module docstring); :mod:`components.watch.report` writes it.

    ``frames`` and ``windows`` are column tables (name → ``(n,)`` array); ``names`` the sources'; ``ranges`` per source
    ``(d, 2)`` the :data:`RANGE_QUANTILES` of its draws; ``truth`` the record against the known weather and
    ``truth_table`` the drive's known weather (:mod:`components.watch.truth`), or None.
    """

    model: str
    box: Any
    drive: Frames
    sources: list[Frames]
    names: list[str]
    options: WatchOptions
    frames: dict[str, np.ndarray]
    windows: dict[str, np.ndarray]
    calibration: Calibration
    densities: SourceDensities
    rule: ConsecutiveRule
    stated: StatedRate
    alarms: list[Alarm]
    ranges: list[np.ndarray]
    truth: dict[str, Any] | None
    timing: dict[str, float]
    notes: list[str] = field(default_factory=list)
    truth_table: dict[str, np.ndarray] | None = None

    @property
    def window_seconds(self) -> float:
        """Seconds of driving per window step: the stride × Δt."""
        return self.options.stride * float(self.drive.frame_seconds)

    @property
    def first_alarm_s(self) -> float | None:
        return self.alarms[0].fired_s if self.alarms else None


def _inputs(model: Any, images: np.ndarray, notes: list[str]) -> np.ndarray:
    """The model's inputs of a batch of frames (a multiple of :data:`~components.watch.settings.FEATURE_GROUP` frames
    from a multiple of it, but the stream's last), computed that many frames at a time: a backbone's float reductions
    may round differently for another number of images, and the groups are then the same whatever the batch. The
    backbone's one-time warnings become notes."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        x = np.concatenate(
            [np.asarray(model.inputs(images[i : i + FEATURE_GROUP])) for i in range(0, len(images), FEATURE_GROUP)]
        )
    for w in caught:
        if str(w.message) not in notes:
            notes.append(str(w.message))
    return x


def _bar(total: int, desc: str, progress: bool) -> Any:
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="frame", disable=None if progress and total >= 2 else True)  # None: a TTY


def read_source(
    model: Any, frames: Frames, k: int, options: WatchOptions, notes: list[str], progress: bool = False
) -> np.ndarray:
    """Source k's fixed draws ``(N, m, d)``, frame by frame in name order (stream ``source-<k>``)."""
    out = np.empty((frames.count, options.draws_per_image, model.posterior.dim))
    done = 0
    with _bar(frames.count, f"pidc watch: source {frames.path.name}", progress) as bar:
        for batch in frames.batches(options.batch):
            x = _inputs(model, batch.images, notes)
            if batch.index[-1] >= out.shape[0]:  # a video holding more frames than its header states
                out = np.concatenate([out, np.empty((batch.index[-1] + 1 - out.shape[0], *out.shape[1:]))])
            out[batch.index] = frame_draws(
                model.posterior, x, batch.index, options.draws_per_image, options.seed, f"source-{k}"
            )
            done = int(batch.index[-1]) + 1
            bar.update(len(batch.index))
    return out[:done]


def _size_note(model: Any, frames: Frames) -> str | None:
    learned = model.learned_size(frames.size)
    if learned is False:
        h, w = frames.size
        return (
            f"{frames.path}: frames of {w}×{h} pixels; {model.name} learned from {model.learned_from}: its calibration "
            "does not cover them"
        )
    return None


def _source_ranges(draws: Sequence[np.ndarray]) -> list[np.ndarray]:
    return [np.quantile(d.reshape(-1, d.shape[-1]), RANGE_QUANTILES, axis=0).T for d in draws]


def _alarms(rule: ConsecutiveRule, windows: dict[str, np.ndarray], levels: np.ndarray, box: Any) -> list[Alarm]:
    w1 = np.stack([windows[f"{n}_w1"] for n in box.names], axis=1)
    out = []
    for s in rule.segments(windows["flagged"]):
        part = w1[s.first : s.last + 1]
        share = np.mean(part > levels, axis=0)
        ratio = np.mean(part / levels, axis=0)
        cause = [box.names[j] for j in np.argsort(-ratio) if share[j] >= CAUSE_SHARE]
        end = windows["end_s"]
        out.append(Alarm(s, float(end[s.first]), float(end[s.fired]), float(end[s.last]), cause, share, ratio))
    return out


class _Columns:
    """A column table gathered as it grows: blocks of rows (:meth:`extend`) or one row at a time (:meth:`append`, kept
    as Python scalars until :meth:`table` joins them)."""

    def __init__(self) -> None:
        self._blocks: dict[str, list[np.ndarray]] = {}
        self._rows: dict[str, list[Any]] = {}

    def extend(self, **columns: Any) -> None:
        for name, value in columns.items():
            self._blocks.setdefault(name, []).append(np.asarray(value))

    def append(self, **values: Any) -> None:
        for name, value in values.items():
            self._rows.setdefault(name, []).append(value.item() if isinstance(value, np.generic) else value)

    def table(self) -> dict[str, np.ndarray]:
        out = {name: np.concatenate(parts) for name, parts in self._blocks.items()}
        return out | {name: np.asarray(values) for name, values in self._rows.items()}


def _watch_drive(
    model: Any,
    drive: Frames,
    shape: WindowShape,
    densities: SourceDensities,
    calibration: Calibration,
    options: WatchOptions,
    notes: list[str],
    progress: bool,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The drive's frame and window tables (steps 2 of the module docstring)."""
    posterior, box, m = model.posterior, model.posterior.box, options.draws_per_image
    recent = RecentFrames(shape, options.samples, posterior.dim)
    weights = shape.weights
    solver = SimplexLeastSquares()
    frames, windows = _Columns(), _Columns()
    times: list[float] = []  # every frame's time: 8 bytes a frame
    with _bar(drive.count, f"pidc watch: {drive.path.name}", progress) as bar:
        for batch in drive.batches(options.batch):
            x = _inputs(model, batch.images, notes)
            draws = frame_draws(posterior, x, batch.index, options.samples, options.seed, "drive")
            median, low, high = frame_summaries(draws)
            frames.extend(frame=batch.index, image=np.asarray(batch.names), time_s=batch.time_s)
            for j, name in enumerate(box.names):
                frames.extend(**{f"{name}_median": median[:, j], f"{name}_low": low[:, j], f"{name}_high": high[:, j]})
            times.extend(batch.time_s.tolist())
            for end, window in recent.push(draws):
                seed = derive_seed(options.seed, "watch", "window", int(end))
                d_median, d_low, d_high = domain_summary(window, weights, seed)
                rel = relate_window(window[:, :m], weights, densities, options.n_points, seed, solver)
                beyond = rel.wasserstein > calibration.levels
                start = end - shape.length + 1
                windows.append(
                    first_frame=start,
                    last_frame=end,
                    start_s=times[start],
                    end_s=times[end],
                    gap=rel.gap,
                    relative_gap=rel.relative_gap,
                    flagged=calibration.detector.decide(rel.relative_gap),
                    degenerate=rel.degenerate,
                    beyond=";".join(n for n, b in zip(box.names, beyond, strict=True) if b),
                )
                for j, name in enumerate(box.names):
                    windows.append(
                        **{
                            f"{name}_median": d_median[j],
                            f"{name}_low": d_low[j],
                            f"{name}_high": d_high[j],
                            f"{name}_w1": rel.wasserstein[j],
                            f"{name}_beyond": bool(beyond[j]),
                        }
                    )
                for name, lam in zip(densities.names, rel.weights, strict=True):
                    windows.append(**{f"weight_{name}": lam})
            bar.update(batch.index.size)
    seen = len(times)
    if seen < shape.length:
        what = f"--window {options.window}" if options.decay is None else f"--decay {options.decay:g}"
        raise WatchError(
            f"{what}: a window of {shape.length} frames is longer than the drive {drive.path} ({seen} frames)"
        )
    table = windows.table()
    return frames.table(), {"window": np.arange(table["last_frame"].size), **table}


@dataclass
class PreparedSources:
    """The sources read and the decision calibrated once, for any number of drives watched with the same ``options``
    (:func:`prepare_sources`; :func:`watch` takes it as ``prepared``).

    Attributes:
        sources: the sources' frames; ``names`` their names.
        options: the :class:`~components.watch.settings.WatchOptions` they were prepared with.
        densities: the sources' kernel densities (their density blocks).
        calibration: the threshold and in-ODD levels (calibration blocks) and the evaluation blocks' gaps.
        ranges: per source ``(d, 2)`` the :data:`RANGE_QUANTILES` of its draws.
        notes: the sources' notes (sizes the model did not learn, the backbone's warnings).
        seconds: the wall time of reading and calibrating, seconds.
    """

    sources: list[Frames]
    names: list[str]
    options: WatchOptions
    densities: SourceDensities
    calibration: Calibration
    ranges: list[np.ndarray]
    notes: list[str]
    seconds: float


def _check_window(drive: Frames, shape: WindowShape, options: WatchOptions) -> None:
    if drive.frame_seconds is None:
        raise WatchError(f"{drive.path}: the drive's frames have no times")
    if drive.count < shape.length:
        what = f"--window {options.window}" if options.decay is None else f"--decay {options.decay:g}"
        raise WatchError(
            f"{what}: a window of {shape.length} frames is longer than the drive {drive.path} ({drive.count} frames)"
        )


def prepare_sources(
    model: Any, sources: Sequence[Frames], names: Sequence[str], options: WatchOptions, progress: bool = False
) -> PreparedSources:
    """Step 1 of the module docstring: the sources' fixed draws, their densities and the calibrated decision.

    Arguments:
        model: a :class:`~components.export.lookup.RegisteredPosterior`.
        sources: the sources' frames (in name order; times not needed).
        names: the sources' names (distinct).
        options: the :class:`~components.watch.settings.WatchOptions` (every drive watched with the result uses them).
        progress: show tqdm bars.

    Raises:
        WatchError: sources too short to calibrate, a saturated threshold, an unreadable source.
    """
    shape = WindowShape(options.length, options.stride, options.decay)
    check_sources(names, [f.count for f in sources], options.block, shape, options.false_alarm_rate)
    notes: list[str] = [n for n in (_size_note(model, f) for f in sources) if n]
    start = time.perf_counter()
    source_draws = [read_source(model, f, k, options, notes, progress) for k, f in enumerate(sources)]
    densities = SourceDensities.build(
        names,
        density_draws(source_draws, options.block),
        options.bandwidth_scale,
        options.source_centres,
        derive_seed(options.seed, "watch", "sources"),
    )
    calibration = calibrate(
        names,
        source_draws,
        densities,
        shape,
        options.block,
        options.n_points,
        options.false_alarm_rate,
        options.seed,
        progress,
    )
    ranges = _source_ranges(source_draws)
    return PreparedSources(
        list(sources), list(names), options, densities, calibration, ranges, notes, time.perf_counter() - start
    )


def watch(
    model: Any,
    drive: Frames,
    sources: Sequence[Frames],
    names: Sequence[str],
    options: WatchOptions,
    progress: bool = False,
    prepared: PreparedSources | None = None,
) -> WatchResult:
    """Watch ``drive`` against ``sources`` (see the module docstring).

    Arguments:
        model: a :class:`~components.export.lookup.RegisteredPosterior` (``posterior``, ``inputs``, ``name``).
        drive: the drive's :class:`~components.watch.frames.Frames` (timed).
        sources: the sources' frames (in name order; times not needed).
        names: the sources' names (distinct).
        options: the :class:`~components.watch.settings.WatchOptions`.
        progress: show tqdm bars (sources, calibration, drive).
        prepared: the sources already read and calibrated by :func:`prepare_sources` with the same sources, names and
            options (a folder of drives against the same sources reads them once); None: read them here.

    Raises:
        WatchError: a window longer than the drive, sources too short to calibrate, a saturated threshold, an
            unreadable or truncated drive or source, frames of mixed sizes, ``prepared`` made for other sources or
            options.
    """
    shape = WindowShape(options.length, options.stride, options.decay)
    _check_window(drive, shape, options)
    if prepared is None:
        prepared = prepare_sources(model, sources, names, options, progress)
    elif (
        prepared.options != options
        or prepared.names != list(names)
        or [f.path for f in prepared.sources] != [f.path for f in sources]
    ):
        raise WatchError("the prepared sources were read with other sources, names or options than this watch's")
    densities, calibration, ranges = prepared.densities, prepared.calibration, prepared.ranges
    notes: list[str] = [n for n in [_size_note(model, drive), *prepared.notes] if n]
    start = time.perf_counter() - prepared.seconds
    rule = ConsecutiveRule(options.consecutive)
    window_seconds = options.stride * float(drive.frame_seconds)
    stated = stated_rate(
        rule,
        [calibration.detector.decide_many(h.gaps) for h in calibration.evaluation],
        window_seconds,
        options.interval_level,
    )
    sources_s = prepared.seconds
    frames, windows = _watch_drive(model, drive, shape, densities, calibration, options, notes, progress)
    box = model.posterior.box
    windows["alarm"] = rule.alarms(windows["flagged"])
    alarms = _alarms(rule, windows, calibration.levels, box)
    wall = time.perf_counter() - start
    drive_s = wall - sources_s
    seconds = float(frames["time_s"][-1] - frames["time_s"][0] + drive.frame_seconds)
    truth = None
    table = read_truth(drive)
    source_tables = [read_truth(f) for f in sources]
    if table is not None and all(t is not None for t in source_tables):
        truth = against_truth(table, sources_range(source_tables), [(a.fired_s, a.cause) for a in alarms], seconds)
    timing = {
        "sources_seconds": sources_s,
        "drive_seconds": drive_s,
        "wall_seconds": wall,
        "drive_frames": int(frames["frame"].size),
        "frames_per_second": frames["frame"].size / drive_s if drive_s > 0 else float("nan"),
        "drive_length_seconds": seconds,
        "realtime_factor": seconds / drive_s if drive_s > 0 else float("nan"),
    }
    return WatchResult(
        model.name,
        box,
        drive,
        list(sources),
        list(names),
        options,
        frames,
        windows,
        calibration,
        densities,
        rule,
        stated,
        alarms,
        ranges,
        truth,
        timing,
        notes,
        table if truth is not None else None,
    )
