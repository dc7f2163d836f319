"""What every flow shares: the params file, the task runner and a progress bar over futures."""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

from prefect.futures import PrefectFuture, as_completed
from prefect.task_runners import ProcessPoolTaskRunner, TaskRunner, ThreadPoolTaskRunner
from tqdm.auto import tqdm

from components.core.config import PROJECT_ROOT, Params, RunnerConfig, load_params

__all__ = ["task_runner", "params_from_argv", "wait_with_progress", "share_api_with_workers", "PROJECT_ROOT"]


def task_runner(cfg: RunnerConfig) -> TaskRunner:
    """The Prefect task runner ``cfg`` names: threads, processes, or Dask (prefect-dask)."""
    if cfg.kind == "threads":
        return ThreadPoolTaskRunner(max_workers=cfg.workers)
    if cfg.kind == "processes":
        return ProcessPoolTaskRunner(max_workers=cfg.workers)
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


def params_from_argv(description: str, argv: Sequence[str] | None = None) -> tuple[Params, Path]:
    """Parse ``--params PATH`` (default: the project's params.yaml) and load it."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--params", type=Path, default=PROJECT_ROOT / "params.yaml", help="params file (default: params.yaml)")
    args = parser.parse_args(argv)
    return load_params(args.params), args.params


def wait_with_progress(futures: Iterable[PrefectFuture], desc: str, total: int | None = None) -> list:
    """Wait for ``futures`` showing a progress bar; results in completion order. Raises the first failure."""
    futures = list(futures)
    results = []
    with tqdm(total=total if total is not None else len(futures), desc=desc, unit="task") as bar:
        for fut in as_completed(futures):
            results.append(fut.result())
            bar.update(1)
    return results
