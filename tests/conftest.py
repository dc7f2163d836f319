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
    p["train"]["variants"] = {"balanced": {"backbone": "cues", "size": 16, "balance": 10.0}}
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


@pytest.fixture(scope="session")
def prefect_server(tmp_path_factory):
    """A real Prefect server on 127.0.0.1 (own PREFECT_HOME), stopped at the end: yields its API URL."""
    import socket
    import subprocess
    import sys
    import time
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    home = tmp_path_factory.mktemp("prefect-server")
    env = dict(os.environ, PREFECT_HOME=str(home), PREFECT_SERVER_ANALYTICS_ENABLED="false")
    env.pop("PREFECT_API_URL", None)
    log = open(home / "server.log", "wb")
    proc = subprocess.Popen([sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port", str(port)],
                            env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}/api"
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                urllib.request.urlopen(f"{url}/health", timeout=2)
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"the Prefect server did not start; see {home / 'server.log'}") from None
                time.sleep(0.5)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
