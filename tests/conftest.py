"""Shared fixtures. Prefect state goes to a temporary folder, never the project's .prefect/."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

os.environ["PREFECT_HOME"] = tempfile.mkdtemp(prefix="pidc-prefect-home-")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.pop("PREFECT_API_URL", None)
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import pytest  # noqa: E402
import yaml  # noqa: E402

from components.config import PROJECT_ROOT  # noqa: E402


@pytest.fixture(scope="session")
def prefect_harness():
    """A temporary Prefect server and database for the tests that run flows in-process."""
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield


def micro_params(**overrides) -> dict:
    """The default params.yaml shrunk to a few tiny images (for pipeline tests)."""
    p = yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())
    p["simulator"].update(height=32, width=32)
    p["data"].update(splits={"train": 24, "val": 8, "test": 8}, shard_size=10, images_per_scene=4)
    p["data"]["runner"].update(kind="threads", workers=2)
    p["contact_sheet"].update(steps=3, scenes=1)
    p["train"]["sizes"] = [8, 16, 24]
    p["evaluate"].update(images=8, samples=400, ppc_images=1, ppc_renders=2, example_images=1)
    for key, value in overrides.items():
        section, _, name = key.partition(".")
        if name:
            p[section][name] = value
        else:
            p[section] = value
    return p


def write_params(folder: Path, **overrides) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "params.yaml"
    path.write_text(yaml.safe_dump(micro_params(**overrides), sort_keys=False))
    return path
