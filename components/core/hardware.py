"""What this process may use: its cores (the CPU affinity and a cgroup's CPU quota) and a torch device.

The runners' ``workers: auto`` and the torch stages' ``device: auto`` are resolved here, once at a stage's start
(``flows/stage.py``), so that a setting the machine cannot honour — more workers than usable cores, ``cuda`` where
torch sees no GPU — is one error naming the key before any work starts. The settings' forms are checked by the
config (``components/core/config.py``); what they mean on this machine is decided here. Torch is imported only by
:func:`resolve_device`.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = [
    "usable_cores",
    "cgroup_cpu_quota",
    "resolve_workers",
    "threads_per_worker",
    "resolve_device",
    "cuda_devices",
    "cuda_devices_without_torch",
    "STAGES",
    "StagePlan",
    "stage_plan",
    "on_this_machine",
]

#: where the cgroup file systems are mounted (v2: one hierarchy; v1: a ``cpu`` or ``cpu,cpuacct`` folder in it)
CGROUP_ROOT = Path("/sys/fs/cgroup")

_DEVICE = re.compile(r"^(auto|cpu|cuda(:(\d+))?)$")


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except (OSError, UnicodeDecodeError):
        return None


def _own_paths(proc_cgroup: Path) -> list[str]:
    """The cgroup paths of this process named in ``/proc/self/cgroup`` (``"0::/a/b"`` in v2, ``"4:cpu,cpuacct:/a"``
    in v1), for the hierarchies that hold the CPU controller."""
    paths = []
    for line in (_read(proc_cgroup) or "").splitlines():
        parts = line.split(":", 2)
        if len(parts) == 3 and (parts[1] == "" or "cpu" in parts[1].split(",")):
            paths.append(parts[2])
    return paths


def _quota_at(folder: Path) -> float | None:
    """The cores the quota of one cgroup ``folder`` allows (v2 ``cpu.max``, v1 ``cpu.cfs_quota_us`` over
    ``cpu.cfs_period_us``), or None where it sets none or a file is missing or unreadable."""
    text = _read(folder / "cpu.max")
    if text is not None:
        fields = text.split()
        if len(fields) == 2 and fields[0] != "max":
            quota, period = fields
        else:
            return None
    else:
        quota, period = _read(folder / "cpu.cfs_quota_us"), _read(folder / "cpu.cfs_period_us")
    try:
        q, p = int(quota), int(period)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return q / p if q > 0 and p > 0 else None  # v1 writes -1 for no quota


def cgroup_cpu_quota(root: str | Path = CGROUP_ROOT, proc_cgroup: str | Path = "/proc/self/cgroup") -> float | None:
    """The CPU time per second that the cgroups of this process allow it (in cores), or None where none is set.

    Every cgroup from this process's own (``proc_cgroup``) up to the ``root`` of its hierarchy is read, and the
    tightest quota counts (a parent's quota bounds its children); the v2 hierarchy (``root/cpu.max``) and v1's
    (``root/cpu/`` or ``root/cpu,cpuacct/``) alike. Missing or unreadable files count as no quota.

    Arguments:
        root: where the cgroup file systems are mounted (a test passes a folder of its own).
        proc_cgroup: the file naming this process's cgroups.

    Returns:
        the quota in cores (1.5 for ``cpu.max`` ``150000 100000``), or None.

    Example:
        >>> cgroup_cpu_quota("/nonexistent") is None
        True
    """
    root = Path(root)
    found = []
    for base in (root, root / "cpu", root / "cpu,cpuacct"):
        if not base.is_dir():
            continue
        for own in _own_paths(Path(proc_cgroup)) or ["/"]:
            folder = base / own.strip("/")
            while True:
                quota = _quota_at(folder)
                if quota is not None:
                    found.append(quota)
                if folder == base or base not in folder.parents:
                    break
                folder = folder.parent
    return min(found) if found else None


def usable_cores(root: str | Path = CGROUP_ROOT, proc_cgroup: str | Path = "/proc/self/cgroup") -> int:
    """The cores this process may use: the CPUs of its affinity mask (``os.sched_getaffinity``; ``os.cpu_count``
    where the platform has none), capped by its cgroups' CPU quota (:func:`cgroup_cpu_quota`) rounded down, and at
    least 1.

    Arguments:
        root: where the cgroup file systems are mounted.
        proc_cgroup: the file naming this process's cgroups.

    Returns:
        a whole number of cores ≥ 1 (what ``workers: auto`` means).

    Example:
        >>> usable_cores() >= 1
        True
    """
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    quota = cgroup_cpu_quota(root, proc_cgroup)
    if quota is not None:
        cores = min(cores, math.floor(quota))
    return max(1, cores)


def resolve_workers(setting: int | str, cores: int, key: str) -> int:
    """The workers a runner's ``workers`` setting means here: ``auto`` → ``cores``; a whole number is kept when it is
    at most ``cores``.

    Arguments:
        setting: ``"auto"`` or a positive int (its form is the config's check).
        cores: the usable cores (:func:`usable_cores`).
        key: the setting's dotted key, for the error.

    Returns:
        the number of workers, 1 ≤ workers ≤ cores.

    Raises:
        ValueError: naming the key, the setting and the usable cores, when it asks for more workers than cores.

    Example:
        >>> resolve_workers("auto", 4, "train.runner.workers"), resolve_workers(2, 4, "train.runner.workers")
        (4, 2)
    """
    if setting == "auto":
        return cores
    if isinstance(setting, bool) or not isinstance(setting, int) or setting < 1:
        raise ValueError(f"{key}: must be a positive whole number or auto, got {setting!r}")
    if setting > cores:
        raise ValueError(
            f"{key}: {setting} workers, but this process may use {cores} core{'s' if cores != 1 else ''} "
            "(its CPU affinity and cgroup quota); set workers: auto or at most that"
        )
    return setting


def threads_per_worker(cores: int, workers: int) -> int:
    """The torch (or other) threads each of ``workers`` parallel workers gets of ``cores``: ``cores // workers``, at
    least 1.

    Example:
        >>> threads_per_worker(16, 4), threads_per_worker(2, 4)
        (4, 1)
    """
    return max(1, cores // max(1, workers))


def cuda_devices() -> int:
    """The CUDA devices torch sees here (0 without a CUDA build of torch, a driver or a GPU); imports torch."""
    import torch

    return torch.cuda.device_count() if torch.cuda.is_available() else 0


def cuda_devices_without_torch() -> int:
    """The CUDA devices torch would see, told without importing it (``pidc config check`` stays a fraction of a
    second): 0 for a CPU build of torch (its ``torch/version.py`` names no CUDA) or where the NVIDIA driver lists no GPU
    (``/proc/driver/nvidia/gpus``), else the GPUs it lists; torch's own answer where it is already imported. A
    prediction for the plan: a stage asks torch (:func:`cuda_devices`).

    Example:
        >>> cuda_devices_without_torch() >= 0
        True
    """
    import importlib.util
    import sys

    if "torch" in sys.modules:
        return cuda_devices()
    spec = importlib.util.find_spec("torch")
    folders = list(spec.submodule_search_locations or []) if spec else []
    build = _read(Path(folders[0]) / "version.py") if folders else None
    if not build or not re.search(r"^cuda\b.*=\s*['\"]", build, re.M):
        return 0
    try:
        return len(list(Path("/proc/driver/nvidia/gpus").iterdir()))
    except OSError:
        return 0


def resolve_device(setting: str, key: str, devices: int | None = None) -> str:
    """The torch device a ``device`` setting means here: ``auto`` → ``cuda`` when torch sees a CUDA device, else
    ``cpu``; ``cpu``; ``cuda`` or ``cuda:N`` when torch sees that device.

    Arguments:
        setting: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``.
        key: the setting's dotted key, for the error.
        devices: the CUDA devices there are (default: torch's answer, :func:`cuda_devices`).

    Returns:
        ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (a string for ``torch.device``).

    Raises:
        ValueError: naming the key and what was found, for another form, for ``cuda`` where torch sees no CUDA device
            (a CPU build of torch, no driver, no GPU) and for ``cuda:N`` beyond the devices it sees.

    Example:
        >>> resolve_device("cpu", "train.device"), resolve_device("auto", "train.device", devices=0)
        ('cpu', 'cpu')
    """
    match = _DEVICE.match(setting) if isinstance(setting, str) else None
    if match is None:
        raise ValueError(f"{key}: must be auto, cpu, cuda or cuda:N (N a device index), got {setting!r}")
    if setting == "cpu":
        return "cpu"
    count = cuda_devices() if devices is None else devices
    if setting == "auto":
        return "cuda" if count else "cpu"
    if not count:
        raise ValueError(
            f"{key}: {setting}, but torch sees no CUDA device here (a CPU build of torch, or no GPU or driver); "
            f"set {key.rsplit('.', 1)[-1]}: auto or cpu"
        )
    if match.group(3) is not None and int(match.group(3)) >= count:
        raise ValueError(f"{key}: {setting}, but torch sees {count} CUDA device(s) here (cuda:0 … cuda:{count - 1})")
    return setting


#: the stages with a task runner: ``(stage, its runner's key, its device's key or None, threads per worker fixed or
#: None)``. Generate renders one image at a time per worker and evaluate runs one onnxruntime thread per worker (on
#: the CPU); the others give each worker ``cores // workers`` threads.
STAGES: tuple[tuple[str, str, str | None, int | None], ...] = (
    ("generate", "data.runner", None, 1),
    ("features", "data.runner", "backbones.device", None),
    ("train", "train.runner", "train.device", None),
    ("export", "export.runner", None, None),
    ("evaluate", "evaluate.runner", None, 1),
)


@dataclass(frozen=True)
class StagePlan:
    """What a stage runs with on this machine: its runner's kind, its workers, the threads of each, its device (None:
    the stage runs no torch model, or onnxruntime on the CPU)."""

    stage: str
    kind: str
    workers: int
    threads: int
    device: str | None


def _at(params: Any, key: str) -> Any:
    for part in key.split("."):
        params = getattr(params, part)
    return params


def _workers(runner: Any, cores: int, key: str) -> int:
    if runner.kind == "dask" and runner.dask_address:  # an existing cluster's workers are not this machine's cores
        return cores if runner.workers == "auto" else runner.workers
    return resolve_workers(runner.workers, cores, f"{key}.workers")


def stage_plan(params: Any, stage: str, cores: int | None = None, devices: int | None = None) -> StagePlan:
    """The plan of ``stage`` (one of :data:`STAGES`) under the validated ``params`` (``components.core.config.Params``)
    on this machine.

    Arguments:
        params: the validated params.
        stage: the stage's name.
        cores: the usable cores (default: :func:`usable_cores`).
        devices: the CUDA devices there are (default: torch's answer, :func:`cuda_devices`).

    Returns:
        the :class:`StagePlan`.

    Raises:
        ValueError: naming the key, when its workers or its device cannot be had here.
    """
    cores = usable_cores() if cores is None else cores
    _, runner_key, device_key, fixed = next(row for row in STAGES if row[0] == stage)
    runner = _at(params, runner_key)
    workers = _workers(runner, cores, runner_key)
    device = resolve_device(_at(params, device_key), device_key, devices) if device_key else None
    return StagePlan(stage, runner.kind, workers, fixed or threads_per_worker(cores, workers), device)


def on_this_machine(params: Any, cores: int | None = None) -> Any:
    """``params`` (``components.core.config.Params``) with every runner's ``workers`` a number and every ``device``
    resolved here (:func:`resolve_workers`, :func:`resolve_device`): what a stage runs with, decided once at its start.

    Arguments:
        params: the validated params.
        cores: the usable cores (default: :func:`usable_cores`).

    Returns:
        a copy of ``params`` (the frozen models copied where they change).

    Raises:
        ValueError: naming the first key whose workers or device cannot be had here.
    """
    cores = usable_cores() if cores is None else cores
    sections: dict[str, dict[str, Any]] = {}
    for _, runner_key, device_key, _ in STAGES:
        section, name = runner_key.split(".")
        runner = _at(params, runner_key)
        sections.setdefault(section, {})[name] = runner.model_copy(
            update={"workers": _workers(runner, cores, runner_key)}
        )
        if device_key:
            section, name = device_key.split(".")
            sections.setdefault(section, {})[name] = resolve_device(_at(params, device_key), device_key)
    return params.model_copy(
        update={section: getattr(params, section).model_copy(update=fields) for section, fields in sections.items()}
    )
