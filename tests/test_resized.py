"""Camera-like renders (`simulator.render_sizes`): the exact area resize, the per-scene render size, the simulator that
composes them, its data through the generate flow, its params' errors and what a model card of such renders covers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import stats

from components.core import weather
from components.core.config import ConfigError, load_params
from components.core.images import render_shape
from components.simulate import dataset
from components.simulate.base import make_simulator
from components.simulate.procedural import ProceduralSimulator
from components.simulate.resized import ResizedRenders, area_resize, area_weights, render_height
from tests.conftest import write_params

RAINY = weather.weather_from_theta(np.array([40.0, 20.0, 70.0, 35.0, 60.0, 50.0]), 120.0)


@pytest.mark.parametrize(("n", "m"), [(384, 128), (200, 128), (129, 128), (1000, 7), (7, 3), (5, 5)])
def test_area_weights_spread_every_input_pixel_over_the_outputs(n, m):
    index, weight = area_weights(n, m)
    dense = np.zeros((m, n), dtype=np.int64)
    np.add.at(dense, (np.repeat(np.arange(m), index.shape[1]), index.ravel()), weight.ravel())
    assert (dense.sum(axis=1) == n).all()  # each output: the mean over n/m input pixels, in units of 1/m
    assert (dense.sum(axis=0) == m).all()  # each input pixel's light all goes somewhere, once


def test_area_resize_is_the_block_mean_and_opencvs_area_average():
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (96, 120, 3), dtype=np.uint8)
    blocks = image.reshape(32, 3, 40, 3, 3).astype(np.float64).mean(axis=(1, 3))
    np.testing.assert_array_equal(area_resize(image, (32, 40)), np.floor(blocks + 0.5).astype(np.uint8))
    for shape, out in (
        ((384, 384), (128, 128)),
        ((200, 250), (128, 128)),
        ((131, 129), (128, 128)),
        ((77, 50), (9, 13)),
    ):
        image = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
        ours = area_resize(image, out).astype(int)
        theirs = cv2.resize(image, out[::-1], interpolation=cv2.INTER_AREA).astype(int)
        assert np.abs(ours - theirs).max() <= 1 and (ours != theirs).mean() < 0.01, shape
    flat = np.full((250, 190, 3), 77, dtype=np.uint8)
    assert (area_resize(flat, (128, 97)) == 77).all()
    assert area_resize(flat, (250, 190)) is flat


@pytest.mark.parametrize(
    ("image", "size", "word"),
    [
        (np.zeros((64, 64, 3), np.uint8), (65, 64), "shrinks only"),
        (np.zeros((64, 64, 3), np.float32), (32, 32), "uint8"),
        (np.zeros((64, 64), np.uint8), (32, 32), r"\(H, W, C\)"),
    ],
)
def test_area_resize_names_what_it_cannot_do(image, size, word):
    with pytest.raises(ValueError, match=word):
        area_resize(image, size)


def test_render_height_is_uniform_over_the_sizes_and_a_function_of_the_scene():
    heights = np.array([render_height(s, 140, 149) for s in range(5000)])
    counts = np.bincount(heights - 140, minlength=10)
    assert counts.size == 10 and stats.chisquare(counts).pvalue > 1e-3
    assert [render_height(s, 140, 149) for s in range(50)] == heights[:50].tolist()  # no state: the seed alone
    assert render_shape(128, 128, 300) == (300, 300) and render_shape(96, 160, 150) == (150, 250)
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="scene_seed must be a non-negative int"):
            render_height(bad, 140, 149)


def test_resized_renders_render_each_scene_at_its_size_and_shrink_it():
    sim = ResizedRenders(32, 32, (40, 72))
    base = ProceduralSimulator(32, 32)
    assert sim.version == f"{base.version}+resized-40-72" and sim.version != base.version
    seen = set()
    for scene in range(6):
        h = sim.render_height(scene)
        seen.add(h)
        large = ProceduralSimulator(h, h).render(RAINY, scene)
        image = sim.render(RAINY, scene)
        assert image.shape == (32, 32, 3) and image.dtype == np.uint8
        np.testing.assert_array_equal(image, area_resize(large, (32, 32)))
        # another weather of the same scene: the same size (a posterior predictive check re-renders its image's kind)
        clear = weather.weather_from_theta(np.array([0.0, 0.0, 0.0, 60.0, 0.0, 0.0]), 120.0)
        np.testing.assert_array_equal(
            sim.render(clear, scene), area_resize(ProceduralSimulator(h, h).render(clear, scene), (32, 32))
        )
    assert len(seen) > 1
    with pytest.raises(ValueError, match=r"height \(32\) ≤ low ≤ high"):
        ResizedRenders(32, 32, (24, 64))


@pytest.mark.parametrize(
    ("overrides", "word"),
    [
        ({"render_sizes": [64, 48]}, r"height \(32\) ≤ low ≤ high ≤ 2048"),
        ({"render_sizes": [16, 48]}, r"height \(32\) ≤ low ≤ high ≤ 2048"),
        ({"render_sizes": [64, 4096]}, r"≤ 2048"),
        ({"render_sizes": [64]}, "render_sizes"),
        ({"render_sizes": [64, 96], "backend": "carla"}, "needs backend: procedural"),
    ],
)
def test_bad_render_sizes_are_named(tmp_path, overrides, word):
    p = write_params(tmp_path, simulator=_simulator_section(**overrides))
    with pytest.raises(ConfigError, match=word) as error:
        load_params(p)
    assert "simulator" in str(error.value)


def _simulator_section(**overrides) -> dict:
    import yaml

    from tests.conftest import PROJECT_ROOT

    section = yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())["simulator"]
    return section | {"height": 32, "width": 32} | overrides


def test_generate_renders_the_resized_kind_and_the_in_memory_split_matches(tmp_path, prefect_harness):
    from components.simulate.in_memory import render_split
    from flows.generate import generate

    params_path = write_params(tmp_path, simulator=_simulator_section(render_sizes=[40, 64]))
    params = load_params(params_path)
    sim = make_simulator(params.simulator)
    assert isinstance(sim, ResizedRenders) and sim.render_sizes == (40, 64)
    manifest = generate(str(params_path))
    assert manifest["renderer"].endswith("+resized-40-64")
    test = dataset.open_split(tmp_path / "data", "test", verify=True)
    images = test.images()
    assert images.shape == (48, 32, 32, 3)
    rows = test.weather[:8]
    expected = [
        area_resize(
            ProceduralSimulator(*render_shape(32, 32, render_height(int(s), 40, 64))).render(
                dict(zip(weather.ALL_NAMES, r, strict=True)), int(s)
            ),
            (32, 32),
        )
        for r, s in zip(rows, test.scene_seed[:8], strict=True)
    ]
    np.testing.assert_array_equal(images[:8], np.stack(expected))
    in_memory, _ = render_split(params, "test", 8, workers=1)
    np.testing.assert_array_equal(in_memory, images[:8])
    native = write_params(tmp_path / "native")
    assert generate(str(native))["content_hash"] != manifest["content_hash"]


def test_a_card_of_resized_renders_covers_their_sizes(tmp_path):
    from components.export.lookup import RegisteredPosterior

    class Card:
        def __init__(self, renders):
            self.card = {"model_id": "m", "training_renders": renders}

    def model(renders):
        return RegisteredPosterior(tmp_path, Card(renders), None)

    native = model({"simulator": "procedural", "height": 128, "width": 128, "render_sizes": None})
    assert native.learned_size((128, 128)) and not native.learned_size((256, 256))
    assert native.learned_from == "128×128 renders"
    older = model({"simulator": "procedural", "height": 128, "width": 128})  # exported before render_sizes existed
    assert older.learned_size((128, 128)) and not older.learned_size((130, 128))
    camera = model({"simulator": "procedural", "height": 96, "width": 160, "render_sizes": [120, 300]})
    assert camera.learned_size((150, 250)) and camera.learned_size((300, 500))
    assert camera.learned_size((96, 160))  # frames already shrunk to the model's images
    assert not camera.learned_size((150, 150)) and not camera.learned_size((301, 502))
    assert not camera.learned_size((110, 183))  # below the lowest render
    assert camera.training_renders == (96, 160, (120, 300)) and native.training_renders == (128, 128, None)
    assert camera.learned_from == "renders 120–300 pixels high, area-resized to 160×96"
    unknown = model({})
    assert unknown.learned_size((128, 128)) is None and unknown.learned_from is None
    assert unknown.training_renders is None


def test_the_camera_profile_renders_resized_images():
    from tests.conftest import PROJECT_ROOT

    params = load_params(PROJECT_ROOT / "params.yaml", profile="camera")
    assert params.simulator.render_sizes == (128, 384) and params.simulator.height == 128
    assert isinstance(make_simulator(params.simulator), ResizedRenders)
