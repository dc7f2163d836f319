"""The backbone registry and the three embedded backbones (cues, tiny, cnn)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from components.core import seeding
from components.features.backbones import EMBEDDED, PACKAGED, PRETRAINED, Backbone, available, get_backbone
from components.features.backbones.cues import FEATURE_NAMES
from components.simulate.procedural import ProceduralSimulator

SEED = 2026
CLEAR = dict(
    cloudiness=20.0,
    fog_density=0.0,
    precipitation=0.0,
    sun_altitude_angle=45.0,
    wind_intensity=0.0,
    precipitation_deposits=0.0,
    sun_azimuth_angle=100.0,
)


def _quiet(name: str, **options) -> Backbone:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return get_backbone(name, **options)


def _extract(backbone: Backbone, images: np.ndarray) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return backbone.extract(images)


@pytest.fixture(scope="module")
def textures() -> np.ndarray:
    """Eight 128×128 random smooth-ish RGB textures (uint8)."""
    g = seeding.rng(SEED, "test", "backbones", "textures")
    coarse = g.uniform(0, 255, size=(8, 16, 16, 3))
    fine = g.normal(0, 25, size=(8, 128, 128, 3))
    img = np.repeat(np.repeat(coarse, 8, axis=1), 8, axis=2) + fine
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def renders() -> dict[str, np.ndarray]:
    """Four scenes rendered by the procedural simulator under clear, foggy, night, rainy and wet (puddles) weather."""
    sim = ProceduralSimulator(128, 128)
    out = {}
    changes = {
        "clear": {},
        "fog": {"fog_density": 80.0},
        "night": {"sun_altitude_angle": -40.0},
        "rain": {"precipitation": 80.0},
        "wet": {"precipitation_deposits": 90.0},
    }
    for key, change in changes.items():
        w = {**CLEAR, **change}
        out[key] = np.stack([sim.render(w, seeding.derive_seed(SEED, "test", "scene", i)) for i in range(4)])
    return out


# -- registry -----------------------------------------------------------------------------------------
def test_registry_lists_embedded_then_packaged_then_pretrained() -> None:
    assert available() == [*EMBEDDED, *PACKAGED, *PRETRAINED]
    for name in EMBEDDED:
        b = _quiet(name)
        assert isinstance(b, Backbone) and isinstance(b, torch.nn.Module) and b.name == name


def test_unknown_name_lists_known_ones() -> None:
    with pytest.raises(ValueError, match="unknown backbone 'vgg'.*cues.*tiny.*cnn.*efficientnet_lite0.*resnet50.*clip"):
        get_backbone("vgg")


def test_unknown_option_names_the_accepted_ones() -> None:
    with pytest.raises(ValueError, match="no option.*'depth'.*seed, dim, width"):
        get_backbone("cnn", depth=3)
    with pytest.raises(ValueError, match="grid must be an integer"):
        get_backbone("tiny", grid=1)


# -- common contract ----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", EMBEDDED)
def test_shapes_dtypes_and_determinism(name: str, textures: np.ndarray) -> None:
    b = _quiet(name)
    f1 = _extract(b, textures)
    f2 = _extract(_quiet(name), textures)  # a fresh instance (cnn: same default seed)
    assert f1.shape == (len(textures), b.dim) and f1.dtype == np.float32
    assert np.isfinite(f1).all()
    np.testing.assert_array_equal(f1, f2)
    # batching does not change features
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        np.testing.assert_allclose(b.extract(textures, batch_size=3), f1, rtol=1e-5, atol=1e-5)
        x = b.preprocess(textures[:2])
    assert tuple(x.shape) == (2, 3, *b.input_size) and x.dtype == torch.float32
    assert b.trainable == (name == "cnn")


@pytest.mark.parametrize("name", ["cues", "tiny"])
def test_calls_in_chunks_give_the_features_of_whole_batches_to_the_bit(name: str, renders: dict) -> None:
    """``cpu_chunk`` is a matter of speed only: the cached features do not depend on it (nor on the batch size). The
    cues' learned blocks are the exception: the wet-road detector's and the weather reader's convolutions round by the
    call's batch (to ~1e-7 and ~1e-6), so their columns agree to 1e-5 only; the features stage always calls them in
    the same chunks."""
    images = np.concatenate(list(renders.values()))  # 20 rendered images: chunks of 16 leave a tail of 4
    b = _quiet(name)
    assert b.cpu_chunk == 16  # the setting the features stage runs
    chunked = _extract(b, images)
    learned = ("wet_road_", "reader_")
    exact = np.array([not n.startswith(learned) for n in b.feature_names]) if name == "cues" else slice(None)
    for chunk in (3, None):  # chunks with a tail of 2; the whole batch
        b.cpu_chunk = chunk
        again = _extract(b, images)
        np.testing.assert_array_equal(again[:, exact], chunked[:, exact], err_msg=f"{name}, calls of {chunk}")
        np.testing.assert_allclose(again, chunked, rtol=1e-5, atol=1e-5, err_msg=f"{name}, calls of {chunk}")


@pytest.mark.parametrize("name", EMBEDDED)
def test_bad_input_is_a_clear_error(name: str, textures: np.ndarray) -> None:
    b = _quiet(name)
    with pytest.raises(ValueError, match="dtype uint8"):
        b.preprocess(textures.astype(np.float32) / 255)
    with pytest.raises(ValueError, match=r"\(n, H, W, 3\).*\(2, 128, 128, 4\)"):
        b.preprocess(np.zeros((2, 128, 128, 4), np.uint8))
    with pytest.raises(TypeError, match="numpy uint8 array"):
        b.preprocess(torch.zeros(2, 128, 128, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match="batch_size"):
        b.extract(textures, batch_size=0)


def test_resize_is_announced_once_and_is_area_interpolation(textures: np.ndarray) -> None:
    tiny = get_backbone("tiny")
    big = np.repeat(np.repeat(textures[:2], 2, axis=1), 2, axis=2)  # 256×256, each pixel doubled
    with pytest.warns(UserWarning, match="'tiny'.*256×256.*128×128.*area"):
        x = tiny.preprocess(big)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tiny.preprocess(big)  # said once per instance
        direct = tiny.preprocess(textures[:2])
    torch.testing.assert_close(x, direct, rtol=0, atol=0)  # 2×2 means of equal pixels are exact


def test_single_image_is_a_batch_of_one(textures: np.ndarray) -> None:
    b = get_backbone("cues")
    np.testing.assert_allclose(b.extract(textures[0]), b.extract(textures[:1]), rtol=1e-6, atol=1e-6)


# -- cues -----------------------------------------------------------------------------------------------
def test_cues_names_match_dim() -> None:
    b = get_backbone("cues")
    assert b.dim == len(FEATURE_NAMES) == len(set(FEATURE_NAMES)) == 377


def test_cues_mirror_symmetry(textures: np.ndarray) -> None:
    """A left-right flip reverses edge orientation (bin k ↔ −k), mirrors the 4×4 grid's and the 8-column sky
    thumbnail's columns and swaps the left and right walls, and leaves every other cue unchanged."""
    b = get_backbone("cues")
    f = b.extract(textures)
    g = b.extract(np.ascontiguousarray(textures[:, :, ::-1]))
    perm = np.arange(len(FEATURE_NAMES))
    for prefix in ("edge_hist", "fine_edge_hist"):
        idx = [FEATURE_NAMES.index(f"{prefix}{k}") for k in range(8)]
        for k in range(8):
            perm[idx[k]] = idx[(-k) % 8]
    for prefix in ("grid_log_y", "grid_log_r_over_g", "grid_log_b_over_g"):
        for r in range(4):
            for c in range(4):
                perm[FEATURE_NAMES.index(f"{prefix}{r}{c}")] = FEATURE_NAMES.index(f"{prefix}{r}{3 - c}")
    for ch in "Lab":
        for r in range(3):
            for c in range(8):
                perm[FEATURE_NAMES.index(f"sky_lab_{ch}_{r}{c}")] = FEATURE_NAMES.index(f"sky_lab_{ch}_{r}{7 - c}")
    for q in (10, 50, 90):
        left, right = FEATURE_NAMES.index(f"left_wall_log_y_q{q}"), FEATURE_NAMES.index(f"right_wall_log_y_q{q}")
        perm[left], perm[right] = right, left
    for name in FEATURE_NAMES:  # lines slanted one way (╱) mirror into the other (╲)
        if name.startswith("ridge_slash_"):
            slash, backslash = FEATURE_NAMES.index(name), FEATURE_NAMES.index(name.replace("slash", "backslash"))
            perm[slash], perm[backslash] = backslash, slash
    np.testing.assert_allclose(g, f[:, perm], rtol=1e-3, atol=2e-3)
    # the backbone's own permutation (derived from the feature names) is this one, and mirrors its cached features
    assert b.mirror_index() == tuple(perm.tolist())
    np.testing.assert_allclose(b.mirror_inputs(torch.from_numpy(f)).numpy(), g, rtol=1e-3, atol=2e-3)


