"""Simulated drives: frames of a moving car whose weather θ(t) over time is known.

A drive is ``n = round(seconds · fps)`` frames at times ``t_k = k / fps`` seconds. Its weather θ(t) is

- a **walk** inside a box: per walked parameter an Ornstein–Uhlenbeck process seen through the normal CDF Φ,
  θ(t) = low + (high − low) · Φ(z(t)), z a stationary OU process of unit variance sampled exactly at the frames,
  z_{k+1} = ρ z_k + √(1 − ρ²) ξ_k, ξ_k ~ N(0, 1) (:func:`uniform_ou`). θ never leaves [low, high], its marginal is
  uniform on it (a walk covers its box evenly, edges included, as an ODD's sources should), and with
  ρ = 2 sin(π a / 6) its lag-1 autocorrelation is exactly a = exp(−Δt/τ), Δt = 1/fps, τ = ``correlation_s`` seconds
  (a Gaussian copula's Pearson correlation of uniforms is (6/π) arcsin(ρ/2)); at lag m it is (6/π) arcsin(ρ^m/2),
  within 0.023 of a^m. A reflected OU process has a truncated normal marginal: kept narrow, it rarely visits the
  faces; made wide, its reflections shorten the correlation time (lag-1 0.939 against a = 0.951 at σ = width/4).
  The parameters not in the box are **held** at given values (:data:`DEFAULT_HELD` for the ones not given);
- **events** layered on it, in their order: :class:`Fog` (fog rolling in), :class:`Rain` (rain starting, puddles
  following with a lag, clouds rising) and :class:`Dusk` (the sun going down). Each ramps a parameter linearly from
  its value to a target, v(t) = (1 − r) v + r · target, r = clip((t − start_s)/duration_s, 0, 1): untouched until
  start_s, at the target from start_s + duration_s on.

The car drives: frame k is rendered in scene ``k // (fps · scene_seconds)`` (a new map, spawn point, camera and traffic
every ``scene_seconds``), so consecutive frames share a scene, whose geometry the renderer builds once and caches
(:class:`components.simulate.procedural.renderer.ProceduralSimulator`), while the view changes over the drive. Every
draw descends from the drive's seed (:mod:`components.core.seeding`): the walk of parameter ``name`` from the stream
``(seed, "drive", "walk", name)``, scene j's seed ``derive_seed(seed, "drive", "scene", j)``; the same seed gives
byte-identical frames and tables, and a longer drive of the same seed starts as the shorter one.

:meth:`Drive.frames` streams ``(time_s, weather, image)`` without holding the drive; :func:`write_folder` writes
``OUT/000000.png …``, ``times.csv``, ``weather.csv`` (the truth) and ``drive.json``; :func:`write_video` an ``.avi``
(MJPG), ``.mp4`` (mp4v) or ``.mkv`` (FFV1, lossless) with ``OUT.weather.csv`` and ``OUT.drive.json`` beside it;
:func:`first_exit` the first time θ(t) leaves a box (the benchmarks' known exit time).

Used by the ``pidc`` CLI (``drive``) and the benchmarks of ``pidc watch``; no pipeline stage imports it (nor does
``pidc``'s parser: the command imports it when it runs). SciPy and the renderer are imported when first needed.

Example:
    >>> from components.simulate.drive import Drive, Fog, first_exit
    >>> drive = Drive(seconds=120, seed=0, events=(Fog(start_s=30, duration_s=60, target=40),))
    >>> table = drive.weather_table()
    >>> fog = table["fog_density"]
    >>> fog.shape, float(fog[fog.size - 1])
    ((1200,), 40.0)
    >>> first_exit(table, {"fog_density": (0, 10)}).parameters
    ('fog_density',)
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import secrets
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import numpy as np

from components.core.files import atomic_folder, atomic_write_bytes
from components.core.images import RENDER_SIDES
from components.core.opencv import ipp_off
from components.core.seeding import derive_seed, rng
from components.core.weather import PARAMETERS, PREDICTED, complete_weather
from components.simulate.base import Simulator
from components.simulate.contact_sheet import BASE_WEATHER

__all__ = [
    "DRIVEN",
    "DEFAULT_BOX",
    "DEFAULT_HELD",
    "DRIVE_DEFAULTS",
    "VIDEO_CODECS",
    "Fog",
    "Rain",
    "Dusk",
    "Event",
    "EVENTS",
    "event_from_dict",
    "Frame",
    "Exit",
    "Drive",
    "check_box",
    "check_held",
    "uniform_ou",
    "ramp",
    "first_exit",
    "exits",
    "frame_names",
    "write_folder",
    "write_video",
    "video_sidecars",
    "read_weather_csv",
]

#: The parameters a drive sets: θ's six (:data:`components.core.weather.PREDICTED`) and the nuisance sun azimuth.
DRIVEN: tuple[str, ...] = (*PREDICTED, "sun_azimuth_angle")

#: A moderate daytime box (physical units): some clouds, light haze, the sun between 30° and 60°, light wind.
DEFAULT_BOX: dict[str, tuple[float, float]] = {
    "cloudiness": (10.0, 40.0),
    "fog_density": (0.0, 10.0),
    "sun_altitude_angle": (30.0, 60.0),
    "wind_intensity": (0.0, 30.0),
}

#: The values of the parameters outside the box: :data:`components.simulate.contact_sheet.BASE_WEATHER` (a pleasant
#: day: no rain, a dry road, the sun's azimuth 135°).
DEFAULT_HELD: dict[str, float] = dict(BASE_WEATHER)

#: The other defaults of a drive: frames per second, image side (pixels; the default profile's 128), correlation time
#: τ of the walk (seconds), seconds per scene.
DRIVE_DEFAULTS: dict[str, float] = {
    "fps": 10.0,
    "size": 128,
    "correlation_s": 30.0,
    "scene_seconds": 1.0,
}

#: Video file extensions → OpenCV fourcc: MJPG (lossy, small), mp4v (lossy), FFV1 (lossless, larger).
VIDEO_CODECS: dict[str, str] = {".avi": "MJPG", ".mp4": "mp4v", ".mkv": "FFV1"}

# slack of the frame and scene counts against floating-point rounding (e.g. 0.3 · 10 = 2.9999999999999996)
_EPS = 1e-9


def _number(what: str, value: object) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{what} must be finite, got {v!r}")
    return v


def _positive(what: str, value: object, unit: str = "s") -> float:
    v = _number(what, value)
    if v <= 0:
        raise ValueError(f"{what} must be > 0{' ' + unit if unit else ''}, got {v:g}")
    return v


def _known(name: object, what: str) -> str:
    if name not in DRIVEN:
        raise ValueError(f"{what}: unknown parameter {name!r}; known: {', '.join(DRIVEN)}")
    return str(name)


def _in_range(name: str, value: object, what: str) -> float:
    p = PARAMETERS[name]
    v = _number(f"{what} {name}", value)
    if not p.low <= v <= p.high:
        raise ValueError(f"{what} {name} = {v:g} is outside its range {p.describe_range()}")
    return v


def check_box(box: Mapping[str, Sequence[float]], *, what: str = "box") -> dict[str, tuple[float, float]]:
    """The walk's box, checked: ``{name: (low, high)}`` with names in :data:`DRIVEN`, each face within the parameter's
    range and low ≤ high (low = high holds the parameter there).

    Raises:
        ValueError: one line starting with ``what``, naming the parameter and its range.
    """
    out: dict[str, tuple[float, float]] = {}
    for name, pair in box.items():
        name = _known(name, what)
        pair = tuple(pair)
        if len(pair) != 2:
            raise ValueError(f"{what} {name}: needs (low, high), got {pair!r}")
        low, high = (_in_range(name, v, what) for v in pair)
        if low > high:
            raise ValueError(f"{what} {name}: low {low:g} > high {high:g}")
        out[name] = (low, high)
    return out


def check_held(held: Mapping[str, float], box: Mapping[str, object] = {}, *, what: str = "held") -> dict[str, float]:
    """The held values, checked: names in :data:`DRIVEN` not walked in ``box``, values within their ranges.

    Raises:
        ValueError: one line starting with ``what``, naming the parameter and its range (or that it is walked).
    """
    out: dict[str, float] = {}
    for name, value in held.items():
        name = _known(name, what)
        if name in box:
            raise ValueError(f"{what} {name}: it is walked in the box; hold it or walk it, not both")
        out[name] = _in_range(name, value, what)
    return out


def ramp(values: np.ndarray, times: np.ndarray, start_s: float, duration_s: float, target: float) -> np.ndarray:
    """``values`` ramped linearly to ``target``: (1 − r)·values + r·target, r = clip((t − start_s)/duration_s, 0, 1).

    Arguments:
        values: ``(n,)`` the parameter before the ramp, physical units.
        times: ``(n,)`` seconds.
        start_s: the ramp's start, seconds.
        duration_s: the ramp's length, seconds (> 0).
        target: the value from ``start_s + duration_s`` on.

    Returns:
        ``(n,)`` float64: ``values`` exactly up to ``start_s``, ``target`` exactly from ``start_s + duration_s``.
    """
    r = np.clip((np.asarray(times, dtype=np.float64) - start_s) / duration_s, 0.0, 1.0)
    return (1.0 - r) * values + r * target


@dataclass(frozen=True)
class _Event:
    """An event's timing: it starts at ``start_s`` ≥ 0 and lasts ``duration_s`` > 0 seconds."""

    start_s: float
    duration_s: float
    target: float

    kind: ClassVar[str] = ""
    parameter: ClassVar[str] = ""

    def __post_init__(self) -> None:
        start = _number(f"{self.kind} event: start", self.start_s)
        if start < 0:
            raise ValueError(f"{self.kind} event: start must be >= 0 s, got {start:g}")
        object.__setattr__(self, "start_s", start)
        object.__setattr__(self, "duration_s", _positive(f"{self.kind} event: duration", self.duration_s))
        object.__setattr__(self, "target", _in_range(self.parameter, self.target, f"{self.kind} event: target"))

    @property
    def end_s(self) -> float:
        """The time (seconds) from which the event's parameters all sit at their targets."""
        return self.start_s + self.duration_s

    def apply(self, values: dict[str, np.ndarray], times: np.ndarray) -> None:
        """Ramp this event's parameter(s) of ``values`` (name → ``(n,)``) in place, at ``times`` ``(n,)`` seconds."""
        values[self.parameter] = ramp(values[self.parameter], times, self.start_s, self.duration_s, self.target)

    def to_dict(self) -> dict[str, Any]:
        """``{"kind": …, field: value, …}``, as in ``drive.json``; :func:`event_from_dict` reads it back."""
        return {"kind": self.kind, **{f.name: getattr(self, f.name) for f in fields(self)}}


