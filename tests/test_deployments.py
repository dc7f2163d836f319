"""The scheduled deployments of prefect.yaml end to end, as docs/monitoring.md runs them by hand: a real Prefect server,
a `process` work pool and a worker, `prefect deploy` from the file, runs triggered with `prefect deployment run` and
executed by the worker in a project built with `dvc repro`, and the schedules the server registered.

The deployments monitor (flows/monitor.py): each run judges the registered models on new draws of its date, writes
reports/monitoring/<date>/ and one MLflow run in the monitoring experiment, leaves the DVC pipeline as it was, and fails
on an alarm. The project is the micro project's params with one informative model (cues on 2 000 images, calibrated
within its band), so that a healthy run completes and a run on recorded images with wrong labels fails."""

from __future__ import annotations

import csv
import datetime as dt
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import httpx
import mlflow
import numpy as np
import psutil
import pytest
import yaml

from components.core import weather
from components.core.config import PROJECT_ROOT, load_params
from components.monitor import draws
from components.simulate.contact_sheet import save_png
from components.simulate.procedural import ProceduralSimulator
from tests.conftest import build_project, run_in

FINAL = {"COMPLETED", "FAILED", "CRASHED", "CANCELLED"}
RUN_TIMEOUT_S = 300
#: one model informative enough to notice wrong labels and calibrated within its band (~95 s of `dvc repro`); the alarm
#: level 0.999 keeps a healthy run from failing by chance (each check's false alarms ≤ 0.1 %)
MONITORED_PROJECT = {
    "data.splits": {"train": 2000, "val": 200, "test": 120},
    "data.shard_size": 500,
    "backbones": {"names": ["cues"], "pretrained_dir": None, "batch_size": 256, "device": "cpu"},
    "train.sizes": [2000],
    "train.epochs": 20,
    "train.scale_to": 8,
    "train.variants": {},
    "train.flow": {
        "transforms": 2,
        "hidden_features": [32, 32],
        "bins": 8,
        "passes": 2,
        "ensemble": 1,
        "standardize": True,
        "context_layers": [],
    },
    "monitor.images": 32,
    "monitor.alarm_level": 0.999,
}

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