def test_cues_see_synthetic_haze(textures: np.ndarray) -> None:
    """Koschmieder haze I = J t + A (1 − t) lifts the dark channel and lowers contrast and transmission."""
    b = get_backbone("cues")
    j = textures.astype(np.float64)
    hazy = np.clip(j * 0.4 + 220.0 * 0.6, 0, 255).astype(np.uint8)
    f, g = b.extract(textures), b.extract(hazy)
    col = FEATURE_NAMES.index
    assert (g[:, col("dark_mean")] > f[:, col("dark_mean")]).all()
    assert (g[:, col("transmission")] < f[:, col("transmission")]).all()
    for i in range(8):
        assert (g[:, col(f"contrast_row{i}")] < f[:, col(f"contrast_row{i}")]).all()
    assert (g[:, col("edge_log_energy")] < f[:, col("edge_log_energy")]).all()


def test_cues_orientation_of_streaks() -> None:
    """Vertical stripes fill bin 0; stripes slanted by ±45° fill bins 2 and 6."""
    yy, xx = np.mgrid[0:128, 0:128]
    stripes = [127 + 100 * np.sin(0.6 * xx), 127 + 100 * np.sin(0.4 * (xx + yy)), 127 + 100 * np.sin(0.4 * (xx - yy))]
    images = np.stack([np.repeat(s[..., None], 3, axis=2) for s in stripes]).astype(np.uint8)
    f = get_backbone("cues").extract(images)
    hist = f[:, [FEATURE_NAMES.index(f"edge_hist{k}") for k in range(8)]]
    assert hist[0, 0] > 0.95 and max(hist[1, 2], hist[1, 6]) > 0.9 and max(hist[2, 2], hist[2, 6]) > 0.9
    assert np.argmax(hist[1]) != np.argmax(hist[2])  # the sign of the slant is kept