@dataclass(frozen=True)
class Fog(_Event):
    """Fog rolling in: fog_density ramps from its value to ``target`` (%) over [start_s, start_s + duration_s]."""

    kind: ClassVar[str] = "fog"
    parameter: ClassVar[str] = "fog_density"


@dataclass(frozen=True)
class Dusk(_Event):
    """Dusk: sun_altitude_angle ramps from its value to ``target`` (degrees) over [start_s, start_s + duration_s]."""

    kind: ClassVar[str] = "dusk"
    parameter: ClassVar[str] = "sun_altitude_angle"


@dataclass(frozen=True)
class Rain(_Event):
    """Rain starting: precipitation ramps to ``target`` (%) over [start_s, end_s]; cloudiness ramps to
    ``cloudiness_target`` (%) over the same interval; precipitation_deposits follows ``lag_s`` seconds later, ramping
    to ``deposits_target`` (% ; default ``target``) over [start_s + lag_s, end_s + lag_s] (puddles lag the rain, as in
    CARLA's ``dynamic_weather.py``)."""

    lag_s: float = 30.0
    deposits_target: float | None = None
    cloudiness_target: float = 90.0

    kind: ClassVar[str] = "rain"
    parameter: ClassVar[str] = "precipitation"

    def __post_init__(self) -> None:
        super().__post_init__()
        lag = _number("rain event: lag", self.lag_s)
        if lag < 0:
            raise ValueError(f"rain event: lag must be >= 0 s, got {lag:g}")
        object.__setattr__(self, "lag_s", lag)
        deposits = self.target if self.deposits_target is None else self.deposits_target
        object.__setattr__(
            self, "deposits_target", _in_range("precipitation_deposits", deposits, "rain event: deposits")
        )
        object.__setattr__(
            self, "cloudiness_target", _in_range("cloudiness", self.cloudiness_target, "rain event: clouds")
        )

    @property
    def end_s(self) -> float:
        return self.start_s + self.lag_s + self.duration_s

    def apply(self, values: dict[str, np.ndarray], times: np.ndarray) -> None:
        super().apply(values, times)
        values["cloudiness"] = ramp(values["cloudiness"], times, self.start_s, self.duration_s, self.cloudiness_target)
        values["precipitation_deposits"] = ramp(
            values["precipitation_deposits"],
            times,
            self.start_s + self.lag_s,
            self.duration_s,
            self.deposits_target,  # type: ignore[arg-type]
        )


