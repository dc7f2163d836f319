"""The timeline figure of a watch: the drive's weather over time against the sources, the relation, the alarms.

One panel per parameter: each frame's posterior median (line) and 68.27 % HDI (band) over time, each source's range
shaded (the 0.5–99.5 % quantiles of its frames' draws), and, for a drive of known weather, the truth (dashed). Then
λ̂ over time (stacked, one colour per source), and the windows' relative gap with the calibrated threshold (dots
above it are flagged windows). Alarm segments are shaded red across every panel, from the rule's firing to the
segment's last window; a drive's exit from the sources' range (known weather) is a vertical dashed line.

Used by the ``pidc watch`` command (``timeline.png``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["timeline_figure"]

_SOURCE_COLOURS = (
    "tab:blue",
    "tab:green",
    "tab:orange",
    "tab:purple",
    "tab:brown",
    "tab:pink",
    "tab:olive",
    "tab:cyan",
)


def timeline_figure(result: Any) -> Any:
    """The timeline of a :class:`~components.watch.run.WatchResult` as a :class:`matplotlib.figure.Figure`."""
    from components.plots.canvas import new_figure

    box, frames, windows = result.box, result.frames, result.windows
    d = box.dim
    fig = new_figure(12.0, 1.6 * (d + 2) + 0.6)
    axes = fig.subplots(d + 2, 1, sharex=True)
    t = frames["time_s"]
    colours = [_SOURCE_COLOURS[k % len(_SOURCE_COLOURS)] for k in range(len(result.names))]
    for j, name in enumerate(box.names):
        ax = axes[j]
        for k, source in enumerate(result.names):
            low, high = result.ranges[k][j]
            ax.axhspan(low, high, color=colours[k], alpha=0.12, lw=0, label=f"{source}'s range" if j == 0 else None)
        ax.fill_between(t, frames[f"{name}_low"], frames[f"{name}_high"], color="0.6", alpha=0.5, lw=0, step="mid")
        ax.plot(t, frames[f"{name}_median"], color="k", lw=0.8, label="frame median, 68.27 % HDI" if j == 0 else None)
        if result.truth_table is not None:
            ax.plot(
                result.truth_table["time_s"],
                result.truth_table[name],
                "--",
                color="tab:red",
                lw=0.8,
                label="truth" if j == 0 else None,
            )
        ax.set_ylim(box.low[j], box.high[j])
        ax.set_ylabel(f"{name.replace('_', ' ')}\n[{box.units[j]}]", fontsize=8)
    ax = axes[d]
    end = windows["end_s"]
    lam = np.stack([windows[f"weight_{n}"] for n in result.names])
    ax.stackplot(end, lam, colors=colours, alpha=0.7, labels=[f"λ̂ {n}" for n in result.names])
    ax.set_ylim(0, 1)
    ax.set_ylabel("λ̂", fontsize=8)
    ax.legend(loc="upper right", fontsize=7, ncol=min(4, len(result.names)))
    ax = axes[d + 1]
    gap = windows["relative_gap"]
    flagged = windows["flagged"].astype(bool)
    ax.plot(end, gap, color="k", lw=0.8)
    ax.plot(end[flagged], gap[flagged], ".", color="tab:red", ms=3, label="flagged window")
    threshold = result.calibration.detector.threshold
    ax.axhline(threshold, color="tab:red", lw=1, ls="--", label=f"threshold {threshold:.3g}")
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("relative gap", fontsize=8)
    ax.set_xlabel("time [s]")
    ax.legend(loc="upper left", fontsize=7)
    exit_s = None if result.truth is None else result.truth["exit_s"]
    for ax in axes:
        for a in result.alarms:
            ax.axvspan(a.fired_s, a.end_s, color="tab:red", alpha=0.15, lw=0)
        if exit_s is not None:
            ax.axvline(exit_s, color="tab:red", ls=":", lw=1)
        ax.tick_params(labelsize=7)
    axes[0].legend(loc="upper right", fontsize=7, ncol=3)
    first = result.first_alarm_s
    alarm = "no alarm" if first is None else f"first alarm {first:.1f} s, {len(result.alarms)} segment(s)"
    fig.suptitle(f"{result.drive.path.name} against {', '.join(result.names)} ({result.model}): {alarm}", fontsize=10)
    return fig
