"""What a Prefect task run costs: the same work in one task per item or in batches of items (``data.shards_per_task``).

The ``generate`` and ``features`` stages fan out over the dataset's shards (108 in the default profile). Each Prefect
task run is bookkept on the API (a task run and its states) and shipped to a worker process; this measures that cost
with the stages' own runner (``flows.stage.task_runner``: a process pool of ``--workers``) and helpers
(``flows.stage.batches``, ``wait_with_progress``): ``--items`` items of ``--work-ms`` milliseconds of CPU each
(a busy loop), one task per item against ``--batch`` items per task, alternated ``--repeats`` times.

    .venv/bin/python benchmarks/bench_tasks.py --items 108 --work-ms 0 --batch 1 4

Talks to the Prefect server of ``PREFECT_API_URL`` (``bash run.sh`` starts one) or, without it, a temporary one.
Prints a table and one JSON line (``{"benchmark": "tasks", ...}``) with machine information.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from machine import machine_info  # benchmarks/machine.py (the script's folder is on sys.path)  # noqa: E402
from prefect import flow, task  # noqa: E402

from components.core.config import RunnerConfig  # noqa: E402
from flows.stage import batches, share_api_with_workers, task_runner, wait_with_progress  # noqa: E402


def busy(ms: float) -> None:
    """Spin the CPU for ``ms`` milliseconds (process time)."""
    end = time.process_time() + ms / 1000.0
    while time.process_time() < end:
        pass


@task(name="bench-items")
def items_task(items: list[int], work_ms: float) -> list[int]:
    for _ in items:
        busy(work_ms)
    return items


@flow(name="bench-tasks")
def fan_out(n: int, per_task: int, work_ms: float) -> float:
    """Seconds to run ``n`` items in tasks of ``per_task`` items (submission to the last result)."""
    share_api_with_workers()
    t0 = time.perf_counter()
    futures = [items_task.submit(b, work_ms) for b in batches(list(range(n)), per_task)]
    done = wait_with_progress(futures, desc=f"{per_task} per task", total=n, unit="item", per_item=True)
    if sorted(done) != list(range(n)):
        raise RuntimeError("items lost or repeated")
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--items", type=int, default=108, help="items (shards) to process")
    p.add_argument("--work-ms", type=float, default=0.0, help="CPU milliseconds of work per item")
    p.add_argument("--batch", type=int, nargs="+", default=[1, 4], help="items per task, each compared")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args(argv)
    if a.items < 1 or a.workers < 1 or a.repeats < 1 or a.work_ms < 0 or min(a.batch) < 1:
        p.error("--items, --workers, --repeats and every --batch must be >= 1, --work-ms >= 0")

    def run_all() -> dict[int, list[float]]:
        runner = task_runner(RunnerConfig(kind="processes", workers=a.workers, dask_address=None))
        seconds: dict[int, list[float]] = {b: [] for b in a.batch}
        for _ in range(a.repeats):  # alternated: a drifting load affects every batch size alike
            for b in a.batch:
                seconds[b].append(fan_out.with_options(task_runner=runner)(a.items, b, a.work_ms))
        return seconds

    if os.environ.get("PREFECT_API_URL"):
        seconds = run_all()
    else:
        from prefect.testing.utilities import prefect_test_harness

        with prefect_test_harness(server_startup_timeout=120):
            seconds = run_all()
    ideal = a.items * a.work_ms / 1000.0 / a.workers
    base = statistics.median(seconds[a.batch[0]])
    print(
        f"| items per task | tasks | median s | ratio to {a.batch[0]} per task | cost per task run, pool start included (s) |"
    )
    print("|---|---|---|---|---|")
    rows = []
    for b in a.batch:
        med = statistics.median(seconds[b])
        tasks = -(-a.items // b)
        rows.append({"per_task": b, "tasks": tasks, "seconds": seconds[b], "median": med})
        print(f"| {b} | {tasks} | {med:.1f} | {med / base:.2f} | {(med - ideal) * a.workers / tasks:.3f} |")
    print(
        json.dumps(
            {
                "benchmark": "tasks",
                "items": a.items,
                "work_ms": a.work_ms,
                "workers": a.workers,
                "rows": rows,
                **machine_info(),
            }
        )
    )


if __name__ == "__main__":
    main()