def test_cues_respond_to_rendered_weather(renders: dict[str, np.ndarray]) -> None:
    b = get_backbone("cues")
    clear, fog, night = (b.extract(renders[k]) for k in ("clear", "fog", "night"))
    col = FEATURE_NAMES.index
    assert (fog[:, col("edge_log_energy")] < clear[:, col("edge_log_energy")]).all()  # fog erases detail
    assert (fog[:, col("contrast_row3")] < clear[:, col("contrast_row3")]).all()
    assert (night[:, col("v_q50")] < clear[:, col("v_q50")]).all()  # night is dark
    assert (night[:, col("v_hist0")] > clear[:, col("v_hist0")] + 0.05).all()


def test_cues_see_rendered_rain_streaks_and_puddles(renders: dict[str, np.ndarray]) -> None:
    """Version 3: rain streaks add thin vertical lines; puddles (deposits 90 %) darken the road under a mirror of the
    sky, so fewer of its pixels are as blue as the sky — in each of the four scenes."""
    b = get_backbone("cues")
    clear, rain, wet = (b.extract(renders[k]) for k in ("clear", "rain", "wet"))
    col = FEATURE_NAMES.index
    assert (rain[:, col("ridge_vertical_frac0.005")] > clear[:, col("ridge_vertical_frac0.005")]).all()
    assert (wet[:, col("puddle_mid_sky_blue_frac")] < clear[:, col("puddle_mid_sky_blue_frac")] - 0.04).all()


