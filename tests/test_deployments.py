"""The scheduled deployments of prefect.yaml end to end, as the README runs them by hand: a real Prefect server,
a `process` work pool and a worker, `prefect deploy` from the file, a run triggered with `prefect deployment run`
and executed by the worker on a copy of the micro project, and the schedules the server registered."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import psutil
import pytest
import yaml

from components.core.config import PROJECT_ROOT
from tests.conftest import copy_project

FINAL = {"COMPLETED", "FAILED", "CRASHED", "CANCELLED"}
OUTPUTS = {
    "flows/evaluate.py:evaluate": "reports/task1/metrics.json",
    "flows/task3.py:task3": "reports/task3/metrics.json",
}
RUN_TIMEOUT_S = 300

# Loaded by every Python process the worker starts (through PYTHONPATH): at exit, records which source files of
# code outside the Python installation (the project's components/ and flows/) the process imported.
IMPORT_PROBE = """
import atexit, json, os, sys

def _record():
    roots = {os.path.realpath(p) for p in (sys.prefix, sys.base_prefix)}
    files = {name: os.path.realpath(f) for name, m in list(sys.modules.items())
             if isinstance(f := getattr(m, "__file__", None), str) and os.path.isabs(f) and name != "sitecustomize"
             and not any(os.path.realpath(f).startswith(r + os.sep) for r in roots)}
    with open(os.path.join(os.environ["PIDC_IMPORT_PROBE"], f"{os.getpid()}.json"), "w") as out:
        json.dump({"cwd": os.getcwd(), "modules": files}, out)

