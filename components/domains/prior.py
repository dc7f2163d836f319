"""Your own prior: posterior draws under the training prior reweighted to a user's prior (importance sampling).

A registry model gives draws θᵢ ~ q(θ | x) ≈ p(θ | x) ∝ p(x | θ) π_train(θ), where π_train is the prior the model
learned under: uniform on the training box (``prior:`` in params.yaml; the generate stage draws θ uniformly on it).
Under another prior π_user that has a density with respect to π_train,

    p_user(θ | x) = p(θ | x) r(θ) / Z(x),      r(θ) = π_user(θ) / π_train(θ),      Z(x) = E_{p(θ | x)}[r(θ)],

so the draws weighted wᵢ = r(θᵢ) / Σⱼ r(θⱼ) are a weighted sample of p_user(θ | x) (self-normalized importance
sampling). Their effective sample size ESS = (Σ wᵢ)² / Σ wᵢ² ∈ [0, m] says how many unweighted draws they are worth:
m when π_user ∝ π_train on the posterior's support, few when π_user puts its mass where the image's posterior has
little (a dry-world prior and an image of heavy rain). Drawing n of them with replacement by weight
(sampling-importance-resampling) gives plain draws for medians, HDIs, histograms and kernel densities.

A user's prior (:class:`UserPrior`) is a product of one density per named parameter on its training range; the
parameters not named keep the training prior (their ratio r is 1). Each density is uniform on a sub-range, a normal
truncated to a range, a beta scaled to a range, or a mixture of these. A point mass (or a point mass plus a
continuous part) cannot be reached by reweighting: it has no density with respect to π_train (no draw of q ever hits
the point), so the file format refuses it. The file format (YAML, :func:`read_prior`) is described in docs/cli.md
("Your own prior").

Used by the ``pidc`` CLI (``characterize``, ``domain``, ``relate`` with ``--prior``).

Example:
    A standard normal posterior on [−5, 5] (the uniform training prior), reweighted to a prior N(1, 1):

    >>> import numpy as np
    >>> from components.core.weather import Box
    >>> box = Box(np.array([-5.0]), np.array([5.0]), names=("t",))
    >>> prior = parse_prior({"t": {"normal": [1, 1]}}, box, "toy.yaml")
    >>> draws = np.random.default_rng(0).standard_normal((20000, 1))
    >>> found = reweight(draws, prior, box)
    >>> round(float(found.weights @ draws[:, 0]), 1)  # the posterior N(0.5, 1/2)'s mean
    0.5
    >>> 4000 < found.ess < 20000
    True
"""

from __future__ import annotations

import hashlib
import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy import special, stats

from components.core import weather
from components.core.checks import whole_number
from components.core.seeding import derive_seed, rng

__all__ = [
    "PriorError",
    "Uniform",
    "TruncatedNormal",
    "ScaledBeta",
    "Mixture",
    "UserPrior",
    "parse_prior",
    "read_prior",
    "training_prior",
    "log_ratio",
    "effective_sample_size",
    "Reweighted",
    "reweight",
    "resample",
    "ReweightedPosterior",
    "ess_summary",
]

#: How close to 1 a mixture's weights must sum.
WEIGHT_TOLERANCE = 1e-6
#: The data sources whose θ the generate stage draws uniformly on the prior box (the card's ``training_renders``).
UNIFORM_SOURCES = ("procedural", "carla")
#: How close to a face of its range a beta's argument is taken (where a or b < 1 its density is infinite on the face).
_FACE = 1e-12
#: Keys that mean a point mass, refused with the reason.
_POINT_KEYS = ("point", "point_mass", "dirac", "delta", "fixed", "value", "constant")
_KINDS = ("uniform", "normal", "beta", "mixture")
_POINT_MASS = (
    "a point mass has no density with respect to the training prior (no posterior draw ever hits the point "
    "exactly), so reweighting cannot give it; use a narrow density near it, e.g. {beta: [1, 50]} near the low end "
    "or {normal: [VALUE, 1]}"
)


class PriorError(ValueError):
    """A prior file or a model's card that cannot give the importance weights: one line naming the file (or card),
    the parameter and the problem."""


# --- one parameter's densities ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Uniform:
    """Uniform on ``[low, high]`` (physical units): log π(t) = −log(high − low) inside, −inf outside."""

    low: float
    high: float

    def log_prob(self, t: np.ndarray) -> np.ndarray:
        """``t (n,)`` → ``(n,)`` log-densities per unit of the parameter."""
        inside = (t >= self.low) & (t <= self.high)
        return np.where(inside, -math.log(self.high - self.low), -np.inf)

    def describe(self) -> str:
        return f"uniform [{self.low:g}, {self.high:g}]"