Event = Fog | Rain | Dusk
#: The events by kind (``drive.json``'s ``"kind"``, ``pidc drive --event KIND:…``).
EVENTS: dict[str, type[_Event]] = {cls.kind: cls for cls in (Fog, Rain, Dusk)}


def event_from_dict(d: Mapping[str, Any]) -> Event:
    """The event of a ``drive.json`` entry (:meth:`Fog.to_dict` etc.).

    Raises:
        ValueError: an unknown kind or field, or a value the event refuses.
    """
    d = dict(d)
    kind = d.pop("kind", None)
    if kind not in EVENTS:
        raise ValueError(f"unknown event kind {kind!r}; known: {', '.join(EVENTS)}")
    cls = EVENTS[kind]
    names = [f.name for f in fields(cls)]
    unknown = [k for k in d if k not in names]
    if unknown:
        raise ValueError(f"{kind} event: unknown field(s) {', '.join(unknown)}; known: {', '.join(names)}")
    try:
        return cls(**d)  # type: ignore[return-value]
    except TypeError:
        missing = [f.name for f in fields(cls) if f.name not in d and f.name in ("start_s", "duration_s", "target")]
        raise ValueError(f"{kind} event: missing {', '.join(missing)}") from None


def uniform_ou(low: float, high: float, n: int, dt: float, correlation_s: float, noise: np.ndarray) -> np.ndarray:
    """A walk in [low, high] with a uniform marginal and lag-1 autocorrelation exp(−dt/τ): low + w Φ(z_k).

    z_0 = ξ_0, z_k = ρ z_{k−1} + √(1 − ρ²) ξ_k (a stationary Ornstein–Uhlenbeck process of unit variance, sampled
    exactly every ``dt`` seconds), ρ = 2 sin(π a / 6), a = exp(−dt/τ), w = high − low.

    Arguments:
        low: the box's lower face.
        high: its upper face, ≥ low (low = high gives the constant low).
        n: frames.
        dt: seconds between frames.
        correlation_s: τ, seconds.
        noise: ``(n,)`` standard normal draws ξ.

    Returns:
        ``(n,)`` float64 in [low, high].
    """
    from scipy.special import ndtr

    w = high - low
    if w == 0 or n == 0:
        return np.full(n, low, dtype=np.float64)
    a = math.exp(-dt / correlation_s)
    rho = 2.0 * math.sin(math.pi * a / 6.0)
    b = math.sqrt(1.0 - rho * rho)
    xi = noise.tolist()
    z = [0.0] * n
    x = xi[0]
    for k in range(n):
        if k:
            x = rho * x + b * xi[k]
        z[k] = x
    return np.clip(low + w * ndtr(np.asarray(z, dtype=np.float64)), low, high)


