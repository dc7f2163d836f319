"""The two checks of a monitoring run and the alarms that fail it.

**Calibration (Task I).** A model's calibration error max_l |c(l) − l| on the run's n images with S posterior draws each
is compared with the band of a perfectly calibrated model on the same n and S: the ``level`` quantile of that model's
calibration error (:func:`components.evaluate.task1.calibration_band`, simulated). A calibrated model exceeds its band
with probability 1 − level; a model that drifted (or images whose labels are wrong) exceeds it more often, the more
images the run judges.

**False alarms of the ODD decision (Task III).** The pipeline's threshold is the r-th smallest of m relative gaps of
in-ODD calibration targets (r = ⌈(m + 1)(1 − α)⌉, ``reports/task3/metrics.json``). On n new in-ODD targets that are
exchangeable with the calibration targets (nothing changed), the number K flagged follows the beta-binomial
BB(n, m + 1 − r, r) exactly, whatever the distribution of the gaps: the share of in-ODD targets above the r-th of m
order statistics is Beta(m + 1 − r, r), and given it K is binomial. As m → ∞ it tends to the binomial B(n, α) of the
nominal rate α (:func:`false_alarm_interval` gives that one when m is not known); with a finite m the binomial
interval is too narrow and would alarm more often than 1 − level. The alarm fires when K leaves the central interval
that holds at least ``level`` of that distribution: too many false alarms (in-ODD gaps grew: the decision breaks its
promise) or too few (they shrank: the threshold no longer sits where it was calibrated).

**Many models in one run.** A run that judges k models (the weekly run: every registered model) checks each against
its band at the level 1 − (1 − level)/k (:func:`model_level`, Bonferroni: valid whatever the dependence between the
models' errors on the run's shared images), so that all k calibration checks of healthy models together fire with
probability ≤ 1 − level, as the one check of a run that judges the champion alone; the band of that level is simulated
with as many more replicates as keep its tail as well sampled (:func:`band_replicates`).

A run whose checks raise an alarm ends with :class:`MonitoringAlarm` (after its report is written), naming each alarm.

Used by the scheduled monitoring (``flows/monitor.py``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from components.core.checks import whole_number
from components.domains.relative import OddDetector, false_alarm_interval
from components.domains.sweep import FalseAlarmCheck

__all__ = [
    "MonitoringAlarm",
    "model_level",
    "band_replicates",
    "calibration_alarm",
    "false_alarm_interval",
    "CalibratedOdd",
    "FalseAlarmTest",
    "alarms",
]


class MonitoringAlarm(RuntimeError):
    """A monitoring run found a model outside its calibration band or an ODD false-alarm count outside its
    interval; the message names every alarm."""


def model_level(level: float, models: int) -> float:
    """The level of each of ``models`` calibration checks of one run such that healthy models raise any of them with
    probability ≤ 1 − ``level``: 1 − (1 − level)/models (Bonferroni)."""
    whole_number("models", models, low=1, floats=True)
    if not 0.0 < float(level) < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    return 1.0 - (1.0 - float(level)) / int(models)


def band_replicates(replicates: int, reference_level: float, level: float) -> int:
    """Simulations for the band at ``level`` that put as many of them above it as ``replicates`` put above the band at
    ``reference_level`` (the evaluate stage's, ``evaluate.band_replicates`` at ``evaluate.band_level``): the quantile's
    Monte Carlo error, relative to its tail 1 − level, stays what it is there. Never fewer than ``replicates``."""
    tail = replicates * (1.0 - float(reference_level))
    return max(int(replicates), math.ceil(tail / (1.0 - float(level)) - 1e-6))


def calibration_alarm(model: str, metrics: Mapping[str, float]) -> str | None:
    """The alarm of ``model`` whose Task I ``metrics`` (``calibration_error``, ``calibration_band``, ``images``,
    ``samples``; optionally ``calibration_level``, the band's quantile, and ``resized_images``, those of another size
    than the model's training renders) put it outside its band, else None."""
    error, band = float(metrics["calibration_error"]), float(metrics["calibration_band"])
    if error <= band:
        return None
    resized = int(metrics.get("resized_images") or 0)
    why = (
        f"; {resized} of the images were resized from another size than its training renders, which its calibration "
        "does not cover (docs/studies/other-resolutions.md)"
        if resized
        else ""
    )
    level = metrics.get("calibration_level")
    quantile = "" if level is None else f" (its {100 * float(level):.4g} % quantile)"
    return (
        f"calibration alarm: {model} has a calibration error of {error:.3f} on {int(metrics['images'])} images "
        f"({int(metrics['samples'])} draws each), outside the band {band:.3f}{quantile} of a perfectly calibrated "
        f"model{why}"
    )


@dataclass(frozen=True)
class CalibratedOdd:
    """The ODD decision as the ``task3`` stage calibrated it (``reports/task3/metrics.json``).

    Attributes:
        model: the model it was calibrated for (its relative gaps).
        detector: threshold, α and the number m of calibration targets.
        calibrated_on: the target kind, ``fresh`` (in-ODD part from other images of the sources' weather) or ``paper``.
        bag_sizes: source bag → its images.
        pool_sizes: source bag → the images of its fresh pool.
    """

    model: str
    detector: OddDetector
    calibrated_on: str
    bag_sizes: dict[str, int]
    pool_sizes: dict[str, int]

    @classmethod
    def from_metrics(cls, metrics: Mapping, path: str | Path) -> CalibratedOdd:
        """From the content of ``reports/task3/metrics.json`` at ``path``; ``ValueError`` naming the file and key."""
        try:
            odd = metrics["odd"]
            detector = OddDetector(
                float(odd["threshold"]), float(odd["false_alarm_rate"]), int(odd["calibration_targets"])
            )
            bags = {k: v for k, v in metrics["bags"].items() if k != "b0"}
            calibrated = cls(
                str(metrics["model"]),
                detector,
                str(odd["calibrated_on"]),
                {k: int(v["images"]) for k, v in bags.items()},
                {k: int(v.get("fresh_pool", 0)) for k, v in bags.items()},
            )
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise ValueError(
                f"{path}: not the Task III metrics the monitoring needs (model, bags, odd.threshold, "
                f"odd.false_alarm_rate, odd.calibration_targets, odd.calibrated_on): {type(e).__name__} {e}; "
                "re-run `dvc repro task3`"
            ) from None
        if calibrated.calibrated_on not in ("paper", "fresh"):
            raise ValueError(f"{path}: odd.calibrated_on is {calibrated.calibrated_on!r}, expected paper or fresh")
        if int(odd.get("rank", detector.rank)) != detector.rank:
            raise ValueError(f"{path}: odd.rank {odd['rank']} is not ⌈(m+1)(1−α)⌉ = {detector.rank}")
        return calibrated


@dataclass(frozen=True)
class FalseAlarmTest:
    """The ODD decision's false alarms on a run's new in-ODD targets against their interval.

    Attributes:
        check: the count, rate and Clopper–Pearson interval of the rate (:class:`~components.domains.sweep.FalseAlarmCheck`).
        level: the interval's probability.
        low: the lower end of the interval of the count.
        high: its upper end.
        distribution: the count's distribution.
        binomial: the binomial interval of α on as many targets (for reference: it ignores the threshold's spread).
    """

    check: FalseAlarmCheck
    level: float
    low: int
    high: int
    distribution: str
    binomial: tuple[int, int]

    @classmethod
    def of(cls, check: FalseAlarmCheck, detector: OddDetector, level: float) -> FalseAlarmTest:
        """``check`` (flags of the ``detector`` on new in-ODD targets) against :func:`false_alarm_interval`."""
        low, high, name = false_alarm_interval(
            check.n, detector.false_alarm_rate, level, detector.n_calibration, detector.rank
        )
        binomial = false_alarm_interval(check.n, detector.false_alarm_rate, level)[:2]
        return cls(check, float(level), low, high, name, binomial)

    @property
    def alarm(self) -> bool:
        """True when the count lies outside ``[low, high]``."""
        return not self.low <= self.check.flagged <= self.high

    def message(self, model: str) -> str | None:
        """The alarm's message, or None."""
        if not self.alarm:
            return None
        c = self.check
        side = "more" if c.flagged > self.high else "fewer"
        return (
            f"ODD false-alarm alarm: {model}'s ODD decision flagged {c.flagged} of {c.n} new in-ODD {c.targets} targets "
            f"({c.rate:.3f} at α = {c.alpha:g}), {side} than the {100 * self.level:g} % interval [{self.low}, "
            f"{self.high}] of the {self.distribution} count"
        )

    def to_dict(self) -> dict:
        return self.check.to_dict() | {
            "interval_low": self.low,
            "interval_high": self.high,
            "interval_level": self.level,
            "interval_distribution": self.distribution,
            "binomial_interval_low": self.binomial[0],
            "binomial_interval_high": self.binomial[1],
            "alarm": self.alarm,
        }


def alarms(models: Mapping[str, Mapping[str, float]], odd: FalseAlarmTest | None, odd_model: str | None) -> list[str]:
    """Every alarm of a run: the calibration alarm of each model of ``models`` (model id → Task I metrics) and the
    false-alarm alarm of ``odd`` (the test of ``odd_model``'s ODD decision; None when it did not run)."""
    found = [a for m, metrics in models.items() if (a := calibration_alarm(m, metrics))]
    if odd is not None and (a := odd.message(str(odd_model))):
        found.append(a)
    return found
