"""The champion: the model the evaluation recommends (the ``evaluate`` stage, then Tasks II and III and the CLI).

The rule today: the lowest Task I value of ``export.champion_metric`` (lower is better), ties broken by model id.

Used by the ``evaluate`` stage only; ``task2``, ``task3`` and the CLI read its pick from ``reports/task1/champion.json``
(:mod:`components.export.lookup`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

__all__ = ["choose_champion"]


def choose_champion(metrics: Mapping[str, Mapping[str, float]], metric: str) -> tuple[str, float]:
    """The model id with the lowest finite ``metric`` among ``metrics`` (per model id), and that value."""
    scored = {m: float(v[metric]) for m, v in metrics.items() if np.isfinite(v.get(metric, np.nan))}
    if not scored:
        raise ValueError(f"no model has a finite {metric}: cannot choose a champion")
    best = min(sorted(scored), key=lambda m: scored[m])
    return best, scored[best]