def _start_worker(pool: str, folder: Path, env: dict) -> tuple[subprocess.Popen, Path]:
    """A `process` worker of ``pool`` started in ``folder``/worker (its own session, so that :func:`_stop` can end
    it and its flow runs), logging to ``folder``/worker.log."""
    (folder / "worker").mkdir()
    worker_log = folder / "worker.log"
    with open(worker_log, "wb") as log:
        worker = subprocess.Popen(
            [sys.executable, "-m", "prefect", "worker", "start", "--pool", pool],
            cwd=folder / "worker",
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    return worker, worker_log


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


def _wait_until_final(api: httpx.Client, run_id: str, worker_log: Path, expected: str) -> dict:
    """The flow run once final; the test fails with its logs and the worker's when it is not in state ``expected``."""
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while True:
        run = api.get(f"/flow_runs/{run_id}").raise_for_status().json()
        if run["state"]["type"] in FINAL or time.monotonic() > deadline:
            break
        time.sleep(1)
    if run["state"]["type"] != expected:
        logs = api.post(
            "/logs/filter", json={"logs": {"flow_run_id": {"any_": [run_id]}}, "sort": "TIMESTAMP_DESC", "limit": 40}
        ).json()
        log_text = "\n".join(f"{entry['timestamp']} {entry['message']}" for entry in reversed(logs))
        worker_text = worker_log.read_text(errors="replace")[-6000:]
        pytest.fail(
            f"flow run {run['name']} ({run_id}) is {run['state']['type']} (expected {expected}) after "
            f"{RUN_TIMEOUT_S} s at most: {run['state'].get('message')}\n--- flow run logs ---\n{log_text}\n"
            f"--- worker log ---\n{worker_text}"
        )
    return run


def _recorded_with_wrong_labels(project: Path, folder: Path, n: int) -> Path:
    """A recorded folder (PNGs + labels.csv) of ``n`` new images of the project's simulator, each labelled with the
    weather of the next image (every label wrong, their distribution the prior's)."""
    params = load_params(project / "params.yaml")
    simulator = ProceduralSimulator(params.simulator.height, params.simulator.width)
    draw = draws.simulated_draw(simulator, params, 4242, n)
    folder.mkdir(parents=True)
    with open(folder / "labels.csv", "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["image", *weather.PREDICTED])
        for i, (image, label) in enumerate(zip(draw.images, np.roll(draw.theta, 1, axis=0), strict=True)):
            save_png(folder / f"frame_{i:03d}.png", image)
            out.writerow([f"frame_{i:03d}.png", *(f"{v:.4f}" for v in label)])
    return folder


@pytest.fixture(scope="module")
def monitored_project(tmp_path_factory, prefect_server) -> Path:
    """A project built with `dvc repro` whose registered champion is worth monitoring (MONITORED_PROJECT)."""
    return build_project(tmp_path_factory.mktemp("monitored-project") / "repo", prefect_server, **MONITORED_PROJECT)


def _dvc_status(project: Path) -> str:
    r = run_in([sys.executable, "-m", "dvc", "status"], project)
    assert r.returncode == 0, r.stdout + r.stderr
    return r.stdout.strip()


def _monitoring_run(client: mlflow.MlflowClient, experiment: str, flow_run_id: str):
    """The MLflow run of a flow run in the monitoring experiment, found by its tag."""
    exp = client.get_experiment_by_name(experiment)
    assert exp is not None, f"no MLflow experiment {experiment!r}"
    runs = client.search_runs([exp.experiment_id], f"tags.`pidc.prefect_flow_run` = '{flow_run_id}'")
    assert len(runs) == 1, [r.info.run_name for r in runs]
    return runs[0]


@pytest.mark.slow
def test_prefect_yaml_deployments_monitor_on_a_process_worker(monitored_project, prefect_server, tmp_path):
    spec = yaml.safe_load((PROJECT_ROOT / "prefect.yaml").read_text())
    project = monitored_project.resolve()
    assert (project / "prefect.yaml").read_text() == (PROJECT_ROOT / "prefect.yaml").read_text()
    wanted = [d for d in spec["deployments"] if d["name"] != WATCH_DEPLOYMENT]  # the watch: the test below
    assert {d["entrypoint"] for d in wanted} == {"flows/monitor.py:monitor"}
    assert sorted(d["parameters"]["models"] for d in wanted) == ["all", "champion"]
    pools = {d["work_pool"]["name"] for d in wanted}
    assert len(pools) == 1, pools
    pool = pools.pop()
    assert _dvc_status(project) == "Data and pipelines are up to date."
    params = load_params(project / "params.yaml")
    wrong = _recorded_with_wrong_labels(project, tmp_path / "recorded", params.monitor.images)

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
    worker, worker_log = _start_worker(pool, tmp_path, worker_env)
    try:
        # deploy as docs/monitoring.md does, from the project root with PIDC_PROJECT set
        _prefect(["deploy", "--all", "--no-prompt"], project, {**env, "PIDC_PROJECT": str(project)})

        with httpx.Client(base_url=prefect_server, timeout=30) as api:
            names = [d["name"] for d in wanted]
            deployed = (
                api.post("/deployments/filter", json={"deployments": {"name": {"any_": names}}})
                .raise_for_status()
                .json()
            )
            by_name = {d["name"]: d for d in deployed}
            assert sorted(by_name) == sorted(names)
            for want in wanted:
                got = by_name[want["name"]]
                assert got["entrypoint"] == want["entrypoint"] and got["work_pool_name"] == pool
                assert got["parameters"] == want["parameters"]
                # the path of the checkout it was deployed from, resolved at deploy time
                assert got["pull_steps"] == [
                    {"prefect.deployments.steps.set_working_directory": {"directory": str(project)}}
                ]
                schedules = [
                    (s["schedule"].get("cron"), s["schedule"].get("timezone"), s["active"]) for s in got["schedules"]
                ]
                assert schedules == [(s["cron"], s["timezone"], s.get("active", True)) for s in want["schedules"]]
                assert schedules and all(cron and tz for cron, tz, _ in schedules)

            # by hand, as docs/monitoring.md shows; the worker runs them side by side
            triggers = {
                "nightly": ["monitor/nightly"],
                "weekly": ["monitor/weekly"],
                "wrong-labels": [
                    "monitor/nightly",
                    "--params",
                    json.dumps({"source": str(wrong), "date": "2000-01-02"}),
                ],
            }
            run_ids = {}
            for key, args in triggers.items():
                out = _prefect(["deployment", "run", *args], project, env)
                found = re.search(r"UUID: ([0-9a-f-]{36})", out)
                assert found, out
                run_ids[key] = found.group(1)
            runs = {
                key: _wait_until_final(api, run_id, worker_log, "FAILED" if key == "wrong-labels" else "COMPLETED")
                for key, run_id in run_ids.items()
            }
        _wait_for_flow_run_processes(worker)
    finally:
        _stop(worker)

    message = runs["wrong-labels"]["state"]["message"]
    assert "MonitoringAlarm" in message and "calibration alarm: cues-2000" in message, message

    client = mlflow.MlflowClient(tracking_uri=f"sqlite:///{project / 'mlflow.db'}")
    champion = client.get_model_version_by_alias(params.export.registered_model, "champion")
    version = str(champion.version)
    for key, run in runs.items():
        assert run["deployment_id"] == by_name[triggers[key][0].partition("/")[2]]["id"]
        # the run's date: the one given, else the UTC date of its scheduled start
        given = run["parameters"].get("date")
        expected = dt.datetime.fromisoformat(run["expected_start_time"]).astimezone(dt.UTC).date()
        day = given or expected.isoformat()
        which = run["parameters"]["models"]
        report_dir = project / "reports" / "monitoring" / day / which
        report = json.loads((report_dir / "metrics.json").read_text())
        assert (report_dir / "coverage.png").stat().st_size > 0
        assert report["date"] == day and report["models_monitored"] == which
        assert report["images"] == params.monitor.images and report["samples"] == params.monitor.samples
        model = report["models"]["cues-2000"]
        assert model["registered_version"] == version and "champion" in model["aliases"]
        assert model["calibration_band"] == report["calibration_band"] > 0
        # one model judged: its band at the alarm level itself (k models: 1 − (1 − level)/k each)
        assert model["calibration_level"] == report["calibration_level"] == pytest.approx(params.monitor.alarm_level)
        assert (
            (model["calibration_error"] > model["calibration_band"])
            == (key == "wrong-labels")
            == bool(report["alarms"])
        )
        assert model["resized_images"] == 0  # every image, simulated or recorded, of the training renders' size
        if key == "wrong-labels":
            assert report["source"] == str(wrong) and report["alarms"][0].startswith("calibration alarm: cues-2000")
            assert "resized" not in report["alarms"][0]
        else:
            odd = report["odd"]
            assert odd["model"] == "cues-2000" and odd["n"] == params.monitor.false_alarm_targets
            assert odd["interval_low"] <= odd["flagged"] <= odd["interval_high"] and not odd["alarm"]

        logged = _monitoring_run(client, params.monitor.experiment, run["id"])
        assert logged.info.run_name == f"monitor-{day}" + ("" if which == "champion" else "-all")
        assert logged.info.status == ("FAILED" if key == "wrong-labels" else "FINISHED")
        tags = logged.data.tags
        assert tags["pidc.date"] == day and tags["pidc.model"] == "cues-2000"
        assert tags["pidc.registered_version"] == version and tags["pidc.models_monitored"] == which
        # metrics are logged to 6 significant digits (flows.tracking._digits)
        assert logged.data.metrics["task1.champion.calibration_error"] == pytest.approx(
            model["calibration_error"], rel=1e-5
        )
        history = client.get_metric_history(logged.info.run_id, "task1.cues-2000.calibration_error")
        midnight = dt.datetime.fromisoformat(day).replace(tzinfo=dt.UTC)
        assert [(m.step, m.timestamp) for m in history] == [
            ((midnight.date() - dt.date(1970, 1, 1)).days, int(midnight.timestamp() * 1000))
        ]
        assert {a.path for a in client.list_artifacts(logged.info.run_id, "monitoring")} == {
            "monitoring/metrics.json",
            "monitoring/coverage.png",
        }

    # the pipeline is as it was: reports/monitoring and the MLflow store are no DVC output nor dependency
    assert _dvc_status(project) == "Data and pipelines are up to date."

    # the flow runs imported the project's own components/ and flows/, not the editable install's (PROJECT_ROOT)
    records = [json.loads(p.read_text()) for p in (probe / "records").glob("*.json")]
    for r in records:
        elsewhere = {n: f for n, f in r["modules"].items() if not f.startswith(str(project) + os.sep)}
        assert not elsewhere, f"a process of the worker imported code from outside the project: {elsewhere}"
    script = str(project / "flows" / "monitor.py")
    flow_runs = [r for r in records if script in r["modules"].values()]
    assert len(flow_runs) >= len(run_ids), [sorted(r["modules"]) for r in records]
    assert all(r["cwd"] == str(project) and {"components", "flows"} <= set(r["modules"]) for r in flow_runs), flow_runs


# --- the watch of a folder of drives (flows/watch.py, deployment watch-drives) -------------------------------------

WATCH_DEPLOYMENT = "watch-drives"
#: the watch's settings for drives of seconds at 10 frames/s (the defaults are for drives of minutes): windows of 1 s
#: every 0.2 s, blocks of 4 s, the threshold at α = 0.02 (the largest of the 64 calibration windows' gaps), an alarm
#: after 5 consecutive flagged windows
WATCH_SETTINGS = {"window": 10, "stride": 2, "block": 40, "false_alarm_rate": 0.02, "consecutive": 5}
#: the sources (two days walking fast over their boxes, 32 s each) and the drives' box (inside the clear day's)
WATCH_CLEAR = {"cloudiness": (0, 30), "fog_density": (0, 10), "sun_altitude_angle": (40, 70), "wind_intensity": (0, 30)}
WATCH_CLOUDY = WATCH_CLEAR | {"cloudiness": (60, 95), "precipitation": (0, 30)}
WATCH_INSIDE = {"cloudiness": (5, 25), "fog_density": (2, 8), "sun_altitude_angle": (45, 65), "wind_intensity": (5, 25)}
DRIVE_SECONDS = 20.0


def _watched_world(project: Path, root: Path) -> dict[str, Path]:
    """Two source drives and a folder of two drives, rendered at the project's image size: ``inside`` walks inside the
    clear day's box; ``fog`` is the same kind of drive in dense fog (95 %) on every frame."""
    from components.simulate.drive import Drive, write_folder

    sim = load_params(project / "params.yaml").simulator
    assert sim.height == sim.width, "drives are square"
    size = sim.height
    inside = {"box": WATCH_INSIDE, "correlation_s": 10.0, "size": size, "seconds": DRIVE_SECONDS}
    fog = inside | {"box": {k: v for k, v in WATCH_INSIDE.items() if k != "fog_density"}, "held": {"fog_density": 95.0}}
    return {
        "clear": write_folder(
            Drive(seconds=32, seed=11, size=size, box=WATCH_CLEAR, correlation_s=3.0), root / "clear"
        ),
        "cloudy": write_folder(
            Drive(seconds=32, seed=12, size=size, box=WATCH_CLOUDY, correlation_s=3.0), root / "cloudy"
        ),
        "inside": write_folder(Drive(seed=13, **inside), root / "drives" / "inside"),
        "fog": write_folder(Drive(seed=14, **fog), root / "drives" / "fog"),
    }


def _flow_run_logs(api: httpx.Client, run_id: str, until: str, timeout: float = 30) -> str:
    """The log lines of a flow run, once a line holding ``until`` has arrived (a run's logs are sent in batches)."""
    deadline = time.monotonic() + timeout
    while True:
        logs = api.post(
            "/logs/filter", json={"logs": {"flow_run_id": {"any_": [run_id]}}, "sort": "TIMESTAMP_ASC", "limit": 200}
        ).raise_for_status()
        text = "\n".join(entry["message"] for entry in logs.json())
        if until in text or time.monotonic() > deadline:
            return text
        time.sleep(0.5)


@pytest.mark.slow
def test_watch_drives_deployment_fails_naming_the_drive_that_left_the_odd(monitored_project, prefect_server, tmp_path):
    """The deployment watch-drives on a process worker: the first run watches both drives, logs an MLflow run each and
    ends FAILED naming the fog drive; a second run finds nothing new, skips both and completes.

    It cannot pass by chance: the same rule must alarm on one drive and stay silent on the other, so neither a watch
    that always alarms nor one that never does passes, and an uninformative model (whose fog windows would look like
    the sources') fails. The fog drive is far outside the sources (fog 95 % on every frame against ≤ 10 %): with this
    weak model (cues on 2 000 images of 32×32 pixels) every one of its windows has a relative gap above 0.999 against
    a threshold of 0.28, and fog's W₁ is 13 times its in-ODD level (cloudiness, second, 1.8 times). The in-ODD drive's
    windows stayed below the threshold but for one in 20 seconds (at most two consecutive ones over twelve such drives
    of other seeds, measured), and an alarm needs five."""
    deployments = yaml.safe_load((PROJECT_ROOT / "prefect.yaml").read_text())["deployments"]
    spec = next(d for d in deployments if d["name"] == WATCH_DEPLOYMENT)
    assert spec["entrypoint"] == "flows/watch.py:watch_folder"
    assert set(spec["parameters"]) == {"folder", "sources"} and isinstance(spec["parameters"]["sources"], list)
    assert [s["interval"] for s in spec["schedules"]] == [600]
    project = monitored_project.resolve()
    world = _watched_world(project, tmp_path / "world")
    pool = spec["work_pool"]["name"]

    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    env = {**os.environ, "PREFECT_API_URL": prefect_server, "PATH": path}
    env.pop("PYTHONPATH", None)
    _prefect(["work-pool", "create", pool, "--type", "process", "--overwrite"], tmp_path, env)
    worker_env = {**env, "PREFECT_WORKER_QUERY_SECONDS": "1"}
    worker_env.pop("PIDC_PROJECT", None)  # the worker knows nothing of the project
    worker, worker_log = _start_worker(pool, tmp_path, worker_env)
    parameters = {
        "folder": str(world["inside"].parent),
        "sources": [str(world["clear"]), str(world["cloudy"])],
        **WATCH_SETTINGS,
    }
    try:
        _prefect(["deploy", "--name", WATCH_DEPLOYMENT, "--no-prompt"], project, {**env, "PIDC_PROJECT": str(project)})
        with httpx.Client(base_url=prefect_server, timeout=30) as api:
            found = api.post("/deployments/filter", json={"deployments": {"name": {"any_": [WATCH_DEPLOYMENT]}}})
            (deployed,) = found.raise_for_status().json()
            assert deployed["entrypoint"] == spec["entrypoint"] and deployed["work_pool_name"] == pool
            assert deployed["parameters"] == spec["parameters"]
            (schedule,) = deployed["schedules"]
            assert schedule["schedule"]["interval"] == 600 and schedule["active"]
            # paused, so that no scheduled run (of the template's folder) comes between the runs triggered here
            api.patch(f"/deployments/{deployed['id']}/schedules/{schedule['id']}", json={"active": False})
            pending = api.post(
                "/flow_runs/filter",
                json={
                    "deployments": {"id": {"any_": [deployed["id"]]}},
                    "flow_runs": {"state": {"type": {"any_": ["SCHEDULED"]}}},
                },
            ).raise_for_status()
            for run in pending.json():
                api.delete(f"/flow_runs/{run['id']}").raise_for_status()

            def trigger() -> str:
                args = ["deployment", "run", f"watch/{WATCH_DEPLOYMENT}", "--params", json.dumps(parameters)]
                out = _prefect(args, project, env)
                found = re.search(r"UUID: ([0-9a-f-]{36})", out)
                assert found, out
                return found.group(1)

            first_id = trigger()
            first = _wait_until_final(api, first_id, worker_log, "FAILED")
            second_id = trigger()
            second = _wait_until_final(api, second_id, worker_log, "COMPLETED")
            _wait_for_flow_run_processes(worker)
            # the flow's last line: "<n> drive(s) watched, <m> skipped; …"
            first_logs, second_logs = (_flow_run_logs(api, i, "drive(s) watched") for i in (first_id, second_id))
    finally:
        _stop(worker)

    # the first run: FAILED, naming the fog drive, its first alarm (at the earliest the rule can fire: the end of its
    # 5th window, every window flagged) and its cause; not the drive that stayed inside
    length, stride, k = WATCH_SETTINGS["window"], WATCH_SETTINGS["stride"], WATCH_SETTINGS["consecutive"]
    fired = (length - 1 + (k - 1) * stride) / 10.0
    message = first["state"]["message"]
    assert (
        "DrivesLeftOdd" in message
        and f"1 of 2 drives left the ODD of the sources: fog at {fired:.1f} s (fog_density" in message
    ), message
    assert "inside" not in message, message
    assert "inside: 200 frames, 0 alarms" in first_logs and "fog: 200 frames, 1 alarm(s): LEFT THE ODD" in first_logs

    params = load_params(project / "params.yaml")
    client = mlflow.MlflowClient(tracking_uri=f"sqlite:///{project / 'mlflow.db'}")
    version = str(client.get_model_version_by_alias(params.export.registered_model, "champion").version)
    out = project / "reports" / "watch"
    for name, outside in (("inside", False), ("fog", True)):
        summary = json.loads((out / name / "summary.json").read_text())
        assert summary["drive"]["frames"] == 200 and summary["model"] == "cues-2000"
        assert summary["watched"]["model"] == {
            "uri": "models:/pidc@champion",
            "name": params.export.registered_model,
            "version": version,
            "id": "cues-2000",
        }
        assert summary["watched"]["prefect_flow_run"] == first_id
        assert {k: summary["settings"][k] for k in WATCH_SETTINGS} == WATCH_SETTINGS
        assert (out / name / "timeline.png").stat().st_size > 10_000
        assert len((out / name / "frames.csv").read_text().splitlines()) == 201
        if outside:
            assert summary["first_alarm_s"] == pytest.approx(fired) and len(summary["alarms"]) == 1
            assert summary["alarms"][0]["cause"][0] == "fog_density"
            assert summary["truth"]["exit_s"] == 0.0 and summary["truth"]["exit_parameters"] == ["fog_density"]
        else:
            assert summary["alarms"] == [] and summary["truth"]["exit_s"] is None
    assert "fog: watched already" in second_logs and "inside: watched already" in second_logs
    assert "0 drive(s) watched, 2 skipped" in second_logs

    # one MLflow run per drive, all of the first flow run: the second logged none
    experiment = client.get_experiment_by_name("pidc-watch")
    runs = {r.info.run_name: r for r in client.search_runs([experiment.experiment_id])}
    assert sorted(runs) == ["fog", "inside"]
    for name, run in runs.items():
        outside = name == "fog"
        tags, metrics = run.data.tags, run.data.metrics
        assert tags["pidc.drive"] == name and tags["pidc.prefect_flow_run"] == first_id
        assert tags["pidc.outside"] == str(outside).lower() and tags["pidc.registered_version"] == version
        assert run.info.status == ("FAILED" if outside else "FINISHED")
        assert run.data.params["model_version"] == version and run.data.params["sources"] == "clear, cloudy"
        assert run.data.params["settings.consecutive"] == str(k)
        assert metrics["alarms"] == (1 if outside else 0) and metrics["frames"] == 200
        assert metrics["realtime_factor"] > 0
        assert ("first_alarm_s" in metrics) == outside
        assert {a.path for a in client.list_artifacts(run.info.run_id)} == {"summary.json", "timeline.png"}
        logged = json.loads(Path(client.download_artifacts(run.info.run_id, "summary.json", str(tmp_path))).read_text())
        assert logged == json.loads((out / name / "summary.json").read_text())
        assert logged["watched"]["mlflow_run"] == run.info.run_id
    assert second["state"]["type"] == "COMPLETED"
    assert _dvc_status(project) == "Data and pipelines are up to date."
