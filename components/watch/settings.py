"""The settings of a watch: :data:`WATCH_DEFAULTS` (the one place its defaults are written) and :class:`WatchOptions`,
checked, each bad value a :class:`~components.watch.errors.WatchError` naming the ``pidc watch`` option.

Frames and windows are counted in frames, times in seconds; a window's statistic is Task III's relative gap
δ(λ̂)/mean(b²) (unitless), and the rule's rate is in false alarms per hour of in-ODD driving.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from components.watch.errors import WatchError

__all__ = ["WATCH_DEFAULTS", "FEATURE_GROUP", "OPTION_NAMES", "WatchOptions", "decay_length"]

#: The defaults of ``pidc watch`` (and of :class:`WatchOptions`):
#:
#: - ``samples``: posterior draws per frame for its median and 68.27 % HDI (the CLI's ``MIN_SAMPLES`` or more);
#: - ``draws_per_image``: the first so many of them are the frame's fixed draws, the support of the windows' kernel
#:   densities and of their marginals (``pidc relate``'s 64);
#: - ``window``: frames per window (30: 3 s at 10 frames/s); ``stride``: frames from one window's end to the next's (5:
#:   0.5 s); ``decay``: None, or the weight factor per frame of age of an exponentially decaying window, which then
#:   spans the frames whose weight is at least ``decay_tolerance`` of the newest's;
#: - ``block``: frames per block of the sources, cycled density, calibration, density, evaluation (300: 30 s);
#: - ``n_points``: n_W, points drawn from each window where the densities are compared (Task III);
#: - ``bandwidth_scale``: the kernels' bandwidth in units of Scott's rule on the sources' density frames;
#: - ``source_centres``: kernel centres kept per source (a seeded subsample of its density frames' pooled draws), also
#:   the mixture's draws of the per-parameter W₁;
#: - ``false_alarm_rate``: α, the share of in-ODD windows above the threshold (calibrated on held-out windows);
#: - ``consecutive``: k, the rule alarms after k consecutive windows above the threshold;
#: - ``batch``: frames read and drawn at once, a multiple of :data:`FEATURE_GROUP` (bounds memory; results do not
#:   depend on it);
#: - ``interval_level``: the level of the Poisson (Garwood) interval of the stated false alarms per hour.
WATCH_DEFAULTS: dict[str, Any] = {
    "samples": 256,
    "draws_per_image": 64,
    "window": 30,
    "stride": 5,
    "decay": None,
    "decay_tolerance": 0.01,
    "block": 300,
    "n_points": 64,
    "bandwidth_scale": 3.0,
    "source_centres": 4096,
    "false_alarm_rate": 0.01,
    "consecutive": 3,
    "batch": 64,
    "interval_level": 0.95,
}

#: Frames whose backbone features are computed in one call, groups aligned on the stream's frame numbers: a backbone's
#: float reductions may round differently for another number of images (the cues backbone's features of one frame
#: differed by 5e-7 between batches of 5 and of 64), so ``batch`` is a multiple of it and results do not depend on
#: ``batch``. Measured: 8–11 ms a frame for groups of 8 to 64 on one thread, no faster for larger groups.
FEATURE_GROUP = 16

#: The ``pidc watch`` option of each setting, as errors name them.
OPTION_NAMES: dict[str, str] = {
    "samples": "--samples",
    "draws_per_image": "--draws-per-image",
    "window": "--window",
    "stride": "--stride",
    "decay": "--decay",
    "decay_tolerance": "decay_tolerance",
    "block": "--block",
    "n_points": "--points",
    "bandwidth_scale": "--bandwidth-scale",
    "source_centres": "--source-centres",
    "false_alarm_rate": "--false-alarm-rate",
    "consecutive": "--consecutive",
    "batch": "--batch",
    "interval_level": "interval_level",
    "seed": "--seed",
}


def decay_length(decay: float, tolerance: float) -> int:
    """Frames of an exponentially decaying window: the ages 0 … L−1 whose weight decay^age is at least ``tolerance``
    of the newest's, L = ⌊log(tolerance)/log(decay)⌋ + 1 (1 for decay 0 < decay ≪ tolerance).

    Examples:
        >>> decay_length(0.9, 0.01)  # 0.9⁴³ = 0.0108, 0.9⁴⁴ = 0.0097
        44
    """
    return int(math.floor(math.log(tolerance) / math.log(decay) + 1e-9)) + 1


def _whole(name: str, value: object, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise WatchError(f"{OPTION_NAMES[name]} must be a whole number ≥ {low}, got {value!r}")
    return int(value)


@dataclass(frozen=True)
class WatchOptions:
    """The settings of a watch (see :data:`WATCH_DEFAULTS` for their meanings and units), checked at construction.

    ``decay`` None: windows of ``window`` equally weighted frames; else exponentially decaying windows of
    :attr:`length` frames (``window`` is then not used).
    """

    samples: int = WATCH_DEFAULTS["samples"]
    draws_per_image: int = WATCH_DEFAULTS["draws_per_image"]
    window: int = WATCH_DEFAULTS["window"]
    stride: int = WATCH_DEFAULTS["stride"]
    decay: float | None = WATCH_DEFAULTS["decay"]
    decay_tolerance: float = WATCH_DEFAULTS["decay_tolerance"]
    block: int = WATCH_DEFAULTS["block"]
    n_points: int = WATCH_DEFAULTS["n_points"]
    bandwidth_scale: float = WATCH_DEFAULTS["bandwidth_scale"]
    source_centres: int = WATCH_DEFAULTS["source_centres"]
    false_alarm_rate: float = WATCH_DEFAULTS["false_alarm_rate"]
    consecutive: int = WATCH_DEFAULTS["consecutive"]
    batch: int = WATCH_DEFAULTS["batch"]
    interval_level: float = WATCH_DEFAULTS["interval_level"]
    seed: int = 0

    def __post_init__(self) -> None:
        _whole("samples", self.samples, 2)
        _whole("draws_per_image", self.draws_per_image, 2)
        if self.draws_per_image > self.samples:
            raise WatchError(
                f"--draws-per-image {self.draws_per_image} must not exceed --samples {self.samples}: the fixed draws "
                "are the first of each frame's draws"
            )
        _whole("window", self.window, 2)
        _whole("stride", self.stride, 1)
        if self.decay is not None:
            if not (0.0 < float(self.decay) < 1.0):
                raise WatchError(f"--decay must be in (0, 1) (the weight factor per frame of age), got {self.decay:g}")
            if not (0.0 < float(self.decay_tolerance) < 1.0):
                raise WatchError(f"decay_tolerance must be in (0, 1), got {self.decay_tolerance:g}")
            if self.length < 2:
                raise WatchError(
                    f"--decay {self.decay:g} keeps only the newest frame above {self.decay_tolerance:g} of its weight; "
                    "a window needs two frames or more: use a decay closer to 1"
                )
        _whole("block", self.block, 2)
        if self.block < self.length + (self.consecutive - 1) * self.stride:
            raise WatchError(
                f"--block {self.block} is shorter than a window ({self.length} frames) and the rule's "
                f"{self.consecutive - 1} more strides of {self.stride}: a held-out block could never raise an alarm; "
                f"use --block ≥ {self.length + (self.consecutive - 1) * self.stride}"
            )
        _whole("n_points", self.n_points, 1)
        if not (0.0 < float(self.bandwidth_scale) < math.inf):
            raise WatchError(f"--bandwidth-scale must be a positive number, got {self.bandwidth_scale:g}")
        _whole("source_centres", self.source_centres, 2)
        alpha = float(self.false_alarm_rate)
        if not (0.0 < alpha < 1.0):
            raise WatchError(f"--false-alarm-rate must be in (0, 1) (a share of in-ODD windows), got {alpha:g}")
        _whole("consecutive", self.consecutive, 1)
        _whole("batch", self.batch, 1)
        if self.batch % FEATURE_GROUP:
            raise WatchError(
                f"--batch must be a multiple of {FEATURE_GROUP} (features are computed {FEATURE_GROUP} frames at a "
                f"time, so that results do not depend on the batch), got {self.batch}"
            )
        if not (0.0 < float(self.interval_level) < 1.0):
            raise WatchError(f"interval_level must be in (0, 1), got {self.interval_level:g}")
        _whole("seed", self.seed, 0)

    @property
    def length(self) -> int:
        """L, the frames of a window: ``window``, or :func:`decay_length` of ``decay``."""
        return self.window if self.decay is None else decay_length(float(self.decay), float(self.decay_tolerance))

    @property
    def calibration_windows_needed(self) -> int:
        """⌈(1−α)/α⌉: the fewest held-out windows whose split-conformal rank sets a threshold at α."""
        return math.ceil((1.0 - self.false_alarm_rate) / self.false_alarm_rate - 1e-9)

    def to_dict(self) -> dict[str, Any]:
        """The settings, and the window's length L, as JSON."""
        return asdict(self) | {"length": self.length}
