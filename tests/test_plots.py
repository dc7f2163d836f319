"""The figures: HDR thresholds against analytic Gaussian values, the numbers behind the plots, PNG files, bad inputs."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from components import plots
from components.core.seeding import rng
from components.core.weather import Box
from components.evaluate.diagnostics import roc_curve

LEVELS = (0.6827, 0.9545, 0.9973)
LOG_2PI = math.log(2 * math.pi)


# --- analytic χ² distributions (closed forms, no scipy) ------------------------------------------------------


def chi2_6_cdf(x: float) -> float:
    """P(χ²₆ ≤ x) = 1 − e^{−x/2} (1 + x/2 + x²/8)."""
    return 1.0 - math.exp(-x / 2) * (1 + x / 2 + x * x / 8)


def chi2_6_pdf(x: float) -> float:
    return x * x * math.exp(-x / 2) / 16.0


def chi2_5_cdf(x: float) -> float:
    """P(χ²₅ ≤ x) = erf(√(x/2)) − √(2x/π) e^{−x/2} (1 + x/3)."""
    if x <= 0:
        return 0.0
    return math.erf(math.sqrt(x / 2)) - math.sqrt(2 * x / math.pi) * math.exp(-x / 2) * (1 + x / 3)


def chi2_6_quantile(level: float) -> float:
    lo, hi = 0.0, 200.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if chi2_6_cdf(mid) < level else (lo, mid)
    return 0.5 * (lo + hi)


def standard_normal_6d(n: int, *keys: str) -> tuple[np.ndarray, np.ndarray]:
    z = rng(7, "test_plots", *keys).standard_normal((n, 6))
    return z, -3 * LOG_2PI - 0.5 * (z**2).sum(axis=1)


def test_chi2_helpers_match_known_quantiles():
    # the 68.27/95.45/99.73 % quantiles of χ²₆ (tabulated: 7.0385, 12.8489, 20.0619)
    assert [round(chi2_6_quantile(a), 3) for a in LEVELS] == [7.039, 12.849, 20.062]


# --- hdr_log_threshold -----------------------------------------------------------------------------------


@pytest.mark.parametrize("level", LEVELS)
def test_hdr_threshold_matches_chi2_for_a_6d_standard_normal(level):
    # q = N(0, I₆): log q = −3 log 2π − r²/2 with r² ~ χ²₆, so t_α = −3 log 2π − χ²₆⁻¹(α)/2.
    n = 200_000
    _, lp = standard_normal_6d(n, "threshold")
    q = chi2_6_quantile(level)
    expected = -3 * LOG_2PI - q / 2
    # MC tolerance: 5 standard deviations of the sample α-quantile of r², sd = √(α(1−α)/n) / f(q), halved for t
    tol = 5 * math.sqrt(level * (1 - level) / n) / chi2_6_pdf(q) / 2
    got = plots.hdr_log_threshold(lp, level)
    assert abs(got - expected) < tol, (got, expected, tol)
    assert abs(plots.in_hdr(lp, level).mean() - level) < 1e-4


@pytest.mark.parametrize("level", [0.0, 1.0, -0.2, 1.5, float("nan")])
def test_hdr_threshold_rejects_levels_outside_the_open_unit_interval(level):
    with pytest.raises(ValueError, match=r"strictly inside \(0, 1\)"):
        plots.hdr_log_threshold(np.zeros(1000), level)


def test_hdr_threshold_needs_enough_samples_and_a_clean_1d_array():
    _, lp = standard_normal_6d(371, "few")
    plots.hdr_log_threshold(lp, 0.9973)  # ⌈1/0.0027⌉ = 371 is enough
    with pytest.raises(ValueError, match=r"needs at least 371 samples.*got 370"):
        plots.hdr_log_threshold(lp[:370], 0.9973)
    with pytest.raises(ValueError, match=r"shape \(n,\)"):
        plots.hdr_log_threshold(lp.reshape(7, 53), 0.5)
    with pytest.raises(ValueError, match="non-finite"):
        plots.hdr_log_threshold(np.r_[lp, np.nan], 0.5)


# --- the numbers behind the marginal histograms -----------------------------------------------------------


def test_marginal_hdr_mass_follows_the_gaussian_expectation():
    # θ = centre + scale·z, z ~ N(0, I₆). A sample is in the 6-D HDR at α iff |z|² ≤ c = χ²₆⁻¹(α), so the
    # HDR mass of the first marginal around x = z₁ has density φ(x)·P(χ²₅ ≤ c − x²).
    n, level, bins = 40_000, 0.6827, 20
    z, lp = standard_normal_6d(n, "marginal")
    centre, scale = np.array([50, 50, 50, 0, 50, 50.0]), np.array([12, 12, 12, 20, 12, 12.0])
    theta = centre + scale * z
    edges, inside, outside = plots.marginal_hdr_histograms(theta, lp - np.log(scale).sum(), level, Box.full(), bins)
    assert inside.shape == outside.shape == (6, bins) and len(edges) == 6
    in_box = Box.full().contains(theta)
    assert abs(inside.sum(axis=1).mean() - level) < 0.005
    assert np.allclose(
        (inside + outside).sum(axis=1),
        [
            np.mean((theta[:, k] >= 0) & (theta[:, k] <= 100)) if k != 3 else np.mean(np.abs(theta[:, 3]) <= 90)
            for k in range(6)
        ],
    )
    assert in_box.mean() > 0.99

    c = chi2_6_quantile(level)
    x = np.linspace(-5, 5, 20_001)
    phi = np.exp(-0.5 * x**2) / math.sqrt(2 * math.pi)
    f5 = np.array([chi2_5_cdf(c - v * v) for v in x])
    dens = phi * f5
    z_edges = (edges[0] - centre[0]) / scale[0]
    expected = np.array(
        [
            np.trapezoid(dens[(x >= a) & (x <= b)], x[(x >= a) & (x <= b)])
            for a, b in zip(z_edges[:-1], z_edges[1:], strict=False)
        ]
    )
    assert abs(expected.sum() - level) < 1e-3  # the formula itself integrates to α
    sd = np.sqrt(expected * (1 - expected) / n)
    assert np.all(np.abs(inside[0] - expected) <= 5 * sd + 2e-3), np.c_[inside[0], expected]
    # nothing outside |z₁| ≤ √c can be in the HDR
    centres = 0.5 * (z_edges[:-1] + z_edges[1:])
    assert np.all(inside[0][np.abs(centres) - 0.5 * np.diff(z_edges) > math.sqrt(c)] == 0)


def test_marginal_figure_draws_those_numbers(tmp_path):
    z, lp = standard_normal_6d(3000, "figure")
    theta = np.array([50, 50, 50, 0, 50, 50.0]) + 15 * z
    fig = plots.marginal_histograms(theta, lp, truth=theta[0], bins=25)
    edges, inside, _ = plots.marginal_hdr_histograms(theta, lp, 0.6827, None, 25)
    heights = np.array([p.get_height() for p in fig.axes[0].patches[:25]])
    assert np.allclose(heights, inside[0] / np.diff(edges[0]))
    plots.save_figure(fig, tmp_path / "m.png", dpi=60)


# --- 2-D marginals: mass-ordered grid thresholds ----------------------------------------------------------


@pytest.mark.parametrize("smooth", [0.0, 1.0])
def test_grid_hdr_regions_enclose_the_stated_mass_with_the_gaussian_area(smooth):
    # 2-D Gaussian with σ = (8, 5): its HDR at α is an ellipse of area π σx σy (−2 log(1 − α)).
    n = 100_000
    g = rng(7, "test_plots", "grid")
    x, y = 50 + 8 * g.standard_normal(n), 40 + 5 * g.standard_normal(n)
    xe, ye, mass = plots.grid_density(x, y, (0, 100), (0, 100), bins=100, smooth=smooth)
    assert abs(mass.sum() - 1) < 1e-9
    thresholds = plots.grid_hdr_thresholds(mass, LEVELS)
    assert np.all(np.diff(thresholds) < 0)
    cell = (xe[1] - xe[0]) * (ye[1] - ye[0])
    for level, t in zip(LEVELS, thresholds, strict=False):
        region = mass >= t
        # the smallest superlevel set reaching α: without the cells at the threshold it holds less than α
        assert mass[mass > t].sum() < level <= mass[region].sum()
        area = region.sum() * cell
        expected = math.pi * 8 * 5 * -2 * math.log(1 - level)
        assert abs(area / expected - 1) < 0.08 + 0.04 * smooth, (level, area, expected)


# --- ROC, styles, best epoch, zoom ranges -----------------------------------------------------------------


def test_roc_auc_is_the_mann_whitney_probability():
    g = rng(7, "test_plots", "roc")
    neg = np.round(g.normal(0, 1, 60), 1)  # rounding makes ties
    pos = np.round(g.normal(0.8, 1, 45), 1)
    fpr, tpr, auc = roc_curve(neg, pos)
    mw = np.mean(pos[:, None] > neg[None, :]) + 0.5 * np.mean(pos[:, None] == neg[None, :])
    assert abs(auc - mw) < 1e-12
    assert fpr[0] == tpr[0] == 0 and fpr[-1] == tpr[-1] == 1
    assert np.all(np.diff(fpr) >= 0) and np.all(np.diff(tpr) >= 0)
    assert roc_curve([0, 1, 2], [3, 4])[2] == 1.0
    assert roc_curve([1, 2, 3], [1, 2, 3])[2] == 0.5


def test_model_styles_colour_by_backbone_and_line_by_size():
    names = [f"{b}-{s}" for b in ("resnet", "dinov2", "clip") for s in ("500k", "5k", "50k")]
    st = plots.model_styles(names)
    assert st["resnet-5k"]["color"] == st["resnet-500k"]["color"] != st["clip-5k"]["color"]
    assert st["resnet-5k"]["linestyle"] == st["clip-5k"]["linestyle"] == "-"
    assert st["dinov2-500k"]["linestyle"] == ":"
    other = plots.model_styles([f"model {k}" for k in range(12)])
    assert len({(str(s["color"]), str(s["linestyle"])) for s in other.values()}) == 12


def test_best_epoch_is_the_lowest_validation_loss_ignoring_nan():
    assert plots.best_epoch({"train": [3, 2, 1, 0.5], "val": [3, 1.5, np.nan, 2]}) == ("val", 2)
    assert plots.best_epoch({"loss": [3, 2, 2.5]}) == ("loss", 2)


def test_zoomed_ranges_hold_the_samples_core_and_the_truth():
    z, lp = standard_normal_6d(4000, "zoom")
    theta = np.array([20, 50, 50, 0, 50, 80.0]) + 3 * z
    truth = np.array([40, 50, 50, 0, 50, 80.0])
    r = plots.corner_ranges(theta, lp, truth, zoom=True)
    full = plots.corner_ranges(theta, lp, truth, zoom=False)
    assert np.array_equal(full, np.stack([Box.full().low, Box.full().high], 1))
    assert np.all(r[:, 0] >= full[:, 0]) and np.all(r[:, 1] <= full[:, 1])
    assert np.all(r[:, 1] - r[:, 0] < 45)
    assert r[0, 0] < 20 - 3 * 2 and r[0, 1] >= 40  # widened to the ground truth
    core = theta[plots.in_hdr(lp, 0.9973)]
    assert np.all((core >= r[:, 0]) & (core <= r[:, 1]))


# --- every function writes a PNG that decodes, with content ------------------------------------------------


def _images(k, h=48, w=80, key="img"):
    g = rng(7, "test_plots", key)
    base = np.linspace(0, 255, w, dtype=np.float64)[None, :, None] * np.ones((k, h, 1, 3))
    return np.clip(base + g.normal(0, 20, base.shape), 0, 255).astype(np.uint8)


def _figures():
    z, lp = standard_normal_6d(1500, "png")
    theta = np.clip(np.array([30, 60, 20, 10, 50, 70.0]) + 10 * z, Box.full().low, Box.full().high)
    truth = theta[0]
    lv = np.linspace(0, 1, 21)
    etas = [0.0, 0.5, 1.0]
    g = rng(7, "test_plots", "values")
    return {
        "marginals": lambda: plots.marginal_histograms(theta, lp, truth),
        "corner": lambda: plots.corner_plot(theta, lp, truth, zoom=True, bins=25),
        "corner_compare": lambda: plots.corner_compare(theta, theta[::-1] + 5, ("true", "estimate"), bins=20),
        "coverage": lambda: plots.coverage_plot(
            {f"{b}-{s}": (lv, lv**p) for b in ("resnet", "clip") for s, p in (("5k", 0.7), ("50k", 1.3))}
        ),
        "superiority": lambda: plots.superiority_boxplot({"resnet-5k": g.random(50), "clip-5k": g.random(50) ** 2}),
        "ppc": lambda: plots.ppc_sheet(
            _images(1)[0], _images(3, key="post"), _images(2, key="prior"), {"posterior": [0.1, 0.2, 0.3]}
        ),
        "loss": lambda: plots.loss_curves({"train": [3, 2, 1.5, 1.2], "val": [3.1, 2.2, 2.0, 2.1]}),
        "grid": lambda: plots.image_grid(_images(5), 3, titles=list("abcde")),
        "by_level": lambda: plots.boxplots_by_level(
            {e: g.random(20) * (1 + e) for e in etas}, {e: g.random(20) + 2 for e in etas}, "η", "δ"
        ),
        "roc": lambda: plots.roc_curves({e: roc_curve(g.random(30), g.random(30) + e) for e in etas[1:]}),
        "roc_alarm": lambda: plots.roc_curves(
            {e: roc_curve(g.random(30), g.random(30) + e) for e in etas[1:]},
            operating_points={e: (0.05, min(1.0, 0.3 + e)) for e in etas[1:]},
            alpha=0.05,
        ),
        "marginals_overlay": lambda: plots.marginals_overlay(
            theta, theta[::-1] + 5, theta[::2], reference=theta + 10, notes=[f"W₁ {k}" for k in range(6)]
        ),
        "held_out": lambda: plots.held_out_curve(np.r_[-3.0, 0.0, 0.2, 0.3, 0.31, 0.30], 3),
        "relation": lambda: plots.relation_marginals(
            theta, [theta[::2], theta[1::2] + 5], [0.3, 0.7], ["a", "b"], notes=[f"W₁ {k}" for k in range(6)]
        ),
    }


@pytest.mark.parametrize("name", list(_figures()))
def test_every_figure_is_a_png_with_content(name, tmp_path):
    path = plots.save_figure(_figures()[name](), tmp_path / f"{name}.png", dpi=60)
    assert [p.name for p in tmp_path.iterdir()] == [f"{name}.png"]  # no temporary file left behind
    image = imread(path)
    assert image.ndim == 3 and image.shape[0] >= 150 and image.shape[1] >= 250, image.shape
    rgb = image[..., :3]
    assert rgb.std() > 0.02 and len(np.unique(rgb.reshape(-1, 3), axis=0)) > 20


def test_save_figure_rejects_unknown_formats_and_non_figures(tmp_path):
    fig = plots.new_figure(2, 2)
    with pytest.raises(ValueError, match="image format"):
        plots.save_figure(fig, tmp_path / "x.notaformat")
    with pytest.raises(TypeError, match="matplotlib Figure"):
        plots.save_figure("figure", tmp_path / "x.png")
    assert list(tmp_path.iterdir()) == []


def test_plots_neither_load_pyplot_nor_switch_backend_and_close_pyplot_figures(tmp_path):
    code = (
        "import sys, matplotlib; b = matplotlib.get_backend(); import components.plots as p; "
        "f = p.loss_curves({'val': [2.0, 1.0]}); "
        "print('matplotlib.pyplot' in sys.modules, b == matplotlib.get_backend()); "
        "import matplotlib.pyplot as plt; g = plt.figure(); g.add_subplot().plot([0, 1]); "
        f"p.save_figure(g, {str(tmp_path / 'g.png')!r}); print(plt.get_fignums() == [])"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={"MPLBACKEND": "svg", "PATH": ""},
        cwd=Path(__file__).resolve().parents[1],
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "True", "True"]
    assert (tmp_path / "g.png").stat().st_mode & 0o777 == 0o644


# --- bad inputs --------------------------------------------------------------------------------------------

_THETA = np.full((500, 6), 50.0) + np.arange(500)[:, None] % 7
_LP = -np.arange(500, dtype=float) / 100


@pytest.mark.parametrize(
    "call, error, message",
    [
        (lambda: plots.marginal_histograms(_THETA[:, :5], _LP), ValueError, r"samples must have shape \(n, 6\)"),
        (lambda: plots.marginal_histograms(_THETA, _LP[:-1]), ValueError, r"log_prob must have shape \(500,\)"),
        (
            lambda: plots.marginal_histograms(_THETA, _LP, truth=np.zeros(5)),
            ValueError,
            r"truth must have shape \(6,\)",
        ),
        (lambda: plots.marginal_histograms(_THETA, _LP, level=1.0), ValueError, r"strictly inside \(0, 1\)"),
        (lambda: plots.marginal_histograms(_THETA, _LP, box=(0, 1)), TypeError, "components.core.weather.Box"),
        (lambda: plots.corner_plot(_THETA, _LP, levels=(0.5, 1.2)), ValueError, r"strictly inside \(0, 1\)"),
        (lambda: plots.corner_plot(_THETA[:100], _LP[:100], zoom=True), ValueError, "needs at least 371 samples"),
        (
            lambda: plots.corner_plot(_THETA, reference_samples=np.zeros((4, 3))),
            ValueError,
            "reference_samples must have shape",
        ),
        (lambda: plots.coverage_plot({"m": (np.linspace(0, 1, 5), np.ones(4))}), ValueError, "one length"),
        (
            lambda: plots.coverage_plot({"m": (np.linspace(0, 1, 5), np.full(5, 1.5))}),
            ValueError,
            r"coverage must lie in \[0, 1\]",
        ),
        (lambda: plots.superiority_boxplot({"m": [0.2, 1.3]}), ValueError, r"pi\['m'\] must lie in \[0, 1\]"),
        (lambda: plots.superiority_boxplot({}), ValueError, "pi is empty"),
        (lambda: plots.ppc_sheet(_images(1)[0].astype(float), _images(2)), TypeError, "observed must be uint8"),
        (
            lambda: plots.ppc_sheet(_images(1)[0], _images(2)[0]),
            ValueError,
            r"posterior_renders must have shape \(k, H, W, 3\)",
        ),
        (
            lambda: plots.ppc_sheet(_images(1)[0], _images(2), distances=[1.0]),
            ValueError,
            r"distances\['posterior'\] must have shape \(2,\)",
        ),
        (lambda: plots.image_grid(_images(3), 2, titles=["a"]), ValueError, "one entry per image"),
        (lambda: plots.image_grid(_images(3), 0), ValueError, "ncols must be a positive integer"),
        (lambda: plots.loss_curves({"val": [np.nan, np.nan]}), ValueError, r"history\['val'\] has no finite value"),
        (lambda: plots.loss_curves({"val": [1.0, np.inf]}), ValueError, r"non-finite values \(only NaN is allowed\)"),
        (lambda: plots.corner_plot(_THETA, _LP[:10]), ValueError, r"log_prob must have shape \(500,\)"),
        (lambda: plots.boxplots_by_level({0.0: [1.0]}, {0.5: [1.0]}), ValueError, "baseline has level"),
        (lambda: roc_curve([0.1, np.inf], [1.0]), ValueError, "non-finite"),
        (lambda: plots.roc_curves({0.5: ([0.0, 1.0], [0.0], 0.5)}), ValueError, "one length"),
        (lambda: plots.roc_curves({}), ValueError, "non-empty mapping"),
        (
            lambda: plots.roc_curves({0.5: ([0.0, 1.0], [0.0, 1.0], 0.5)}, operating_points={0.4: (0.1, 0.2)}),
            ValueError,
            r"operating_points must have the curves' levels \[0.5\], got \[0.4\]",
        ),
        (lambda: plots.roc_curves({0.5: ([0.0, 1.0], [0.0, 1.0], 0.5)}, alpha=1.0), ValueError, "alpha must be"),
        (lambda: plots.held_out_curve(np.array([0.0, np.nan]), 1), ValueError, "held_out must be finite"),
        (lambda: plots.held_out_curve(np.zeros(4), 4), ValueError, r"steps must index held_out \(0…3\)"),
        (
            lambda: plots.marginals_overlay(_THETA, _THETA, _THETA, reference=_THETA[:, :5]),
            ValueError,
            r"reference must have shape \(n, 6\)",
        ),
        (
            lambda: plots.relation_marginals(_THETA, [_THETA], [0.5, 0.5], ["a"]),
            ValueError,
            r"weights must be 1 non-negative numbers",
        ),
        (lambda: plots.relation_marginals(_THETA, [_THETA], [1.0], ["a", "b"]), ValueError, "names must name every"),
    ],
)
def test_bad_inputs_give_clear_errors(call, error, message):
    with pytest.raises(error, match=message):
        call()


def test_model_styles_keep_the_grid_scheme_beside_variants():
    grid = ["cues-1000", "cues-10000", "cnn-1000", "cnn-10000"]
    alone = plots.model_styles(grid)
    styles = plots.model_styles(grid + ["cues-10000-balanced", "cues-10000-ensemble"])
    assert all(styles[n] == alone[n] for n in grid)
    a, b = styles["cues-10000-balanced"], styles["cues-10000-ensemble"]
    assert a["color"] != b["color"] and a["linewidth"] > 2 and a["color"] not in {s["color"] for s in alone.values()}
