"""Shared fixtures. Prefect state goes to a temporary folder, never the project's .prefect/."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ["PREFECT_HOME"] = tempfile.mkdtemp(prefix="pidc-prefect-home-")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.pop("PREFECT_API_URL", None)
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import pytest  # noqa: E402
import yaml  # noqa: E402

from components.core.config import PROJECT_ROOT  # noqa: E402


@pytest.fixture(scope="session")
def prefect_harness():
    """A temporary Prefect server and database for the tests that run flows in-process."""
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield


def micro_params(**overrides) -> dict:
    """The default params.yaml shrunk to a few tiny images (for pipeline tests)."""
    p = yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())
    p["simulator"].update(height=32, width=32)
    p["data"].update(splits={"train": 24, "val": 16, "test": 48}, shard_size=10, images_per_scene=4)
    p["data"]["runner"].update(kind="threads", workers=2)
    p["contact_sheet"].update(steps=3, scenes=1)
    p["train"]["sizes"] = [8, 16, 24]
    p["train"]["scale_to"] = 8  # no small-data scaling of epochs and widths: the micro models train for seconds
    p["train"]["variants"] = {"balanced": {"backbone": "cues", "size": 16, "balance": 10.0, "ensemble": 1}}
    p["evaluate"].update(images=8, samples=400, ppc_images=1, ppc_renders=2, example_images=1)
    p["evaluate"]["named"].update(presets="none", scenes=2, draws=400, toy_images=24)  # two own weathers
    p["evaluate"]["named"]["weathers"] = {
        k: p["evaluate"]["named"]["weathers"][k] for k in ("pidc:ClearHighSun", "pidc:StormNoon")
    }
    p["evaluate"]["named"]["local_test"].update(
        calibration_images="all", summary_draws=8, test_draws=50, steps=20, null_trials=19, test_images="all"
    )
    p["export"]["champion_max_calibration_error"] = 1.0  # models trained for seconds are not calibrated: any may win
    # the deconvolved estimate (not the default) so that its path through the stage runs too
    p["task2"].update(
        images=16,
        images_per_scene=4,
        samples=200,
        estimate="deconvolved",
        deconvolution={"draws_per_image": 4, "max_steps": 20, "folds": 2},
    )
    p["task3"].update(
        bags={  # wide sub-boxes: the micro test split is small
            "b0": {"box": {"sun_altitude_angle": [-90, -10]}, "max_images": 8},
            "b1": {"box": {"sun_altitude_angle": [0, 90], "cloudiness": [0, 50]}, "max_images": 3},
            "b2": {
                "box": {"sun_altitude_angle": [0, 90], "cloudiness": [50, 100], "precipitation": [0, 50]},
                "max_images": 2,
            },
            "b3": {
                "box": {"sun_altitude_angle": [0, 90], "cloudiness": [50, 100], "precipitation": [50, 100]},
                "max_images": 2,
            },
        },
        etas=[0.0, 0.5, 1.0],
        repetitions=3,
        n_points=8,
        calibration_targets=20,
        false_alarm_targets=20,
        false_alarm_rate=0.1,
    )
    p["monitor"].update(images=16, samples=200, false_alarm_targets=20)  # a scheduled run in seconds
    for key, value in overrides.items():
        section, _, name = key.partition(".")
        if name:
            p[section][name] = value
        else:
            p[section] = value
    return p


def write_params(folder: Path, **overrides) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "params.yaml"
    path.write_text(yaml.safe_dump(micro_params(**overrides), sort_keys=False))
    return path


@pytest.fixture(scope="session")
def prefect_server(tmp_path_factory):
    """A real Prefect server on 127.0.0.1 (own PREFECT_HOME), stopped at the end: yields its API URL."""
    import socket
    import subprocess
    import sys
    import time
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    home = tmp_path_factory.mktemp("prefect-server")
    env = dict(os.environ, PREFECT_HOME=str(home), PREFECT_SERVER_ANALYTICS_ENABLED="false")
    env.pop("PREFECT_API_URL", None)
    log = open(home / "server.log", "wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port", str(port)],
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    url = f"http://127.0.0.1:{port}/api"
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                urllib.request.urlopen(f"{url}/health", timeout=2)
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"the Prefect server did not start; see {home / 'server.log'}") from None
                time.sleep(0.5)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()


IMAGENET_MEAN, IMAGENET_STD = [0.485, 0.456, 0.406], [0.229, 0.224, 0.225]


def _tiny_checkpoint(name: str, folder: Path, seed: int) -> None:
    """A randomly initialised tiny model of ``name``'s architecture + its image processor, saved."""
    import torch
    import transformers
    from transformers.models.bit.image_processing_pil_bit import BitImageProcessorPil
    from transformers.models.clip.image_processing_pil_clip import CLIPImageProcessorPil
    from transformers.models.convnext.image_processing_pil_convnext import ConvNextImageProcessorPil

    vit = dict(
        hidden_size=32, num_hidden_layers=2, num_attention_heads=2, intermediate_size=64, image_size=32, patch_size=8
    )
    with torch.random.fork_rng(devices=[]):  # weights drawn from a seeded stream, global RNG untouched
        torch.manual_seed(seed)
        if name == "resnet50":
            model = transformers.ResNetModel(
                transformers.ResNetConfig(embedding_size=8, hidden_sizes=[8, 16], depths=[1, 1])
            )
            processor = ConvNextImageProcessorPil(
                size={"shortest_edge": 32}, crop_pct=0.875, image_mean=IMAGENET_MEAN, image_std=IMAGENET_STD
            )
        elif name == "dinov2":
            model = transformers.Dinov2Model(transformers.Dinov2Config(**vit))
            processor = BitImageProcessorPil(
                size={"shortest_edge": 36},
                crop_size={"height": 32, "width": 32},
                image_mean=IMAGENET_MEAN,
                image_std=IMAGENET_STD,
            )
        elif name == "clip":
            model = transformers.CLIPVisionModel(transformers.CLIPVisionConfig(**vit))
            processor = CLIPImageProcessorPil(size={"shortest_edge": 32}, crop_size={"height": 32, "width": 32})
        else:
            raise ValueError(f"no tiny checkpoint for {name!r}; pretrained backbones: resnet50, dinov2, clip")
    model.save_pretrained(folder)
    processor.save_pretrained(folder)


