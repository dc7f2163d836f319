"""Named weathers (components/evaluate/named.py, the evaluate stage's part): a correct posterior's cells stay inside
a correct model's range, a wrong one's fall out; the weathers, scenes and recorded folders as ``evaluate.named``
names them; bad folders named."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from components.core import presets, seeding, weather
from components.core.weather import Box
from components.evaluate import named
from components.evaluate.local import posterior_summary
from tests.conftest import write_params

BOX = weather.Box.from_mapping({})  # the physical ranges: the default prior


def _truths(g: np.random.Generator, k: int) -> np.ndarray:
    """k named-weather truths: each parameter on its lower face, its upper face or inside, at random."""
    inside = g.uniform(BOX.low, BOX.high, (k, BOX.dim))
    face = g.integers(0, 3, (k, BOX.dim))
    return np.where(face == 0, BOX.low, np.where(face == 1, BOX.high, inside))


def _rows(scale: float, seed: int, k: int = 20, n: int = 48) -> list[dict]:
    """k weathers of n images each, θ ~ their truth, x = θ + σ·ε, characterized by the exact truncated posterior with
    its scale × σ (1: correct; < 1: overconfident)."""
    g = np.random.default_rng(seed)
    sigma = 0.06 * BOX.width
    rows = []
    for i, t in enumerate(_truths(g, k)):
        truth = np.broadcast_to(t, (n, BOX.dim)).copy()
        x = truth + sigma * g.standard_normal(truth.shape)
        draws = named.exact_truncated_draws(x, scale * sigma, BOX, 500, g)
        s = named.NamedSet(f"w{i}", "own", truth, np.zeros((n, 1, 1, 3), np.uint8))
        rows.append(named.weather_row(s, draws, BOX, 0.5, 480, np.random.default_rng(seed + 1000 + i)))
    return rows


def _flagged(rows: list[dict]) -> tuple[float, float]:
    cells = [c for r in rows for c in r["parameters"].values()]
    return np.mean([c["below"] for c in cells]), np.mean([c["above"] for c in cells])


def test_a_correct_posterior_stays_inside_a_correct_models_range():
    """The exact posterior at 20 boundary-heavy weathers × 6 parameters: its 68 % coverage is outside the 95 % range
    of a correct model's in about 5 % of the 120 cells (binomial: ≤ 12 % with probability > 0.99), and the pooled
    coverage is near the toy's."""
    below, above = _flagged(_rows(1.0, 0))
    assert below + above <= 0.12
    pooled = named.pooled(_rows(1.0, 1), BOX)["parameters"]
    for p in pooled.values():
        assert abs(p["coverage68"] - p["toy68"]) < 0.08
        assert p["ci68"][0] <= p["coverage68"] <= p["ci68"][1]


def test_an_overconfident_posterior_falls_below_the_range():
    """Half the right width: the HDIs cover far less than a correct model's, in most cells (the faces aside, where
    the tolerance covers a truth however narrow the interval)."""
    below, above = _flagged(_rows(0.5, 2))
    assert below >= 0.4
    assert above <= 0.05


def test_the_toy_is_a_truncated_normal_inside_the_box():
    g = np.random.default_rng(3)
    x = np.array([[BOX.low[0] - 5.0, *((BOX.low + BOX.high)[1:] / 2)]])
    sigma = np.full(BOX.dim, 4.0)
    d = named.exact_truncated_draws(x, sigma, BOX, 20000, g)[0]
    assert np.all((d >= BOX.low) & (d <= BOX.high))
    from scipy.stats import truncnorm

    a, b = (BOX.low[0] - x[0, 0]) / 4.0, (BOX.high[0] - x[0, 0]) / 4.0
    assert abs(d[:, 0].mean() - truncnorm.mean(a, b, loc=x[0, 0], scale=4.0)) < 0.1
    assert abs(d[:, 2].mean() - x[0, 2]) < 0.1


def test_the_weathers_are_carlas_presets_and_ones_own():
    own = {"mine": {p: 0.0 for p in weather.PREDICTED}}
    w = named.named_weathers("carla", own)
    assert list(w)[: len(presets.USABLE)] == list(presets.USABLE) and list(w)[-1] == "mine"
    assert w["ClearNoon"] == ("preset", presets.preset_weather("ClearNoon"))
    kind, full = w["mine"]
    assert kind == "own" and full["sun_azimuth_angle"] == presets.PRESET_SUN_AZIMUTH and len(full) == 13
    assert list(named.named_weathers("none", own)) == ["mine"]


def test_the_scenes_are_new_and_distinct():
    seeds = named.scene_seeds(2026, "ClearNoon", 24)
    assert len(set(seeds)) == 24 and seeds == named.scene_seeds(2026, "ClearNoon", 24)
    named.check_new_scenes({1, 2, 3}, 2026, ["ClearNoon", "mine"], 24)
    with pytest.raises(ValueError, match="1 scene seeds of the named weathers are the dataset's"):
        named.check_new_scenes({seeds[5]}, 2026, ["ClearNoon"], 24)