class Frame(NamedTuple):
    """One frame of a drive: its time (seconds), its complete weather (13 CARLA parameters) and its image
    ``(size, size, 3)`` uint8 RGB."""

    time_s: float
    weather: dict[str, float]
    image: np.ndarray


class Exit(NamedTuple):
    """The first frame whose weather is outside a box: its time (seconds), index, and the parameters outside."""

    time_s: float
    frame: int
    parameters: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class Drive:
    """A simulated drive (see the module docstring).

    Attributes:
        seconds: its length, seconds (> 0; at least one frame).
        seed: the root of every draw (walk, scenes), a non-negative integer.
        fps: frames per second (> 0).
        size: the images' side, pixels (within :data:`components.core.images.RENDER_SIDES`).
        box: the walked parameters → (low, high), physical units (:func:`check_box`); default (None):
            :data:`DEFAULT_BOX` less the parameters in ``held``.
        held: the values of some parameters outside the box; the others take :data:`DEFAULT_HELD`'s.
        correlation_s: τ of the walk, seconds (> 0).
        events: scripted events, applied in this order over the walk; each starts within the drive.
        scene_seconds: seconds per scene (> 0): a new scene (map, camera, traffic) every so many seconds.
    """

    seconds: float
    seed: int
    fps: float = DRIVE_DEFAULTS["fps"]
    size: int = int(DRIVE_DEFAULTS["size"])
    box: Mapping[str, tuple[float, float]] | None = None
    held: Mapping[str, float] = field(default_factory=dict)
    correlation_s: float = DRIVE_DEFAULTS["correlation_s"]
    events: tuple[Event, ...] = ()
    scene_seconds: float = DRIVE_DEFAULTS["scene_seconds"]

    def __post_init__(self) -> None:
        seconds = _positive("seconds", self.seconds)
        fps = _positive("fps", self.fps, "frames/s")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int | np.integer) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")
        low, high = RENDER_SIDES
        if isinstance(self.size, bool) or not isinstance(self.size, int | np.integer) or not low <= self.size <= high:
            raise ValueError(f"size must be a whole number of pixels within {low}..{high}, got {self.size!r}")
        box = check_box({n: v for n, v in DEFAULT_BOX.items() if n not in self.held} if self.box is None else self.box)
        held = check_held(self.held, box)
        events = tuple(self.events)
        for e in events:
            if not isinstance(e, _Event):
                raise ValueError(f"events must be Fog, Rain or Dusk, got {e!r}")
            if e.start_s >= seconds:
                raise ValueError(
                    f"{e.kind} event: start {e.start_s:g} s is not within the drive's {seconds:g} s; it would never "
                    "happen"
                )
        for name, v in (
            ("seconds", seconds),
            ("fps", fps),
            ("seed", int(self.seed)),
            ("size", int(self.size)),
            ("box", box),
            ("held", {n: held.get(n, DEFAULT_HELD[n]) for n in DRIVEN if n not in box}),
            ("correlation_s", _positive("correlation time", self.correlation_s)),
            ("events", events),
            ("scene_seconds", _positive("scene seconds", self.scene_seconds)),
        ):
            object.__setattr__(self, name, v)
        if self.n_frames < 1:
            raise ValueError(f"a drive of {seconds:g} s at {fps:g} frames/s has no frame; make it longer")

    @property
    def n_frames(self) -> int:
        """n = round(seconds · fps)."""
        return int(math.floor(self.seconds * self.fps + 0.5))

    def times(self) -> np.ndarray:
        """``(n,)`` float64: t_k = k / fps, seconds."""
        return np.arange(self.n_frames, dtype=np.float64) / self.fps

    def scene_index(self, k: int) -> int:
        """The scene j of frame k: ⌊t_k / scene_seconds⌋."""
        return int(math.floor(k / (self.fps * self.scene_seconds) + _EPS))

    def scene_seed(self, k: int) -> int:
        """The renderer's scene seed of frame k: ``derive_seed(seed, "drive", "scene", j)``."""
        return derive_seed(self.seed, "drive", "scene", self.scene_index(k))

    def odd_box(self) -> dict[str, tuple[float, float]]:
        """The drive's own ODD, all of :data:`DRIVEN`: the walk's box, each held parameter as (value, value)."""
        return {n: self.box[n] if n in self.box else (self.held[n], self.held[n]) for n in DRIVEN}

    def weather_table(self) -> dict[str, np.ndarray]:
        """θ(t) and the azimuth at every frame: ``{"time_s": (n,), name: (n,) for name in DRIVEN}``, float64, physical
        units: the walk (or the held values), then the events."""
        n, t = self.n_frames, self.times()
        values: dict[str, np.ndarray] = {}
        for name in DRIVEN:
            if name in self.box:
                low, high = self.box[name]
                noise = rng(self.seed, "drive", "walk", name).standard_normal(n)
                values[name] = uniform_ou(low, high, n, 1.0 / self.fps, self.correlation_s, noise)
            else:
                values[name] = np.full(n, self.held[name], dtype=np.float64)
        for e in self.events:
            e.apply(values, t)
        return {"time_s": t, **values}

    def frames(self, simulator: Simulator | None = None) -> Iterator[Frame]:
        """Stream the drive's frames in time order, rendering each when asked (nothing is held but the scene cache).

        Arguments:
            simulator: the renderer (default: a :class:`~components.simulate.procedural.renderer.ProceduralSimulator`
                of ``size × size`` keeping two scenes).

        Yields:
            :class:`Frame` ``(time_s, weather, image)``, the image ``(size, size, 3)`` uint8 RGB.
        """
        if simulator is None:
            from components.simulate.procedural.renderer import ProceduralSimulator

            simulator = ProceduralSimulator(self.size, self.size, cache_size=2)
        ipp_off()  # in the thread that iterates (renders): the same pixels on every CPU (components/core/opencv.py)
        table = self.weather_table()
        seed, scene = -1, -1
        for k, t in enumerate(table["time_s"].tolist()):
            j = self.scene_index(k)
            if j != scene:
                scene, seed = j, derive_seed(self.seed, "drive", "scene", j)
            w = complete_weather({n: float(table[n][k]) for n in DRIVEN})
            yield Frame(t, w, simulator.render(w, seed))

    def to_dict(self, version: str | None = None) -> dict[str, Any]:
        """The drive as ``drive.json`` holds it: its settings, events, frame count, its own ODD's first exits
        (:func:`exits` of :meth:`odd_box`) and the renderer's ``version`` when given."""
        table = self.weather_table()
        first = first_exit(table, self.odd_box())
        return {
            "fps": self.fps,
            "seconds": self.seconds,
            "frames": self.n_frames,
            "seed": self.seed,
            "size": [self.size, self.size],
            "scene_seconds": self.scene_seconds,
            "box": {n: list(v) for n, v in self.box.items()},
            "held": dict(self.held),
            "correlation_seconds": self.correlation_s,
            "events": [e.to_dict() for e in self.events],
            "first_exit": None if first is None else first._asdict() | {"parameters": list(first.parameters)},
            "exits": exits(table, self.odd_box()),
            "renderer": version,
        }


