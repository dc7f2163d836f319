"""watch — a drive followed frame by frame: per-frame posteriors, windows related to the sources, and the alarm.

- :mod:`~components.watch.settings`: the defaults (:data:`~components.watch.settings.WATCH_DEFAULTS`) and the checked
  options of a watch.
- :mod:`~components.watch.errors`: the one-line error of a bad drive, source or option.
- :mod:`~components.watch.frames`: a drive's frames and times streamed in batches, from a video or a folder.
- :mod:`~components.watch.draws`: posterior draws seeded per frame, and each frame's median and 68.27 % HDI.
- :mod:`~components.watch.timeline`: the windows over a stream of frames (a fixed length or exponential decay).
- :mod:`~components.watch.relation`: a window related to the sources (Task III: λ̂, the relative gap, W₁ per
  parameter).
- :mod:`~components.watch.calibration`: the sources cut into blocks, the threshold and the in-ODD levels calibrated on
  held-out windows.
- :mod:`~components.watch.sequential`: the rule over windows (consecutive flagged windows) and its false alarms per
  hour measured on held-out windows.
- :mod:`~components.watch.truth`: the known weather of a simulated drive and the rule's measured detection delay.
- :mod:`~components.watch.run`: the whole watch of a drive (:func:`~components.watch.run.watch`; the sources read and
  calibrated once for many drives by :func:`~components.watch.run.prepare_sources`).
- :mod:`~components.watch.folder`: a folder of drives: listing, fingerprints, which are watched already.
- :mod:`~components.watch.report`: the tables, the JSON summary; :mod:`~components.watch.plot`: the timeline figure.

Downstream of :mod:`components.domains` (Tasks II and III) and the registry's runtime; no DVC stage imports it. Used by
the ``pidc watch`` command and the ``watch`` flow (flows/watch.py).
"""

__all__ = [
    "settings",
    "errors",
    "frames",
    "draws",
    "timeline",
    "relation",
    "calibration",
    "sequential",
    "truth",
    "run",
    "report",
    "plot",
    "folder",
]
