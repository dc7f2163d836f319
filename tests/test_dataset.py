"""The dataset: deterministic plans, nested prefixes, atomic shards, resume and validated reading."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from components.core import weather
from components.core.config import load_params
from components.simulate import dataset
from components.simulate.in_memory import render_split
from components.simulate.procedural import ProceduralSimulator

BOX = weather.Box.full()
ROOT = Path(__file__).resolve().parents[1]


def _plan(name="train", size=30, seed=5, **kw):
    args = dict(seed=seed, box=BOX, images_per_scene=4, shard_size=10, renderer_version="test", resolution=(32, 32))
    args.update(kw)
    return dataset.plan_split(name, size, **args)


@pytest.fixture(scope="module")
def sim():
    return ProceduralSimulator(32, 32)


def _render_all(plan, sim, root):
    for spec in plan.shards():
        dataset.render_shard(plan.rows(spec), sim, root)


def test_plan_is_deterministic_and_nested():
    a, b = _plan(size=30), _plan(size=30)
    np.testing.assert_array_equal(a.weather, b.weather)
    small = _plan(size=12)
    np.testing.assert_array_equal(small.weather, a.weather[:12])
    np.testing.assert_array_equal(small.scene_seed, a.scene_seed[:12])
    assert not np.array_equal(_plan(seed=6).weather, a.weather)
    assert not np.array_equal(_plan(name="test").weather[:5], a.weather[:5])
    assert BOX.contains(weather.theta_from_weather(a.weather)).all()
    # blocks of images_per_scene consecutive images share a scene, scenes differ between blocks
    assert len(set(a.scene_seed[:4])) == 1 and a.scene_seed[3] != a.scene_seed[4]
    assert [(s.start, s.stop) for s in a.shards()] == [(0, 10), (10, 20), (20, 30)]


@pytest.mark.parametrize("field, value", [("size", -3), ("size", 0), ("shard_size", 0), ("images_per_scene", 1.5)])
def test_plan_rejects_bad_sizes(field, value):
    kw = {field: value}
    size = kw.pop("size", 30)
    with pytest.raises(ValueError, match=field):
        _plan(size=size, **kw)


def test_plan_rejects_unknown_split_and_missing_seed():
    with pytest.raises(ValueError, match="unknown split 'dev'"):
        _plan(name="dev")
    with pytest.raises(ValueError, match="seed is required"):
        _plan(seed=None)


def test_write_read_round_trip_is_byte_identical(tmp_path, sim):
    plans = [_plan(n, s) for n, s in (("train", 30), ("val", 10), ("test", 10))]
    for root in (tmp_path / "a", tmp_path / "b"):
        for p in plans:
            _render_all(p, sim, root)
        manifest = dataset.write_manifest(
            root, plans, renderer_version="test", resolution=(32, 32), seed=5, box=BOX, images_per_scene=4
        )
    for f in sorted((tmp_path / "a").rglob("*.npz")):
        assert f.read_bytes() == (tmp_path / "b" / f.relative_to(tmp_path / "a")).read_bytes(), f
    split = dataset.open_split(tmp_path / "a", "train", verify=True)
    assert len(split) == 30 and split.resolution == (32, 32)
    np.testing.assert_array_equal(split.theta, weather.theta_from_weather(plans[0].weather))
    images = split.images()
    assert images.shape == (30, 32, 32, 3) and images.dtype == np.uint8
    np.testing.assert_array_equal(split.images(stop=12), images[:12])
    # the stored image is the simulator's image of that weather and scene
    w = dict(zip(weather.ALL_NAMES, split.weather[13], strict=False))
    np.testing.assert_array_equal(images[13], sim.render(w, int(split.scene_seed[13])))
    assert manifest["splits"]["train"]["count"] == 30
    assert manifest["content_hash"] == json.loads((tmp_path / "b" / "manifest.json").read_text())["content_hash"]


def test_damaged_shards_are_detected(tmp_path, sim):
    plan = _plan(size=30)
    _render_all(plan, sim, tmp_path)
    specs = plan.shards()
    assert all(dataset.shard_is_done(s, tmp_path) for s in specs)
    dataset.write_manifest(
        tmp_path, [plan], renderer_version="test", resolution=(32, 32), seed=5, box=BOX, images_per_scene=4
    )

    # truncated: not done, and the reader refuses it
    path = specs[1].path(tmp_path)
    path.write_bytes(path.read_bytes()[:-100])
    assert not dataset.shard_is_done(specs[1], tmp_path)
    with pytest.raises(dataset.DatasetError, match=r"shard-00001.npz: shard does not match the manifest"):
        dataset.open_split(tmp_path, "train")
    # same size, one flipped byte: only the hash sees it
    dataset.render_shard(plan.rows(specs[1]), sim, tmp_path)
    raw = bytearray(path.read_bytes())
    raw[-7] ^= 0xFF
    path.write_bytes(bytes(raw))
    assert dataset.shard_is_done(specs[1], tmp_path, verify_hash=False)
    assert not dataset.shard_is_done(specs[1], tmp_path)
    with pytest.raises(dataset.DatasetError, match="does not match the manifest"):
        dataset.open_split(tmp_path, "train", verify=True)
    # deleted
    specs[2].path(tmp_path).unlink()
    assert not dataset.shard_is_done(specs[2], tmp_path)
    with pytest.raises(dataset.DatasetError, match="shard-00002.npz: shard listed in .* is missing"):
        dataset.open_split(tmp_path, "train")
    # a shard of another plan (e.g. another seed) is stale
    other = _plan(size=30, seed=99)
    assert not dataset.shard_is_done(other.shards()[0], tmp_path)
    # a manifest cannot be written while shards are unfinished
    specs[0].receipt_path(tmp_path).unlink()
    with pytest.raises(dataset.DatasetError, match="shard not finished"):
        dataset.write_manifest(
            tmp_path, [plan], renderer_version="test", resolution=(32, 32), seed=5, box=BOX, images_per_scene=4
        )


def test_orphans_removed_when_split_shrinks(tmp_path, sim):
    big = _plan(size=30)
    _render_all(big, sim, tmp_path)
    small = _plan(size=15)
    removed = dataset.remove_orphans(tmp_path, small)
    assert sorted(p.name for p in removed) == ["shard-00002.json", "shard-00002.npz"]


def test_missing_dataset_is_a_clear_error(tmp_path):
    with pytest.raises(dataset.DatasetError, match="no dataset manifest; run the generate stage"):
        dataset.open_split(tmp_path, "train")
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(dataset.DatasetError, match="corrupt manifest"):
        dataset.open_split(tmp_path, "train")


def test_in_memory_rendering_gives_the_shards_images(tmp_path) -> None:
    """The first images of a split rendered in memory (``in_memory.render_split``) are byte for byte those of the
    generate stage's shard writer."""
    params = load_params(ROOT / "params.yaml")
    images, theta = render_split(params, "test", 8, workers=1)
    sim = ProceduralSimulator(params.simulator.height, params.simulator.width)
    plan = dataset.plan_split(
        "test",
        8,
        seed=params.seed,
        box=params.box,
        images_per_scene=params.data.images_per_scene,
        shard_size=8,
        renderer_version=sim.version,
        resolution=(sim.height, sim.width),
    )
    spec = plan.shard(0)
    dataset.render_shard(plan.rows(spec), sim, tmp_path)
    with np.load(spec.path(tmp_path)) as shard:
        np.testing.assert_array_equal(images, shard["images"])
        np.testing.assert_array_equal(theta, shard["weather"][:, :6].astype(np.float32))
    # a piece of the plan from a later row: the same images and weathers as the whole split's rows
    tail, tail_theta = render_split(params, "test", 3, workers=1, start=5)
    np.testing.assert_array_equal(tail, images[5:])
    np.testing.assert_array_equal(tail_theta, theta[5:])
    for bad in ({"size": 0}, {"size": 2, "start": -1}):
        with pytest.raises(ValueError, match="size and workers must be ≥ 1 and start ≥ 0"):
            render_split(params, "test", workers=1, **{"size": 2} | bad)
