"""What every stage's flow does first, and the task runners of the fan-out stages.

:func:`parse_stage_args` reads a stage's command line (``--params`` plus the stage's own arguments) and validates the
params file before any work starts: a bad or incomplete params file ends the command with exit code 2 and one line
naming ``file: dotted.key`` (what ``dvc repro`` shows). :func:`open_stage` is the first line of a flow body: the
params, the project's folders and the run logger. Both resolve the params for this machine
(:func:`load_for_this_machine`): every runner's ``workers: auto`` becomes the usable cores and every ``device`` a
torch device, or a setting the machine cannot honour is the same one-line error.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from prefect import get_run_logger
from prefect.futures import PrefectFuture, as_completed
from prefect.task_runners import ProcessPoolTaskRunner, TaskRunner, ThreadPoolTaskRunner
from tqdm.auto import tqdm

from components.core.config import PROJECT_ROOT, ConfigError, Params, RunnerConfig, load_params
from components.core.hardware import on_this_machine, usable_cores
from components.core.paths import ProjectPaths

__all__ = [
    "Stage",
    "load_for_this_machine",
    "open_stage",
    "parse_stage_args",
    "use_all_cores",
    "task_runner",
    "share_api_with_workers",
    "check_dask_cluster",
    "DaskClusterError",
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


def load_for_this_machine(params_file: Path) -> Params:
    """The params file, validated and resolved for this process (``components.core.hardware.on_this_machine``: the
    runners' workers numbers, the devices torch devices); ``ConfigError`` naming the key when it is bad or asks for
    more cores or another device than this machine has."""
    params = load_params(params_file)
    try:
        return on_this_machine(params)
    except ValueError as e:
        raise ConfigError(f"{params_file}: {e}") from None


def open_stage(params_path: str | Path) -> Stage:
    """Load the params file for this machine (:func:`load_for_this_machine`; ``ConfigError`` naming the key when it
    is bad) inside a flow run."""
    params_file = Path(params_path)
    params = load_for_this_machine(params_file)
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
        params = load_for_this_machine(args.params)
    except ConfigError as e:
        parser.exit(2, f"{parser.prog}: {e.one_line()}\n")
    _loaded.update(prog=parser.prog, params=params, params_file=Path(args.params).resolve())
    return args, params


#: what :func:`parse_stage_args` read last (the command's name, its params and their file): a Dask runner's preflight
#: names its key (``train.runner.dask_address``) and checks that the workers see the same params file
_loaded: dict[str, Any] = {}


def use_all_cores() -> None:
    """Let torch use every core this process may use (a stage that trains or exports runs alone)."""
    import torch

    torch.set_num_threads(usable_cores())


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
            try:
                check_dask_cluster(cfg.dask_address, _runner_key(cfg), params_file=_loaded.get("params_file"))
            except DaskClusterError as e:  # before any work, one line (as a bad params file: exit 2)
                print(f"{_loaded.get('prog', 'pidc')}: {e}", file=sys.stderr)
                raise SystemExit(2) from None
            _main_by_its_name()
            return DaskTaskRunner(address=cfg.dask_address)
        # a local cluster of threads: the cluster starts before the flow body, so worker processes could not be
        # pointed at the flow's temporary Prefect server and would each start their own
        return DaskTaskRunner(cluster_kwargs={"n_workers": 1, "threads_per_worker": cfg.workers, "processes": False})
    raise ValueError(f"unknown task runner kind {cfg.kind!r}; known: threads, processes, dask")


def _main_by_its_name() -> None:
    """Let the tasks of a flow run as ``python -m flows.<stage>`` be pickled by their module's name.

    Run with ``-m``, the stage's module is ``__main__``: its functions (an ``lru_cache`` of it, a task's helpers)
    pickle as ``__main__.<name>``, which a Dask worker (whose ``__main__`` is ``dask worker``) cannot find; a process
    pool's workers re-import the main module, Dask's do not. The module is registered under its own name
    (``flows.generate``) and its functions and classes renamed to it, so that the workers import it."""
    main = sys.modules.get("__main__")
    name = getattr(getattr(main, "__spec__", None), "name", None)
    if main is None or not name or name == "__main__":
        return
    sys.modules.setdefault(name, main)
    for obj in list(vars(main).values()):
        if getattr(obj, "__module__", None) == "__main__" and isinstance(obj, type | Callable):
            try:
                obj.__module__ = name
            except (AttributeError, TypeError):
                pass


class DaskClusterError(ConfigError):
    """A runner's ``dask_address`` names no usable Dask cluster: nobody answers, no workers, or workers that cannot
    run the project's tasks (another environment, another project folder, no Prefect server to report to)."""


_RUNNER_KEYS = ("data.runner", "train.runner", "export.runner", "evaluate.runner")


