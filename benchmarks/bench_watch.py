"""``pidc watch`` on simulated drives whose weather is known: false alarms per hour on drives that stay in the sources'
hull, the delay to the first alarm on drives that leave it at a known time, and the time and memory of a one-hour
drive (issue #56, part 3).

The model is ``--model`` (default the registry's champion) at the default watch options
(:data:`components.watch.settings.WATCH_DEFAULTS`); the drives are :class:`components.simulate.drive.Drive` at 10
frames/s, ``--size`` pixels (default 128, the default profile's). Every seed descends from ``--seed``
(:func:`components.core.seeding.derive_seed`). Modes, each alone or ``all`` in turn:

- ``sources``: three source drives of ``--source-seconds`` each from distinct boxes (:data:`SOURCES`: a clear day, an
  overcast day, an evening; fog 0–10 % in all, no rain), walking fast (τ = 10 s) so that minutes cover each box;
  rendered once into ``--out``/sources/ (a folder of PNGs each, named by a hash of the drive).
- ``in-odd``: ``--in-odd-drives`` drives of ``--in-odd-seconds``, drive i walking (τ = 30 s) inside source i mod 3's
  box shrunk by 10 % of its width on each side, so that its truth stays in the sources' range (the drives that leave
  it nonetheless, where a short source did not reach a face, are counted, and only their driving before the exit is
  in-ODD); every alarm before an exit is a false alarm. Their count per hour of in-ODD driving, with its Garwood 95 %
  interval, against the rate the rule states (``result.stated``: its alarms on the sources' held-out evaluation
  blocks, with that count's interval): within the promise when the measured rate is at most the stated interval's
  upper end.
- ``exits``: drives that walk 40 s inside a source's shrunk box (source i mod 3), then fog rolls in over 60 s
  (:class:`~components.simulate.drive.Fog`) from the walk's value to the sources' highest fog + Δ, Δ in ``--exits``
  (``15=8,30=20,60=8``: Δ = +15, +30, +60 points, 8, 20 and 8 drives), and 20 s at that fog (``--exit-seconds
  40,60,20``); and ``--dusk-drives`` drives in the evening box whose sun sets
  (:class:`~components.simulate.drive.Dusk`) over the ramp to 30° below the sources' lowest sun. Per kind and size: the delay from the truth's exit of the sources' range
  (:func:`components.simulate.drive.first_exit`, as ``result.truth`` measures it) to the first alarm fired at or after
  it, its median and 90 % quantile in seconds and frames (empirical: the smallest delay within which that share of
  the drives alarmed; a drive with no alarm by its end counts as never), the share of drives alarmed within 10 s
  and the share of alarmed drives whose alarm names the parameter that left first in its cause, each with its
  Clopper–Pearson 95 % interval, and the false alarms before the exits.
- ``hour``: a drive of ``--hour-seconds`` (default one hour: 36 000 frames) inside the clear box, rendered once as a
  lossless FFV1 ``.mkv`` (the sources' frames are lossless PNGs: an MJPG ``.avi``, ``--hour-video avi``, differs from
  them by its compression, which the champion reads as a wet road and alarms on), watched by ``pidc watch`` in a
  child process that writes every output: its wall time against the drive's length (the realtime factor), its CPU
  time, and its peak resident memory (``os.wait4``'s ``ru_maxrss``) against 2 GB; its alarms are false alarms.

One thread: ``OMP_NUM_THREADS`` and the BLAS libraries' counts are set to 1 before numpy loads, OpenCV's and torch's
thread counts to 1, onnxruntime runs one thread (``load_registered(threads=1)``); the JSON records the CPU seconds per
wall second. In ``in-odd`` and ``exits`` the sources are read and the decision calibrated once per process
(:class:`SourcesOnce`, :func:`components.watch.run.prepare_sources`: the same numbers as a watch that reads them
itself, as each frame's draws are seeded by its number). Drives are
rendered into a temporary folder under ``--out``, watched and removed; each drive's record is kept in
``--out``/<mode>.jsonl, keyed by the model, the options, the sources and the drive, so that a run resumes where it
stopped and a finished one prints again at once. ``--quick`` is a smoke scale (minutes); ``--set NAME=VALUE`` changes a
watch option (for tests). Usage::

    .venv/bin/python benchmarks/bench_watch.py all --quick
    .venv/bin/python benchmarks/bench_watch.py all                     # the full scale: 1.5–2 h on 2 cores
    .venv/bin/python benchmarks/bench_watch.py exits --exits 30=40

Prints a table per mode and one JSON line (``{"benchmark": "watch", ...}``) with the machine's details, also written
to ``--out``/<mode>.json.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# isort: off
import components  # noqa: E402,F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Iterable, Sequence  # noqa: E402
from dataclasses import dataclass, fields, replace  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from benchmarks.machine import machine_info  # noqa: E402
from components.core.seeding import derive_seed  # noqa: E402
from components.simulate.drive import Drive, Dusk, Fog, read_weather_csv, write_folder, write_video  # noqa: E402
from components.watch.sequential import garwood_interval  # noqa: E402
from components.watch.settings import OPTION_NAMES, WatchOptions  # noqa: E402
from components.watch.truth import sources_range  # noqa: E402

DEFAULT_OUT = ROOT / "benchmarks" / "results" / "watch"
MODES = ("sources", "in-odd", "exits", "hour")

#: The sources' boxes (physical units; the parameters not named are held at the drive's defaults: no rain, a dry road,
#: the sun's azimuth 135°).
SOURCES: dict[str, dict[str, tuple[float, float]]] = {
    "clear": {"cloudiness": (0, 30), "fog_density": (0, 10), "sun_altitude_angle": (40, 70), "wind_intensity": (0, 30)},
    "overcast": {
        "cloudiness": (60, 95),
        "fog_density": (0, 10),
        "sun_altitude_angle": (20, 50),
        "wind_intensity": (10, 50),
    },
    "evening": {
        "cloudiness": (10, 50),
        "fog_density": (0, 10),
        "sun_altitude_angle": (5, 25),
        "wind_intensity": (0, 30),
    },
}
#: τ of the sources' walks and of the drives', seconds.
SOURCE_CORRELATION_S = 10.0
DRIVE_CORRELATION_S = 30.0
#: The share of a source box's width each drive's box stays away from each face.
MARGIN = 0.1
#: The dusk exits' sun: this many degrees below the sources' lowest.
DUSK_BELOW = 30.0
#: The targets: an alarm within this many seconds of the exit, in this share of the drives; the cause named in at least
#: this share; the one-hour drive below this peak memory (bytes).
WITHIN_S, WITHIN_SHARE, CAUSE_SHARE, MEMORY_LIMIT = 10.0, 0.9, 0.9, 2e9
#: The child process of ``hour``: ``pidc watch`` on one OpenCV thread.
CHILD = (
    "import components, sys, cv2; cv2.setNumThreads(1); from components.cli.main import main; "
    "sys.exit(main(sys.argv[1:]))"
)


@dataclass(frozen=True)
class Scale:
    """How much of each mode to run (see the module docstring)."""

    source_seconds: float
    in_odd_drives: int
    in_odd_seconds: float
    exits: dict[int, int]
    dusk_drives: int
    hour_seconds: float
    exit_seconds: tuple[float, float, float] = (40.0, 60.0, 20.0)

    @property
    def exit_drive_seconds(self) -> float:
        return sum(self.exit_seconds)


FULL = Scale(480.0, 6, 600.0, {15: 8, 30: 20, 60: 8}, 8, 3600.0)
QUICK = Scale(120.0, 1, 60.0, {15: 1, 30: 1, 60: 1}, 1, 120.0)


# --- statistics -----------------------------------------------------------------------------------------------------


def delay_quantile(delays: Sequence[float], q: float) -> float:
    """The smallest delay within which at least a share ``q`` of the drives alarmed (inf for a drive that never did;
    the result is inf when fewer than ``q`` of them alarmed at all): numpy's inverted-CDF quantile.

    Example:
        >>> delay_quantile([3.0, 1.0, 2.0, math.inf], 0.5), delay_quantile([3.0, 1.0, 2.0, math.inf], 0.9)
        (2.0, inf)
    """
    if not delays:
        return math.nan
    return float(np.quantile(np.asarray(delays, dtype=np.float64), q, method="inverted_cdf"))


def share_interval(k: int, n: int, level: float = 0.95) -> tuple[float, float, float]:
    """``k / n`` and its Clopper–Pearson (exact binomial) ``level`` interval; NaNs for ``n = 0``."""
    if n == 0:
        return math.nan, math.nan, math.nan
    ci = stats.binomtest(k, n).proportion_ci(confidence_level=level, method="exact")
    return k / n, float(ci.low), float(ci.high)


# --- drives and their keys ------------------------------------------------------------------------------------------


def inner_box(box: dict[str, tuple[float, float]], margin: float = MARGIN) -> dict[str, tuple[float, float]]:
    """``box`` with each face moved inwards by ``margin`` × its width."""
    return {n: (lo + margin * (hi - lo), hi - margin * (hi - lo)) for n, (lo, hi) in box.items()}


def _digest(value: Any) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()[:12]


def _version(size: int) -> str:
    from components.simulate.procedural.renderer import ProceduralSimulator

    return ProceduralSimulator(size, size).version


def drive_key(drive: Drive) -> str:
    """A hash of the drive's settings and the renderer's version: the same key, the same frames."""
    return _digest(drive.to_dict(_version(drive.size)))


def source_drives(seconds: float, size: int, seed: int) -> dict[str, Drive]:
    """The sources (:data:`SOURCES`), ``seconds`` each."""
    return {
        name: Drive(
            seconds,
            derive_seed(seed, "bench-watch", "source", name),
            size=size,
            box=box,
            correlation_s=SOURCE_CORRELATION_S,
        )
        for name, box in SOURCES.items()
    }


def render_sources(drives: dict[str, Drive], folder: Path, progress: bool = True) -> dict[str, Path]:
    """Each source's folder of frames ``folder/<name>-<key>``, rendered when missing."""
    from tqdm.auto import tqdm

    out = {}
    for name, drive in drives.items():
        path = folder / f"{name}-{drive_key(drive)}"
        if not (path / "drive.json").is_file():
            with tqdm(
                total=drive.n_frames, desc=f"bench_watch: source {name}", disable=None if progress else True
            ) as b:
                write_folder(drive, path, progress=b.update)
        out[name] = path
    return out


