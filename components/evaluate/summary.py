"""Per-parameter summaries of posterior draws: median, highest-density interval (HDI), mean, standard deviation.

The HDI of a 1-D marginal from m draws is the shortest interval holding ⌈mass·m⌉ of them (Hyndman 1996 for one
interval): sort the draws, slide a window of that many, keep the narrowest. It is the 68.27 % highest-density
*interval* of each marginal by default (the paper's 1σ-equivalent level); for a multimodal marginal it is the
shortest single interval, which may span a gap between modes. All values are in the physical units of θ.

Used by the ``pidc`` CLI only (``characterize``, ``domain``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from components.core.weather import Box

__all__ = ["HDI_MASS", "hdi", "Summary", "summarize", "format_summary"]

#: The default credible mass of the intervals, 68.27 % (±1σ of a normal).
HDI_MASS: float = 0.6827


def hdi(draws: np.ndarray, mass: float = HDI_MASS) -> tuple[np.ndarray, np.ndarray]:
    """Shortest intervals holding ⌈mass·m⌉ of the draws, per column.

    Arguments:
        draws: ``(m,)`` or ``(m, d)`` samples (m ≥ 1, finite).
        mass: the credible mass in (0, 1].

    Returns:
        ``(low, high)``, each of shape ``()`` or ``(d,)`` like one row of ``draws``.
    """
    a = np.asarray(draws, dtype=np.float64)
    if a.ndim not in (1, 2) or a.shape[0] == 0:
        raise ValueError(f"draws must have shape (m,) or (m, d) with m ≥ 1, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("draws must be finite")
    if not (0.0 < float(mass) <= 1.0):
        raise ValueError(f"mass must be in (0, 1], got {mass!r}")
    one = a.ndim == 1
    s = np.sort(a.reshape(a.shape[0], -1), axis=0)
    m = s.shape[0]
    k = min(m, max(1, math.ceil(float(mass) * m - 1e-9)))  # draws inside the interval
    widths = s[k - 1 :] - s[: m - k + 1]  # (m − k + 1, d)
    start = np.argmin(widths, axis=0)
    cols = np.arange(s.shape[1])
    low, high = s[start, cols], s[start + k - 1, cols]
    return (low[0], high[0]) if one else (low, high)


@dataclass(frozen=True)
class Summary:
    """Per-parameter statistics of ``(m, d)`` draws; every field has shape ``(d,)`` in θ's physical units."""

    median: np.ndarray
    low: np.ndarray
    high: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    mass: float
    draws: int

    def to_dict(self, box: Box) -> dict:
        """``{"hdi_mass", "draws", "parameters": {name: {"unit", "median", "hdi_low", "hdi_high", "mean", "std"}}}``
        with ``box``'s names and units in θ's order (for JSON)."""
        if box.dim != self.median.shape[0]:
            raise ValueError(f"the box has {box.dim} parameters, the summary {self.median.shape[0]}")
        columns = {
            "median": self.median,
            "hdi_low": self.low,
            "hdi_high": self.high,
            "mean": self.mean,
            "std": self.std,
        }
        return {
            "hdi_mass": self.mass,
            "draws": self.draws,
            "parameters": {
                name: {"unit": unit, **{k: float(v[j]) for k, v in columns.items()}}
                for j, (name, unit) in enumerate(zip(box.names, box.units, strict=True))
            },
        }


def summarize(draws: np.ndarray, mass: float = HDI_MASS) -> Summary:
    """Median, ``mass`` HDI (:func:`hdi`), mean and standard deviation (ddof 1; 0 for one draw) of ``(m, d)`` draws."""
    a = np.asarray(draws, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"draws must have shape (m, d), got shape {a.shape}")
    low, high = hdi(a, mass)
    std = a.std(axis=0, ddof=1) if a.shape[0] > 1 else np.zeros(a.shape[1])
    return Summary(np.median(a, axis=0), low, high, a.mean(axis=0), std, float(mass), int(a.shape[0]))


def format_summary(summary: Summary, box: Box, moments: bool = False) -> str:
    """A text table, one row per parameter: ``name [unit]``, median, the HDI ``[low, high]`` (and mean, std).

    Numbers are printed with 2 decimals, in ``box``'s units; ``box`` gives the names and units in θ's order.
    """
    d = summary.median.shape[0]
    if box.dim != d:
        raise ValueError(f"the box has {box.dim} parameters, the summary {d}")
    label = f"{100 * summary.mass:.2f} % HDI"
    header = f"{'parameter':<30}{'median':>9}  {label:<20}"
    if moments:
        header += f"{'mean':>9}{'std':>9}"
    lines = [header.rstrip()]
    for j, (name, unit) in enumerate(zip(box.names, box.units, strict=False)):
        row = f"{f'{name} [{unit}]' if unit else name:<30}{summary.median[j]:>9.2f}  "
        row += f"{f'[{summary.low[j]:.2f}, {summary.high[j]:.2f}]':<20}"
        if moments:
            row += f"{summary.mean[j]:>9.2f}{summary.std[j]:>9.2f}"
        lines.append(row.rstrip())
    return "\n".join(lines)
