"""The weather space of the paper (Table 1): CARLA's 13 weather parameters.

Six parameters are predicted; together they form θ ∈ ℝ⁶ in the order of :data:`PREDICTED`
(cloudiness, fog density, precipitation, sun altitude, wind intensity, precipitation deposits).
The sun azimuth is a nuisance drawn uniformly and never predicted; the other six are fixed.

Everything here is numpy only: it is shared by the simulator, the dataset, the torch posterior and
the torch-free runtime. Arrays of θ have shape ``(..., 6)`` in physical units (percent or degrees).

The bijection :func:`to_unbounded` / :func:`to_physical` maps the prior's box onto ℝ⁶ by a scaled
logit per parameter, so that a flow living in ℝ⁶ puts no mass outside the physical ranges; its
log-Jacobian :func:`log_abs_det_jacobian` converts densities between the two spaces.

Used by every stage and the ``pidc`` CLI.

References:
    Halin, Piérard et al., "Physically Interpretable Probabilistic Domain Characterization", Table 1 (the weather
    parameters, their ranges and the fixed values).

Examples:
    >>> from components.core import weather
    >>> weather.SHORT_NAMES
    ('cloud', 'fog', 'rain', 'sun', 'wind', 'deposit')
    >>> w = weather.weather_from_theta([20, 0, 60, 35, 10, 40], sun_azimuth_angle=90)
    >>> len(w), w["fog_distance"]
    (13, 0.75)
    >>> weather.theta_from_weather(w).tolist()
    [20.0, 0.0, 60.0, 35.0, 10.0, 40.0]
    >>> weather.validate_weather({"sun_altitude_angle": 120})
    Traceback (most recent call last):
    ...
    ValueError: weather parameter 'sun_altitude_angle' = 120 is outside its range [-90, 90] deg
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Parameter",
    "PARAMETERS",
    "PREDICTED",
    "SHORT_NAMES",
    "NUISANCE",
    "FIXED",
    "ALL_NAMES",
    "Box",
    "sample_azimuth",
    "EDGE_EPS",
    "validate_weather",
    "complete_weather",
    "theta_from_weather",
    "weather_from_theta",
    "weather_array",
    "to_unbounded",
    "to_physical",
    "log_abs_det_jacobian",
]


@dataclass(frozen=True)
class Parameter:
    """One CARLA weather parameter.

    Attributes:
        name: CARLA's keyword (``carla.WeatherParameters`` field).
        low: the lower end of the physical range (inclusive), in ``unit``.
        high: the upper end of the physical range (inclusive), in ``unit``; ``inf`` where CARLA sets no bound.
        unit: ``"%"``, ``"deg"`` or ``"m"``/``""`` for the fixed ones.
        role: ``"predicted"``, ``"nuisance"`` or ``"fixed"``.
        short: a short label for plots and tables.
        fixed: the fixed value (``role == "fixed"`` only).
    """

    name: str
    low: float
    high: float
    unit: str
    role: str
    short: str
    fixed: float | None = None

    def describe_range(self) -> str:
        return f"[{self.low:g}, {self.high:g}] {self.unit}".rstrip()


_TABLE: tuple[Parameter, ...] = (
    # predicted (θ, in this order)
    Parameter("cloudiness", 0.0, 100.0, "%", "predicted", "cloud"),
    Parameter("fog_density", 0.0, 100.0, "%", "predicted", "fog"),
    Parameter("precipitation", 0.0, 100.0, "%", "predicted", "rain"),
    Parameter("sun_altitude_angle", -90.0, 90.0, "deg", "predicted", "sun"),
    Parameter("wind_intensity", 0.0, 100.0, "%", "predicted", "wind"),
    Parameter("precipitation_deposits", 0.0, 100.0, "%", "predicted", "deposit"),
    # nuisance
    Parameter("sun_azimuth_angle", 0.0, 360.0, "deg", "nuisance", "azimuth"),
    # fixed (paper, Table 1); ranges are CARLA's clamps
    Parameter("fog_distance", 0.0, math.inf, "m", "fixed", "fog_dist", 0.75),
    Parameter("fog_falloff", 0.0, math.inf, "", "fixed", "fog_falloff", 0.1),
    Parameter("mie_scattering_scale", 0.0, 5.0, "", "fixed", "mie", 0.03),
    Parameter("rayleigh_scattering_scale", 0.0, 2.0, "", "fixed", "rayleigh", 0.0331),
    Parameter("scattering_intensity", 0.0, math.inf, "", "fixed", "scattering", 1.0),
    Parameter("wetness", 0.0, 100.0, "%", "fixed", "wetness", 0.0),
)

#: All 13 parameters by CARLA name.
PARAMETERS: dict[str, Parameter] = {p.name: p for p in _TABLE}
#: The 13 names in the canonical storage order (predicted, nuisance, fixed).
ALL_NAMES: tuple[str, ...] = tuple(p.name for p in _TABLE)
#: The predicted parameters, in the order of θ.
PREDICTED: tuple[str, ...] = tuple(p.name for p in _TABLE if p.role == "predicted")
#: Short labels of θ, same order.
SHORT_NAMES: tuple[str, ...] = tuple(PARAMETERS[n].short for n in PREDICTED)
#: The nuisance parameters (drawn uniformly on their range, not predicted).
NUISANCE: tuple[str, ...] = tuple(p.name for p in _TABLE if p.role == "nuisance")
#: The fixed parameters and their values.
FIXED: dict[str, float] = {p.name: float(p.fixed) for p in _TABLE if p.role == "fixed"}  # type: ignore[arg-type]

_LOWS = np.array([PARAMETERS[n].low for n in PREDICTED])
_HIGHS = np.array([PARAMETERS[n].high for n in PREDICTED])


def _check_value(name: str, value: object, low: float, high: float, where: str = "") -> float:
    p = PARAMETERS[name]
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{where}weather parameter {name!r} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{where}weather parameter {name!r} must be finite, got {v!r}; range {p.describe_range()}")
    if not (low <= v <= high):
        raise ValueError(
            f"{where}weather parameter {name!r} = {v:g} is outside its range [{low:g}, {high:g}] {p.unit}".rstrip()
        )
    return v


def validate_weather(weather: Mapping[str, object], *, where: str = "") -> dict[str, float]:
    """Check a weather mapping (CARLA names → values) and return it as floats.

    Fixed parameters, when given, must equal their fixed value (the renderer and the posteriors are only defined
    there). Missing parameters are allowed here (:func:`complete_weather` requires and fills them).

    Arguments:
        weather: CARLA parameter names → numbers in physical units (%, degrees, metres).
        where: a prefix of the error messages (e.g. a file name).

    Returns:
        The same names → ``float``.

    Raises:
        ValueError: naming the parameter and its range, for an unknown name, a non-number, a non-finite value, a
            value outside the physical range or a fixed parameter given another value.
    """
    if not isinstance(weather, Mapping):
        raise ValueError(
            f"{where}a weather must be a mapping of CARLA parameter names to numbers, got {type(weather).__name__}"
        )
    out: dict[str, float] = {}
    for name, value in weather.items():
        if name not in PARAMETERS:
            raise ValueError(f"{where}unknown weather parameter {name!r}; known: {', '.join(ALL_NAMES)}")
        p = PARAMETERS[name]
        v = _check_value(name, value, p.low, p.high, where)
        if p.role == "fixed" and not math.isclose(v, p.fixed, rel_tol=1e-9, abs_tol=1e-12):  # type: ignore[arg-type]
            raise ValueError(f"{where}weather parameter {name!r} is fixed to {p.fixed:g} in pidc, got {v:g}")
        out[name] = v
    return out


def complete_weather(weather: Mapping[str, object], *, where: str = "") -> dict[str, float]:
    """Validate ``weather`` and fill the missing parameters: fixed ones take their fixed value.

    Arguments:
        weather: CARLA parameter names → numbers; the six predicted parameters and the sun azimuth are required.
        where: a prefix of the error messages (e.g. a file name).

    Returns:
        All 13 parameters → ``float``, in :data:`ALL_NAMES` order.

    Raises:
        ValueError: as :func:`validate_weather`, or naming every missing required parameter and its range.
    """
    out = validate_weather(weather, where=where)
    missing = [n for n in PREDICTED + NUISANCE if n not in out]
    if missing:
        raise ValueError(
            f"{where}weather is missing {', '.join(repr(m) for m in missing)}; "
            + "; ".join(f"{m} in {PARAMETERS[m].describe_range()}" for m in missing)
        )
    for name, value in FIXED.items():
        out.setdefault(name, value)
    return {n: out[n] for n in ALL_NAMES}


def weather_array(weather: Mapping[str, object]) -> np.ndarray:
    """A complete, validated weather as a float64 vector of 13 values in :data:`ALL_NAMES` order."""
    w = complete_weather(weather)
    return np.array([w[n] for n in ALL_NAMES], dtype=np.float64)


def theta_from_weather(weather: Mapping[str, float] | np.ndarray) -> np.ndarray:
    """θ, the six predicted parameters, from a weather.

    Arguments:
        weather: a mapping of CARLA names (validated; the predicted parameters required), or an array ``(..., 13)``
            of rows in :data:`ALL_NAMES` order.

    Returns:
        θ, ``(6,)`` for a mapping or ``(..., 6)`` for rows, float64 in physical units, in :data:`PREDICTED` order.
    """
    if isinstance(weather, Mapping):
        w = validate_weather(weather)
        return np.array([w[n] for n in PREDICTED], dtype=np.float64)
    arr = np.asarray(weather, dtype=np.float64)
    if arr.shape[-1] != len(ALL_NAMES):
        raise ValueError(f"weather rows must have {len(ALL_NAMES)} values in ALL_NAMES order, got shape {arr.shape}")
    return arr[..., : len(PREDICTED)]


def weather_from_theta(theta: Iterable[float], sun_azimuth_angle: float) -> dict[str, float]:
    """A complete weather mapping from θ and a sun azimuth.

    Arguments:
        theta: 6 values in :data:`PREDICTED` order, physical units (% and degrees).
        sun_azimuth_angle: the nuisance sun azimuth, degrees in [0, 360].

    Returns:
        All 13 parameters → ``float`` (the fixed ones at their values), as :func:`complete_weather`.
    """
    t = np.asarray(list(theta), dtype=np.float64)
    if t.shape != (len(PREDICTED),):
        raise ValueError(f"θ must have {len(PREDICTED)} values ({', '.join(PREDICTED)}), got shape {t.shape}")
    w = {n: float(v) for n, v in zip(PREDICTED, t, strict=False)}
    w["sun_azimuth_angle"] = float(sun_azimuth_angle)
    return complete_weather(w)


@dataclass(frozen=True, eq=False)
class Box:
    """An axis-aligned box ``[low, high]`` in θ-space: the support of a uniform prior.

    The weather prior is the 6-D box of :data:`PREDICTED` (:meth:`full`, :meth:`from_mapping`); the
    same class serves boxes of any dimension ``d`` (e.g. 1–2-D toys whose posterior is known).

    Attributes:
        low: read-only float64 array ``(d,)`` of the lower faces, physical units, finite.
        high: read-only float64 array ``(d,)`` of the upper faces, physical units, finite, ``low < high``.
        names: one name per parameter (used in messages; ``θ0, θ1, …`` when not given). A name that is a
            weather parameter must stay within its physical range.
        units: one unit per parameter (from :data:`PARAMETERS` for weather names, else ``""``).

    Examples:
        >>> import numpy as np
        >>> from components.core.weather import Box
        >>> box = Box.from_mapping({"sun_altitude_angle": (0, 90)})  # daytime only
        >>> box.dim, box.low[3].item(), box.high[3].item()
        (6, 0.0, 90.0)
        >>> round(box.log_volume(), 3)  # log(100⁵ · 90): the uniform prior's density is 1/(100⁵ · 90)
        27.526
        >>> theta = box.sample(np.random.default_rng(0), 4)
        >>> theta.shape, bool(box.contains(theta).all())
        ((4, 6), True)
    """

    low: np.ndarray
    high: np.ndarray
    names: tuple[str, ...] = ()
    units: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        low = np.atleast_1d(np.asarray(self.low, dtype=np.float64)).copy()
        high = np.atleast_1d(np.asarray(self.high, dtype=np.float64)).copy()
        if low.ndim != 1 or low.shape != high.shape or low.size == 0:
            raise ValueError(
                f"a box needs two 1-D arrays of equal length >= 1, got shapes {low.shape} and {high.shape}"
            )
        d = low.size
        names = tuple(self.names) or tuple(f"θ{i}" for i in range(d))
        units = tuple(self.units) or tuple(PARAMETERS[n].unit if n in PARAMETERS else "" for n in names)
        if len(names) != d or len(units) != d:
            raise ValueError(f"a box of dimension {d} needs {d} names and units, got {len(names)} and {len(units)}")
        for i, name in enumerate(names):
            if name in PARAMETERS:
                p = PARAMETERS[name]
                for v in (low[i], high[i]):
                    _check_value(name, v, p.low, p.high, "prior box: ")
            if not (math.isfinite(low[i]) and math.isfinite(high[i]) and low[i] < high[i]):
                raise ValueError(f"prior box: {name!r} needs finite low < high, got [{low[i]:g}, {high[i]:g}]")
        low.setflags(write=False)
        high.setflags(write=False)
        for attr, value in (("low", low), ("high", high), ("names", names), ("units", units)):
            object.__setattr__(self, attr, value)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Box):
            return NotImplemented
        return (
            np.array_equal(self.low, other.low)
            and np.array_equal(self.high, other.high)
            and self.names == other.names
            and self.units == other.units
        )

    def __hash__(self) -> int:
        return hash((self.low.tobytes(), self.high.tobytes(), self.names, self.units))

    @classmethod
    def full(cls) -> Box:
        """The whole physical range of every predicted parameter (the paper's prior)."""
        return cls(_LOWS.copy(), _HIGHS.copy(), PREDICTED)

    @classmethod
    def from_mapping(cls, ranges: Mapping[str, Iterable[float]]) -> Box:
        """The 6-D weather box from ``{name: (low, high)}``; missing names take their full physical range."""
        unknown = [k for k in ranges if k not in PREDICTED]
        if unknown:
            raise ValueError(f"prior box: unknown predicted parameter(s) {unknown}; known: {', '.join(PREDICTED)}")
        low, high = _LOWS.copy(), _HIGHS.copy()
        for i, name in enumerate(PREDICTED):
            if name in ranges:
                pair = list(ranges[name])
                if len(pair) != 2:
                    raise ValueError(f"prior box: {name!r} needs [low, high], got {pair}")
                low[i], high[i] = pair
        return cls(low, high, PREDICTED)

    @property
    def dim(self) -> int:
        """d, the number of parameters."""
        return int(self.low.size)

    @property
    def width(self) -> np.ndarray:
        """high − low, shape ``(d,)``."""
        return self.high - self.low

    def log_volume(self) -> float:
        """log of the box volume in physical units (e.g. %⁵·deg for the weather box)."""
        return float(np.log(self.width).sum())

    def contains(self, theta: np.ndarray) -> np.ndarray:
        """Boolean mask of shape ``theta.shape[:-1]``: inside the closed box (NaN is outside)."""
        t = np.asarray(theta, dtype=np.float64)
        return np.all((t >= self.low) & (t <= self.high), axis=-1)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` draws of θ from the uniform prior on the box, shape ``(n, d)``."""
        if n < 0:
            raise ValueError(f"number of prior samples must be >= 0, got {n}")
        return self.low + rng.random((n, self.dim)) * self.width

    def log_prob(self, theta: np.ndarray) -> np.ndarray:
        """Uniform prior log-density in physical units; ``-inf`` outside the box."""
        inside = self.contains(theta)
        return np.where(inside, -self.log_volume(), -np.inf)

    def check(self, theta: object, *, what: str = "θ") -> None:
        """Raise ``ValueError`` naming the first parameter of ``theta`` ``(..., d)`` outside the box or non-finite.

        ``theta`` is an array or a (CPU or GPU) torch tensor.
        """
        if hasattr(theta, "detach"):  # a torch tensor, without importing torch here
            theta = theta.detach().cpu().double().numpy()  # type: ignore[union-attr]
        t = np.asarray(theta, dtype=np.float64)
        if t.shape[-1:] != (self.dim,):
            raise ValueError(f"{what} must have shape (..., {self.dim}) ({', '.join(self.names)}), got {t.shape}")
        flat = t.reshape(-1, self.dim)
        for i, name in enumerate(self.names):
            col = flat[:, i]
            bad = ~np.isfinite(col) | (col < self.low[i]) | (col > self.high[i])
            if bad.any():
                j = int(np.argmax(bad))
                raise ValueError(
                    f"{what}: {name!r} = {float(col[j])!r} at row {j} is outside the prior box "
                    f"[{self.low[i]:g}, {self.high[i]:g}] {self.units[i]}".rstrip()
                )


def sample_azimuth(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` nuisance sun azimuths, uniform on [0, 360) degrees."""
    return rng.random(n) * 360.0


# --- the bijection between the box and ℝ⁶ (scaled logit) --------------------------------------

#: Distance (as a fraction of the box width) kept from the box's faces when mapping to ℝ⁶, so that
#: θ exactly on a face maps to a finite point (|z| ≤ logit(1 − EDGE_EPS) ≈ 13.8).
EDGE_EPS = 1e-6


def to_unbounded(theta: np.ndarray, box: Box) -> np.ndarray:
    """z = logit(u), u = (θ − low)/(high − low) clipped to [ε, 1 − ε]; shape preserved."""
    u = (np.asarray(theta, dtype=np.float64) - box.low) / box.width
    u = np.clip(u, EDGE_EPS, 1.0 - EDGE_EPS)
    return np.log(u) - np.log1p(-u)


def to_physical(z: np.ndarray, box: Box) -> np.ndarray:
    """θ = low + (high − low)·σ(z): the inverse of :func:`to_unbounded`; never leaves the box."""
    u = 0.5 * (1.0 + np.tanh(0.5 * np.asarray(z, dtype=np.float64)))  # stable sigmoid
    return np.clip(box.low + box.width * u, box.low, box.high)


def log_abs_det_jacobian(z: np.ndarray, box: Box) -> np.ndarray:
    """log |det ∂θ/∂z| at z, summed over the 6 parameters; shape ``z.shape[:-1]``.

    log p_θ(θ) = log p_z(z) − log |det ∂θ/∂z|.
    """
    z = np.asarray(z, dtype=np.float64)
    # log σ(z) + log σ(−z) = −softplus(−z) − softplus(z)
    per = np.log(box.width) - np.logaddexp(0.0, -z) - np.logaddexp(0.0, z)
    return per.sum(axis=-1)
