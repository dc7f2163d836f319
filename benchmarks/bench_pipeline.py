"""The whole pipeline on 1 core and on 2: each stage's parallel efficiency, and the pipeline's own overhead.

The working tree's files (``git ls-files -co --exclude-standard``: tracked and untracked-not-ignored, so no data,
features, models, caches, MLflow or Prefect state) are copied once at the start, so that every run runs the same code
however the tree changes meanwhile. For each ``--cpus`` set (default ``0`` then ``0,1``) the script builds a fresh
scratch project from that copy — the scaled params.yaml, ``dvc.lock`` removed, ``.venv`` a link to this project's
(never installed into: the run stops unless ``scripts/setup.sh``'s stamp says it is set up for this tree), ``git
init`` and one commit — and runs it as ``bash run.sh`` would, all under ``taskset -c <cpus>``: one local Prefect
server (``PREFECT_HOME`` in the scratch project, a free port), then ``bash run.sh`` with ``PREFECT_API_URL`` pointing
at it (so it runs ``scripts/setup.sh`` and one ``dvc repro``). Every runner's ``workers: auto`` is the cores of the
affinity mask (``components/core/hardware.py``), so ``taskset -c 0`` runs every stage on 1 worker and ``taskset -c
0,1`` on 2.

What is timed (wall clock of this process; the flow runs' times are the Prefect server's, the same clock):

- the whole run: from starting the Prefect server to ``run.sh``'s exit, split into the server's start (until
  ``/api/health`` answers), ``scripts/setup.sh`` (until its last line, the versions), DVC's start (until its first
  ``Running stage``) and the stages;
- each DVC stage: from DVC's ``Running stage '<stage>':`` line to the next one (the last stage: to ``run.sh``'s
  exit). One ``dvc repro`` as ``run.sh`` runs it, its output read line by line as it comes; a stage's time so
  includes its process start, its flow run, DVC hashing and caching its outputs and writing ``dvc.lock``;
- each stage's flow run: queried from the Prefect server after the run (``POST /api/flow_runs/filter``): its
  ``end_time − start_time`` (the time in the Running state); a flow run belongs to the stage during which it started.

Definitions printed with the figures:

- parallel efficiency of a stage on k cores = T1 / (k · Tk), T1 and Tk its wall times on 1 and on k cores (1: the
  k cores are all used, 1/k: no gain); the flow-run efficiency is the same of the flow runs' times alone;
- flow-run share of a stage = its flow runs' time / its wall time (the rest: its process start and DVC's work);
- overhead = whole wall − Σ flow-run times: set-up, the Prefect server's start, DVC's own work, every stage's Python
  start and imports before its flow run starts and after it ends; its share = overhead / whole wall.

``--scale`` shrinks the run by scaling every setting that counts the data's images (the others are params.yaml's):
``data.splits``, ``data.shard_size`` (the same number of shards and Prefect tasks per split), ``train.sizes`` and the
variants' sizes, and the training settings measured in images or samples — ``train.scale_to``,
``train.sample_budget``, ``train.embedding_sample_budget``, ``train.input_noise_max_size``,
``train.ensemble_min_size`` — so that every model trains the same epochs, widths, noise and ensemble as at full scale
on ``scale`` × its images; and the counts of split images that evaluate and Task III read
(``evaluate.images``, ``evaluate.named.local_test.calibration_images`` and ``.test_images``,
``task3.bags.*.max_images``). Each is rounded half up, at least 1. Not scaled: ``train.compile_min_steps`` (a model
compiles when its training is long enough to pay the compile, as the pipeline decides at that size) and the work that
does not depend on the data's size (Task II's bag, the draws, the named weathers, Task III's targets).
``--set KEY=VALUE`` (a YAML value) overrides any setting after the scaling. The result is validated as the stages do
(``components.core.config``), and a bad one is one line naming the key.

    python benchmarks/bench_pipeline.py [--scale 0.2] [--cpus 0 0,1] [--set KEY=VALUE ...] [--out DIR] [--keep]

Each finished run is kept in ``--out`` (``benchmarks/results/pipeline/<key>/``, the key a hash of the scaled params
and of the pipeline's files: components, flows, profiles, scripts, dvc.yaml …): a second call with the same settings
on the same code reuses the runs it finished (``--force`` reruns them) and reruns an interrupted one from nothing.
The timestamped output of each run is ``<key>/cpus-<ids>.log``; the copy of the tree (``<key>/tree``) and the
scratch projects are deleted after their runs unless ``--keep``. The torch compile cache (outside the project) is not
cleared. Run it on a quiet machine: other jobs change both the times and the efficiencies (torch with 2 threads
collapses beside another CPU job).

Prints the table (stage, seconds per cpu set, parallel efficiency, flow-run efficiency, flow-run share), the stages
below an efficiency of 0.85 with the first-order reason (the flow itself, or what runs around it), each run's
overhead, and one JSON line with every figure and the machine's details.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# isort: off
import components  # noqa: E402,F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse  # noqa: E402
import copy  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import signal  # noqa: E402
import socket  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
import urllib.request  # noqa: E402
from collections.abc import Iterable, Sequence  # noqa: E402
from datetime import UTC, datetime  # noqa: E402
from importlib import metadata  # noqa: E402

import yaml  # noqa: E402

from benchmarks.machine import machine_info  # noqa: E402
from components.core.config import ConfigError, load_params, parse_params  # noqa: E402
from components.core.hardware import STAGES, cgroup_cpu_quota, resolve_workers  # noqa: E402

DEFAULT_OUT = ROOT / "benchmarks" / "results" / "pipeline"

#: the settings that count the data's images, scaled by ``--scale`` (``*`` any key of that mapping)
SCALED = (
    "data.splits.train",
    "data.splits.val",
    "data.splits.test",
    "data.shard_size",
    "train.sizes",
    "train.variants.*.size",
    "train.scale_to",
    "train.sample_budget",
    "train.embedding_sample_budget",
    "train.input_noise_max_size",
    "train.ensemble_min_size",
    "evaluate.images",
    "evaluate.named.local_test.calibration_images",
    "evaluate.named.local_test.test_images",
    "task3.bags.*.max_images",
)

#: the efficiency below which a stage is named, and the reason sought (issue #58)
EFFICIENCY_FLOOR = 0.85

#: files of the working tree that do not change what the pipeline runs: left out of the results' key
_NOT_PIPELINE = re.compile(r"^(docs/|tests/|benchmarks/)|\.md$")

_RUNNING = re.compile(r"Running stage '([^']+)':")

#: run in a scratch project: its own config module validates its params.yaml (one line on stdout, exit 1 if bad)
_CHECK = (
    "from components.core.config import ConfigError, load_params\n"
    "try:\n    load_params('params.yaml')\n"
    "except ConfigError as e:\n    print(e.one_line()); raise SystemExit(1)"
)


# --- pure helpers (tests/test_bench_pipeline.py) -------------------------------------------------------------------


def parse_cpus(text: str) -> tuple[int, ...]:
    """CPU ids as ``taskset -c`` takes them (``0``, ``0,1``, ``0-3,6``), sorted, each once.

    Raises:
        ValueError: for anything else, naming the text.
    """
    ids: set[int] = set()
    for part in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if not m:
            raise ValueError(f"--cpus {text!r}: expected CPU ids such as 0 or 0,1 or 0-3")
        low, high = int(m[1]), int(m[2] if m[2] is not None else m[1])
        if high < low:
            raise ValueError(f"--cpus {text!r}: the range {low}-{high} is empty")
        ids.update(range(low, high + 1))
    return tuple(sorted(ids))


def check_cpus(sets: Sequence[tuple[int, ...]], allowed: Iterable[int]) -> None:
    """Every set's CPUs are among ``allowed`` (this process's affinity mask), and no set comes twice.

    Raises:
        ValueError: naming the first unknown CPU ids or the repeated set.
    """
    allowed = set(allowed)
    for cpus in sets:
        unknown = sorted(set(cpus) - allowed)
        if unknown:
            raise ValueError(
                f"--cpus {cpu_text(cpus)}: CPU {', '.join(map(str, unknown))} not in this process's affinity "
                f"(os.sched_getaffinity(0) = {cpu_text(sorted(allowed))})"
            )
    seen = [cpu_text(c) for c in sets]
    repeated = sorted({s for s in seen if seen.count(s) > 1})
    if repeated:
        raise ValueError(f"--cpus: {', '.join(repeated)} given more than once")


def cpu_text(cpus: Iterable[int]) -> str:
    """``taskset -c``'s form of a CPU set: ``0,1``."""
    return ",".join(str(c) for c in cpus)


