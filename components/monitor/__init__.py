"""monitor — scheduled monitoring: the registered models judged on new labelled images, and the alarms.

- :mod:`~components.monitor.draws`: the run's date and seeds, new simulated images (Task I) and new images of the
  sources' weather (the fresh pools of Task III's in-ODD targets).
- :mod:`~components.monitor.recorded`: a folder of recorded images with their labels (``labels.csv``), validated.
- :mod:`~components.monitor.checks`: the calibration alarm, the ODD decision's false-alarm interval, the alarms.

Downstream of every other package (it reuses the evaluation's metrics and Task III's sweep); the one DVC stage that
imports it is ``evaluate``, for :mod:`~components.monitor.recorded` (named weathers from recorded folders). Used by the scheduled monitoring (``flows/monitor.py``, the deployments of ``prefect.yaml``).
"""

__all__ = ["draws", "recorded", "checks"]