def _runner_key(cfg: RunnerConfig) -> str:
    """The dotted key of ``cfg`` in the params :func:`parse_stage_args` read (``runner`` when they are not known)."""
    params = _loaded.get("params")
    for key in _RUNNER_KEYS:
        section, _, name = key.partition(".")
        if params is not None and getattr(getattr(params, section, None), name, None) is cfg:
            return key
    return "runner"


#: what must be the same on the flow's machine and every Dask worker for the tasks to give the same bytes
_SAME_ON_WORKERS = ("pidc", "torch", "numpy", "opencv-python-headless", "prefect", "prefect-dask", "distributed")


def _facts_function() -> Callable[[str | None], dict[str, str]]:
    """The function of what :func:`check_dask_cluster` compares between this process and each worker (called with
    the params file's path). Nested, so cloudpickle sends its code by value: a worker that cannot import the project
    still answers why."""
    names = _SAME_ON_WORKERS

    def facts(params_file: str | None) -> dict[str, str]:
        import hashlib
        import importlib
        import importlib.metadata as metadata
        import platform

        out = {"python": platform.python_version()}
        for dist in names:
            try:
                out[dist] = metadata.version(dist)
            except metadata.PackageNotFoundError:
                out[dist] = "not installed"
        try:
            out["project"] = str(Path(importlib.import_module("flows.stage").__file__).resolve().parents[1])
        except Exception as e:  # noqa: BLE001 (any failure to import the project is the answer)
            out["project"] = f"not importable ({type(e).__name__}: {e})"
        if params_file:
            try:
                out["params file"] = hashlib.sha256(Path(params_file).read_bytes()).hexdigest()[:12]
            except OSError:
                out["params file"] = "not found"
        return out

    return facts


def check_dask_cluster(
    address: str, key: str = "runner", timeout: float = 5.0, params_file: str | Path | None = None
) -> dict[str, dict[str, str]]:
    """Check, before any work, that the Dask scheduler at ``address`` answers, has workers, and that each worker
    runs the same environment and project as this process; raise :class:`DaskClusterError` (one line naming
    ``<key>.dask_address`` and what was found) otherwise.

    Arguments:
        address: the scheduler's address, ``tcp://host:port``.
        key: the runner's dotted key in the params (``data.runner``), named by the error.
        timeout: seconds to wait for the scheduler's answer, and for a first worker.
        params_file: the stage's params file: each worker must read the same bytes at the same path (the project
            folder shared at one path on every machine).

    Returns:
        Worker address → what was compared (Python and package versions, the project's folder, the params file's
        hash).

    Raises:
        DaskClusterError: nobody answers at ``address``, it is not a Dask scheduler, no worker joined in ``timeout``,
            a worker differs from this process, or no Prefect server is configured (every worker would start its own).
    """
    import socket

    from distributed import Client
    from distributed.comm import parse_address
    from distributed.comm.addressing import parse_host_port

    where = f"{key}.dask_address"
    try:
        protocol, loc = parse_address(address)
        host, port = parse_host_port(loc, default_port=8786) if protocol in ("tcp", "tls") else (None, None)
    except ValueError as e:
        raise DaskClusterError(f"{where}: {address!r} is not a Dask address ({e}); expected tcp://host:8786") from None
    if host is not None:  # a plain TCP connect first: a crisp reason, without Dask's retries
        try:
            socket.create_connection((host, port), timeout=timeout).close()
        except ConnectionRefusedError:
            raise DaskClusterError(f"{where}: no Dask scheduler answers at {address} (connection refused)") from None
        except TimeoutError:
            raise DaskClusterError(
                f"{where}: no Dask scheduler answers at {address} (no answer in {timeout:g} s)"
            ) from None
        except OSError as e:
            raise DaskClusterError(f"{where}: no Dask scheduler answers at {address} ({e.strerror or e})") from None
    from prefect.settings import get_current_settings

    if not get_current_settings().api.url:
        raise DaskClusterError(
            f"{where}: {address} is a remote cluster but no Prefect server is configured: set PREFECT_API_URL to a "
            "server every worker reaches (each would start a temporary one of its own)"
        )
    try:
        client = Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError) as e:
        raise DaskClusterError(f"{where}: {address} answers but not as a Dask scheduler ({e})") from None
    try:
        try:
            client.wait_for_workers(1, timeout=timeout)
        except TimeoutError:
            raise DaskClusterError(
                f"{where}: the Dask scheduler at {address} has no workers after {timeout:g} s "
                f"(start them with `dask worker {address}` in the project folder)"
            ) from None
        file = str(params_file) if params_file else None
        here, there = _facts_function()(file), client.run(_facts_function(), file)
    finally:
        client.close()
    for worker, facts in sorted(there.items()):
        differs = [f"{k} {here[k]} here, {facts.get(k, 'unknown')} there" for k in here if facts.get(k) != here[k]]
        if differs:
            raise DaskClusterError(
                f"{where}: Dask worker {worker} differs from this process: {'; '.join(differs)} (start the workers "
                "in the same project folder, shared at the same path, with the same environment)"
            )
    return there


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
