"""What this process may use: cgroup CPU quotas read from files, ``workers: auto`` and ``device: auto`` resolved, and
a setting this machine cannot honour refused with one line naming its key before any work starts.

The quota files are written into a temporary folder passed as the cgroup root, so the parsing is tested on known
contents (v2 ``cpu.max``, v1 ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``) whatever this machine's cgroups are. The
device tests that need a CUDA-less torch are skipped where torch sees a GPU (their GPU counterparts are the stages'
own tests run with ``device: cuda`` there).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from components.core import hardware
from components.core.config import ConfigError, load_params, parse_params
from tests.conftest import micro_params, write_params

NO_CUDA = pytest.mark.skipif(torch.cuda.is_available(), reason="torch sees a CUDA device here")


def _v2(root: Path, text: str, own: str = "/") -> Path:
    """A v2 hierarchy at ``root`` with ``cpu.max`` = ``text`` in this process's cgroup ``own``; the
    ``/proc/self/cgroup`` file naming it."""
    folder = root / own.strip("/")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cpu.max").write_text(text + "\n")
    proc = root.parent / f"{root.name}-proc-cgroup"
    proc.write_text(f"0::{own}\n")
    return proc


@pytest.mark.parametrize(
    ("text", "quota"),
    [("max 100000", None), ("150000 100000", 1.5), ("250000 100000", 2.5), ("50000 100000", 0.5), ("garbage", None)],
)
def test_cgroup_v2_quota(tmp_path, text, quota):
    """``cpu.max`` is ``$MAX $PERIOD`` (``max``: no quota): the quota in cores is their ratio; an unreadable line
    counts as none."""
    proc = _v2(tmp_path / "cg", text)
    assert hardware.cgroup_cpu_quota(tmp_path / "cg", proc) == quota


def test_the_tightest_quota_from_the_own_cgroup_up_counts(tmp_path):
    """A parent's quota bounds its children: 3 cores at the root, 1.5 in this process's cgroup → 1.5; and the other
    way round → 1.5 as well."""
    root = tmp_path / "cg"
    proc = _v2(root, "150000 100000", own="/a/b")
    (root / "cpu.max").write_text("300000 100000\n")
    assert hardware.cgroup_cpu_quota(root, proc) == 1.5
    (root / "a" / "b" / "cpu.max").write_text("max 100000\n")
    (root / "a" / "cpu.max").write_text("150000 100000\n")
    assert hardware.cgroup_cpu_quota(root, proc) == 1.5


@pytest.mark.parametrize(("quota", "period", "cores"), [("-1", "100000", None), ("200000", "100000", 2.0)])
def test_cgroup_v1_quota(tmp_path, quota, period, cores):
    """v1's CPU controller (``cpu,cpuacct``): ``cfs_quota_us`` over ``cfs_period_us``, -1 for none."""
    folder = tmp_path / "cg" / "cpu,cpuacct"
    folder.mkdir(parents=True)
    (folder / "cpu.cfs_quota_us").write_text(quota)
    (folder / "cpu.cfs_period_us").write_text(period)
    proc = tmp_path / "proc-cgroup"
    proc.write_text("4:cpu,cpuacct:/\n3:memory:/\n")
    assert hardware.cgroup_cpu_quota(tmp_path / "cg", proc) == cores


def test_no_cgroup_files_is_no_quota(tmp_path):
    assert hardware.cgroup_cpu_quota(tmp_path / "none", tmp_path / "none-either") is None


@pytest.mark.parametrize(("text", "cap"), [("max 100000", None), ("150000 100000", 1), ("250000 100000", 2)])
def test_usable_cores_is_the_affinity_capped_by_the_quota_rounded_down(tmp_path, text, cap):
    """1.5 cores of quota → 1, 2.5 → 2 (a worker per whole core), never more than the affinity mask's CPUs."""
    affinity = len(os.sched_getaffinity(0))
    proc = _v2(tmp_path / "cg", text)
    assert hardware.usable_cores(tmp_path / "cg", proc) == (affinity if cap is None else min(affinity, cap))


def test_usable_cores_is_at_least_one(tmp_path):
    assert hardware.usable_cores(tmp_path / "cg", _v2(tmp_path / "cg", "10000 100000")) == 1


def test_workers_auto_and_pinned():
    assert hardware.resolve_workers("auto", 3, "data.runner.workers") == 3
    assert hardware.resolve_workers(2, 3, "data.runner.workers") == 2
    with pytest.raises(ValueError, match=r"^train\.runner\.workers: 4 workers, but this process may use 3 cores"):
        hardware.resolve_workers(4, 3, "train.runner.workers")


def test_threads_per_worker():
    assert [hardware.threads_per_worker(16, w) for w in (1, 3, 16, 32)] == [16, 5, 1, 1]


def test_device_auto_and_cpu():
    """``auto`` is CUDA exactly when torch sees it; ``cpu`` is always the CPU (without importing torch's CUDA)."""
    assert hardware.resolve_device("auto", "train.device") == ("cuda" if torch.cuda.is_available() else "cpu")
    assert hardware.resolve_device("cpu", "train.device") == "cpu"


