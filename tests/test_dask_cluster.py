"""The fan-out stages on an existing Dask cluster (``runner.kind: dask`` with a ``dask_address``), started with Dask's
own command line: ``dask scheduler`` and two ``dask worker`` processes on the loopback address, in the project folder
with the Prefect server of the session (docs/cluster.md). A scheduler nobody answers is one line before any work."""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

from components.core.config import PROJECT_ROOT
from tests.conftest import FAST_TRAINING, micro_params, new_project, run_in, write_params

DASK = str(Path(sys.executable).parent / "dask")
RUNNERS = ("data.runner", "train.runner", "export.runner", "evaluate.runner")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(procs: list[subprocess.Popen]) -> None:
    """End each process group (a worker's nanny and its worker process), SIGKILL after 20 s."""
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


@contextmanager
def dask_cluster(project: Path, logs: Path, prefect_api: str, workers: int = 2):
    """``dask scheduler`` on a free loopback port and ``workers`` ``dask worker`` processes (one thread each) started
    in ``project`` with it on PYTHONPATH and PREFECT_API_URL set; yields the scheduler's address once it sees every
    worker; every process group is ended on the way out, failures included."""
    from distributed import Client

    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    logs.mkdir(parents=True, exist_ok=True)
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    env = {**os.environ, "PYTHONPATH": str(project), "PATH": path, "PREFECT_API_URL": prefect_api}
    procs: list[subprocess.Popen] = []

    def start(name: str, cmd: list[str]) -> None:
        log = open(logs / f"{name}.log", "wb")
        procs.append(
            subprocess.Popen(cmd, cwd=project, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        )
        log.close()

    try:
        start("scheduler", [DASK, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"])
        for i in range(workers):
            start(
                f"worker-{i}",
                [DASK, "worker", address, "--nthreads", "1", "--nworkers", "1", "--no-dashboard", "--host", "127.0.0.1"]
                + ["--local-directory", str(logs / f"worker-{i}")],
            )
        deadline = time.monotonic() + 120
        while True:
            try:
                with Client(address, timeout=5, set_as_default=False) as client:
                    if workers:
                        client.wait_for_workers(workers, timeout=max(1.0, deadline - time.monotonic()))
                break
            except (OSError, TimeoutError):
                if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
                    raise RuntimeError(f"the Dask cluster did not start; see {logs}") from None
                time.sleep(0.5)
        yield address
    finally:
        _stop(procs)


def runners(kind: str, address: str | None = None, workers: int = 2) -> dict:
    """Every fan-out runner of the micro params set to ``kind`` (their other keys kept); export's with one worker
    unless ``processes`` (the params refuse parallel exports in one process: torch's ONNX exporter)."""
    p = micro_params()
    return {
        key: {
            **p[key.split(".")[0]]["runner"],
            "kind": kind,
            "workers": 1 if key == "export.runner" and kind != "processes" else workers,
            "dask_address": address,
        }
        for key in RUNNERS
    }


def fast_training() -> dict:
    """``FAST_TRAINING`` over the micro params' own ``backbones`` section (its other keys kept)."""
    return {**FAST_TRAINING, "backbones": {**micro_params()["backbones"], **FAST_TRAINING["backbones"]}}


def hashes(folder: Path) -> dict[str, str]:
    """Relative path → SHA-256 of every file under ``folder``. A ``.gitignore`` is DVC's bookkeeping, one line per
    output in the order DVC happened to commit them (which ``dvc repro`` and ``dvc repro features`` need not share):
    its sorted lines are hashed, so the same outputs give the same hash and a missing or extra one still differs."""

    def content(p: Path) -> bytes:
        return b"\n".join(sorted(p.read_bytes().splitlines())) if p.name == ".gitignore" else p.read_bytes()

    return {
        str(p.relative_to(folder)): hashlib.sha256(content(p)).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_an_unanswered_dask_address_is_one_line_before_any_work(tmp_path):
    """Nobody listens on a port just freed: the stage ends with exit 2 and one line naming the runner's key and the
    refused connection, in seconds (no Dask retries), and writes no data."""
    address = f"tcp://127.0.0.1:{free_port()}"
    params = write_params(tmp_path, **{"data.runner": {"kind": "dask", "workers": 2, "dask_address": address}})
    t0 = time.monotonic()
    r = run_in([sys.executable, "-m", "flows.generate", "--params", str(params)], PROJECT_ROOT, timeout=120)
    elapsed = time.monotonic() - t0
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert lines == [
        f"generate.py: data.runner.dask_address: no Dask scheduler answers at {address} (connection refused)"
    ]
    assert not (tmp_path / "data").exists()
    assert elapsed < 60, elapsed  # the interpreter's imports (seconds under load), not a connection's time-outs


def test_the_preflight_names_what_the_cluster_lacks(tmp_path, prefect_server):
    """A scheduler without workers, then workers started outside the project (they cannot import it): each is one
    error naming the key; the project's own workers pass and report the same environment as this process."""
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from flows.stage import DaskClusterError, check_dask_cluster

    params = write_params(tmp_path / "project")
    with temporary_settings({PREFECT_API_URL: prefect_server}):
        with dask_cluster(tmp_path / "project", tmp_path / "logs-0", prefect_server, workers=0) as address:
            with pytest.raises(
                DaskClusterError, match=r"^train\.runner\.dask_address: the Dask scheduler at .* has no"
            ):
                check_dask_cluster(address, "train.runner", timeout=2)
        other = tmp_path / "other"  # another copy of the project's code: not the folder this process runs
        for name in ("components", "flows"):
            shutil.copytree(PROJECT_ROOT / name, other / name, ignore=shutil.ignore_patterns("__pycache__"))
        with dask_cluster(other, tmp_path / "logs-1", prefect_server, workers=1) as address:
            with pytest.raises(DaskClusterError) as e:
                check_dask_cluster(address, "data.runner", params_file=params)
        message = str(e.value)
        assert message.startswith("data.runner.dask_address: Dask worker tcp://127.0.0.1:") and "\n" not in message
        assert f"project {PROJECT_ROOT.resolve()} here, {other} there" in message, message
        with dask_cluster(PROJECT_ROOT, tmp_path / "logs-2", prefect_server, workers=2) as address:
            facts = check_dask_cluster(address, "data.runner", params_file=params)
    assert len(facts) == 2 and all(f["project"] == str(PROJECT_ROOT.resolve()) for f in facts.values())


@pytest.mark.slow
def test_the_micro_pipeline_on_a_dask_cluster_gives_the_processes_runners_bytes(tmp_path, prefect_server):
    """`dvc repro` of the micro project with every fan-out stage on a scheduler and two workers started with Dask's
    command line: every stage runs, and data/ and features/ are byte for byte those of `dvc repro features` with the
    ``processes`` runner (the renders and features are seeded per shard: no runner may change a byte)."""
    reference = new_project(tmp_path / "processes", **fast_training(), **runners("processes"))
    r = run_in([sys.executable, "-m", "dvc", "repro", "features"], reference, env={"PREFECT_API_URL": prefect_server})
    assert r.returncode == 0, r.stdout + r.stderr

    repo = tmp_path / "dask"
    new_project(repo, **fast_training())
    with dask_cluster(repo, tmp_path / "logs", prefect_server) as address:
        write_params(repo, **fast_training(), **runners("dask", address))
        r = run_in([sys.executable, "-m", "dvc", "repro"], repo, env={"PREFECT_API_URL": prefect_server}, timeout=1200)
        assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    for folder in ("data", "features"):
        ours, theirs = hashes(repo / folder), hashes(reference / folder)
        differ = sorted(k for k in ours.keys() | theirs.keys() if ours.get(k) != theirs.get(k))
        assert ours and not differ, f"{folder}: {differ}"
    assert (repo / "reports/task1/metrics.json").is_file() and (repo / "reports/task1/champion.json").is_file()
