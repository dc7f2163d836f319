"""The sequential rule over windows and its false alarms per hour of in-ODD driving, measured on held-out windows.

A window is *flagged* when its relative gap exceeds the calibrated threshold (probability ≤ α for an in-ODD window).
Consecutive windows overlap (a stride shorter than a window), so flags come in runs, and one flag says little; the
rule alarms when k consecutive windows are flagged (:class:`ConsecutiveRule`), and the alarm lasts while the windows
stay flagged: one *alarm segment* per run of at least k flagged windows, fired at its k-th window. Its cost is a
latency of (k − 1) strides after the first flagged window.

Its false alarms per hour are not assumed from α: the rule is run over the held-out evaluation blocks of the sources
(in-ODD driving that neither the densities nor the threshold saw), block by block, and the alarms counted. Each window
stands for one stride of driving, so a block of w windows is w·s·Δt seconds of exposure; the rate is
alarms / exposure, with the exact Poisson (Garwood) interval of its count (:func:`garwood_interval`).

Used by :mod:`components.watch.run`.

References:
    Garwood, "Fiducial limits for the Poisson distribution", Biometrika 1936 (the interval).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats

__all__ = ["Segment", "ConsecutiveRule", "garwood_interval", "StatedRate", "stated_rate"]


@dataclass(frozen=True)
class Segment:
    """An alarm segment, as window indices of its sequence.

    Attributes:
        first: the first flagged window of the run.
        fired: the window at which the rule fired (first + k − 1).
        last: the run's last flagged window (inclusive).
        open: whether the run lasts to the sequence's last window (the alarm had not ended).
    """

    first: int
    fired: int
    last: int
    open: bool


@dataclass(frozen=True)
class ConsecutiveRule:
    """Alarm after k consecutive flagged windows (k ≥ 1; k = 1 alarms at every flagged window).

    Examples:
        >>> rule = ConsecutiveRule(3)
        >>> flags = [0, 1, 1, 0, 1, 1, 1, 1, 0, 1, 1, 1]
        >>> [(s.first, s.fired, s.last, s.open) for s in rule.segments(flags)]
        [(4, 6, 7, False), (9, 11, 11, True)]
        >>> rule.alarms(flags).astype(int).tolist()
        [0, 0, 0, 0, 0, 0, 1, 1, 0, 0, 0, 1]
    """

    k: int

    def __post_init__(self) -> None:
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < 1:
            raise ValueError(f"k must be a whole number of windows ≥ 1, got {self.k!r}")

    def segments(self, flags: Sequence[bool] | np.ndarray) -> list[Segment]:
        """The alarm segments of one sequence of window flags ``(n,)`` (True = above the threshold)."""
        f = np.asarray(flags, dtype=bool)
        out: list[Segment] = []
        start = None
        for i, flagged in enumerate(f.tolist() + [False]):
            if flagged and start is None:
                start = i
            elif not flagged and start is not None:
                if i - start >= self.k:
                    out.append(Segment(start, start + self.k - 1, i - 1, i == f.size))
                start = None
        return out

    def alarms(self, flags: Sequence[bool] | np.ndarray) -> np.ndarray:
        """``(n,)`` bool: whether the rule is in alarm at each window (from a segment's firing to its last window)."""
        out = np.zeros(len(flags), dtype=bool)
        for s in self.segments(flags):
            out[s.fired : s.last + 1] = True
        return out


def garwood_interval(count: int, exposure: float, level: float = 0.95) -> tuple[float, float]:
    """The exact central ``level`` interval of a Poisson rate from ``count`` events in ``exposure`` (any unit):
    [χ²((1−level)/2; 2c)/2, χ²((1+level)/2; 2c+2)/2] / exposure, the lower end 0 for c = 0.

    Examples:
        >>> [round(v, 3) for v in garwood_interval(0, 1.0)]  # no event in one hour: at most 3.689 per hour
        [0.0, 3.689]
    """
    if count < 0 or exposure <= 0:
        raise ValueError(f"need count ≥ 0 and exposure > 0, got {count} and {exposure}")
    tail = (1.0 - level) / 2.0
    low = 0.0 if count == 0 else float(stats.chi2.ppf(tail, 2 * count) / 2.0)
    high = float(stats.chi2.ppf(1.0 - tail, 2 * count + 2) / 2.0)
    return low / exposure, high / exposure


@dataclass(frozen=True)
class StatedRate:
    """The rule's false alarms measured on held-out in-ODD windows.

    Attributes:
        alarms: alarm segments among them (false alarms, as every window is in the ODD).
        hours: the exposure, hours of driving (each window one stride).
        per_hour: alarms / hours.
        low: the Garwood interval's lower end, per hour.
        high: its upper end, per hour.
        level: the interval's level.
        windows: the windows run through.
        flagged: how many of them were above the threshold (their share estimates the per-window α).
        sequences: the held-out blocks (sequences the rule restarts on).
    """

    alarms: int
    hours: float
    per_hour: float
    low: float
    high: float
    level: float
    windows: int
    flagged: int
    sequences: int

    @property
    def window_rate(self) -> float:
        """The share of the windows that were flagged."""
        return self.flagged / self.windows if self.windows else float("nan")

    def to_dict(self) -> dict:
        return asdict(self) | {"window_rate": self.window_rate}


def stated_rate(
    rule: ConsecutiveRule, sequences: Sequence[np.ndarray], window_seconds: float, level: float = 0.95
) -> StatedRate:
    """The rule's false alarms per hour over in-ODD ``sequences`` (each ``(w,)`` flags of one held-out block, in time
    order, the rule restarted on each), each window standing for ``window_seconds`` of driving (the stride × Δt)."""
    if not sequences:
        raise ValueError("no sequence of in-ODD windows to measure the rule on")
    if not window_seconds > 0:
        raise ValueError(f"window_seconds must be positive, got {window_seconds!r}")
    alarms = sum(len(rule.segments(f)) for f in sequences)
    windows = int(sum(len(f) for f in sequences))
    flagged = int(sum(int(np.count_nonzero(f)) for f in sequences))
    hours = windows * window_seconds / 3600.0
    low, high = garwood_interval(alarms, hours, level)
    return StatedRate(alarms, hours, alarms / hours, low, high, level, windows, flagged, len(sequences))
