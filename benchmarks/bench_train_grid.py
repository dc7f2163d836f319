"""The train stage's two schedules side by side: the models one after the other on every core, or ``workers`` at a
time with ``cores // workers`` torch threads each (``train.runner``).

Each run is the real stage command, ``python -m flows.train --params <tmp>/params.yaml``, on the pipeline's data and
feature caches (linked into a temporary project folder, so ``models/``, ``reports/`` and ``mlflow.db`` are the
temporary folder's and the pipeline's are not touched; run ``dvc repro features`` first). Every run starts from no
models (the checkpoints of a run would otherwise let the next one resume), and the two schedules alternate, A B A B,
so that a drift in the machine's speed hits both. The grid is ``params.yaml``'s backbones at ``--sizes``.

    python benchmarks/bench_train_grid.py [--sizes 5000] [--repeats 2] [--workers 2]

Prints each run's wall time, the medians and their ratio, and one JSON line with the machine's details.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.machine import machine_info  # noqa: E402
from components.core.config import PROJECT_ROOT, load_params  # noqa: E402


def project_copy(folder: Path, sizes: list[int], workers: int) -> Path:
    """A project folder whose params train ``sizes`` with ``workers`` workers, reading the pipeline's data and
    features through links; returns its params file."""
    params = load_params(PROJECT_ROOT / "params.yaml")
    for name in ("data", "features"):
        source = PROJECT_ROOT / name
        if not source.is_dir():
            raise SystemExit(f"{source} is missing: run `dvc repro features` first")
        (folder / name).symlink_to(source)
    for backbone in params.backbones.names:
        if not (PROJECT_ROOT / "features" / backbone / "manifest.json").is_file():
            raise SystemExit(f"no feature cache for {backbone!r}: run `dvc repro features@{backbone}` first")
    raw = yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())
    raw["train"]["sizes"] = sizes
    raw["train"]["variants"] = {}
    raw["train"]["runner"] = {"kind": "processes", "workers": workers, "dask_address": None}
    path = folder / "params.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    (folder / "profiles").symlink_to(PROJECT_ROOT / "profiles")
    return path


def run_stage(params: Path) -> float:
    """Wall seconds of one train stage from no models."""
    for name in ("models", "reports", "mlflow.db", "mlruns"):
        target = params.parent / name
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
    env = {**os.environ, "PYTHONPATH": str(PROJECT_ROOT)}
    env.pop("MLFLOW_TRACKING_URI", None)
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "flows.train", "--params", str(params)],
        cwd=PROJECT_ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    seconds = time.perf_counter() - start
    if done.returncode:
        raise SystemExit(f"the train stage failed ({params}):\n{done.stderr[-3000:]}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[5000], help="training sizes of the grid (5000)")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each schedule, alternating (2)")
    parser.add_argument("--workers", type=int, default=2, help="models at a time in the parallel schedule (2)")
    args = parser.parse_args()
    cores = os.cpu_count() or 1
    schedules = {
        f"one at a time, {cores} threads": 1,
        f"{args.workers} at a time, {max(1, cores // args.workers)} thread(s) each": args.workers,
    }
    with tempfile.TemporaryDirectory(prefix="pidc-bench-grid-") as tmp:
        files = {}
        for name, workers in schedules.items():
            folder = Path(tmp) / f"w{workers}"
            folder.mkdir()
            files[name] = project_copy(folder, args.sizes, workers)
        seconds: dict[str, list[float]] = {name: [] for name in schedules}
        for r in range(args.repeats):
            for name in schedules:
                seconds[name].append(run_stage(files[name]))
                print(f"run {r + 1}, {name}: {seconds[name][-1]:.1f} s", flush=True)
    medians = {name: statistics.median(v) for name, v in seconds.items()}
    sequential, parallel = (medians[n] for n in schedules)
    print()
    print("| schedule | wall seconds (median) | runs |")
    print("|---|---|---|")
    for name, v in seconds.items():
        print(f"| {name} | {medians[name]:.1f} | {', '.join(f'{s:.1f}' for s in v)} |")
    print(f"\nratio one-at-a-time / parallel: {sequential / parallel:.2f}")
    grid = load_params(PROJECT_ROOT / "params.yaml").backbones.names
    print(
        json.dumps(
            machine_info(
                benchmark="train_grid",
                backbones=list(grid),
                sizes=args.sizes,
                seconds=seconds,
                ratio=sequential / parallel,
            )
        )
    )


if __name__ == "__main__":
    main()