@NO_CUDA
@pytest.mark.parametrize("device", ["cuda", "cuda:0"])
def test_cuda_without_cuda_names_the_key(device):
    with pytest.raises(ValueError, match=rf"^backbones\.device: {device}, but torch sees no CUDA device here"):
        hardware.resolve_device(device, "backbones.device")


def test_a_device_beyond_those_torch_sees_names_the_key():
    with pytest.raises(ValueError, match=r"^train\.device: cuda:99, but torch sees"):
        hardware.resolve_device("cuda:99", "train.device")


@pytest.mark.parametrize("device", ["cuda:x", "gpu", "CUDA", "cuda:", " cpu"])
def test_a_malformed_device_is_a_config_error(device):
    p = micro_params()
    p["train"]["device"] = device
    with pytest.raises(ConfigError, match=r"train\.device: must be auto, cpu, cuda or cuda:N"):
        parse_params(p)
    with pytest.raises(ValueError, match=r"^train\.device: must be auto, cpu, cuda or cuda:N"):
        hardware.resolve_device(device, "train.device")


@pytest.mark.parametrize("workers", [0, -1, "2", True, 1.5, "all"])
def test_bad_workers_are_a_config_error(workers):
    p = micro_params()
    p["evaluate"]["runner"]["workers"] = workers
    with pytest.raises(ConfigError, match=r"evaluate\.runner\.workers: must be auto or a whole number ≥ 1"):
        parse_params(p)


def test_parallel_exports_in_threads_are_refused_with_auto_too():
    """``auto`` may mean several exports at once, which need processes; ``workers: 1`` with threads is fine."""
    p = micro_params()
    p["export"]["runner"].update(kind="threads", workers="auto")
    with pytest.raises(ConfigError, match=r"export\.runner: kind 'threads' with auto workers"):
        parse_params(p)
    p["export"]["runner"]["workers"] = 1
    assert parse_params(p).export.runner.workers == 1


def test_the_params_on_this_machine():
    """Every runner's ``auto`` becomes the given cores, a pinned number stays; ``auto`` devices are resolved; the
    rest of the params is unchanged."""
    p = micro_params()
    p["data"]["runner"]["workers"] = "auto"
    p["train"]["runner"]["workers"] = 1
    params = parse_params(p)
    here = hardware.on_this_machine(params, cores=3)
    assert (here.data.runner.workers, here.train.runner.workers) == (3, 1)
    assert (here.evaluate.runner.workers, here.export.runner.workers) == (3, 3)
    assert here.train.device == here.backbones.device == hardware.resolve_device("auto", "train.device")
    assert here.train.model_dump(exclude={"runner", "device"}) == params.train.model_dump(exclude={"runner", "device"})
    plan = hardware.stage_plan(params, "train", cores=3)
    assert (plan.kind, plan.workers, plan.threads) == ("processes", 1, 3)
    assert hardware.stage_plan(params, "evaluate", cores=3).device is None


def test_too_many_workers_stop_a_stage_before_it_starts(tmp_path):
    """A stage's command (:func:`flows.stage.parse_stage_args`) exits 2 with one line naming the file and the key."""
    from flows.stage import load_for_this_machine, parse_stage_args

    cores = hardware.usable_cores()
    path = write_params(tmp_path, **{"train.runner": {"kind": "processes", "workers": cores + 1, "dask_address": None}})
    with pytest.raises(ConfigError, match=rf"params\.yaml: train\.runner\.workers: {cores + 1} workers, but this"):
        load_for_this_machine(path)
    with pytest.raises(SystemExit) as stop:
        parse_stage_args("a stage", ["--params", str(path)])
    assert stop.value.code == 2
    assert load_params(path).train.runner.workers == cores + 1  # the file itself is valid: a check of form


@NO_CUDA
def test_cuda_here_stops_a_stage_before_it_starts(tmp_path):
    from flows.stage import load_for_this_machine

    path = write_params(tmp_path, **{"train.device": "cuda"})
    with pytest.raises(ConfigError, match=r"params\.yaml: train\.device: cuda, but torch sees no CUDA device here"):
        load_for_this_machine(path)


def test_the_torch_stages_put_their_networks_on_the_resolved_device():
    """The features stage's backbone and the train stage's model go to the resolved device (here the CPU, the same
    code path as ``cuda``'s: ``torch.device`` and ``Module.to``), and a backbone's fingerprint does not depend on it."""
    from components.features.backbones import get_backbone
    from components.posterior import NPE
    from components.posterior.model import FlowConfig
    from flows.features import _backbone
    from flows.train import _on_device

    backbone = _backbone("cues", "{}", "cpu")  # its frozen networks are parameters that move
    assert backbone._device() == torch.device("cpu")
    assert backbone.fingerprint() == get_backbone("cues").fingerprint()
    params = parse_params(micro_params())
    model = NPE(None, 4, params.box, FlowConfig(transforms=1, hidden_features=(8,), bins=4), seed=0)
    assert _on_device(model, "cpu") == torch.device("cpu") and model.device == torch.device("cpu")
