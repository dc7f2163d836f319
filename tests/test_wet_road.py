"""The cues' wet-road detector (components/features/backbones/wet_road.py) and its training script: mirror
equivariance by construction, the features' ranges, the shipped weights checked against their card, and what the
shipped detector reads: the wet share of the road rises with the deposits in rendered scenes."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from components.core import seeding
from components.core.files import sha256_file
from components.features.backbones import wet_road
from components.simulate.procedural import ProceduralSimulator

ROOT = Path(__file__).resolve().parents[1]
SEED = 20261127
CLEAR = {
    "cloudiness": 10.0,
    "fog_density": 0.0,
    "precipitation": 0.0,
    "sun_altitude_angle": 35.0,
    "wind_intensity": 0.0,
    "sun_azimuth_angle": 120.0,
}


def test_detector_is_mirror_equivariant() -> None:
    """Symmetric kernels: the logits of a mirrored image are the mirrored logits, for any weights."""
    torch.manual_seed(0)
    net = wet_road.WetRoadNet().eval()
    for p in net.parameters():
        p.data.normal_(0.0, 0.5)
    x = torch.rand(3, 3, 128, 128)
    with torch.no_grad():
        torch.testing.assert_close(net(x.flip(-1)), net(x).flip(-1), rtol=1e-5, atol=1e-5)
        f = wet_road.wet_road_features(net, x)
        torch.testing.assert_close(wet_road.wet_road_features(net, x.flip(-1)), f, rtol=1e-5, atol=1e-5)
    assert f.shape == (3, len(wet_road.FEATURE_NAMES)) == (3, 2 * len(wet_road.BANDS))
    assert bool(((f >= 0) & (f <= 1)).all())
    rows = [r for band in wet_road.BANDS for r in band]
    assert wet_road.ROWS[0] <= min(rows) and max(rows) <= wet_road.ROWS[1] and rows == sorted(rows)


def test_shipped_detector_reads_the_wet_share() -> None:
    """In four scenes under a clear sky, the shipped detector's wet share of the road 10–25 m ahead (rows 67–86) and
    nearer (86–106) rises with the deposits, from a dry road to a flooded one, by more than 0.2."""
    net = wet_road.load_detector()
    card = json.loads(wet_road.CARD.read_text())
    assert card["sha256"] == sha256_file(wet_road.WEIGHTS) and card["channels"] == wet_road.CHANNELS
    sim = ProceduralSimulator(128, 128)
    levels = (0.0, 35.0, 70.0, 100.0)
    wet = [k for k, n in enumerate(wet_road.FEATURE_NAMES) if n.startswith("wet_road_wet_share") and "_r6" not in n]
    assert len(wet) == 6  # the bands from row 67 on
    for i in range(4):
        scene = seeding.derive_seed(SEED, "test", "wet_road", i)
        images = np.stack([sim.render({**CLEAR, "precipitation_deposits": d}, scene) for d in levels])
        x = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0
        with torch.no_grad():
            share = wet_road.wet_road_features(net, x)[:, wet].mean(1).numpy()
        assert np.all(np.diff(share) > 0), (scene, share)
        assert share[-1] - share[0] > 0.2, (scene, share)  # its level varies from scene to scene (a flooded road
        # looks like a dark dry one); its rise with the deposits is what the flow reads


def test_load_detector_refuses_missing_and_modified_weights(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="train_wet_road.py"):
        wet_road.load_detector(tmp_path / "none.pt", tmp_path / "none.json")
    weights, card = tmp_path / "wet_road.pt", tmp_path / "wet_road.json"
    shutil.copy(wet_road.WEIGHTS, weights)
    shutil.copy(wet_road.CARD, card)
    wet_road.load_detector(weights, card)
    state = torch.load(weights, weights_only=True)
    state["head.bias"] = state["head.bias"] + 1.0
    torch.save(state, weights)
    with pytest.raises(ValueError, match="differs from"):
        wet_road.load_detector(weights, card)


def test_training_script_writes_weights_its_card_accepts(tmp_path: Path) -> None:
    """A tiny run of scripts/train_wet_road.py: weights and a card that load_detector accepts, the same weights when
    run again with the same seed."""
    out = tmp_path / "a" / "wet_road.pt"
    cmd = [sys.executable, str(ROOT / "scripts" / "train_wet_road.py"), "--images", "4", "--validation", "4"]
    cmd += ["--epochs", "1", "--seed", "7", "--threads", "1", "--out"]
    for target in (out, tmp_path / "b" / "wet_road.pt"):
        done = subprocess.run([*cmd, str(target)], cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
    card = json.loads(out.with_suffix(".json").read_text())
    assert (card["training_images"], card["epochs"], card["seed"]) == (4, 1, 7)
    assert card["sha256"] == json.loads((tmp_path / "b" / "wet_road.json").read_text())["sha256"]
    wet_road.load_detector(out, out.with_suffix(".json"))
    bad = subprocess.run([*cmd[:-1], "--images", "1"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--images must be at least 2, got 1" in bad.stderr