def in_odd_drives(scale: Scale, size: int, seed: int) -> list[tuple[str, Drive]]:
    """Drive i walks inside source i mod 3's shrunk box."""
    names = list(SOURCES)
    out = []
    for i in range(scale.in_odd_drives):
        name = names[i % len(names)]
        s = derive_seed(seed, "bench-watch", "in-odd", i)
        out.append(
            (
                name,
                Drive(
                    scale.in_odd_seconds, s, size=size, box=inner_box(SOURCES[name]), correlation_s=DRIVE_CORRELATION_S
                ),
            )
        )
    return out


@dataclass(frozen=True)
class ExitDrive:
    """An exit drive: its ``kind`` (``fog`` or ``dusk``), ``size`` (points or degrees beyond the sources' range), the
    source whose box it starts in, and the drive."""

    kind: str
    size: float
    start_box: str
    drive: Drive


def exit_drives(scale: Scale, size: int, seed: int, hull: dict[str, tuple[float, float]]) -> list[ExitDrive]:
    """The fog exits per Δ (drive i in source i mod 3's shrunk box) and the dusk exits (the evening box)."""
    names = list(SOURCES)
    inside, ramp, _ = scale.exit_seconds
    seconds = scale.exit_drive_seconds
    out = []
    for delta, n in scale.exits.items():
        target = hull["fog_density"][1] + delta
        if target > 100.0:
            raise SystemExit(f"--exits {delta}: the sources' fog {hull['fog_density'][1]:.1f} + {delta} exceeds 100 %")
        for i in range(n):
            name = names[i % len(names)]
            s = derive_seed(seed, "bench-watch", "exit", "fog", delta, i)
            event = Fog(start_s=inside, duration_s=ramp, target=target)
            drive = Drive(
                seconds, s, size=size, box=inner_box(SOURCES[name]), correlation_s=DRIVE_CORRELATION_S, events=(event,)
            )
            out.append(ExitDrive("fog", float(delta), name, drive))
    sun = hull["sun_altitude_angle"][0] - DUSK_BELOW
    for i in range(scale.dusk_drives):
        s = derive_seed(seed, "bench-watch", "exit", "dusk", i)
        event = Dusk(start_s=inside, duration_s=ramp, target=sun)
        drive = Drive(
            seconds, s, size=size, box=inner_box(SOURCES["evening"]), correlation_s=DRIVE_CORRELATION_S, events=(event,)
        )
        out.append(ExitDrive("dusk", DUSK_BELOW, "evening", drive))
    return out