@pytest.fixture(scope="session")
def tiny_checkpoint():
    """``tiny_checkpoint(name, folder, seed)`` saves a tiny randomly initialised (seeded) checkpoint of pretrained
    backbone ``name``'s architecture (ResNet / DINOv2 / CLIP, 32×32 input) with its image processor into ``folder``,
    loadable through the real path (``get_backbone(name, path=folder)``). Same seed, same weights."""
    return _tiny_checkpoint


#: the smallest flow the tests train (params.yaml's ``train.flow`` section)
TINY_FLOW = {
    "transforms": 1,
    "hidden_features": [16],
    "bins": 4,
    "passes": 2,
    "ensemble": 1,
    "standardize": True,
    "context_layers": [16, 8],
}

FAST_TRAINING = {
    "train.epochs": 2,
    "train.embedding_epochs": 1,
    "train.sizes": [8, 24],
    "train.scale_to": 8,
    "train.variants": {"ensemble": {"backbone": "cues", "size": 24, "balance": 0.0, "ensemble": 2}},
    "backbones": {"names": ["cues", "cnn"], "pretrained_dir": None, "batch_size": 256, "device": "cpu"},
    "train.flow": TINY_FLOW,
    # one base scale τ: the micro project's 16 validation pairs cannot hold two (a gate on models trained for seconds
    # may put all but one pair in the night regime, a clear error by design); tests/test_train_flow.py covers the regime
    "train.temperature_regime": None,
}


def run_in(cmd, cwd, env: dict | None = None, timeout: float = 600, **kw) -> subprocess.CompletedProcess:
    """Run ``cmd`` in ``cwd`` with this interpreter's ``python`` first on PATH (DVC runs stage commands through
    the shell) and ``cwd`` on PYTHONPATH (the project's copies of components/ and flows/, not the editable install's)."""
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    full_env = {**os.environ, "PYTHONPATH": str(cwd), "PATH": path, **(env or {})}
    return subprocess.run(cmd, cwd=cwd, env=full_env, capture_output=True, text=True, timeout=timeout, **kw)


def copy_project(src: Path, dst: Path) -> Path:
    """A full copy of a project folder (git and DVC state, cache and outputs included) to change on its own."""
    shutil.copytree(src, dst, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
    return dst


@pytest.fixture(scope="session")
def micro_project(tmp_path_factory, prefect_server) -> Path:
    """A micro pidc project built once with `dvc repro`: a temp git repo with the project's components/, flows/,
    dvc.yaml and prefect.yaml, params.yaml shrunk to a few tiny images and FAST_TRAINING, every stage run through
    its Prefect flow against the session's Prefect server. Shared: read it, or change a `copy_project` of it."""
    return build_project(tmp_path_factory.mktemp("micro-project") / "repo", prefect_server, **FAST_TRAINING)


def new_project(repo: Path, **overrides) -> Path:
    """A pidc project in ``repo``, not yet run: a git repo with the project's components/, flows/, profiles/,
    dvc.yaml, prefect.yaml and .dvcignore, params.yaml = :func:`micro_params` with ``overrides``, DVC initialised."""
    repo.mkdir(parents=True)
    for name in ("components", "flows", "profiles"):  # profiles/: a dependency of the stages (params `profile`)
        shutil.copytree(PROJECT_ROOT / name, repo / name, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("dvc.yaml", "prefect.yaml", ".dvcignore"):
        if (PROJECT_ROOT / name).is_file():
            shutil.copy(PROJECT_ROOT / name, repo / name)
    write_params(repo, **overrides)
    dvc = [sys.executable, "-m", "dvc"]
    for cmd in (["git", "init", "-q"], dvc + ["init", "-q"], dvc + ["config", "core.analytics", "false"]):
        r = run_in(cmd, repo)
        assert r.returncode == 0, r.stdout + r.stderr
    return repo


def build_project(repo: Path, prefect_server: str, **overrides) -> Path:
    """:func:`new_project` built with `dvc repro`: every stage run through its Prefect flow against the Prefect server
    ``prefect_server`` (one server for every stage, as run.sh)."""
    new_project(repo, **overrides)
    dvc = [sys.executable, "-m", "dvc"]
    r = run_in(dvc + ["repro"], repo, env={"PREFECT_API_URL": prefect_server})
    if r.returncode != 0:
        raise RuntimeError(f"`dvc repro` of the project in {repo} failed:\n{r.stdout}\n{r.stderr}")
    return repo