@dataclass(frozen=True)
class TruncatedNormal:
    """N(mean, std²) truncated to ``[low, high]`` and normalized there."""

    mean: float
    std: float
    low: float
    high: float

    def mass(self) -> float:
        """The normal's mass on ``[low, high]`` (before the truncation normalizes it), float64."""
        a, b = (self.low - self.mean) / self.std, (self.high - self.mean) / self.std
        return float(special.ndtr(b) - special.ndtr(a)) if a < 0 else float(special.ndtr(-a) - special.ndtr(-b))

    def log_prob(self, t: np.ndarray) -> np.ndarray:
        a, b = (self.low - self.mean) / self.std, (self.high - self.mean) / self.std
        inside = (t >= self.low) & (t <= self.high)
        out = stats.truncnorm.logpdf(np.where(inside, t, self.low), a, b, loc=self.mean, scale=self.std)
        return np.where(inside, out, -np.inf)

    def describe(self) -> str:
        return f"normal({self.mean:g}, {self.std:g}) truncated to [{self.low:g}, {self.high:g}]"


@dataclass(frozen=True)
class ScaledBeta:
    """Beta(a, b) scaled to ``[low, high]``: π(t) = Beta((t − low)/(high − low); a, b) / (high − low)."""

    a: float
    b: float
    low: float
    high: float

    def log_prob(self, t: np.ndarray) -> np.ndarray:
        width = self.high - self.low
        inside = (t >= self.low) & (t <= self.high)
        # a draw exactly on a face would get an infinite density where a or b < 1: kept finite (q's draws never are:
        # the bijection keeps them EDGE_EPS of the width inside)
        u = np.clip((np.where(inside, t, self.low) - self.low) / width, _FACE, 1.0 - _FACE)
        out = stats.beta.logpdf(u, self.a, self.b) - math.log(width)
        return np.where(inside, out, -np.inf)

    def describe(self) -> str:
        return f"beta({self.a:g}, {self.b:g}) on [{self.low:g}, {self.high:g}]"


Density = Uniform | TruncatedNormal | ScaledBeta


@dataclass(frozen=True)
class Mixture:
    """Σₖ wₖ πₖ(t), the wₖ > 0 summing to 1, each πₖ a normalized density (not a mixture)."""

    weights: tuple[float, ...]
    components: tuple[Density, ...]

    def log_prob(self, t: np.ndarray) -> np.ndarray:
        parts = np.stack([math.log(w) + c.log_prob(t) for w, c in zip(self.weights, self.components, strict=True)])
        return special.logsumexp(parts, axis=0)

    def describe(self) -> str:
        return " + ".join(f"{w:g} × {c.describe()}" for w, c in zip(self.weights, self.components, strict=True))


Factor = Density | Mixture


@dataclass(frozen=True)
class UserPrior:
    """A user's prior on the training box: π_user(θ) = Πⱼ πⱼ(θⱼ), one density per named parameter (``factors``,
    by index into ``box``) and the training prior's uniform density on the others.

    Attributes:
        box: the training box (:class:`components.core.weather.Box`), θ ``(n, d)`` in its order and units.
        factors: ``{j: density of θⱼ}`` for the named parameters.
        source: where it was read from (a file name), for messages and reports.
    """

    box: weather.Box
    factors: Mapping[int, Factor]
    source: str = "prior"

    def log_prob(self, theta: np.ndarray) -> np.ndarray:
        """log π_user(θ) for ``theta (n, d)`` in physical units → ``(n,)``; −inf outside the box."""
        t = np.asarray(theta, dtype=np.float64)
        out = np.where(self.box.contains(t), 0.0, -np.inf)
        for j in range(self.box.dim):
            if j in self.factors:
                out = out + self.factors[j].log_prob(t[:, j])
            else:
                out = out - math.log(self.box.width[j])
        return out

    def describe(self) -> dict[str, str]:
        """``{parameter: its density in words}`` for the named parameters (the others keep the training prior)."""
        return {self.box.names[j]: self.factors[j].describe() for j in sorted(self.factors)}


# --- reading a prior file ------------------------------------------------------------------------------------------


