"""Task III for one target: its six 1-D marginals beside the fitted mixture of the sources' and each source's.

Each panel shows one parameter on the prior's range as step histograms (probability density per unit of the
parameter): each source (thin, dashed, labelled with its λ̂ₖ), the mixture Σₖ λ̂ₖ sourceₖ that Task III fitted (blue;
source k's draws weighted λ̂ₖ / nₖ) and the target (red). Where the red and blue steps part, the target's weather is
not one the sources explain; a note per panel (e.g. the W₁ between them) goes into its title.

Used (through :mod:`components.plots`) by the ``pidc relate`` command.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from components.core.weather import Box
from components.plots.checks import as_samples
from components.plots.overlay import Marginals, overlay_marginals

__all__ = ["relation_marginals"]

_TARGET, _MIXTURE = "#d62728", "#1f5fa8"
_SOURCES = ("#7f7f7f", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf")


def relation_marginals(
    target: object,
    sources: Sequence[object],
    weights: object,
    names: Sequence[str],
    box: Box | None = None,
    notes: Sequence[str] | None = None,
    title: str | None = None,
    bins: int = 50,
) -> Figure:
    """2×3 panels, one per parameter: the marginals of ``target`` (``(n, 6)`` draws, physical units), of the mixture
    of ``sources`` (one ``(nₖ, 6)`` array each) with ``weights`` λ̂ ``(K,)``, and of each source (named by ``names``),
    on the box's range (default: the physical ranges). ``notes``: six strings appended to the panel titles."""
    s = [as_samples(x, f"source {k}") for k, x in enumerate(sources)]
    if len(names) != len(s) or not s:
        raise ValueError(f"names must name every source ({len(s)}), got {len(names)}")
    lam = np.asarray(weights, dtype=np.float64)
    if lam.shape != (len(s),) or not np.all(np.isfinite(lam)) or np.any(lam < 0) or lam.sum() <= 0:
        raise ValueError(f"weights must be {len(s)} non-negative numbers with a positive sum, got {lam.tolist()}")
    lam = lam / lam.sum()
    series = [
        Marginals(x, f"{n} (λ̂ {lam[k]:.2f})", _SOURCES[k % len(_SOURCES)], "--", 0.9)
        for k, (x, n) in enumerate(zip(s, names, strict=True))
    ]
    per_draw = np.concatenate([np.full(len(x), lam[k] / len(x)) for k, x in enumerate(s)])  # source k's: λ̂ₖ / nₖ
    series += [
        Marginals(np.concatenate(s), "fitted mixture Σ λ̂ₖ sourceₖ", _MIXTURE, width=1.8, weights=per_draw),
        Marginals(target, "target", _TARGET, width=1.8),
    ]
    return overlay_marginals(
        series,
        box,
        notes,
        title or "The target's marginals beside the sources' fitted mixture",
        bins,
        legend_columns=min(len(series), 5),
    )
