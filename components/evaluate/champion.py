"""The champion: the model the evaluation recommends (the ``evaluate`` stage, then Tasks II and III and the CLI).

The rule: the sharpest model among those calibrated within noise. Sharpness is the test NLL (a proper score: it
rewards the true posterior and nothing sharper or wider); "calibrated within noise" means a calibration error inside
the band a perfectly calibrated model shows on the same number of images (``within_band``, see
:func:`components.evaluate.task1.calibration_band`).

1. ``within_band``: the lowest test NLL among the models with ``within_band`` true;
2. ``ceiling``: when no model is within its band, the lowest test NLL among those whose calibration error is at most
   ``export.champion_max_calibration_error`` — recorded as such, never silently;
3. otherwise no model is fit to be recommended: :class:`NoChampionError`.

Ties are broken by model id. The runner-up (MLflow alias ``challenger``) is the model the same rule picks once the
champion is set aside.

Used by the ``evaluate`` stage only; ``task2``, ``task3`` and the CLI read its pick from ``reports/task1/champion.json``
(:mod:`components.export.lookup`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

__all__ = ["RULES", "POINTER_METRICS", "NoChampionError", "Pick", "choose_champion", "champion_pointer"]

#: The branches of the rule, in the order they are tried.
RULES: tuple[str, ...] = ("within_band", "ceiling")
#: The metrics the pointer ``champion.json`` repeats for the champion and the runner-up.
POINTER_METRICS: tuple[str, ...] = (
    "calibration_error",
    "calibration_band",
    "within_band",
    "test_nll",
    "info_gain_nats",
)


class NoChampionError(ValueError):
    """No model is within its calibration band nor below the calibration-error ceiling."""


@dataclass(frozen=True)
class Pick:
    """A model chosen by the rule: its id, the branch (:data:`RULES`) and why, in words."""

    model: str
    rule: str
    reason: str


def _number(metrics: Mapping[str, object], key: str, model: str) -> float:
    try:
        value = float(metrics[key])  # type: ignore[arg-type]
    except KeyError:
        raise KeyError(f"model {model!r} has no Task I metric {key!r}") from None
    return value


def _pick(metrics: Mapping[str, Mapping[str, object]], ceiling: float) -> Pick | None:
    nll = {m: _number(v, "test_nll", m) for m, v in metrics.items()}
    error = {m: _number(v, "calibration_error", m) for m, v in metrics.items()}
    finite = [m for m in sorted(metrics) if math.isfinite(nll[m]) and math.isfinite(error[m])]
    within = [m for m in finite if bool(metrics[m]["within_band"])]
    if within:
        best = min(within, key=lambda m: nll[m])
        return Pick(
            best,
            "within_band",
            f"lowest test NLL ({nll[best]:.3f} nats) among the {len(within)} model(s) whose calibration error lies "
            f"within the band of a perfectly calibrated model ({', '.join(within)})",
        )
    below = [m for m in finite if error[m] <= ceiling]
    if below:
        best = min(below, key=lambda m: nll[m])
        return Pick(
            best,
            "ceiling",
            f"no model's calibration error lies within its band; lowest test NLL ({nll[best]:.3f} nats) among the "
            f"{len(below)} model(s) with a calibration error ≤ export.champion_max_calibration_error = {ceiling:g} "
            f"({', '.join(below)})",
        )
    return None


def choose_champion(
    metrics: Mapping[str, Mapping[str, object]], max_calibration_error: float
) -> tuple[Pick, Pick | None]:
    """The champion and the runner-up (None when no other model qualifies) of the Task I ``metrics`` (model id →
    ``{"calibration_error", "within_band", "test_nll", …}``) under the rule of this module.

    Raises:
        NoChampionError: no model is within its band and none has a calibration error ≤ ``max_calibration_error``
            (the message lists every model's calibration error and band).
        KeyError: a model lacks one of the metrics the rule reads.
    """
    if not metrics:
        raise NoChampionError("no model was evaluated: cannot choose a champion")
    if not 0.0 < float(max_calibration_error) <= 1.0:
        raise ValueError(f"max_calibration_error must be in (0, 1], got {max_calibration_error!r}")
    champion = _pick(metrics, float(max_calibration_error))
    if champion is None:
        rows = ", ".join(
            f"{m}: {float(v['calibration_error']):.3f} (band {float(v.get('calibration_band', math.nan)):.3f})"
            for m, v in sorted(metrics.items())
        )
        raise NoChampionError(
            f"no champion: no model's calibration error lies within its band, and none is ≤ "
            f"export.champion_max_calibration_error = {float(max_calibration_error):g} ({rows}); recalibrate the "
            "models (e.g. train.variants) or raise the ceiling in params.yaml knowingly"
        )
    rest = {m: v for m, v in metrics.items() if m != champion.model}
    runner_up = _pick(rest, float(max_calibration_error)) if rest else None
    return champion, runner_up


def champion_pointer(
    metrics: Mapping[str, Mapping[str, object]], champion: Pick, runner_up: Pick | None
) -> dict[str, object]:
    """The content of ``reports/task1/champion.json``: the champion's id, the rule's branch and reason, its
    :data:`POINTER_METRICS`, and the runner-up with the same (``null`` when there is none)."""

    def entry(pick: Pick) -> dict[str, object]:
        values = metrics[pick.model]
        return {
            "model": pick.model,
            "rule": pick.rule,
            "reason": pick.reason,
            "metrics": {k: values[k] for k in POINTER_METRICS if k in values},
        }

    return entry(champion) | {"runner_up": entry(runner_up) if runner_up else None}