class _DuplicateKey(yaml.YAMLError):
    pass


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, but a key written twice in one mapping is an error (PyYAML keeps the last silently)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[object, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, list | dict):
                continue
            if key in seen:
                raise _DuplicateKey(
                    f"line {key_node.start_mark.line + 1}: {key} appears twice (first at line {seen[key]})"
                )
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


def _number(value: object, what: str, fail: Any) -> float:
    """``value`` as a finite float (never a bool), else ``fail(message)``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(float(value)):
        raise fail(f"{what} must be a finite number, got {value!r}")
    return float(value)


def _pair(value: object, what: str, names: str, fail: Any) -> tuple[float, float]:
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise fail(f"{what} takes [{names}], got {value!r}")
    first, second = names.split(", ")
    return _number(value[0], f"{what}'s {first}", fail), _number(value[1], f"{what}'s {second}", fail)


def _range(value: object, what: str, low: float, high: float, unit: str, fail: Any) -> tuple[float, float]:
    """A sub-range ``[a, b]`` of the training range ``[low, high]``, a < b."""
    a, b = _pair(value, what, "low, high", fail)
    if not a < b:
        raise fail(f"{what} needs low < high, got [{a:g}, {b:g}]")
    if a < low or b > high:
        raise fail(
            f"{what} [{a:g}, {b:g}] lies outside the parameter's training range [{low:g}, {high:g}] {unit}".rstrip()
        )
    return a, b


def _density(spec: object, low: float, high: float, unit: str, fail: Any, nested: bool = False) -> Factor:
    """One parameter's density from its mapping (``{uniform: [a, b]}``, ``{normal: [mean, std], range: …}``,
    ``{beta: [a, b], range: …}``, ``{mixture: [{weight: w, …}, …]}``) on the training range ``[low, high]``."""
    if isinstance(spec, numbers.Real) and not isinstance(spec, bool):
        raise fail(f"a number ({spec:g}) is a point mass: {_POINT_MASS}")
    if not isinstance(spec, Mapping):
        raise fail(f"expected a mapping such as {{beta: [1, 8]}} (one of {', '.join(_KINDS)}), got {spec!r}")
    keys = [str(k) for k in spec if not (nested and k == "weight")]
    point = [k for k in keys if k in _POINT_KEYS]
    if point:
        raise fail(f"{point[0]!r}: {_POINT_MASS}")
    kinds = [k for k in keys if k in _KINDS]
    extra = [k for k in keys if k not in (*_KINDS, "range")]
    if extra:
        raise fail(f"unknown key {extra[0]!r}; expected one of {', '.join(_KINDS)} (and range for normal and beta)")
    if len(kinds) != 1:
        found = ", ".join(kinds) if kinds else "none"
        raise fail(f"expected exactly one of {', '.join(_KINDS)}, got {found}")
    kind = kinds[0]
    if "range" in spec and kind not in ("normal", "beta"):
        raise fail(f"range applies to normal and beta only, not to {kind}")
    a, b = _range(spec["range"], "range", low, high, unit, fail) if "range" in spec else (low, high)
    value = spec[kind]
    if kind == "uniform":
        return Uniform(*_range(value, "uniform", low, high, unit, fail))
    if kind == "normal":
        mean, std = _pair(value, "normal", "mean, std", fail)
        if std <= 0:
            raise fail(f"normal's std must be positive, got {std:g}")
        density = TruncatedNormal(mean, std, a, b)
        if density.mass() <= 0.0:
            raise fail(
                f"normal({mean:g}, {std:g}) is zero on [{a:g}, {b:g}] (its mass there underflows): the density is "
                "zero on the whole box"
            )
        return density
    if kind == "beta":
        alpha, beta = _pair(value, "beta", "a, b", fail)
        if alpha <= 0 or beta <= 0:
            raise fail(f"beta's a and b must be positive, got [{alpha:g}, {beta:g}]")
        return ScaledBeta(alpha, beta, a, b)
    if nested:
        raise fail("a mixture's component cannot be a mixture (write its components in the outer mixture)")
    if not isinstance(value, list) or not value:
        raise fail(f"mixture takes a non-empty list of components {{weight: w, <density>}}, got {value!r}")
    weights, components = [], []
    for k, item in enumerate(value, start=1):
        inner = _sub(fail, f"mixture component {k}")
        if not isinstance(item, Mapping) or "weight" not in item:
            raise inner(f"expected a mapping with a weight, e.g. {{weight: 0.3, uniform: [{low:g}, {high:g}]}}")
        w = _number(item["weight"], "weight", inner)
        if w <= 0:
            raise inner(f"weight must be positive, got {w:g}")
        weights.append(w)
        components.append(_density(item, low, high, unit, inner, nested=True))
    total = math.fsum(weights)
    if abs(total - 1.0) > WEIGHT_TOLERANCE:
        raise fail(f"mixture weights sum to {total:g}, expected 1 ({' + '.join(f'{w:g}' for w in weights)})")
    return Mixture(tuple(w / total for w in weights), tuple(components))  # type: ignore[arg-type]


def _sub(fail: Any, where: str) -> Any:
    return lambda message: fail(f"{where}: {message}")


def parse_prior(mapping: object, box: weather.Box, source: str = "prior") -> UserPrior:
    """A :class:`UserPrior` on ``box`` from the mapping of a prior file (``{parameter: density spec}``).

    Arguments:
        mapping: what the YAML file holds, ``{name: {uniform: [a, b]} | {normal: [mean, std], range: [a, b]} |
            {beta: [a, b], range: [a, b]} | {mixture: [{weight: w, <one of those>}, …]}}``; ``range`` (optional)
            truncates the normal / scales the beta to a sub-range, default the parameter's whole training range.
        box: the training box (:func:`training_prior`); ranges must lie inside it.
        source: the file's name, for the messages.

    Raises:
        PriorError: ``"<source>: <parameter>: <problem>"`` for an unknown parameter, a range outside the
            parameter's training range, a number that is not finite or out of its domain (std ≤ 0, beta's a or b ≤
            0, low ≥ high), mixture weights not summing to 1, a point mass, or a density zero on the whole box.
    """
    if mapping is None or (isinstance(mapping, Mapping) and not mapping):
        raise PriorError(f"{source}: names no parameter (expected e.g. precipitation: {{beta: [1, 8]}})")
    if not isinstance(mapping, Mapping):
        raise PriorError(f"{source}: the top level must map parameter names to densities, got {mapping!r}")
    factors: dict[int, Factor] = {}
    for name, spec in mapping.items():
        if name not in box.names:
            raise PriorError(f"{source}: {name}: unknown parameter; the model's are {', '.join(box.names)}")
        j = box.names.index(name)

        def fail(message: str, name: str = str(name)) -> PriorError:
            return PriorError(f"{source}: {name}: {message}")

        factors[j] = _density(spec, float(box.low[j]), float(box.high[j]), box.units[j], fail)
    return UserPrior(box, factors, source)


def read_prior(path: str | Path, box: weather.Box) -> UserPrior:
    """The :class:`UserPrior` of the YAML file ``path`` on the training ``box`` (:func:`parse_prior`); a
    :class:`PriorError` naming the file when it is missing, unreadable, not YAML, or has a key twice."""
    path = Path(path)
    if not path.is_file():
        raise PriorError(f"{path}: {'not a file' if path.exists() else 'no such file'}")
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise PriorError(f"{path}: cannot read it ({e.strerror})") from None
    except UnicodeDecodeError as e:
        raise PriorError(f"{path}: not UTF-8 text (byte {e.object[e.start]:#04x} at {e.start})") from None
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as e:
        raise PriorError(f"{path}: not valid YAML: {' '.join(str(e).split())}") from None
    return parse_prior(data, box, str(path))


# --- the training prior --------------------------------------------------------------------------------------------


def training_prior(card: Mapping[str, Any], where: str = "card.json") -> weather.Box:
    """The box of a model's training prior, read from its card (:mod:`components.export.onnx`): the prior is uniform
    on it.

    The card records the training box as the bijection's ``low``/``high`` (the NPE's box, params.yaml's ``prior:``)
    and the data source as ``training_renders.simulator``; rendered data (:data:`UNIFORM_SOURCES`) draw θ uniformly
    on the box (components.simulate.dataset), so that is the training prior. A card without the box, without the
    source, or of a model of recorded images (whose labels' distribution is not uniform and not recorded) is a
    :class:`PriorError`: the importance weights need the prior the model learned under.
    """
    bijection, theta = card.get("bijection"), card.get("theta")
    try:
        names = tuple(theta["names"])  # type: ignore[index]
        low = np.asarray(bijection["low"], dtype=np.float64)  # type: ignore[index]
        high = np.asarray(bijection["high"], dtype=np.float64)  # type: ignore[index]
        box = weather.Box(low, high, names, tuple(theta.get("units") or ()))  # type: ignore[union-attr]
    except (KeyError, TypeError, ValueError) as e:
        raise PriorError(
            f"{where}: the card records no training box (bijection low/high and theta names: {e}); reweighting to "
            "another prior needs the prior the model learned under (re-export it)"
        ) from None
    renders = card.get("training_renders")
    source = renders.get("simulator") if isinstance(renders, Mapping) else None
    if source is None:
        raise PriorError(
            f"{where}: the card does not say what data the model learned from (training_renders.simulator), so its "
            "training prior is unknown; re-export it"
        )
    if source not in UNIFORM_SOURCES:
        raise PriorError(
            f"{where}: the model learned from {source} data, whose weather is not drawn uniformly on the box and "
            "whose distribution the card does not record: no training prior to reweight from"
        )
    return box


# --- importance weights --------------------------------------------------------------------------------------------


def log_ratio(theta: np.ndarray, prior: UserPrior, train: weather.Box) -> np.ndarray:
    """log r(θ) = log π_user(θ) − log π_train(θ), π_train uniform on ``train``: ``(n, d)`` → ``(n,)``, −inf where
    π_user is 0 or θ lies outside the training box."""
    t = np.asarray(theta, dtype=np.float64)
    inside = train.contains(t)
    return np.where(inside, prior.log_prob(t) + train.log_volume(), -np.inf)


def effective_sample_size(weights: np.ndarray) -> np.ndarray | float:
    """Kish's ESS = (Σᵢ wᵢ)² / Σᵢ wᵢ² over the last axis of non-negative ``weights`` (any scale); 0 where all are 0.

    >>> effective_sample_size(np.array([1.0, 1.0, 1.0, 1.0])), effective_sample_size(np.array([1.0, 0, 0, 0]))
    (4.0, 1.0)
    """
    w = np.asarray(weights, dtype=np.float64)
    top = np.max(w, axis=-1, keepdims=True)
    scaled = np.divide(w, top, out=np.zeros_like(w), where=top > 0)
    sq = np.sum(scaled**2, axis=-1)
    ess = np.divide(np.sum(scaled, axis=-1) ** 2, sq, out=np.zeros_like(sq), where=sq > 0)
    return float(ess) if ess.ndim == 0 else ess


@dataclass(frozen=True)
class Reweighted:
    """One input's draws under the user's prior: ``draws (m, d)`` from q(θ | x), ``weights (m,)`` (normalized; all 0
    when π_user is 0 at every draw), ``ess`` and ``log_evidence`` = log Ẑ(x) = log (1/m) Σᵢ r(θᵢ), the Monte Carlo
    estimate of Z(x) = E_q[r]."""

    draws: np.ndarray
    weights: np.ndarray
    ess: float
    log_evidence: float


def reweight(draws: np.ndarray, prior: UserPrior, train: weather.Box) -> Reweighted:
    """The importance weights wᵢ ∝ π_user(θᵢ) / π_train(θᵢ) of ``draws (m, d)`` ~ q(θ | x), their ESS and log Ẑ."""
    d = np.asarray(draws, dtype=np.float64)
    if d.ndim != 2 or d.shape[0] == 0 or d.shape[1] != train.dim:
        raise ValueError(f"draws must have shape (m, {train.dim}) with m ≥ 1, got {d.shape}")
    lw = log_ratio(d, prior, train)
    top = float(np.max(lw))
    if top == -math.inf:
        return Reweighted(d, np.zeros(d.shape[0]), 0.0, -math.inf)
    w = np.exp(lw - top)
    total = float(w.sum())
    return Reweighted(d, w / total, float(effective_sample_size(w)), top + math.log(total / d.shape[0]))


def resample(weights: np.ndarray, n: int, generator: np.random.Generator) -> np.ndarray:
    """``n`` indices drawn i.i.d. with probabilities ``weights (m,)`` (normalized, not all 0): multinomial
    sampling-importance-resampling. A zero-weight draw is never chosen."""
    cdf = np.cumsum(weights)
    if not cdf[-1] > 0:
        raise ValueError("all importance weights are 0: nothing to resample")
    u = generator.random(n) * cdf[-1]
    return np.minimum(np.searchsorted(cdf, u, side="right"), len(cdf) - 1)


# --- a posterior under the user's prior ---------------------------------------------------------------------------


class ReweightedPosterior:
    """q(θ | x) under a user's prior, for prepared inputs: p̂_user(θ | x) = q(θ | x) r(θ) / Ẑ(x).

    :meth:`prepare` draws ``proposals`` θᵢ ~ q(θ | x) per input, once (an input's draws are seeded by the seed and
    the input's bytes, so they depend on nothing else), and keeps their importance weights. Then it satisfies
    :class:`components.domains.absolute.Posterior` on those inputs: :meth:`sample` resamples each input's weighted
    draws (SIR), :meth:`log_prob` is q's density times r over the Monte Carlo evidence Ẑ(x) (a proper density up to
    the estimate of Z). Any :class:`~components.domains.absolute.Domain` or kernel density built on it lives under the
    user's prior.

    Arguments:
        posterior: q(θ | x) (e.g. :class:`components.export.runtime.OnnxPosterior`), with a ``box``.
        prior: the user's prior on the training box.
        train: the training prior's box (:func:`training_prior`); π_train is uniform on it.
        proposals: m, the draws of q per input that are reweighted (≥ 1).
    """

    def __init__(self, posterior: Any, prior: UserPrior, train: weather.Box, proposals: int) -> None:
        self.base = posterior
        self.prior = prior
        self.train = train
        self.proposals = whole_number("proposals", proposals, low=1)
        self._found: dict[bytes, Reweighted] = {}

    @property
    def box(self) -> weather.Box:
        return self.base.box

    @property
    def card(self) -> dict[str, Any]:
        return self.base.card

    @property
    def dim(self) -> int:
        return self.base.box.dim

    def _rows(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float32)
        if x.ndim < 2 or x.shape[0] == 0:
            raise ValueError(f"x must be a non-empty batch (b, ...), got shape {x.shape}")
        return x

    def _entry(self, row: np.ndarray) -> Reweighted:
        found = self._found.get(row.tobytes())
        if found is None:
            raise ValueError("an input that was not prepared: call prepare(x, seed) on every input first")
        return found

    def prepare(self, x: np.ndarray, seed: int) -> np.ndarray:
        """Draw and reweight the proposals of each input of ``x (b, ...)`` not prepared yet; the ESS of every input
        ``(b,)``. Input k's draws use the seed ``derive_seed(seed, "prior", sha256 of its bytes)``."""
        rows = self._rows(x)
        for row in rows:
            key = row.tobytes()
            if key in self._found:
                continue
            digest = hashlib.sha256(key).hexdigest()
            draws = np.asarray(self.base.sample(row[None], self.proposals, derive_seed(seed, "prior", digest)))[0]
            self._found[key] = reweight(draws, self.prior, self.train)
        return self.ess(rows)

    def ess(self, x: np.ndarray) -> np.ndarray:
        """The ESS of each prepared input of ``x (b, ...)`` → ``(b,)``."""
        return np.array([self._entry(row).ess for row in self._rows(x)])

    def sample(self, x: np.ndarray, n: int, seed: int) -> np.ndarray:
        """``n`` draws per prepared input, resampled by weight from its proposals: ``(b, ...)`` → ``(b, n, d)``
        (stream ``(seed, "prior", "resample")``); ValueError for an input whose weights are all 0."""
        rows = self._rows(x)
        n = whole_number("the number of posterior samples n", n, low=1)
        generator = rng(seed, "prior", "resample")
        out = np.empty((rows.shape[0], n, self.dim))
        for i, row in enumerate(rows):
            found = self._entry(row)
            out[i] = found.draws[resample(found.weights, n, generator)]
        return out

    def log_prob(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Row-wise log p̂_user(θᵢ | xᵢ) = log q(θᵢ | xᵢ) + log r(θᵢ) − log Ẑ(xᵢ): ``(n, d), (n, ...)`` → ``(n,)``."""
        rows = self._rows(x)
        t = np.asarray(theta, dtype=np.float64)
        log_z = np.empty(rows.shape[0])
        cache: dict[bytes, float] = {}
        for i, row in enumerate(rows):
            key = row.tobytes()
            if key not in cache:
                cache[key] = self._entry(row).log_evidence
            log_z[i] = cache[key]
        lq = np.asarray(self.base.log_prob(t, rows), dtype=np.float64)
        lr = log_ratio(t, self.prior, self.train)
        with np.errstate(invalid="ignore"):
            out = lq + lr - log_z
        return np.where(np.isfinite(lr) & np.isfinite(log_z), out, -np.inf)


def ess_summary(ess: Sequence[float] | np.ndarray) -> dict[str, float]:
    """``{"min", "median", "max"}`` of the inputs' ESS."""
    e = np.asarray(ess, dtype=np.float64)
    return {"min": float(e.min()), "median": float(np.median(e)), "max": float(e.max())}