def hour_drive(scale: Scale, size: int, seed: int) -> Drive:
    return Drive(
        scale.hour_seconds,
        derive_seed(seed, "bench-watch", "hour"),
        size=size,
        box=inner_box(SOURCES["clear"]),
        correlation_s=DRIVE_CORRELATION_S,
    )


# --- watching -------------------------------------------------------------------------------------------------------


class SourcesOnce:
    """The sources read and the decision calibrated once per process for every drive of the same options
    (:func:`components.watch.run.prepare_sources`, passed to :func:`components.watch.run.watch` as ``prepared``: the
    same numbers as a watch that reads them itself, ``tests/test_bench_scripts.py`` checks it). ``seconds`` holds the
    time spent preparing."""

    def __init__(self) -> None:
        self.prepared: dict[tuple, Any] = {}
        self.seconds = {"prepare_sources": 0.0}

    def get(self, model: Any, frames: list[Any], names: list[str], options: WatchOptions) -> Any:
        """The prepared sources of ``frames`` for ``model`` and ``options``, read the first time they are asked for."""
        from components.watch.run import prepare_sources

        key = (id(model), tuple(str(f.path) for f in frames), tuple(names), options)
        if key not in self.prepared:
            t = time.perf_counter()
            self.prepared[key] = prepare_sources(model, frames, names, options)
            self.seconds["prepare_sources"] += time.perf_counter() - t
        return self.prepared[key]