def scaled_count(n: int, scale: float) -> int:
    """``n · scale`` rounded half up, at least 1."""
    return max(1, math.floor(n * scale + 0.5))


def scale_params(raw: dict, scale: float) -> dict:
    """A copy of the params mapping ``raw`` with every setting of :data:`SCALED` multiplied by ``scale`` (counts:
    :func:`scaled_count`; ``all`` stays ``all``).

    Raises:
        ValueError: when ``scale`` is not positive, a scaled key is missing, or two training sizes become one (the
            grid's shape would be lost).
    """
    if not (isinstance(scale, int | float) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"--scale must be a positive number, got {scale!r}")
    out = copy.deepcopy(raw)
    for key in SCALED:
        for path in _expand(out, key.split(".")):
            parent, name = _parent(out, path, key)
            value = parent[name]
            if isinstance(value, list):
                parent[name] = [scaled_count(v, scale) for v in value]
            elif value != "all":
                parent[name] = scaled_count(value, scale)
    sizes, new = raw["train"]["sizes"], out["train"]["sizes"]
    if len(set(new)) < len(new):
        raise ValueError(
            f"--scale {scale:g} makes train.sizes {list(sizes)} into {new}: two models of one size (the grid's shape "
            "is lost); use a larger scale"
        )
    return out