def first_exit(table: Mapping[str, Any], box: Mapping[str, Sequence[float]]) -> Exit | None:
    """The first frame whose weather leaves the closed ``box``.

    Arguments:
        table: columns ``time_s`` and every parameter of ``box``, each ``(n,)`` (:meth:`Drive.weather_table`,
            :func:`read_weather_csv` or a pandas DataFrame of ``weather.csv``).
        box: parameter → (low, high), physical units.

    Returns:
        :class:`Exit` (time_s, frame, the parameters outside at that frame, in ``box`` order), or None if θ(t) stays
        in the box.
    """
    names = list(box)
    missing = [n for n in ("time_s", *names) if n not in table]
    if missing:
        raise ValueError(f"the weather table has no column {', '.join(repr(m) for m in missing)}")
    outside = np.stack(
        [
            (np.asarray(table[n], dtype=np.float64) < float(box[n][0]))
            | (np.asarray(table[n], dtype=np.float64) > float(box[n][1]))
            for n in names
        ]
    )
    hit = outside.any(axis=0)
    if not hit.any():
        return None
    k = int(np.argmax(hit))
    return Exit(float(np.asarray(table["time_s"])[k]), k, tuple(n for i, n in enumerate(names) if outside[i, k]))


def exits(table: Mapping[str, Any], box: Mapping[str, Sequence[float]]) -> dict[str, float]:
    """Per parameter of ``box``, the first time (seconds) it leaves its range; parameters that stay in are left out."""
    out = {}
    for name, pair in box.items():
        e = first_exit(table, {name: pair})
        if e is not None:
            out[name] = e.time_s
    return out