def test_cues_ridges_find_thin_lines_by_direction() -> None:
    """One-pixel bright lines on grey: vertical ones answer the vertical detector most, ╱ ones the slash detector."""
    grey = np.full((2, 128, 128, 3), 60, np.uint8)
    grey[0, :, ::8] = 200  # vertical lines every 8 columns
    for i in range(128):
        grey[1, i, [(c - i) % 128 for c in range(0, 128, 8)]] = 200  # ╱: column falls as the row rises
    f = get_backbone("cues").extract(grey)
    col = FEATURE_NAMES.index
    vertical, slash, backslash = (f[:, col(f"ridge_{d}_log_mean")] for d in ("vertical", "slash", "backslash"))
    # along its own line a detector averages the full contrast; across another, one pixel in five
    assert vertical[0] > max(slash[0], backslash[0]) + 1.0 and slash[1] > max(vertical[1], backslash[1]) + 1.0


# -- tiny -----------------------------------------------------------------------------------------------
def test_tiny_lab_of_uniform_images() -> None:
    """White → L* = 100, black → L* = 0, neutral → a* = b* = 0, uniform → zero contrast."""
    images = np.stack([np.full((128, 128, 3), v, np.uint8) for v in (255, 0, 119)])
    f = get_backbone("tiny").extract(images).reshape(3, 4, 64)
    np.testing.assert_allclose(f[0, 0], 1.0, atol=1e-3)
    np.testing.assert_allclose(f[1, 0], 0.0, atol=1e-3)
    np.testing.assert_allclose(f[2, 0], 0.50, atol=0.01)  # sRGB 119 ≈ L* 50
    np.testing.assert_allclose(f[:, 1:3], 0.0, atol=1e-3)
    np.testing.assert_allclose(f[:, 3], 0.0, atol=1e-3)


def test_tiny_mirror_reverses_cell_columns(textures: np.ndarray) -> None:
    b = get_backbone("tiny", grid=8)
    f = b.extract(textures).reshape(-1, 4, 8, 8)
    g = b.extract(np.ascontiguousarray(textures[:, :, ::-1])).reshape(-1, 4, 8, 8)
    np.testing.assert_allclose(g, f[..., ::-1], rtol=1e-4, atol=1e-4)
    mirrored = b.mirror_inputs(torch.from_numpy(f.reshape(len(f), -1))).numpy()
    np.testing.assert_allclose(mirrored, g.reshape(len(g), -1), rtol=1e-4, atol=1e-4)


def test_mirror_inputs_flip_a_trainable_backbones_images_and_refuse_what_cannot_mirror(textures: np.ndarray) -> None:
    cnn = get_backbone("cnn")
    with warnings.catch_warnings():
        # the announced 128 → 64 conversion (area interpolation: it commutes with a flip)
        warnings.simplefilter("ignore")
        x, mirrored = cnn.preprocess(textures), cnn.preprocess(textures[:, :, ::-1].copy())
    np.testing.assert_array_equal(cnn.mirror_inputs(x).numpy(), mirrored.numpy())
    with pytest.raises(ValueError, match="expects model inputs"):
        cnn.mirror_inputs(x.flatten(1))
    with pytest.raises(ValueError, match=r"expects features \(n, 377\)"):
        get_backbone("cues").mirror_inputs(torch.zeros(2, 7))

    class Opaque(Backbone):  # frozen features with no known symmetry (as a pretrained network's)
        name = "opaque"
        dim = 3

    with pytest.raises(ValueError, match="'opaque'.*train.mirror: false"):
        Opaque().mirror_inputs(torch.zeros(2, 3))


