"""The cues' frozen networks: the wet-road detector (components/features/backbones/wet_road.py), the weather reader
(weather_reader.py), the loader they share (frozen.py) and their training scripts. Mirror symmetry by construction,
what the shipped networks read in rendered scenes, refusal of missing, modified and foreign weights, deterministic tiny
training runs, and one rendering of the training images for any number of worker processes."""

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
from components.core.config import load_params
from components.core.files import sha256_file
from components.core.weather import SHORT_NAMES, Box
from components.features.backbones import weather_reader as wr
from components.features.backbones import wet_road
from components.simulate.procedural import ProceduralSimulator

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
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
    """Symmetric kernels: the logits of a mirrored image are the mirrored logits, for any weights. Checked in float64,
    where the only difference is rounding (~1e-15 of the logits' scale): in float32 a convolution of mirrored input
    sums in another order, and how far that moves a logit depends on the CPU's kernels (2e-5 of 0.5 on an AMD EPYC),
    not on the kernels' symmetry, which an asymmetric kernel breaks by its weights' size (~0.5 here)."""
    torch.manual_seed(0)
    net = wet_road.WetRoadNet().eval().double()
    for p in net.parameters():
        p.data.normal_(0.0, 0.5)
    x = torch.rand(3, 3, 128, 128, dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(net(x.flip(-1)), net(x).flip(-1), rtol=1e-10, atol=1e-10)
        f = wet_road.wet_road_features(net, x)
        torch.testing.assert_close(wet_road.wet_road_features(net, x.flip(-1)), f, rtol=1e-10, atol=1e-10)
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


def test_detector_training_script_writes_weights_its_card_accepts(tmp_path: Path) -> None:
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


def test_reader_features_are_mirror_invariant_for_any_weights() -> None:
    torch.manual_seed(0)
    net = wr.WeatherReader().eval()
    for p in net.parameters():
        p.data.normal_(0.0, 0.3)
    x = torch.rand(3, 3, 128, 128)
    with torch.no_grad():
        f, g = wr.reader_features(net, x), wr.reader_features(net, x.flip(-1))
    torch.testing.assert_close(g, f, rtol=1e-5, atol=1e-5)
    assert f.shape == (3, len(wr.FEATURE_NAMES)) == (3, 12)
    assert wr.FEATURE_NAMES[:2] == (f"reader_mean_{SHORT_NAMES[0]}", f"reader_log_sd_{SHORT_NAMES[0]}")
    with pytest.raises(ValueError, match=r"expected images \(n, 3, 128, 128\), got shape \(2, 3, 64, 64\)"):
        net(torch.zeros(2, 3, 64, 64))


def test_gaussian_nll_is_minimal_at_the_truth_and_the_right_scale() -> None:
    """The training loss of a Gaussian guess: smallest when the mean is the target and σ the error's scale."""
    target = torch.full((1000, 6), 0.5)
    errors = torch.randn(1000, 6, generator=torch.Generator().manual_seed(1)) * 0.1
    out = torch.stack([target + errors, torch.full_like(target, 0.0)], -1)

    def loss(shift: float, log_sd: float) -> float:
        return float(
            wr.gaussian_nll(torch.stack([target + shift, torch.full_like(target, log_sd)], -1), target + errors)
        )

    best = loss(0.0, float(np.log(0.1)))
    assert best < loss(0.05, float(np.log(0.1))) and best < loss(0.0, float(np.log(0.2)))
    assert best < loss(0.0, float(np.log(0.05)))
    assert float(wr.gaussian_nll(out, target)) > best  # σ = 1 for errors of 0.1


@pytest.mark.parametrize(
    "key,index,levels",
    [
        ("fog_density", 1, (0.0, 25.0, 50.0, 90.0)),
        ("cloudiness", 0, (0.0, 30.0, 60.0, 95.0)),
        ("precipitation", 2, (0.0, 30.0, 60.0, 95.0)),
    ],
)
def test_shipped_reader_follows_the_weather(key: str, index: int, levels: tuple[float, ...]) -> None:
    """In four daylight scenes the shipped reader's guess of fog, clouds and rain rises with the truth and stays within
    a fifth of the range of it; a sun 5° above the horizon is read lower than one at 50°."""
    net = wr.load_reader()
    card = json.loads(wr.CARD.read_text())
    assert card["sha256"] == sha256_file(wr.WEIGHTS) and tuple(card["widths"]) == wr.WIDTHS
    box, sim = Box.full(), ProceduralSimulator(128, 128)
    for i in range(4):
        scene = seeding.derive_seed(SEED, "test", "weather_reader", i)
        images = np.stack([sim.render({**CLEAR, "precipitation_deposits": 0.0, key: v}, scene) for v in levels])
        images = np.concatenate(
            [
                images,
                np.stack(
                    [
                        sim.render({**CLEAR, "precipitation_deposits": 0.0, "sun_altitude_angle": s}, scene)
                        for s in (5.0, 50.0)
                    ]
                ),
            ]
        )
        with torch.no_grad():
            f = wr.reader_features(net, torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0).view(-1, 6, 2)
        guess = box.low + f[..., 0].numpy() * (box.high - box.low)
        assert np.all(np.diff(guess[:4, index]) > 0), (scene, guess[:4, index])
        assert np.all(np.abs(guess[:4, index] - np.array(levels)) < 20.0), (scene, guess[:4, index])
        assert guess[4, 3] < guess[5, 3] - 20.0, (scene, guess[4:, 3])


@pytest.mark.parametrize(
    "load,module,script,bias",
    [
        (wr.load_reader, wr, "train_weather_reader.py", "head.3.bias"),
        (wet_road.load_detector, wet_road, "train_wet_road.py", "head.bias"),
    ],
)
def test_frozen_networks_refuse_missing_modified_and_foreign_weights(
    load, module, script, bias, tmp_path: Path
) -> None:
    with pytest.raises(FileNotFoundError, match=script):
        load(tmp_path / "none.pt", tmp_path / "none.json")
    weights, card = tmp_path / module.WEIGHTS.name, tmp_path / module.CARD.name
    shutil.copy(module.WEIGHTS, weights)
    shutil.copy(module.CARD, card)
    load(weights, card)
    state = torch.load(weights, weights_only=True)
    state[bias] = state[bias] + 1.0
    torch.save(state, weights)
    with pytest.raises(ValueError, match="differs from"):
        load(weights, card)
    meta = json.loads(card.read_text())
    torch.save({"other": torch.zeros(1)}, weights)
    card.write_text(json.dumps({**meta, "sha256": sha256_file(weights)}))
    with pytest.raises(ValueError, match="do not fit the"):
        load(weights, card)


def test_training_images_are_the_same_for_any_workers_and_come_back_from_the_cache(tmp_path: Path) -> None:
    from train_wet_road import render_training_set

    one = render_training_set(6, 7, "test_stream")
    two = render_training_set(6, 7, "test_stream", workers=2, cache=tmp_path)
    again = render_training_set(6, 7, "test_stream", cache=tmp_path)
    assert list(tmp_path.iterdir()) == [tmp_path / "test_stream-6-7.npz"]
    for a, b, c in zip(one, two, again, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


def test_reader_training_script_writes_weights_its_card_accepts(tmp_path: Path) -> None:
    """A tiny run of scripts/train_weather_reader.py: weights and a card that load_reader accepts, the same weights
    when run again with the same seed; bad arguments are refused by name."""
    out = tmp_path / "a" / "weather_reader.pt"
    cmd = [sys.executable, str(ROOT / "scripts" / "train_weather_reader.py"), "--images", "4", "--validation", "4"]
    cmd += ["--epochs", "1", "--batch-size", "2", "--seed", "7", "--threads", "1", "--out"]
    for target in (out, tmp_path / "b" / "weather_reader.pt"):
        done = subprocess.run([*cmd, str(target)], cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
    card = json.loads(out.with_suffix(".json").read_text())
    assert (card["training_images"], card["epochs"], card["seed"], card["batch_size"]) == (4, 1, 7, 2)
    # every parameter by day and by night: a number ≥ 0, or None for a part with no validation image (4 images here)
    errors = card["validation"]["median_abs_error"]
    assert set(errors) == {"day", "night"}
    assert all(list(errors[part]) == list(SHORT_NAMES) for part in errors), errors
    filled = [part for part in errors if all(isinstance(v, float) and v >= 0 for v in errors[part].values())]
    assert filled and all(part in filled or set(errors[part].values()) == {None} for part in errors), errors
    assert card["sha256"] == json.loads((tmp_path / "b" / "weather_reader.json").read_text())["sha256"]
    wr.load_reader(out, out.with_suffix(".json"))
    for bad, message in (
        (["--workers", "0"], "--workers must be at least 1, got 0"),
        (["--lr", "0"], "--lr must be positive"),
    ):
        done = subprocess.run([*cmd[:-1], *bad], cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert done.returncode == 2 and message in done.stderr, done.stderr


def test_sun_head_shares_the_convolutions_and_is_mirror_invariant_for_any_weights() -> None:
    """With the sun head the reader's 12 features are unchanged (the convolutions run once for both heads) and two
    more follow, mirror-invariant by construction."""
    torch.manual_seed(0)
    net = wr.WeatherReader().eval()
    for p in net.parameters():
        p.data.normal_(0.0, 0.3)
    sun = wr.SunHead(wr.WIDTHS[-1] * 16, (8, 4)).eval()
    x = torch.rand(3, 3, 128, 128)
    with torch.no_grad():
        f, g, alone = (
            wr.reader_features(net, x, sun),
            wr.reader_features(net, x.flip(-1), sun),
            wr.reader_features(net, x),
        )
        direct = sun(net.features(x).flatten(1)).flatten(1)
        mirrored = sun(net.features(x.flip(-1)).flatten(1)).flatten(1)
    assert f.shape == (3, len(wr.FEATURE_NAMES) + len(wr.SUN_FEATURE_NAMES)) == (3, 14)
    torch.testing.assert_close(f[:, :12], alone, rtol=0, atol=0)
    torch.testing.assert_close(f[:, 12:], 0.5 * (direct + mirrored), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(g, f, rtol=1e-5, atol=1e-5)


def test_shipped_sun_head_reads_the_sun_higher_as_it_rises() -> None:
    """In four clear daylight scenes the shipped sun head's guess rises with the sun's altitude (10°, 30°, 50°, 70°),
    off by less than 12° on average over the 16 images; its card names the shipped reader."""
    net, sun = wr.load_reader(), wr.load_sun_head()
    card = json.loads(wr.SUN_CARD.read_text())
    assert card["sha256"] == sha256_file(wr.SUN_WEIGHTS)
    assert card["reader_sha256"] == json.loads(wr.CARD.read_text())["sha256"]
    box, sim, levels = Box.full(), ProceduralSimulator(128, 128), np.array([10.0, 30.0, 50.0, 70.0])
    errors = []
    for i in range(4):
        scene = seeding.derive_seed(SEED, "test", "sun_head", i)
        weathers = [{**CLEAR, "precipitation_deposits": 0.0, "sun_altitude_angle": s} for s in levels]
        images = np.stack([sim.render(w, scene) for w in weathers])
        with torch.no_grad():
            f = wr.reader_features(net, torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0, sun)
        guess = box.low[3] + f[:, 12].numpy() * (box.high[3] - box.low[3])
        assert np.all(np.diff(guess) > 0), (scene, guess)
        errors.append(np.abs(guess - levels))
    assert np.mean(errors) < 12.0, np.round(errors, 1)


def test_sun_head_loader_refuses_missing_modified_and_foreign_heads(tmp_path: Path) -> None:
    """Missing or modified weights, and a card that is not JSON or lacks the head's input width, are refused by name as
    for every frozen network; a head whose card names another reader is refused too (it would read convolutions it
    never saw)."""
    with pytest.raises(FileNotFoundError, match="train_sun_head.py"):
        wr.load_sun_head(tmp_path / "none.pt", tmp_path / "none.json")
    weights, card = tmp_path / wr.SUN_WEIGHTS.name, tmp_path / wr.SUN_CARD.name
    shutil.copy(wr.SUN_WEIGHTS, weights)
    shutil.copy(wr.SUN_CARD, card)
    wr.load_sun_head(weights, card)
    meta = json.loads(card.read_text())
    card.write_text(json.dumps({**meta, "reader_sha256": "0" * 64}))
    with pytest.raises(ValueError, match="trained on the reader 0000"):
        wr.load_sun_head(weights, card)
    card.write_text(json.dumps({k: v for k, v in meta.items() if k != "in_features"}))
    with pytest.raises(ValueError, match=r"card has no field 'in_features' \(retrain with python scripts/train_sun"):
        wr.load_sun_head(weights, card)
    card.write_text("{not json")
    with pytest.raises(ValueError, match="card is not valid JSON"):
        wr.load_sun_head(weights, card)
    card.write_text(json.dumps(meta))
    state = torch.load(weights, weights_only=True)
    state["net.4.bias"] = state["net.4.bias"] + 1.0
    torch.save(state, weights)
    with pytest.raises(ValueError, match="differs from"):
        wr.load_sun_head(weights, card)


def test_sun_head_training_script_writes_weights_its_card_accepts(tmp_path: Path) -> None:
    """A tiny run of scripts/train_sun_head.py: weights and a card that load_sun_head accepts, the same weights when
    run again with the same seeds (once from its cache); bad arguments, the pipeline's own seed among them, are
    refused by name."""
    out = tmp_path / "a" / "weather_reader_sun.pt"
    cmd = [sys.executable, str(ROOT / "scripts" / "train_sun_head.py"), "--images", "16", "--validation", "8"]
    cmd += ["--epochs", "2", "--batch-size", "8", "--root-seed", "11", "--seed", "7", "--threads", "1", "--hidden", "8"]
    cmd += ["--cache", str(tmp_path / "cache"), "--out"]
    for target in (out, tmp_path / "b" / "weather_reader_sun.pt"):
        done = subprocess.run([*cmd, str(target)], cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
    assert len(list((tmp_path / "cache").iterdir())) == 2  # the second run read the maps back
    card = json.loads(out.with_suffix(".json").read_text())
    assert (card["training_images"], card["epochs"], card["seed"], card["hidden"]) == (16, 2, 7, [8])
    assert card["data"]["plans"] == {"train": 11, "val": 12} and 1 <= card["best_epoch"] <= 2
    assert set(card["validation"]) == {"sun_head", "reader"}
    assert card["sha256"] == json.loads((tmp_path / "b" / "weather_reader_sun.json").read_text())["sha256"]
    wr.load_sun_head(out, out.with_suffix(".json"))
    # --faces: the clear-sky face's images join the training set; the card names their plans and scores the head there
    faces = tmp_path / "c" / "weather_reader_sun.pt"
    done = subprocess.run(
        [*cmd, str(faces), "--faces", "8", "--face-validation", "4"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    card = json.loads(faces.with_suffix(".json").read_text())
    assert card["data"]["faces"]["plans"] == {"train": 111, "val": 112} and card["data"]["faces"]["images"] == 8
    assert card["data"]["faces"]["box"]["fog_density"] == [0.0, 5.0]
    assert set(card["validation_faces"]) == {"sun_head", "reader"}
    assert card["sha256"] != json.loads(out.with_suffix(".json").read_text())["sha256"]  # other data, other weights
    with np.load(next((tmp_path / "cache").glob("sun_head-faces-train-111-0-8-*.npz"))) as z:
        assert z["theta"].shape == (8, 6) and (z["theta"][:, 1] <= 5.0).all() and (z["theta"][:, 0] <= 20.0).all()
    wr.load_sun_head(faces, faces.with_suffix(".json"))
    seed = load_params(ROOT / "params.yaml").seed
    for bad, message in (
        (["--root-seed", str(seed)], "its plans would be the pipeline's own images"),
        (["--faces", "-1"], "--faces must be >= 0"),
        (["--root-seed", str(seed - 100), "--faces", "4"], "its plans would be the pipeline's own images"),
        (["--hidden", "0"], "--hidden must be positive integers"),
        (["--hidden", "a"], "--hidden must be comma-separated integers"),
    ):
        done = subprocess.run([*cmd[:-1], *bad], cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert done.returncode == 2 and message in done.stderr, done.stderr