def _csv(rows: Sequence[Sequence[object]]) -> bytes:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    return buf.getvalue().encode("utf-8")


def _weather_rows(table: Mapping[str, np.ndarray], first: str, keys: Sequence[object]) -> list[list[object]]:
    cols = [table["time_s"].tolist(), *(table[n].tolist() for n in DRIVEN)]
    return [[first, "time_s", *DRIVEN], *([key, *(repr(c[k]) for c in cols)] for k, key in enumerate(keys))]


def frame_names(n: int) -> list[str]:
    """The PNG names of n frames: zero-padded numbers (6 digits, more past a million), so name order is time order."""
    width = max(6, len(str(max(n - 1, 0))))
    return [f"{k:0{width}d}.png" for k in range(n)]


def write_folder(
    drive: Drive,
    out: str | os.PathLike[str],
    *,
    simulator: Simulator | None = None,
    progress: Callable[[int], object] | None = None,
) -> Path:
    """Render ``drive`` into the folder ``out``: ``000000.png …``, ``times.csv`` (``image,time_s``), ``weather.csv``
    (``image,time_s`` + :data:`DRIVEN`: the truth) and ``drive.json`` (:meth:`Drive.to_dict`).

    The folder appears whole when done (:func:`components.core.files.atomic_folder`; a killed run leaves none).

    Arguments:
        drive: the drive.
        out: a folder that does not exist or is empty.
        simulator: the renderer (default: :meth:`Drive.frames`'s).
        progress: called with 1 after each frame (e.g. a tqdm bar's ``update``).

    Returns:
        ``Path(out)``.

    Raises:
        FileExistsError: ``out`` is a file or a folder that is not empty.
    """
    import cv2

    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(f"{out}: exists and is {'not a folder' if not out.is_dir() else 'not empty'}")
    if simulator is None:
        from components.simulate.procedural.renderer import ProceduralSimulator

        simulator = ProceduralSimulator(drive.size, drive.size, cache_size=2)
    names = frame_names(drive.n_frames)
    with atomic_folder(out, fsync=False) as tmp:
        for name, frame in zip(names, drive.frames(simulator), strict=True):
            ok, buf = cv2.imencode(".png", np.ascontiguousarray(frame.image[:, :, ::-1]))
            if not ok:
                raise ValueError(f"could not encode {out / name} as PNG")
            (tmp / name).write_bytes(buf.tobytes())
            if progress is not None:
                progress(1)
        table = drive.weather_table()
        (tmp / "times.csv").write_bytes(
            _csv([["image", "time_s"], *([n, repr(t)] for n, t in zip(names, table["time_s"].tolist(), strict=True))])
        )
        (tmp / "weather.csv").write_bytes(_csv(_weather_rows(table, "image", names)))
        (tmp / "drive.json").write_text(json.dumps(drive.to_dict(simulator.version), indent=2) + "\n")
    return out


