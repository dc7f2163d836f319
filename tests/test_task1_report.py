"""Task I per model: the draws of the evaluation on an exported posterior, the flat metrics rows, the results table
and the Task I figures (per-parameter heat-maps, the coverage plot with its calibration band)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from matplotlib.image import imread

from components import plots
from components.core import seeding, weather
from components.evaluate import marginals, report, task1
from components.export.onnx import export_posterior
from components.export.runtime import OnnxPosterior
from components.posterior.model import NPE, FlowConfig

BOX = weather.Box.full()


@pytest.fixture(scope="module")
def ensemble(tmp_path_factory) -> OnnxPosterior:
    """A small coupling-flow ensemble of two (random weights) on 12 features, exported and loaded back."""
    model = NPE(None, 12, BOX, FlowConfig(transforms=1, hidden_features=(16,), bins=4, ensemble=2), seed=5)
    rng = seeding.rng(5, "test", "standardization")
    model.fit_standardization(torch.as_tensor(rng.normal(0.0, 1.0, (64, 12)), dtype=torch.float32))
    folder = tmp_path_factory.mktemp("registry") / "tiny"
    export_posterior(model.eval(), folder, card={"backbone": "cues", "train_size": 8}, exporter="torchscript")
    return OnnxPosterior.load(folder)


def test_draws_depend_on_the_image_index_only_and_match_the_densities(ensemble):
    rng = seeding.rng(0, "test", "draws")
    x = rng.normal(size=(9, 12)).astype(np.float32)
    truth = BOX.sample(rng, 9)
    samples, lp, lp_truth = task1.posterior_draws(ensemble, x, truth, 50, seed=11, chunk=4, context_chunk=5)
    again = task1.posterior_draws(ensemble, x, truth, 50, seed=11, chunk=7, context_chunk=2)
    for a, b in zip((samples, lp, lp_truth), again, strict=True):
        np.testing.assert_array_equal(a, b)  # the chunking is a matter of speed only
    head = task1.posterior_draws(ensemble, x[:3], truth[:3], 50, seed=11)
    np.testing.assert_array_equal(head[0], samples[:3])  # evaluating fewer images keeps the first ones' draws
    assert not np.array_equal(task1.posterior_draws(ensemble, x, truth, 50, seed=12)[0], samples)
    assert samples.shape == (9, 50, 6) and BOX.contains(samples).all()
    # every draw's log-density is the posterior's, to float32 rounding: the flows run in float32, whose spacing at
    # |log q| ∈ [32, 64) is 3.8e-6; measured max |lp − log_prob| 3.8e-6 here and 7.6e-6 over 61 seeds (27 450
    # draws), so 8e-5 is a 10× margin. The one exception, by design: a draw within EDGE_EPS·width of a face of the
    # box (|z| > 13.8155, here 1 of 450; 45 of 27 450 over the 61 seeds) carries the density of its own z, while
    # log_prob takes the density at the point clipped onto that margin (the two differed by up to 1.5 nats); such
    # draws must stay rare (< 1 %) for the exemption not to hollow the check out.
    dense = ensemble.log_prob(samples, x)
    u = (samples - BOX.low) / BOX.width
    edge = np.any((u < weather.EDGE_EPS) | (u > 1 - weather.EDGE_EPS), axis=-1)
    assert np.abs(lp - dense)[~edge].max() < 8e-5, np.abs(lp - dense)[~edge].max()
    assert edge.mean() < 0.01, edge.sum()
    clipped = BOX.low + BOX.width * np.clip(u, weather.EDGE_EPS, 1 - weather.EDGE_EPS)
    np.testing.assert_allclose(dense[edge], ensemble.log_prob(clipped, x)[edge], rtol=0, atol=1e-6)
    np.testing.assert_allclose(lp_truth, ensemble.log_prob(truth, x), atol=1e-9)
    with pytest.raises(ValueError, match=r"theta must have shape \(9, 6\)"):
        task1.posterior_draws(ensemble, x, truth[:4], 50, seed=11)


def test_images_evaluated_and_the_order_of_the_work():
    assert task1.images_evaluated("all", 2000) == 2000 and task1.images_evaluated(500, 2000) == 500
    with pytest.raises(ValueError, match="evaluate.images is 2001 but the test split has only 2000"):
        task1.images_evaluated(2001, 2000)
    with pytest.raises(ValueError, match="positive integer or 'all'"):
        task1.images_evaluated("most", 2000)
    cards = {"a-1": {"ensemble": 1, "features": 80}, "cnn-1": {"ensemble": 1, "features": 256}, "e": {"ensemble": 3}}
    assert task1.evaluation_order(["a-1", "cnn-1", "e"], cards) == ["e", "cnn-1", "a-1"]


def _report(seed: int, n: int = 200) -> dict:
    rng = seeding.rng(seed, "test", "report")
    truth = BOX.sample(rng, n)
    draws = np.clip(truth[:, None, :] + rng.normal(size=(n, 400, 6)) * BOX.width / (10 + seed), BOX.low, BOX.high)
    return marginals.parameter_report(draws, truth, BOX)


def _metrics(error: float, nll: float) -> dict:
    return {
        "calibration_error": error,
        "calibration_band": 0.03,
        "within_band": error <= 0.03,
        "coverage_auc_gap": -0.01,
        "pi_median": 0.48,
        "test_nll": nll,
        "test_nll_se": 0.05,
        "info_gain_nats": 3.2,
        "images": 200,
        "samples": 400,
        "ppc_score": 0.9,
    }


def test_one_flat_row_per_model_with_the_same_keys_and_the_results_table():
    rows = {
        "cues-1000": report.model_row(_metrics(0.02, 23.0), _report(1)),
        "cnn-3000": report.model_row(_metrics(0.08, 21.5) | {"extra": 1.0}, _report(2)),
    }
    keys = [list(r) for r in rows.values()]
    assert keys[0] == keys[1] and keys[0][: len(report.HEADLINE)] == list(report.HEADLINE)
    assert {"err_day_cloud", "err_night_sun", "err_night_deposit"} <= set(keys[0]) and len(keys[0]) == 11 + 12 + 7
    night = _report(2)["night"]
    assert rows["cnn-3000"]["night_images"] == night["fog_density"]["images"]
    assert rows["cnn-3000"]["cov68_night_fog"] == night["fog_density"]["coverage68"]
    assert rows["cnn-3000"]["err_day_fog"] == _report(2)["day"]["fog_density"]["median_abs_error"]
    with pytest.raises(KeyError, match="lack calibration_band"):
        report.model_row({k: v for k, v in _metrics(0.02, 23.0).items() if k != "calibration_band"}, _report(1))

    table = report.results_table(rows, champion="cues-1000").splitlines()
    assert len(table) == 2 + 2 and table[0].startswith("| model | calibration error | band (95 %) | within band")
    assert table[2].startswith("| **cues-1000** (champion) | 0.020 | 0.030 | yes | 23.00 |")
    assert table[3].startswith("| cnn-3000 | 0.080 | 0.030 | no | 21.50 | 3.20 ± 0.05 | 0.48 | −0.010 |")
    assert all(line.count("|") == table[0].count("|") for line in table)
    # the lowest night coverage, its parameter and its interval (the report's own Clopper–Pearson bounds)
    lowest = min(weather.PREDICTED, key=lambda p: night[p]["coverage68"])
    fig, short = night[lowest], weather.SHORT_NAMES[weather.PREDICTED.index(lowest)]
    cell = f"{short} {100 * fig['coverage68']:.1f} [{100 * fig['coverage68_low']:.1f}, {100 * fig['coverage68_high']:.1f}] |"
    assert table[3].endswith(cell), (table[3], cell)


def test_parameter_heatmaps_and_coverage_band_are_pngs_with_content(tmp_path):
    figures = {"cues-1000": _report(1), "cnn-3000": _report(3), "cues-10000-ensemble": _report(5)}
    path = plots.save_figure(plots.parameter_heatmaps(figures, box=BOX), tmp_path / "parameters.png", dpi=60)
    image = imread(path)[..., :3]
    assert image.shape[1] > image.shape[0] > 150 and image.std() > 0.05
    lv = np.linspace(0, 1, 21)
    fig = plots.coverage_plot({"a-1": (lv, lv**1.2), "b-1": (lv, lv)}, band=0.05, band_label="95 % band, 500 images")
    assert "95 % band, 500 images\n(±0.050)" in [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert imread(plots.save_figure(fig, tmp_path / "coverage.png", dpi=60)).std() > 0.05
    with pytest.raises(ValueError, match="band must be a half-width"):
        plots.coverage_plot({"a-1": (lv, lv)}, band=1.5)
    del figures["cnn-3000"]["night"]["precipitation"]["coverage95"]
    with pytest.raises(
        ValueError, match=r"report\['cnn-3000'\]\['night'\]\['precipitation'\] lacks a number 'coverage95'"
    ):
        plots.parameter_heatmaps(figures)