def watch_drive(
    model: Any,
    drive: Drive,
    sources: dict[str, Path],
    options: WatchOptions,
    tmp: Path,
    once: SourcesOnce | None = None,
) -> Any:
    """Render ``drive`` into a temporary folder under ``tmp``, watch it against ``sources`` (prepared once by
    ``once``, or read here when None), remove it; the :class:`~components.watch.run.WatchResult`, with
    ``cpu_seconds`` of this process added to its timing."""
    from components.watch.frames import open_frames
    from components.watch.run import watch

    tmp.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=tmp, prefix="drive-") as folder:
        path = write_folder(drive, Path(folder) / "drive")
        frames = [open_frames(p, timed=False) for p in sources.values()]
        prepared = None if once is None else once.get(model, frames, list(sources), options)
        cpu = time.process_time()
        result = watch(model, open_frames(path), frames, list(sources), options, prepared=prepared)
        result.timing["cpu_seconds"] = time.process_time() - cpu
    return result


def _record(result: Any) -> dict[str, Any]:
    """What a drive's watch found, as JSON."""
    truth = result.truth
    if truth is None:
        raise RuntimeError(f"{result.drive.path}: the watch has no truth; the drive or a source lost its weather.csv")
    exit_s = truth["exit_s"]
    ends = result.windows["end_s"]
    inside = ends < exit_s if exit_s is not None else np.ones(ends.size, dtype=bool)
    detected = [a for a in result.alarms if truth["detected_s"] is not None and a.fired_s == truth["detected_s"]]
    return {
        "frames": int(result.frames["frame"].size),
        "fps": 1.0 / float(result.drive.frame_seconds),
        "exit_s": exit_s,
        "exit_parameters": truth["exit_parameters"],
        "in_odd_hours": truth["in_odd_hours"],
        "false_alarms": truth["false_alarms"],
        "detected_s": truth["detected_s"],
        "delay_s": truth["delay_s"],
        "cause": detected[0].cause if detected else None,
        "alarms": [{"fired_s": a.fired_s, "end_s": a.end_s, "cause": a.cause} for a in result.alarms],
        "in_odd_windows": int(inside.sum()),
        "in_odd_flagged": int(np.count_nonzero(result.windows["flagged"][inside])),
        "stated": result.stated.to_dict(),
        "threshold": float(result.calibration.detector.threshold),
        "timing": {k: float(v) for k, v in result.timing.items()},
    }