def video_sidecars(video: str | os.PathLike[str]) -> tuple[Path, Path]:
    """``OUT.weather.csv`` and ``OUT.drive.json`` beside the video ``OUT.avi`` (or ``.mp4``, ``.mkv``)."""
    v = Path(video)
    return v.with_suffix(".weather.csv"), v.with_suffix(".drive.json")


def write_video(
    drive: Drive,
    video: str | os.PathLike[str],
    *,
    simulator: Simulator | None = None,
    progress: Callable[[int], object] | None = None,
) -> Path:
    """Render ``drive`` into the video ``video`` at ``fps`` (:data:`VIDEO_CODECS` by its extension) and write its
    truth beside it (:func:`video_sidecars`): ``OUT.weather.csv`` (``frame,time_s`` + :data:`DRIVEN`, the frame
    a 0-based index) and ``OUT.drive.json``.

    The video is written under a temporary name and renamed when complete; a failed run leaves no video.

    Returns:
        ``Path(video)``.

    Raises:
        ValueError: an extension not in :data:`VIDEO_CODECS`.
        OSError: OpenCV cannot open a writer for it.
    """
    import cv2

    video = Path(video)
    suffix = video.suffix.lower()
    if suffix not in VIDEO_CODECS:
        raise ValueError(f"{video}: a drive video is {', '.join(VIDEO_CODECS)}, got {video.suffix or 'no extension'!r}")
    if simulator is None:
        from components.simulate.procedural.renderer import ProceduralSimulator

        simulator = ProceduralSimulator(drive.size, drive.size, cache_size=2)
    video.parent.mkdir(parents=True, exist_ok=True)
    tmp = video.with_name(f".{video.name}.{secrets.token_hex(4)}.tmp{video.suffix}")  # OpenCV picks the container by it
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*VIDEO_CODECS[suffix]), drive.fps, (drive.size,) * 2)
    try:
        if not writer.isOpened():
            raise OSError(f"{video}: OpenCV cannot write {VIDEO_CODECS[suffix]} video here")
        for frame in drive.frames(simulator):
            writer.write(np.ascontiguousarray(frame.image[:, :, ::-1]))  # OpenCV takes BGR
            if progress is not None:
                progress(1)
        writer.release()
        os.replace(tmp, video)
    except BaseException:
        writer.release()
        tmp.unlink(missing_ok=True)
        raise
    weather_csv, drive_json = video_sidecars(video)
    table = drive.weather_table()
    atomic_write_bytes(weather_csv, _csv(_weather_rows(table, "frame", range(drive.n_frames))))
    atomic_write_bytes(drive_json, (json.dumps(drive.to_dict(simulator.version), indent=2) + "\n").encode())
    return video


def read_weather_csv(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """A drive's ``weather.csv`` (or ``OUT.weather.csv``) as columns: ``image`` (or ``frame``) as written, the others
    float64 ``(n,)`` (:func:`first_exit` takes it)."""
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    if not rows or "time_s" not in rows[0]:
        raise ValueError(f"{path}: not a drive's weather table (no time_s column)")
    header, body = rows[0], rows[1:]
    out: dict[str, np.ndarray] = {}
    for i, name in enumerate(header):
        col = [r[i] for r in body]
        out[name] = np.asarray(col) if name == "image" else np.asarray(col, dtype=np.float64)
    if "frame" in out:
        out["frame"] = out["frame"].astype(np.int64)
    return out
