"""pidc's Prefect flows: thin orchestration over :mod:`components`.

Importing this package points Prefect at project-local state (``.prefect/`` at the project root)
unless the user configured ``PREFECT_HOME`` or a server (``PREFECT_API_URL``), and turns off
telemetry (the machines are offline). It must run before ``prefect`` is imported.

Imported by every stage.
"""

import os
from pathlib import Path

import components  # noqa: F401  (first: it pins numpy's SIMD dispatch before anything imports numpy)

_ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("PREFECT_HOME", str(_ROOT / ".prefect"))
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
# a loaded machine can take longer than Prefect's default 20 s to start the temporary server
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
# MLflow's per-file download bars (logging a model downloads its own files back) drown the stage logs
os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
