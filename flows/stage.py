"""What every stage's flow does first, and the task runners of the fan-out stages.

:func:`parse_stage_args` reads a stage's command line (``--params`` plus the stage's own arguments) and validates the
params file before any work starts: a bad or incomplete params file ends the command with exit code 2 and one line
naming ``file: dotted.key`` (what ``dvc repro`` shows). :func:`open_stage` is the first line of a flow body: the
params, the project's folders and the run logger.
"""

from __future__ import annotations

import argparse
import logging
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from prefect import get_run_logger
from prefect.futures import PrefectFuture, as_completed
from prefect.task_runners import ProcessPoolTaskRunner, TaskRunner, ThreadPoolTaskRunner
from tqdm.auto import tqdm

from components.core.config import PROJECT_ROOT, ConfigError, Params, RunnerConfig, load_params
from components.core.paths import ProjectPaths

__all__ = [
    "Stage",
    "open_stage",
    "parse_stage_args",
    "use_all_cores",
    "task_runner",
    "share_api_with_workers",
    "wait_with_progress",
    "at_most",
    "batches",
]


@dataclass(frozen=True)
class Stage:
    """A running stage: its validated params, the params file, the project's folders and the run logger."""

    params: Params
    params_file: Path
    paths: ProjectPaths
    logger: logging.Logger | logging.LoggerAdapter


def open_stage(params_path: str | Path) -> Stage:
    """Load the params file (``ConfigError`` naming the key when it is bad) inside a flow run."""
    params_file = Path(params_path)
    params = load_params(params_file)
    return Stage(params, params_file, ProjectPaths.of(params, params_file), get_run_logger())


def parse_stage_args(
    description: str, argv: Sequence[str] | None = None, arguments: Sequence[tuple[Sequence[str], dict[str, Any]]] = ()
) -> tuple[argparse.Namespace, Params]:
    """Parse ``--params PATH`` (default: the project's params.yaml) and the stage's ``arguments`` (``(flags, kwargs)``
    pairs for ``add_argument``), and validate the params file: exit 2 with one line naming the bad key otherwise."""
    parser = argparse.ArgumentParser(description=description)
    for flags, kwargs in arguments:
        parser.add_argument(*flags, **kwargs)
    parser.add_argument(
        "--params", type=Path, default=PROJECT_ROOT / "params.yaml", help="params file (default: params.yaml)"
    )
    args = parser.parse_args(argv)
    try:
        params = load_params(args.params)
    except ConfigError as e:
        parser.exit(2, f"{parser.prog}: {e.one_line()}\n")
    return args, params


def use_all_cores() -> None:
    """Let torch use every core (a stage that trains or exports runs alone)."""
    import torch

    torch.set_num_threads(max(1, os.cpu_count() or 1))


def exit_with_parent(poll_seconds: float = 0.5) -> None:
    """In a worker process of a stage's process pool: end it as soon as the process that started it is gone.

    A worker of Python's process pool does not watch its parent: a stage killed by a signal left its workers training
    or rendering on their own (the running task and the next queued one), racing a re-run over the same checkpoint
    and logging every epoch twice. A daemon thread compares ``os.getppid()`` with the parent at start-up (the flow's
    process, which spawned the worker) and calls ``os._exit`` when it changes (the orphan was handed to another
    process)."""
    import threading
    import time

    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_seconds)
        os._exit(70)

    threading.Thread(target=watch, name="pidc-exit-with-parent", daemon=True).start()


def task_runner(cfg: RunnerConfig) -> TaskRunner:
    """The Prefect task runner ``cfg`` names: threads, processes (each worker ends with the stage's process:
    :func:`exit_with_parent`), or Dask (prefect-dask)."""
    if cfg.kind == "threads":
        return ThreadPoolTaskRunner(max_workers=cfg.workers)
    if cfg.kind == "processes":
        return ProcessPoolTaskRunner(max_workers=cfg.workers, initializer=exit_with_parent)
    if cfg.kind == "dask":
        from prefect_dask import DaskTaskRunner

        if cfg.dask_address:  # an existing cluster: its workers must reach the same Prefect server (PREFECT_API_URL)
            return DaskTaskRunner(address=cfg.dask_address)
        # a local cluster of threads: the cluster starts before the flow body, so worker processes could not be
        # pointed at the flow's temporary Prefect server and would each start their own
        return DaskTaskRunner(cluster_kwargs={"n_workers": 1, "threads_per_worker": cfg.workers, "processes": False})
    raise ValueError(f"unknown task runner kind {cfg.kind!r}; known: threads, processes, dask")


def share_api_with_workers() -> str:
    """Point worker processes spawned from here at this flow's Prefect API.

    Without a configured server, Prefect starts a temporary one per process: each worker of a
    process pool (or a local Dask cluster) would start its own (seconds each). Exporting the
    running API's URL before the workers are spawned makes them report to the flow's server.
    Call it inside a flow, before submitting tasks. Returns the URL.
    """
    from prefect.client.orchestration import get_client

    if not os.environ.get("PREFECT_API_URL"):
        with get_client(sync_client=True) as client:
            os.environ["PREFECT_API_URL"] = str(client.api_url)
    return os.environ["PREFECT_API_URL"]


def wait_with_progress(
    futures: Iterable[PrefectFuture], desc: str, total: int | None = None, unit: str = "task", per_item: bool = False
) -> list:
    """Wait for ``futures`` showing a progress bar; results in completion order. Raises the first failure.

    ``per_item``: each future returns a list (one entry per item of its batch, :func:`batches`); the bar counts items
    (``total`` of them) and the results are the lists joined."""
    futures = list(futures)
    results = []
    with tqdm(total=total if total is not None else len(futures), desc=desc, unit=unit) as bar:
        for fut in as_completed(futures):
            out = fut.result()
            if per_item:
                results.extend(out)
                bar.update(len(out))
            else:
                results.append(out)
                bar.update(1)
    return results


def batches(items: Sequence[Any], size: int) -> list[list[Any]]:
    """``items`` in order, in lists of ``size`` (the last may be shorter): one Prefect task per list spares the
    per-task bookkeeping (a task run and its states on the API: 0.1–0.3 s of wall time each,
    docs/studies/fewer-larger-tasks.md)."""
    if size < 1:
        raise ValueError(f"batch size must be >= 1, got {size}")
    return [list(items[i : i + size]) for i in range(0, len(items), size)]


def at_most(workers: int, items: Sequence[str], submit: Callable[[str], PrefectFuture], desc: str) -> dict[str, Any]:
    """Run ``submit(item)`` for every item in order, at most ``workers`` in flight (whatever the flow's task runner: a
    deployment's default thread pool would otherwise start them all at once); results by item. Raises the first
    failure."""
    queue, pending, results = list(items), {}, {}
    with tqdm(total=len(queue), desc=desc, unit="task") as bar:
        while queue or pending:
            while queue and len(pending) < workers:
                item = queue.pop(0)
                pending[submit(item)] = item
            finished = next(as_completed(list(pending)))
            results[pending.pop(finished)] = finished.result()
            bar.update(1)
    return results