def _expand(raw: dict, parts: list[str], done: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """The concrete key paths of a dotted pattern whose ``*`` stands for every key of a mapping."""
    if not parts:
        return [done]
    head, rest = parts[0], parts[1:]
    if head != "*":
        return _expand(raw, rest, (*done, head))
    node: object = raw
    for p in done:
        node = node.get(p, {}) if isinstance(node, dict) else {}
    keys = list(node) if isinstance(node, dict) else []
    return [path for k in keys for path in _expand(raw, rest, (*done, k))]


def _parent(raw: dict, path: tuple[str, ...], key: str) -> tuple[dict, str]:
    node = raw
    for p in path[:-1]:
        if not isinstance(node, dict) or p not in node:
            raise ValueError(f"params.yaml: {key}: missing key (the benchmark scales it)")
        node = node[p]
    if not isinstance(node, dict) or path[-1] not in node:
        raise ValueError(f"params.yaml: {key}: missing key (the benchmark scales it)")
    return node, path[-1]


def apply_settings(raw: dict, settings: Sequence[str]) -> dict:
    """A copy of ``raw`` with each ``KEY=VALUE`` (a dotted key of an existing setting, a YAML value) set.

    Raises:
        ValueError: for a setting without ``=``, an unknown key or a value that is not YAML.
    """
    out = copy.deepcopy(raw)
    for setting in settings:
        key, eq, text = setting.partition("=")
        if not eq or not key.strip():
            raise ValueError(f"--set {setting!r}: expected KEY=VALUE, e.g. train.epochs=2")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ValueError(f"--set {key}: the value is not YAML ({str(e).splitlines()[0]})") from None
        parts = key.strip().split(".")
        try:
            parent, name = _parent(out, tuple(parts), key)
        except ValueError:
            raise ValueError(f"--set {key}: unknown key (not a setting of params.yaml)") from None
        parent[name] = value
    return out


def efficiency(t1: float, tk: float, k: int) -> float:
    """Parallel efficiency T1 / (k · Tk) of a job taking ``t1`` seconds on 1 core and ``tk`` on ``k`` cores."""
    return t1 / (k * tk)


def overhead(wall: float, flow_seconds: Iterable[float]) -> tuple[float, float]:
    """The pipeline's overhead in seconds, wall − Σ flow-run seconds, and its share of the wall."""
    seconds = wall - sum(flow_seconds)
    return seconds, seconds / wall


def stage_windows(events: Sequence[tuple[float, str]], end: float) -> list[tuple[str, float, float]]:
    """Each stage's (name, start, end) from DVC's ``Running stage`` lines (time, stage) in order: a stage ends where
    the next starts, the last one at ``end``."""
    starts = [t for t, _ in events]
    return [(name, t, (starts[i + 1] if i + 1 < len(starts) else end)) for i, (t, name) in enumerate(events)]


def assign_flow_runs(windows: Sequence[tuple[str, float, float]], runs: Sequence[dict]) -> dict[str, list[dict]]:
    """The flow runs (``start``, ``end`` in seconds) of each stage window: those that started in it.

    Raises:
        ValueError: for a flow run that started outside every window or has not ended.
    """
    out: dict[str, list[dict]] = {name: [] for name, _, _ in windows}
    for run in runs:
        if run.get("end") is None:
            raise ValueError(f"flow run {run.get('name')!r} ({run.get('flow')}) has not ended: {run.get('state')}")
        stage = next((name for name, a, b in windows if a <= run["start"] < b), None)
        if stage is None:
            raise ValueError(f"flow run {run.get('name')!r} ({run.get('flow')}) started outside every stage")
        out[stage].append(run)
    return out


# --- the run -------------------------------------------------------------------------------------------------------


def scaled_params(source: Path, scale: float, settings: Sequence[str]) -> str:
    """``source`` resolved (its profile's overrides merged, then ``profile: default``), scaled and ``settings``
    applied, validated: the YAML text of the scratch projects' params.yaml."""
    raw = load_params(source).model_dump(mode="json")
    raw["profile"] = "default"
    raw = apply_settings(scale_params(raw, scale), settings)
    parse_params(raw, source=f"{source.name} × {scale:g}{' with --set' if settings else ''}")
    header = f"# {source.name} scaled by {scale:g} (benchmarks/bench_pipeline.py)" + "".join(
        f"\n# --set {s}" for s in settings
    )
    return header + "\n" + yaml.safe_dump(raw, sort_keys=False, allow_unicode=True)


def check_workers(params_text: str, cores: int, cpus: tuple[int, ...]) -> None:
    """Every runner's ``workers`` can be had on ``cores`` cores (a fixed number above it would end the stage)."""
    params = parse_params(yaml.safe_load(params_text))
    for _, key, _, _ in STAGES:
        section, name = key.split(".")
        runner = getattr(getattr(params, section), name)
        if runner.kind == "dask" and runner.dask_address:
            continue
        try:
            resolve_workers(runner.workers, cores, f"{key}.workers")
        except ValueError as e:
            raise ValueError(f"--cpus {cpu_text(cpus)}: {e}") from None


def tree_files() -> list[str]:
    """The working tree's tracked and untracked-not-ignored files that exist (relative paths)."""
    out = subprocess.run(
        ["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, capture_output=True, check=True
    ).stdout
    names = sorted({n for n in out.decode().split("\0") if n})
    return [n for n in names if (ROOT / n).is_file() or (ROOT / n).is_symlink()]


def copy_files(source: Path, files: Sequence[str], folder: Path) -> list[str]:
    """``files`` of ``source`` copied into a new ``folder``; returns those copied (one deleted meanwhile is not). Its
    ``.dvc/`` is made first: DVC treats a folder holding one as a separate repository, so this project's own ``dvc``
    never takes the copy's dvc.yaml for its stages."""
    if folder.exists():
        shutil.rmtree(folder)
    (folder / ".dvc").mkdir(parents=True)
    copied = []
    for name in files:
        target = folder / name
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            shutil.copy2(source / name, target, follow_symlinks=False)
        except FileNotFoundError:
            continue
        copied.append(name)
    return copied


def results_key(tree: Path, files: Sequence[str], params_text: str) -> str:
    """A hash of the scaled params and of the files that make the pipeline (not docs, tests, benchmarks, *.md)."""
    h = hashlib.sha256(params_text.encode())
    for name in files:
        if _NOT_PIPELINE.search(name) or name in ("params.yaml", "dvc.lock"):
            continue
        h.update(name.encode() + b"\0")
        h.update(os.readlink(tree / name).encode() if (tree / name).is_symlink() else (tree / name).read_bytes())
    return h.hexdigest()[:12]


def make_scratch(folder: Path, tree: Path, files: Sequence[str], params_text: str) -> None:
    """A fresh scratch project in ``folder``: the snapshot's files, the scaled params (validated by the snapshot's own
    code, which the stages run), no dvc.lock, .venv linked, one git commit."""
    copy_files(tree, files, folder)
    (folder / "params.yaml").write_text(params_text, encoding="utf-8")
    check = subprocess.run(
        [str(ROOT / ".venv" / "bin" / "python"), "-c", _CHECK], cwd=folder, env=run_env(folder, None), text=True,
        capture_output=True,
    )  # fmt: skip
    if check.returncode:
        raise SystemExit(f"bench_pipeline: the scratch project's params do not validate: {check.stdout.strip()}")
    (folder / "dvc.lock").unlink(missing_ok=True)
    (folder / ".venv").symlink_to(ROOT / ".venv")
    git = ["git", "-c", "user.name=bench_pipeline", "-c", "user.email=bench@localhost", "-c", "commit.gpgsign=false"]
    for cmd in (["init", "-q"], ["add", "-A"], ["commit", "-q", "-m", "bench_pipeline scratch"]):
        subprocess.run(git + cmd, cwd=folder, check=True, capture_output=True)


def check_setup_stamp(folder: Path) -> None:
    """``scripts/setup.sh`` would only check, not install: its stamp in .venv matches this tree."""
    stamp = hashlib.sha256(
        b"".join((folder / n).read_bytes() for n in ("pyproject.toml", "constraints.txt", "scripts/setup.sh"))
    ).hexdigest()
    found = folder / ".venv" / ".pidc-setup"
    if not found.is_file() or found.read_text().strip() != stamp:
        raise SystemExit(
            "bench_pipeline: .venv is not set up for this tree's pyproject.toml, constraints.txt and scripts/setup.sh "
            "(its stamp differs): run `bash scripts/setup.sh` first; the benchmark never installs into .venv"
        )


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_env(folder: Path, url: str | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "MLFLOW_TRACKING_URI", "VIRTUAL_ENV")}
    env.pop("PREFECT_API_URL", None)
    env.update(PREFECT_HOME=str(folder / ".prefect"), PREFECT_SERVER_ANALYTICS_ENABLED="false", DO_NOT_TRACK="1")
    if url:
        env["PREFECT_API_URL"] = url
    return env


def start_server(folder: Path, cpus: tuple[int, ...]) -> tuple[subprocess.Popen, str]:
    """The Prefect server as run.sh starts it, under ``taskset``; returns it and its API URL once healthy."""
    port = free_port()
    home = folder / ".prefect"
    home.mkdir(parents=True, exist_ok=True)
    log = open(home / "server.log", "wb")  # closed below: the server keeps its own handle
    server = subprocess.Popen(
        ["taskset", "-c", cpu_text(cpus), str(folder / ".venv" / "bin" / "prefect")]
        + ["server", "start", "--host", "127.0.0.1", "--port", str(port)],
        cwd=folder,
        env=run_env(folder, None),
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    log.close()
    url = f"http://127.0.0.1:{port}/api"
    deadline = time.monotonic() + 180
    while True:
        try:
            urllib.request.urlopen(f"{url}/health", timeout=2)
            return server, url
        except OSError:
            if server.poll() is not None or time.monotonic() > deadline:
                stop(server)
                raise SystemExit(
                    f"bench_pipeline: the Prefect server did not start; see {home / 'server.log'}"
                ) from None
            time.sleep(0.25)


def stop(proc: subprocess.Popen | None) -> None:
    """End a process this script started and its process group (its own session: the stages and their workers),
    SIGTERM first, SIGKILL to whatever is left after 30 s (a flow run may outlive its parent on SIGTERM)."""
    if proc is None:
        return
    deadline = time.monotonic() + 30
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        while time.monotonic() < deadline:
            time.sleep(0.5)
            proc.poll()
            os.killpg(proc.pid, 0)  # ProcessLookupError once the group is empty
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def _post(url: str, body: dict) -> list[dict]:
    request = urllib.request.Request(
        url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"}, method="POST"
    )
    with urllib.request.urlopen(request, timeout=30) as response:
        return json.loads(response.read())


def _seconds(stamp: str | None) -> float | None:
    return None if stamp is None else datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


def flow_runs(url: str) -> list[dict]:
    """Every top-level flow run of the server: name, flow, state, start and end (epoch seconds), total_run_time."""
    runs, offset = [], 0
    while True:
        page = _post(f"{url}/flow_runs/filter", {"sort": "START_TIME_ASC", "limit": 200, "offset": offset})
        runs += page
        offset += len(page)
        if len(page) < 200:
            break
    flows = {f["id"]: f["name"] for f in _post(f"{url}/flows/filter", {"limit": 200})}
    return [
        {
            "name": r["name"],
            "flow": flows.get(r["flow_id"], r["flow_id"]),
            "state": r.get("state_type"),
            "start": _seconds(r.get("start_time")),
            "end": _seconds(r.get("end_time")),
            "seconds": (_seconds(r["end_time"]) - _seconds(r["start_time"])) if r.get("end_time") else None,
            "total_run_time": r.get("total_run_time"),
        }
        for r in runs
        if r.get("parent_task_run_id") is None and r.get("start_time")
    ]


def run_pipeline(folder: Path, cpus: tuple[int, ...], log_path: Path) -> dict:
    """``bash run.sh`` of the scratch project under ``taskset -c cpus`` with its own Prefect server: the timings."""
    server = pipeline = None
    load = os.getloadavg()[0]
    t0 = time.time()
    try:
        server, url = start_server(folder, cpus)
        t_server = time.time()
        pipeline = subprocess.Popen(
            ["taskset", "-c", cpu_text(cpus), "bash", "run.sh"],
            cwd=folder,
            env=run_env(folder, url),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        setup_end, events, tail = None, [], []
        with open(log_path, "w", encoding="utf-8", buffering=1) as log:
            log.write(f"# {datetime.now(UTC).isoformat()} taskset -c {cpu_text(cpus)} bash run.sh in {folder}\n")
            for raw in pipeline.stdout:
                t = time.time()
                line = raw.decode(errors="replace").rstrip("\n")
                log.write(f"{t - t0:9.2f} {line}\n")
                tail = (tail + [line])[-60:]
                m = _RUNNING.search(line)
                if m:
                    events.append((t, m[1]))
                    print(f"  {t - t0:8.1f} s  {m[1]}", flush=True)
                elif setup_end is None and not events and line.startswith("pidc "):
                    setup_end = t
        code = pipeline.wait()
        t_end = time.time()
        if code:
            raise SystemExit(
                f"bench_pipeline: `bash run.sh` failed (exit {code}) on --cpus {cpu_text(cpus)}; its log: {log_path}\n"
                + "\n".join(tail[-25:])
            )
        runs = flow_runs(url)
    finally:
        stop(pipeline)
        stop(server)
    return timings(cpus, t0, t_server, setup_end, events, t_end, runs, log_path) | {
        "load_avg_1min_before": load,
        "load_avg_1min_after": os.getloadavg()[0],
    }


def timings(
    cpus: tuple[int, ...],
    t0: float,
    t_server: float,
    setup_end: float | None,
    events: list[tuple[float, str]],
    t_end: float,
    runs: list[dict],
    log_path: Path,
) -> dict:
    """The run's record: the phases, each stage's seconds and flow runs, the overhead."""
    if not events:
        raise SystemExit(f"bench_pipeline: DVC ran no stage (was everything up to date?); see {log_path}")
    windows = stage_windows(events, t_end)
    per_stage = assign_flow_runs(windows, runs)
    setup_end = setup_end if setup_end is not None else events[0][0]
    wall = t_end - t0
    flow_total = [r["seconds"] for rs in per_stage.values() for r in rs]
    over, share = overhead(wall, flow_total)
    return {
        "cpus": list(cpus),
        "workers": workers_for(cpus),
        "started": datetime.fromtimestamp(t0, UTC).isoformat(timespec="seconds"),
        "wall_s": wall,
        "server_s": t_server - t0,
        "setup_s": setup_end - t_server,
        "dvc_start_s": events[0][0] - setup_end,
        "stages": [
            {
                "stage": name,
                "seconds": b - a,
                "flow_seconds": sum(r["seconds"] for r in per_stage[name]),
                "flow_runs": [
                    {k: r[k] for k in ("name", "flow", "seconds", "total_run_time")} for r in per_stage[name]
                ],
            }
            for name, a, b in windows
        ],
        "flow_seconds": sum(flow_total),
        "overhead_s": over,
        "overhead_share": share,
        "log": str(log_path),
    }


def workers_for(cpus: tuple[int, ...]) -> int:
    """What ``workers: auto`` resolves to under ``taskset -c cpus``: the set's size, capped by a cgroup quota."""
    quota = cgroup_cpu_quota()
    return max(1, min(len(cpus), math.floor(quota))) if quota is not None else len(cpus)


# --- the report ----------------------------------------------------------------------------------------------------


def _label(run: dict, runs: Sequence[dict]) -> str:
    k = run["workers"]
    same = sum(r["workers"] == k for r in runs) > 1
    return f"{k} core{'s' if k != 1 else ''}" + (f" [{cpu_text(run['cpus'])}]" if same else "")


def rows_of(run: dict) -> dict[str, tuple[float, float | None]]:
    """Row name → (wall seconds, flow-run seconds or None) of one run, the phases before the stages first."""
    rows: dict[str, tuple[float, float | None]] = {
        "Prefect server start": (run["server_s"], None),
        "scripts/setup.sh": (run["setup_s"], None),
        "DVC start": (run["dvc_start_s"], None),
    }
    for s in run["stages"]:
        rows[s["stage"]] = (s["seconds"], s["flow_seconds"])
    rows["whole run"] = (run["wall_s"], run["flow_seconds"])
    return rows


def report(runs: Sequence[dict]) -> tuple[list[str], dict]:
    """The markdown table and the notes, and the efficiencies by row (against the first 1-core run)."""
    base = next((r for r in runs if r["workers"] == 1), None)
    multi = [r for r in runs if r["workers"] > 1] if base else []
    tables = [rows_of(r) for r in runs]
    names = list(dict.fromkeys(n for t in tables for n in t))
    head = ["stage"] + [f"{_label(r, runs)} (s)" for r in runs]
    for r in multi:
        k = r["workers"]
        head += [f"parallel efficiency T1/({k}·T{k})", f"flow-run efficiency ({k} cores)"]
    head.append("flow-run share (" + " / ".join(_label(r, runs) for r in runs) + ")")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    eff: dict[str, dict[str, float]] = {}
    base_rows = rows_of(base) if base else {}
    for name in names:
        cells = [name] + [f"{t[name][0]:.1f}" if name in t else "—" for t in tables]
        for r in multi:
            rows, label = rows_of(r), cpu_text(r["cpus"])
            if name in rows and name in base_rows:
                e = efficiency(base_rows[name][0], rows[name][0], r["workers"])
                fb, fk = base_rows[name][1], rows[name][1]
                ef = efficiency(fb, fk, r["workers"]) if fb and fk else None
                eff.setdefault(name, {})[label] = e
                if ef is not None:
                    eff[name][f"{label} flow"] = ef
                cells += [f"**{e:.2f}**" if e < EFFICIENCY_FLOOR else f"{e:.2f}", "—" if ef is None else f"{ef:.2f}"]
            else:
                cells += ["—", "—"]
        shares = [f"{t[name][1] / t[name][0]:.0%}" if name in t and t[name][1] is not None else "—" for t in tables]
        lines.append("| " + " | ".join(cells + [" / ".join(shares)]) + " |")
    return lines + [""] + notes(runs, multi, eff), eff


def notes(runs: Sequence[dict], multi: Sequence[dict], eff: dict[str, dict[str, float]]) -> list[str]:
    """Each run's wall and overhead; the stages below the floor and the first-order reason."""
    out = []
    for r in runs:
        around = r["wall_s"] - r["server_s"] - r["setup_s"] - r["dvc_start_s"] - r["flow_seconds"]
        out.append(
            f"- {_label(r, runs)} (taskset -c {cpu_text(r['cpus'])}): whole run {r['wall_s']:.1f} s, flow runs "
            f"{r['flow_seconds']:.1f} s; overhead = wall − Σ flow runs = {r['overhead_s']:.1f} s = "
            f"**{r['overhead_share']:.1%}** of the wall (server start {r['server_s']:.1f} s, setup.sh "
            f"{r['setup_s']:.1f} s, DVC start {r['dvc_start_s']:.1f} s, around the flow runs {around:.1f} s)"
        )
    for r in multi:
        label = cpu_text(r["cpus"])
        for name, e in eff.items():
            if name in ("Prefect server start", "scripts/setup.sh", "DVC start") or e.get(label, 1) >= EFFICIENCY_FLOOR:
                continue
            ef = e.get(f"{label} flow")
            why = (
                "its flow run scales, what runs around it (process start, imports, DVC's hashing) does not"
                if ef is not None and ef >= EFFICIENCY_FLOOR
                else "inside its flow run (serial parts, uneven tasks, shared memory bandwidth): see the log"
            )
            flow = f", flow run {ef:.2f}" if ef is not None else ""
            out.append(f"- below {EFFICIENCY_FLOOR} on {r['workers']} cores: {name} {e[label]:.2f}{flow} — {why}")
    above = sorted({name for name, e in eff.items() for k, v in e.items() if not k.endswith("flow") and v > 1.1})
    if above:
        out.append(
            f"- efficiency above 1.1 ({', '.join(above)}): more than k× faster on k cores, so the machine's speed changed "
            "between the runs (another job, drift); the 1-minute load before and after each run is in the JSON line"
        )
    return out


# --- main ----------------------------------------------------------------------------------------------------------


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scale", type=float, default=0.2, help="the data's images × this (0.2)")
    parser.add_argument("--cpus", nargs="+", default=["0", "0,1"], help="CPU sets for taskset -c, in order (0 0,1)")
    parser.add_argument(
        "--set",
        dest="settings",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a setting after the scaling (YAML)",
    )
    parser.add_argument("--params", type=Path, default=None, help="the params to scale (the tree's params.yaml)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="results and scratch projects")
    parser.add_argument("--keep", action="store_true", help="keep the scratch projects after their runs")
    parser.add_argument("--force", action="store_true", help="rerun the runs already finished")
    return parser.parse_args(argv)


def prepare(args: argparse.Namespace) -> tuple[list[tuple[int, ...]], str, list[str], Path]:
    """Validate the input (one-line errors): the CPU sets, the scaled params. Snapshot the working tree once (every
    run builds its scratch project from the same files, even if the tree changes meanwhile) into the results folder,
    ``<out>/<key>/tree``; returns the CPU sets, the params text, the files and the results folder."""
    for tool in ("taskset", "git"):
        if shutil.which(tool) is None:
            raise SystemExit(f"bench_pipeline: `{tool}` is not on PATH")
    files = tree_files()
    snapshot = args.out / f".snapshot-{os.getpid()}"
    try:
        sets = [parse_cpus(c) for c in args.cpus]
        check_cpus(sets, os.sched_getaffinity(0))
        files = copy_files(ROOT, files, snapshot)
        params_text = scaled_params(args.params or snapshot / "params.yaml", args.scale, args.settings)
        for cpus in sets:
            check_workers(params_text, workers_for(cpus), cpus)
    except (ConfigError, ValueError) as e:
        shutil.rmtree(snapshot, ignore_errors=True)
        raise SystemExit(f"bench_pipeline: {e.one_line() if isinstance(e, ConfigError) else e}") from None
    folder = args.out / results_key(snapshot, files, params_text)
    folder.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(folder / "tree", ignore_errors=True)
    snapshot.rename(folder / "tree")
    (folder / "params.yaml").write_text(params_text, encoding="utf-8")
    return sets, params_text, files, folder


def main(argv: Sequence[str] | None = None) -> None:
    try:
        measure(parse_args(argv))
    except KeyboardInterrupt:
        raise SystemExit("bench_pipeline: interrupted; the runs finished before are kept") from None


def measure(args: argparse.Namespace) -> None:
    """Every run not finished before, then the report."""
    sets, params_text, files, folder = prepare(args)
    print(f"results: {folder} (scaled params: {folder / 'params.yaml'})", flush=True)
    runs = []
    for cpus in sets:
        tag = "cpus-" + "_".join(map(str, cpus))
        done = folder / f"{tag}.json"
        if done.is_file() and not args.force:
            print(f"taskset -c {cpu_text(cpus)}: finished earlier, reused ({done})", flush=True)
            runs.append(json.loads(done.read_text()))
            continue
        scratch = folder / f"scratch-{tag}"
        print(f"taskset -c {cpu_text(cpus)}: a fresh scratch project in {scratch}", flush=True)
        make_scratch(scratch, folder / "tree", files, params_text)
        check_setup_stamp(scratch)
        run = run_pipeline(scratch, cpus, folder / f"{tag}.log")
        done.write_text(json.dumps(run, indent=1))
        print(f"taskset -c {cpu_text(cpus)}: {run['wall_s']:.1f} s", flush=True)
        runs.append(run)
        if not args.keep:
            shutil.rmtree(scratch)
    if not args.keep:  # the copy of the tree, and a scratch project an interrupted run left
        for leftover in (folder / "tree", *folder.glob("scratch-*")):
            shutil.rmtree(leftover)
    lines, eff = report(runs)
    print()
    print(f"pipeline at scale {args.scale:g}" + "".join(f", --set {s}" for s in args.settings))
    print("\n".join(lines))
    print(json.dumps(machine_info(**record(args, folder, runs, eff))))


def record(args: argparse.Namespace, folder: Path, runs: Sequence[dict], eff: dict) -> dict:
    """Everything of the JSON line but the machine's details."""
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    dirty = subprocess.run(["git", "status", "--porcelain"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    versions = {}
    for package in ("torch", "numpy", "prefect", "dvc", "mlflow", "onnxruntime", "opencv-python-headless"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            pass
    return {
        "benchmark": "pipeline",
        "commit": head.stdout.strip() + ("+dirty" if dirty else ""),
        "scale": args.scale,
        "settings": args.settings,
        "results": str(folder),
        "versions": versions,
        "efficiency": eff,
        "runs": list(runs),
    }


if __name__ == "__main__":
    main()