atexit.register(_record)
"""


def _prefect(args: list[str], cwd: Path, env: dict) -> str:
    r = subprocess.run(
        [sys.executable, "-m", "prefect", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=180
    )
    assert r.returncode == 0, f"`prefect {' '.join(args)}` failed ({r.returncode}):\n{r.stdout}\n{r.stderr}"
    return r.stdout


def _descendants(proc: subprocess.Popen) -> list[psutil.Process]:
    """The live processes ``proc`` started, directly or not."""
    try:
        children = psutil.Process(proc.pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []
    alive = []
    for child in children:
        try:
            if child.status() != psutil.STATUS_ZOMBIE:
                alive.append(child)
        except psutil.NoSuchProcess:
            pass
    return alive


def _wait_for_flow_run_processes(worker: subprocess.Popen, timeout: float = 60) -> None:
    """A run is COMPLETED in the API a moment before its processes have exited (and written their import records)."""
    deadline = time.monotonic() + timeout
    while _descendants(worker) and time.monotonic() < deadline:
        time.sleep(0.5)


def _stop(proc: subprocess.Popen) -> None:
    """Stop the worker and every process it started (flow runs get their own process groups)."""
    children = _descendants(proc)
    proc.terminate()  # the worker stops polling; it can linger, so it gets a few seconds
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        children += _descendants(proc)
        proc.kill()
        proc.wait(timeout=30)
    for child in children:
        try:
            child.kill()
        except psutil.NoSuchProcess:
            pass


def _wait_until_final(api: httpx.Client, run_id: str, worker_log: Path) -> dict:
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while True:
        run = api.get(f"/flow_runs/{run_id}").raise_for_status().json()
        if run["state"]["type"] in FINAL or time.monotonic() > deadline:
            break
        time.sleep(1)
    if run["state"]["type"] != "COMPLETED":
        logs = api.post(
            "/logs/filter", json={"logs": {"flow_run_id": {"any_": [run_id]}}, "sort": "TIMESTAMP_DESC", "limit": 40}
        ).json()
        log_text = "\n".join(f"{entry['timestamp']} {entry['message']}" for entry in reversed(logs))
        worker_text = worker_log.read_text(errors="replace")[-6000:]
        pytest.fail(
            f"flow run {run['name']} ({run_id}) is {run['state']['type']} after {RUN_TIMEOUT_S} s at most: "
            f"{run['state'].get('message')}\n--- flow run logs ---\n{log_text}\n--- worker log ---\n{worker_text}"
        )
    return run


@pytest.mark.slow
def test_prefect_yaml_deployments_run_on_a_process_worker(micro_project, prefect_server, tmp_path):
    spec = yaml.safe_load((PROJECT_ROOT / "prefect.yaml").read_text())
    project = copy_project(
        micro_project, tmp_path / "project"
    ).resolve()  # the runs write into it: the shared one stays as built
    shutil.copy(PROJECT_ROOT / "prefect.yaml", project / "prefect.yaml")  # the file under test, deployed from the root
    wanted = spec["deployments"]
    present = [d for d in wanted if (project / d["entrypoint"].partition(":")[0]).is_file()]
    assert "flows/evaluate.py:evaluate" in [d["entrypoint"] for d in present]
    pools = {d["work_pool"]["name"] for d in wanted}
    assert len(pools) == 1, pools
    pool = pools.pop()
    for d in present:  # what the runs must write: gone before they run
        (project / OUTPUTS[d["entrypoint"]]).unlink(missing_ok=True)

    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    env = {**os.environ, "PREFECT_API_URL": prefect_server, "PATH": path}
    env.pop("PYTHONPATH", None)
    _prefect(["work-pool", "create", pool, "--type", "process", "--overwrite"], tmp_path, env)

    probe = tmp_path / "probe"
    (probe / "records").mkdir(parents=True)
    (probe / "sitecustomize.py").write_text(IMPORT_PROBE)
    # the worker knows nothing of the project: no PIDC_PROJECT, started elsewhere
    worker_env = {
        **env,
        "PYTHONPATH": str(probe),
        "PIDC_IMPORT_PROBE": str(probe / "records"),
        "PREFECT_WORKER_QUERY_SECONDS": "1",
    }
    worker_env.pop("PIDC_PROJECT", None)
    (tmp_path / "worker").mkdir()
    worker_log = tmp_path / "worker.log"
    with open(worker_log, "wb") as log:
        worker = subprocess.Popen(
            [sys.executable, "-m", "prefect", "worker", "start", "--pool", pool],
            cwd=tmp_path / "worker",
            env=worker_env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    try:
        # deploy as the README does, from the project root with PIDC_PROJECT set (flows/task3.py may not exist yet)
        selection = ["--all"] if present == wanted else [a for d in present for a in ("--name", d["name"])]
        _prefect(["deploy", *selection, "--no-prompt"], project, {**env, "PIDC_PROJECT": str(project)})

        with httpx.Client(base_url=prefect_server, timeout=30) as api:
            names = [d["name"] for d in present]
            deployed = (
                api.post("/deployments/filter", json={"deployments": {"name": {"any_": names}}})
                .raise_for_status()
                .json()
            )
            by_entrypoint = {d["entrypoint"]: d for d in deployed}
            assert sorted(by_entrypoint) == sorted(d["entrypoint"] for d in present)
            for want in present:
                got = by_entrypoint[want["entrypoint"]]
                assert got["name"] == want["name"] and got["work_pool_name"] == pool
                assert got["parameters"] == want["parameters"] == {"params_path": "params.yaml"}
                # the path of the checkout it was deployed from, resolved at deploy time
                assert got["pull_steps"] == [
                    {"prefect.deployments.steps.set_working_directory": {"directory": str(project)}}
                ]
                schedules = [
                    (s["schedule"].get("cron"), s["schedule"].get("timezone"), s["active"]) for s in got["schedules"]
                ]
                assert schedules == [(s["cron"], s["timezone"], s.get("active", True)) for s in want["schedules"]]
                assert schedules and all(cron and tz for cron, tz, _ in schedules)

            run_ids = {}
            for want in present:  # by hand, as the README shows; the worker runs them side by side
                flow_name = (
                    api.get(f"/flows/{by_entrypoint[want['entrypoint']]['flow_id']}").raise_for_status().json()["name"]
                )
                out = _prefect(["deployment", "run", f"{flow_name}/{want['name']}"], project, env)
                found = re.search(r"UUID: ([0-9a-f-]{36})", out)
                assert found, out
                run_ids[want["entrypoint"]] = found.group(1)
            for entrypoint, run_id in run_ids.items():
                run = _wait_until_final(api, run_id, worker_log)
                assert run["deployment_id"] == by_entrypoint[entrypoint]["id"] and run["parameters"] == {
                    "params_path": "params.yaml"
                }
                assert (project / OUTPUTS[entrypoint]).is_file(), (
                    f"{entrypoint} completed without writing {OUTPUTS[entrypoint]}"
                )
        _wait_for_flow_run_processes(worker)
    finally:
        _stop(worker)

    metrics = json.loads((project / "reports/task1/metrics.json").read_text())
    assert set(metrics) == set(json.loads((micro_project / "reports/task1/metrics.json").read_text()))
    assert all(np.isfinite(m["test_nll"]) for m in metrics.values())

    # the flow runs imported the project's own components/ and flows/, not the editable install's (PROJECT_ROOT)
    records = [json.loads(p.read_text()) for p in (probe / "records").glob("*.json")]
    for r in records:
        elsewhere = {n: f for n, f in r["modules"].items() if not f.startswith(str(project) + os.sep)}
        assert not elsewhere, f"a process of the worker imported code from outside the project: {elsewhere}"
    for entrypoint in run_ids:
        script = str(project / entrypoint.partition(":")[0])
        runs = [r for r in records if script in r["modules"].values()]
        assert runs, f"no process of the worker imported {script}: {[sorted(r['modules']) for r in records]}"
        assert all(r["cwd"] == str(project) and {"components", "flows"} <= set(r["modules"]) for r in runs), runs
