"""Task II: how far the bag's estimate was deconvolved — the held-out log likelihood per EM step.

Step 0 is the training prior, step 1 the mixture of posteriors (the paper's estimate), later steps deconvolve
(:mod:`components.domains.deconvolution`); the step chosen (one-standard-error rule) is marked.

Used (through :mod:`components.plots`) by the ``task2`` stage.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from components.plots.canvas import new_figure

__all__ = ["held_out_curve"]


def held_out_curve(held_out: np.ndarray, steps: int, title: str = "Deconvolution: held-out likelihood") -> Figure:
    """The held-out log likelihood per image ``held_out (S + 1,)`` against the EM step, relative to step 1 (the
    mixture of posteriors), with ``steps`` (the number chosen) marked."""
    h = np.asarray(held_out, dtype=np.float64)
    if h.ndim != 1 or h.size < 2 or not np.all(np.isfinite(h)):
        raise ValueError(f"held_out must be finite with shape (S + 1,), S ≥ 1, got shape {h.shape}")
    if not 0 <= steps < h.size:
        raise ValueError(f"steps must index held_out (0…{h.size - 1}), got {steps}")
    gain = h - h[1]
    x = np.arange(h.size)
    fig = new_figure(7.5, 4.6)
    ax = fig.add_subplot()
    ax.plot(x[1:], gain[1:], linewidth=1.6, color="#1f5fa8", label="held-out log likelihood − the mixture's")
    ax.axvline(steps, color="#d62728", linestyle="--", linewidth=1.2, label=f"chosen: {steps} steps")
    ax.axhline(0.0, color="#7f7f7f", linewidth=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("EM steps (1 = the mixture of posteriors)")
    ax.set_ylabel("nats per image")
    ax.set_title(f"prior (step 0): {gain[0]:+.2f} nats per image", fontsize=9)
    ax.grid(alpha=0.25)
    ax.legend(frameon=False)
    fig.suptitle(title)
    return fig