def _local(seed: int, shift: float) -> dict:
    """The tests of :func:`named.fit_local_tests` on a conjugate Gaussian (θ ~ N(0, I₂), x = θ + ε, p(θ | x) =
    N(x/2, ½ I)) with q = p shifted by ``shift`` posterior sds in parameter ``a``, at 60 observations."""
    g = seeding.rng(seed, "test", "named-lc2st")
    box = Box(np.full(2, -8.0), np.full(2, 8.0), names=("a", "b"))
    off = np.array([shift * np.sqrt(0.5), 0.0])
    q = lambda x, m: x[:, None, :] / 2 + off + np.sqrt(0.5) * g.standard_normal((len(x), m, 2))  # noqa: E731
    theta = g.standard_normal((600, 2))
    x = theta + g.standard_normal((600, 2))
    tests = named.fit_local_tests(
        theta, posterior_summary(q(x, 16), box), q(x, 1)[:, 0], box, steps=60, null_trials=19, seed=seed + 100
    )
    xo = g.standard_normal((60, 2)) * np.sqrt(2)
    return named.local_rejections(tests, posterior_summary(q(xo, 16), box), q(xo, 100), 0.05)


def test_the_local_test_keeps_its_level_at_a_right_posterior():
    """The exact posterior, 8 problems of new seeds (the data and the classifiers' seeds), joint and per-parameter
    tests of 60 observations each: the sets' p-values are exact, so at most 5 of the 24 lie at ≤ 0.05
    (Binomial(24, 0.05): P(≥ 6) ≈ 0.001)."""
    p = []
    for seed in range(8):
        out = _local(seed, 0.0)
        assert list(out) == ["joint", "a", "b"]
        assert all(0.0 <= r["null_range"][0] <= r["null_range"][1] <= 1.0 for r in out.values())
        p += [r["p_value"] for r in out.values()]
    assert sum(v <= 0.05 for v in p) <= 5


def test_the_local_test_names_the_shifted_parameter():
    """q shifted by one posterior sd in ``a`` only: the joint and ``a``'s tests reject (p ≤ 0.05) in at least 3 of 4
    problems, ``b``'s in at most 1 (each rejects a right marginal with probability 0.05)."""
    out = [_local(seed, 1.0) for seed in range(20, 24)]
    assert sum(o["a"]["p_value"] <= 0.05 for o in out) >= 3
    assert sum(o["joint"]["p_value"] <= 0.05 for o in out) >= 3
    assert sum(o["b"]["p_value"] <= 0.05 for o in out) <= 1


def test_a_recorded_folder_is_a_named_weather(tmp_path: Path):
    """A folder of 64-pixel renders against a 32-pixel project: area-resized, its labels the truths; a folder whose
    labels name a missing image fails naming the file and the row."""
    from components.core.config import load_params
    from components.core.paths import ProjectPaths
    from components.evaluate.evaluation import _named_sets

    folder = tmp_path / "dry"
    from components.simulate.procedural import ProceduralSimulator

    sim, theta = ProceduralSimulator(64, 64), []
    folder.mkdir()
    from PIL import Image

    for i in range(3):
        t = np.array([10.0, 0.0, 0.0, 40.0 + i, 5.0, 0.0])
        Image.fromarray(sim.render(weather.weather_from_theta(t, 0.0), 11 + i)).save(folder / f"{i}.png")
        theta.append(t)
    lines = ["image," + ",".join(weather.PREDICTED)] + [
        f"{i}.png," + ",".join(map(str, t.tolist())) for i, t in enumerate(theta)
    ]
    (folder / "labels.csv").write_text("\n".join(lines) + "\n")
    params_file = write_params(tmp_path)
    params = load_params(params_file)
    params = params.model_copy(
        update={
            "evaluate": params.evaluate.model_copy(
                update={"named": params.evaluate.named.model_copy(update={"weathers": {}, "folders": {"dry": "dry"}})}
            )
        }
    )
    sets, note = _named_sets(params, ProjectPaths.of(params, params_file))
    assert note is None and [s.name for s in sets] == ["dry"]
    assert sets[0].kind == "recorded" and sets[0].images.shape == (3, 32, 32, 3)
    np.testing.assert_allclose(sets[0].truth, np.array(theta))
    (folder / "1.png").unlink()
    from components.simulate.labels import RecordedError

    with pytest.raises(RecordedError, match=r"1\.png.*labels\.csv"):
        _named_sets(params, ProjectPaths.of(params, params_file))


def test_the_heatmap_draws_every_cell(tmp_path: Path):
    from components import plots

    rows = _rows(0.5, 4, k=3, n=24)
    for r in rows:
        r["lc2st"] = {p: {"p_value": 0.5 if j else 0.01} for j, p in enumerate(BOX.names)}
    fig = plots.named_heatmap(rows, 0.05, "test")
    texts = [t.get_text() for ax in fig.axes[:2] for t in ax.texts]
    assert len(texts) == 2 * 3 * BOX.dim and any(t.endswith("−") for t in texts)
    plots.save_figure(fig, tmp_path / "named.png")
    assert (tmp_path / "named.png").stat().st_size > 10_000


def test_a_recorded_folders_fingerprint_follows_its_files(tmp_path):
    """The evaluation's key holds each recorded named weather's folder by content: an image changed, added or renamed
    changes it; nothing else does; a missing folder has none."""
    folder = tmp_path / "depot"
    folder.mkdir()
    (folder / "labels.csv").write_text("file\na.png\n")
    (folder / "a.png").write_bytes(b"one")
    first = named.folder_fingerprint(folder)
    assert first == named.folder_fingerprint(folder) and len(first) == 64
    (folder / "a.png").write_bytes(b"two")
    second = named.folder_fingerprint(folder)
    (folder / "a.png").rename(folder / "b.png")
    third = named.folder_fingerprint(folder)
    assert len({first, second, third}) == 3
    assert named.folder_fingerprint(tmp_path / "missing") is None