def test_tiny_respond_to_rendered_weather(renders: dict[str, np.ndarray]) -> None:
    b = get_backbone("tiny")
    clear, fog, night = (b.extract(renders[k]).reshape(-1, 4, 8, 8) for k in ("clear", "fog", "night"))
    assert (night[:, 0, :2].mean((1, 2)) < clear[:, 0, :2].mean((1, 2)) - 0.2).all()  # sky L* drops
    assert (fog[:, 3].mean((1, 2)) < clear[:, 3].mean((1, 2))).all()  # fog lowers local contrast


def test_tiny_fingerprint_depends_on_grid() -> None:
    assert get_backbone("tiny", grid=8).fingerprint() == get_backbone("tiny").fingerprint()
    assert get_backbone("tiny", grid=12).fingerprint() != get_backbone("tiny").fingerprint()
    assert get_backbone("tiny", grid=12).dim == 4 * 144


# -- cnn ------------------------------------------------------------------------------------------------
def test_cnn_seeded_init() -> None:
    a, b, c = (get_backbone("cnn", seed=s) for s in (3, 3, 4))
    for (k, ta), tb in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        torch.testing.assert_close(ta, tb, rtol=0, atol=0, msg=k)
    assert a.fingerprint() == b.fingerprint() != c.fingerprint()
    assert not torch.equal(a.head.weight, c.head.weight)
    assert a.dim == 64 and get_backbone("cnn", dim=128).dim == 128


def test_cnn_trains_jointly_and_fingerprint_follows_weights(renders: dict[str, np.ndarray]) -> None:
    """A few gradient steps through cnn + linear head separate fog from clear: the embedding is trainable."""
    cnn = _quiet("cnn", seed=1)
    assert cnn.trainable and all(p.requires_grad for p in cnn.parameters())
    before = cnn.fingerprint()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        x = torch.cat([cnn.preprocess(renders["clear"]), cnn.preprocess(renders["fog"])])
    y = torch.tensor([0.0] * 4 + [1.0] * 4)
    gen = torch.Generator().manual_seed(seeding.derive_seed(SEED, "test", "head"))
    head = torch.nn.Linear(cnn.dim, 1)
    torch.nn.init.normal_(head.weight, std=0.01, generator=gen)
    torch.nn.init.zeros_(head.bias)
    opt = torch.optim.Adam([*cnn.parameters(), *head.parameters()], lr=3e-3)
    losses = []
    for _ in range(15):
        loss = torch.nn.functional.binary_cross_entropy_with_logits(head(cnn(x)).squeeze(1), y)
        opt.zero_grad()
        loss.backward()
        assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in cnn.parameters())
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
    assert cnn.fingerprint() != before


def test_cnn_rejects_wrong_tensor_size() -> None:
    with pytest.raises(ValueError, match=r"\(n, 3, 64, 64\).*preprocess"):
        get_backbone("cnn")(torch.zeros(1, 3, 128, 128))


def test_extract_restores_training_mode(textures: np.ndarray) -> None:
    cnn = _quiet("cnn")
    cnn.train()
    _extract(cnn, textures[:2])
    assert cnn.training


def test_every_frozen_network_file_is_package_data():
    """The frozen networks' weights and cards ship with a non-editable install: pyproject lists each of them."""
    import tomllib

    from components.core.config import PROJECT_ROOT

    folder = PROJECT_ROOT / "components" / "features" / "backbones"
    shipped = {f.name for f in folder.iterdir() if f.suffix in {".pt", ".json"}}
    listed = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert {"wet_road.pt", "weather_reader.pt", "weather_reader_sun.pt"} <= shipped
    assert shipped == set(listed["components.features.backbones"])