class Records:
    """The records of one mode, ``<out>/<mode>.jsonl`` (one ``{"key", "record"}`` a line), read at start and appended
    to after each drive."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.kept: dict[str, dict] = {}
        if path.is_file():
            for line in path.read_text().splitlines():
                if line.strip():
                    row = json.loads(line)
                    self.kept[row["key"]] = row["record"]

    def get_or_make(self, key: str, make: Callable[[], dict]) -> dict:
        if key not in self.kept:
            record = make()
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.path, "a") as f:
                f.write(json.dumps({"key": key, "record": record}) + "\n")
            self.kept[key] = record
        return self.kept[key]


def _context_key(model_key: str, options: WatchOptions, sources: dict[str, Path]) -> dict:
    return {"model": model_key, "options": options.to_dict(), "sources": [p.name for p in sources.values()]}


def _bar(total: int, desc: str) -> Any:
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="frame", disable=None)


# --- the modes ------------------------------------------------------------------------------------------------------


def run_sources(drives: dict[str, Drive], paths: dict[str, Path]) -> dict[str, Any]:
    tables = {n: read_weather_csv(p / "weather.csv") for n, p in paths.items()}
    hull = sources_range(list(tables.values()))
    print(f"sources ({len(paths)}), 10 frames/s, τ = {SOURCE_CORRELATION_S:g} s:")
    for name, drive in drives.items():
        box = ", ".join(f"{n} {lo:g}–{hi:g}" for n, (lo, hi) in drive.box.items())
        print(f"  {name:<9} {drive.n_frames:>6} frames  {box}  ({paths[name]})")
    print(
        "their range (the hull the truth uses): " + ", ".join(f"{n} {lo:.1f}–{hi:.1f}" for n, (lo, hi) in hull.items())
    )
    return {
        "sources": {n: {"frames": d.n_frames, "box": d.box, "folder": str(paths[n])} for n, d in drives.items()},
        "hull": hull,
    }


def run_in_odd(model, model_key, options, sources, scale, size, seed, out, once) -> dict[str, Any]:  # noqa: ANN001
    drives = in_odd_drives(scale, size, seed)
    records = Records(out / "in-odd.jsonl")
    context = _context_key(model_key, options, sources)
    rows = []
    with _bar(sum(d.n_frames for _, d in drives), "bench_watch: in-ODD drives") as bar:
        for name, drive in drives:
            key = _digest({**context, "drive": drive_key(drive)})
            record = records.get_or_make(
                key, lambda drive=drive: _record(watch_drive(model, drive, sources, options, out / "tmp", once))
            )
            rows.append({"box": name, "seed": drive.seed, "seconds": drive.seconds, **record})
            bar.update(drive.n_frames)
    hours = sum(r["in_odd_hours"] for r in rows)
    false = sum(r["false_alarms"] for r in rows)
    low, high = garwood_interval(false, hours, options.interval_level)
    stated = rows[0]["stated"]
    if any(r["stated"] != stated for r in rows):
        raise RuntimeError("the rule's stated rate differs between drives of the same sources and options")
    windows, flagged = sum(r["in_odd_windows"] for r in rows), sum(r["in_odd_flagged"] for r in rows)
    measured = {"false_alarms": false, "hours": hours, "per_hour": false / hours, "low": low, "high": high}
    within = measured["per_hour"] <= stated["high"]
    overlap = low <= stated["high"] and stated["low"] <= high
    level = f"{100 * options.interval_level:g} %"
    left = [r for r in rows if r["exit_s"] is not None]
    print(
        f"in-ODD drives: {len(rows)} × {scale.in_odd_seconds:g} s = {len(rows) * scale.in_odd_seconds / 3600:.3f} h "
        f"of driving, {hours:.3f} h of it in the sources' range ({len(left)} drive(s) left it)"
    )
    print(
        f"  {'drive':<6}{'box':<10}{'frames':>8}{'left at s':>11}{'false alarms':>14}{'flagged':>10}{'× realtime':>12}"
    )
    for i, r in enumerate(rows):
        share = r["in_odd_flagged"] / max(r["in_odd_windows"], 1)
        rt = r["timing"]["realtime_factor"]
        at = "–" if r["exit_s"] is None else f"{r['exit_s']:.1f}"
        print(f"  {i:<6}{r['box']:<10}{r['frames']:>8}{at:>11}{r['false_alarms']:>14}{100 * share:>9.2f}%{rt:>12.2f}")
    print(
        f"measured: {false} false alarms in {hours:.3f} h = {measured['per_hour']:.2f} per hour "
        f"({level} Garwood {low:.2f}–{high:.2f})"
    )
    print(
        f"stated by the rule: {stated['alarms']} alarms in {stated['hours']:.3f} h of held-out windows = "
        f"{stated['per_hour']:.2f} per hour ({level} Garwood {stated['low']:.2f}–{stated['high']:.2f}); per window "
        f"{100 * stated['window_rate']:.2f} % flagged (α = {100 * options.false_alarm_rate:g} %)"
    )
    print(
        f"within the promise (measured rate ≤ the stated interval's upper end {stated['high']:.2f}/h): "
        f"{'yes' if within else 'NO'}; intervals overlap: {'yes' if overlap else 'NO'}; in-ODD windows flagged: "
        f"{100 * flagged / max(windows, 1):.2f} % of {windows}"
    )
    return {
        "drives": len(rows),
        "drive_seconds": scale.in_odd_seconds,
        "sources_seconds_so_far": dict(once.seconds),
        "measured": measured,
        "stated": stated,
        "within_promise": bool(within),
        "intervals_overlap": bool(overlap),
        "windows": windows,
        "flagged": flagged,
        "left_hull": len(left),
        "per_drive": [
            {k: r[k] for k in ("box", "seed", "frames", "exit_s", "exit_parameters", "in_odd_hours", "false_alarms")}
            | {k: r[k] for k in ("in_odd_windows", "in_odd_flagged")}
            | {"realtime_factor": r["timing"]["realtime_factor"], "alarms": r["alarms"]}
            for r in rows
        ],
        "realtime_factor_median": float(np.median([r["timing"]["realtime_factor"] for r in rows])),
        "cpu_per_wall": sum(r["timing"]["cpu_seconds"] for r in rows) / sum(r["timing"]["wall_seconds"] for r in rows),
    }


def exit_summary(rows: Iterable[dict], within_s: float = WITHIN_S) -> dict[str, Any]:
    """One kind and size of exit: delays (inf where no alarm came), shares with Clopper–Pearson intervals, the false
    alarms before the exits."""
    rows = list(rows)
    fps = rows[0]["fps"]
    left = [r for r in rows if r["exit_s"] is not None]
    delays = [math.inf if r["delay_s"] is None else float(r["delay_s"]) for r in left]
    detected = [r for r in left if r["delay_s"] is not None]
    named = [r for r in detected if r["cause"] and r["cause"][0] == r["exit_parameters"][0]]
    soon = sum(d <= within_s + 1e-9 for d in delays)
    median, q90 = delay_quantile(delays, 0.5), delay_quantile(delays, 0.9)
    return {
        "drives": len(rows),
        "left": len(left),
        "detected": len(detected),
        "delay_median_s": median,
        "delay_q90_s": q90,
        "delay_median_frames": round(median * fps) if math.isfinite(median) else median,
        "delay_q90_frames": round(q90 * fps) if math.isfinite(q90) else q90,
        "within_s": within_s,
        "within": dict(zip(("share", "low", "high"), share_interval(soon, len(left)), strict=True)) | {"k": soon},
        "cause_first": dict(zip(("share", "low", "high"), share_interval(len(named), len(detected)), strict=True))
        | {"k": len(named)},
        "within_target_met": bool(left) and soon / len(left) >= WITHIN_SHARE,
        "cause_target_met": bool(detected) and len(named) / len(detected) >= CAUSE_SHARE,
        "false_alarms_before_exit": sum(r["false_alarms"] for r in rows),
        "hours_before_exit": sum(r["in_odd_hours"] for r in rows),
        "delays_s": delays,
        "causes": [r["cause"] for r in rows],
    }


def finite(value: Any) -> Any:
    """``value`` with every non-finite float (a delay that never came) as None: strict JSON."""
    if isinstance(value, dict):
        return {str(k): finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    if isinstance(value, float | np.floating) and not math.isfinite(value):
        return None
    return value


def _s(v: float, digits: int = 1) -> str:
    return "never" if math.isinf(v) else f"{v:.{digits}f}"


def run_exits(model, model_key, options, sources, scale, size, seed, out, hull, once) -> dict[str, Any]:  # noqa: ANN001
    drives = exit_drives(scale, size, seed, hull)
    records = Records(out / "exits.jsonl")
    context = _context_key(model_key, options, sources)
    groups: dict[tuple[str, float], list[dict]] = {}
    with _bar(sum(e.drive.n_frames for e in drives), "bench_watch: exit drives") as bar:
        for e in drives:
            key = _digest({**context, "drive": drive_key(e.drive)})
            record = records.get_or_make(
                key, lambda e=e: _record(watch_drive(model, e.drive, sources, options, out / "tmp", once))
            )
            groups.setdefault((e.kind, e.size), []).append({"start_box": e.start_box, "seed": e.drive.seed, **record})
            bar.update(e.drive.n_frames)
    sign = {"fog": "+", "dusk": "-"}
    summaries = {f"{kind}{sign[kind]}{size:g}": exit_summary(rows) for (kind, size), rows in groups.items()}
    inside, ramp, after = scale.exit_seconds
    print(
        f"exits: {inside:g} s inside, a {ramp:g} s ramp from inside to Δ beyond the sources' range (fog "
        f"{hull['fog_density'][1]:.1f} %, sun {hull['sun_altitude_angle'][0]:.1f}°), {after:g} s after; delays from "
        "the truth's exit to the first alarm after it"
    )
    head = f"  {'kind':<10}{'drives':>7}{'alarmed':>9}{'median s (frames)':>19}{'90 % s (frames)':>17}"
    print(head + f"{f'≤ {WITHIN_S:g} s [95 % CP]':>24}{'cause first [95 % CP]':>26}{'false before':>14}")
    for name, s in summaries.items():
        w, c = s["within"], s["cause_first"]
        med = f"{_s(s['delay_median_s'])} ({_s(s['delay_median_frames'], 0)})"
        q90 = f"{_s(s['delay_q90_s'])} ({_s(s['delay_q90_frames'], 0)})"
        within = f"{w['k']}/{s['left']} [{w['low']:.2f}, {w['high']:.2f}]"
        cause = f"{c['k']}/{s['detected']} [{c['low']:.2f}, {c['high']:.2f}]" if s["detected"] else "–"
        print(
            f"  {name:<10}{s['drives']:>7}{s['detected']:>9}{med:>19}{q90:>17}{within:>24}{cause:>26}"
            f"{s['false_alarms_before_exit']:>14}"
        )
    for name, s in summaries.items():
        w, c = s["within"]["share"], s["cause_first"]["share"]
        print(
            f"  {name}: alarmed within {WITHIN_S:g} s of the exit in {100 * w:.0f} % of the drives (target ≥ "
            f"{100 * WITHIN_SHARE:.0f} %: {'met' if s['within_target_met'] else 'NOT met'}); the cause named first in "
            f"{100 * c:.0f} % of the alarmed (target ≥ {100 * CAUSE_SHARE:.0f} %: "
            f"{'met' if s['cause_target_met'] else 'NOT met'})"
        )
    return {
        "inside_s": inside,
        "ramp_s": ramp,
        "after_s": after,
        "kinds": summaries,
        "sources_seconds_so_far": dict(once.seconds),
    }


def run_hour(
    args: argparse.Namespace, model_key: str, options: WatchOptions, sources: dict[str, Path], scale: Scale, out: Path
) -> dict[str, Any]:
    drive = hour_drive(scale, args.size, args.seed)
    video = out / f"hour-{drive_key(drive)}.{args.hour_video}"
    if not video.is_file():
        with _bar(drive.n_frames, f"bench_watch: rendering {video.name}") as bar:
            write_video(drive, video, progress=bar.update)
    records = Records(out / "hour.jsonl")
    key = _digest({**_context_key(model_key, options, sources), "drive": drive_key(drive), "video": video.name})

    def make() -> dict:
        target = out / "hour-watch"
        shutil.rmtree(target, ignore_errors=True)
        target.mkdir(parents=True)
        cmd = [sys.executable, "-c", CHILD, "watch", str(video), "--sources", *map(str, sources.values())]
        cmd += ["--out", str(target), "--model", args.model, "--registry", str(args.registry), "--seed", str(args.seed)]
        cmd += [a for name, value in args.set for a in (OPTION_NAMES[name], str(value))]
        env = os.environ | {n: "1" for n in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
        with open(target / "log.txt", "w") as log:
            t = time.perf_counter()
            proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
            _, status, usage = os.wait4(proc.pid, 0)
            wall = time.perf_counter() - t
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode != 0:
            raise SystemExit(f"pidc watch failed ({proc.returncode}): see {target / 'log.txt'}")
        summary = json.loads((target / "summary.json").read_text())
        return {
            "frames": drive.n_frames,
            "seconds": drive.seconds,
            "video_bytes": video.stat().st_size,
            "wall_seconds": wall,
            "cpu_seconds": usage.ru_utime + usage.ru_stime,
            "max_rss_bytes": usage.ru_maxrss * 1024,  # Linux: KiB
            "timing": summary["timing"],
            "alarms": len(summary["alarms"]),
            "truth": summary.get("truth"),
        }

    r = records.get_or_make(key, make)
    factor = r["seconds"] / r["wall_seconds"]
    print(
        f"hour: {r['frames']} frames ({r['seconds']:g} s at 10 frames/s, {video.suffix} {r['video_bytes'] / 1e6:.0f} MB) "
        f"watched by `pidc watch` in {r['wall_seconds']:.0f} s wall: {factor:.2f}× realtime "
        f"({'faster' if factor > 1 else 'SLOWER'} than it lasted; the drive alone "
        f"{r['timing']['realtime_factor']:.2f}×, the sources {r['timing']['sources_seconds']:.0f} s); CPU "
        f"{r['cpu_seconds']:.0f} s ({r['cpu_seconds'] / r['wall_seconds']:.2f} per wall second); peak memory "
        f"{r['max_rss_bytes'] / 1e9:.2f} GB ({'below' if r['max_rss_bytes'] < MEMORY_LIMIT else 'NOT below'} 2 GB); "
        f"{r['alarms']} alarm(s) on this in-ODD drive"
    )
    return r | {
        "realtime_factor": factor,
        "faster_than_realtime": factor > 1,
        "below_memory": r["max_rss_bytes"] < MEMORY_LIMIT,
    }


# --- the command ----------------------------------------------------------------------------------------------------


def _exits_arg(text: str) -> dict[int, int]:
    try:
        pairs = [item.split("=") for item in text.split(",")]
        out = {int(d): int(n) for d, n in pairs}
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected DELTA=DRIVES,… (e.g. 15=8,30=20), got {text!r}") from None
    if any(d <= 0 or n < 0 for d, n in out.items()):
        raise argparse.ArgumentTypeError(f"deltas must be > 0 and drive counts ≥ 0, got {text!r}")
    return out


def _seconds_arg(text: str) -> tuple[float, float, float]:
    try:
        inside, ramp, after = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected INSIDE,RAMP,AFTER seconds (e.g. 40,60,20), got {text!r}") from None
    if inside <= 0 or ramp <= 0 or after < 0:
        raise argparse.ArgumentTypeError(f"expected INSIDE > 0, RAMP > 0 and AFTER ≥ 0 seconds, got {text!r}")
    return inside, ramp, after


def _set_arg(text: str) -> tuple[str, Any]:
    name, _, value = text.partition("=")
    field = {f.name: f for f in fields(WatchOptions)}.get(name)
    if field is None or name == "seed" or not OPTION_NAMES.get(name, "").startswith("--"):
        known = ", ".join(n for n, o in OPTION_NAMES.items() if o.startswith("--") and n != "seed")
        raise argparse.ArgumentTypeError(f"--set {text!r}: expected NAME=VALUE with NAME one of {known}")
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--set {name}: {value!r} is not a number") from None
    return name, int(number) if number.is_integer() and field.type in ("int", int) else number


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("mode", choices=(*MODES, "all"), help="what to run (all: every mode in turn)")
    p.add_argument("--quick", action="store_true", help="the smoke scale: minutes instead of hours")
    p.add_argument("--model", default="champion", help="a registry model (default champion)")
    p.add_argument("--registry", type=Path, default=ROOT / "registry", help="the registry folder")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="renders and records (default %(default)s)")
    p.add_argument("--size", type=int, default=128, help="frames' side, pixels (default 128)")
    p.add_argument("--seed", type=int, default=0, help="the root of every seed (drives and watch)")
    p.add_argument("--source-seconds", type=float, help="seconds per source (full 480, quick 120)")
    p.add_argument("--in-odd-drives", type=int, help="in-ODD drives (full 6, quick 1)")
    p.add_argument("--in-odd-seconds", type=float, help="seconds per in-ODD drive (full 600, quick 60)")
    p.add_argument("--exits", type=_exits_arg, help="fog exits DELTA=DRIVES,… (full 15=8,30=20,60=8; quick one each)")
    p.add_argument("--dusk-drives", type=int, help="dusk exits (full 8, quick 1)")
    p.add_argument("--hour-seconds", type=float, help="the long drive's seconds (full 3600, quick 120)")
    p.add_argument(
        "--exit-seconds",
        type=_seconds_arg,
        help="an exit drive's seconds inside, of the ramp, after it (default 40,60,20)",
    )
    p.add_argument(
        "--hour-video", choices=("mkv", "avi"), default="mkv", help="lossless FFV1 .mkv (default) or MJPG .avi"
    )
    p.add_argument("--set", type=_set_arg, action="append", default=[], metavar="NAME=VALUE", help="a watch option")
    args = p.parse_args(argv)
    base = QUICK if args.quick else FULL
    changes = {f.name: getattr(args, f.name) for f in fields(Scale) if getattr(args, f.name, None) is not None}
    args.scale = scale = replace(base, **changes)
    if min(scale.source_seconds, scale.in_odd_seconds, scale.hour_seconds) <= 0:
        p.error("--source-seconds, --in-odd-seconds and --hour-seconds must be > 0")
    if scale.in_odd_drives < 1 or scale.dusk_drives < 0 or sum(scale.exits.values()) + scale.dusk_drives < 1:
        p.error("--in-odd-drives must be ≥ 1, --dusk-drives ≥ 0, and --exits with --dusk-drives at least one drive")
    return args


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    import cv2

    from components.watch.errors import WatchError

    args = parse(argv)
    cv2.setNumThreads(1)
    scale, out = args.scale, args.out
    try:
        options = WatchOptions(seed=args.seed, **dict(args.set))
    except WatchError as e:
        raise SystemExit(f"--set: {e}") from None
    modes = MODES if args.mode == "all" else (args.mode,)
    drives = source_drives(scale.source_seconds, args.size, args.seed)
    sources = render_sources(drives, out / "sources")
    found = run_sources(drives, sources)
    results: dict[str, Any] = dict(found)
    model_key = None
    if any(m != "sources" for m in modes):
        from components.export.lookup import resolve_model

        folder = resolve_model(args.model, args.registry)
        model_key = f"{folder.name}-{hashlib.sha256((folder / 'card.json').read_bytes()).hexdigest()[:12]}"
    model = None
    if "in-odd" in modes or "exits" in modes:
        from components.export.lookup import load_registered

        model = load_registered(args.model, args.registry, threads=1)
        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(1)
    hull = {n: tuple(v) for n, v in found["hull"].items()}
    once = SourcesOnce()  # in-odd and exits read the sources and calibrate once between them
    if "in-odd" in modes:
        results["in_odd"] = run_in_odd(model, model_key, options, sources, scale, args.size, args.seed, out, once)
    if "exits" in modes:
        results["exits"] = run_exits(model, model_key, options, sources, scale, args.size, args.seed, out, hull, once)
    if "hour" in modes:
        results["hour"] = run_hour(args, model_key, options, sources, scale, out)
    line = {
        "benchmark": "watch",
        "mode": args.mode,
        "quick": args.quick,
        "model": model_key,
        "options": options.to_dict(),
        "changed_options": dict(args.set),
        "scale": {f.name: getattr(scale, f.name) for f in fields(Scale)},
        "size": args.size,
        "seed": args.seed,
        **results,
        "machine": machine_info(threads=1),
    }
    line = finite(line)
    text = json.dumps(line, default=float, allow_nan=False)
    print(text)
    (out / f"{args.mode}{'-quick' if args.quick else ''}.json").write_text(text + "\n")
    return line


if __name__ == "__main__":
    main()
