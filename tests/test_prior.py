"""A user's own prior (components.domains.prior; `pidc characterize|domain|relate --prior FILE`).

The reweighting is tested on a problem whose posterior is known under both priors: a Gaussian likelihood on a bounded
box, whose posterior under the uniform training prior is a truncated normal, and under a truncated-normal user prior
the product of the two Gaussians, truncated. Then the ESS formula on known weights, a user prior equal to the training
prior (equal weights, the draws unchanged in distribution), the densities' normalization, the file's errors (one line
each), the training prior read from a model card, and the CLI on a small registry built here (as
tests/test_cli_registry.py builds one): a dry-world prior moves the precipitation of rainy images toward 0.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import integrate, stats

from components.cli.main import main
from components.core import seeding, weather
from components.domains.absolute import Domain
from components.domains.prior import (
    Mixture,
    PriorError,
    ReweightedPosterior,
    ScaledBeta,
    TruncatedNormal,
    Uniform,
    effective_sample_size,
    parse_prior,
    read_prior,
    resample,
    reweight,
    training_prior,
)
from tests import tiny_registry

DRY_WORLD = Path(__file__).resolve().parents[1] / "docs" / "examples" / "dry-world-prior.yaml"

# the toy: θ = (t0, t1) on [0, 10] × [−5, 5]; Gaussian likelihoods of widths S around the observation x
TOY = weather.Box(np.array([0.0, -5.0]), np.array([10.0, 5.0]), names=("t0", "t1"))
S = np.array([1.5, 1.0])


def truncated(mean: float, std: float, j: int) -> stats.rv_continuous:
    """N(mean, std²) truncated to the toy box's side j."""
    low, high = TOY.low[j], TOY.high[j]
    return stats.truncnorm((low - mean) / std, (high - mean) / std, loc=mean, scale=std)


class ToyPosterior:
    """The exact posterior under the uniform prior on TOY: p(θ | x) = Πⱼ N(θⱼ; xⱼ, Sⱼ²) truncated to the box
    (a Posterior: log_prob(θ, x), sample(x, n, seed))."""

    box = TOY
    card: dict = {}

    def sample(self, x: np.ndarray, n: int, seed: int) -> np.ndarray:
        r = seeding.rng(seed, "toy")
        out = np.empty((len(x), n, 2))
        for i, row in enumerate(np.asarray(x, dtype=np.float64)):
            for j in range(2):
                out[i, :, j] = truncated(row[j], S[j], j).rvs(n, random_state=r)
        return out

    def log_prob(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        return sum(
            stats.truncnorm.logpdf(
                theta[:, j],
                (TOY.low[j] - x[:, j]) / S[j],
                (TOY.high[j] - x[:, j]) / S[j],
                loc=x[:, j],
                scale=S[j],
            )
            for j in range(2)
        )


def product(x0: float, mean: float, std: float) -> stats.rv_continuous:
    """t0's exact posterior under the user prior N(mean, std²) truncated to [0, 10]: the product of the likelihood's
    Gaussian N(x0, S₀²) and the prior's, truncated."""
    precision = 1 / S[0] ** 2 + 1 / std**2
    return truncated((x0 / S[0] ** 2 + mean / std**2) / precision, precision**-0.5, 0)


X = np.array([[2.0, 1.0]], dtype=np.float32)  # the observation: t0's likelihood near the box's low face
USER = {"t0": {"normal": [0, 2]}}  # a user prior N(0, 2²) on t0, truncated to [0, 10]; t1 keeps the uniform


def test_reweighted_draws_follow_the_exact_posterior_under_the_users_prior():
    prior = parse_prior(USER, TOY, "user.yaml")
    posterior = ReweightedPosterior(ToyPosterior(), prior, TOY, proposals=20000)
    (ess,) = posterior.prepare(X, seed=1)
    draws = posterior.sample(X, 4000, seed=2)[0]
    exact = product(2.0, 0.0, 2.0)
    assert stats.kstest(draws[:, 0], exact.cdf).pvalue > 0.01
    assert stats.kstest(draws[:, 1], truncated(1.0, S[1], 1).cdf).pvalue > 0.01  # t1 is not named: unchanged
    # the test can fail: the draws before reweighting are far from that posterior
    before = ToyPosterior().sample(X, 4000, seed=2)[0]
    assert stats.kstest(before[:, 0], exact.cdf).pvalue < 1e-6
    # the weighted moments are the exact ones within their sampling error (σ / √ESS)
    found = posterior._entry(X[0])
    mean = found.weights @ found.draws[:, 0]
    std = math.sqrt(found.weights @ (found.draws[:, 0] - mean) ** 2)
    assert abs(mean - exact.mean()) < 4 * exact.std() / math.sqrt(ess)
    assert abs(std - exact.std()) < 4 * exact.std() / math.sqrt(ess)
    assert 0.5 * 20000 < ess < 20000  # the prior's tilt costs some of the draws, not most
    # log p̂_user(θ | x) is the exact log-density up to the Monte Carlo evidence
    t = np.array([[0.5, 0.0], [1.5, 1.0], [3.0, -2.0]])
    exact_log = exact.logpdf(t[:, 0]) + truncated(1.0, S[1], 1).logpdf(t[:, 1])
    assert posterior.log_prob(t, np.repeat(X, 3, axis=0)) == pytest.approx(exact_log, abs=0.03)


def test_a_domain_on_the_reweighted_posterior_is_the_mixture_of_the_users_posteriors():
    x = np.array([[2.0, 1.0], [7.0, 1.0]], dtype=np.float32)
    posterior = ReweightedPosterior(ToyPosterior(), parse_prior(USER, TOY, "user.yaml"), TOY, proposals=20000)
    posterior.prepare(x, seed=3)
    draws = Domain(posterior, x, weights=[3, 1]).sample(4000, seed=4)
    a, b = product(2.0, 0.0, 2.0), product(7.0, 0.0, 2.0)
    assert stats.kstest(draws[:, 0], lambda t: 0.75 * a.cdf(t) + 0.25 * b.cdf(t)).pvalue > 0.01


def test_the_effective_sample_size_of_known_weights():
    assert effective_sample_size(np.ones(7)) == pytest.approx(7.0)
    assert effective_sample_size(np.array([1.0, 0.0, 0.0])) == pytest.approx(1.0)
    assert effective_sample_size(np.array([2.0, 1.0])) == pytest.approx(9 / 5)  # (2 + 1)² / (4 + 1)
    assert effective_sample_size(np.array([2e-300, 1e-300])) == pytest.approx(9 / 5)  # scale-free, no underflow
    assert effective_sample_size(np.zeros(4)) == 0.0
    assert effective_sample_size(np.array([[1.0, 1.0], [1.0, 0.0]])).tolist() == pytest.approx([2.0, 1.0])


@pytest.mark.parametrize(
    "spec",
    [
        {"t0": {"uniform": [0, 10]}},
        {"t0": {"beta": [1, 1]}},
        {"t0": {"mixture": [{"weight": 0.3, "uniform": [0, 3]}, {"weight": 0.7, "uniform": [3, 10]}]}},
    ],
    ids=["uniform", "beta(1, 1)", "mixture of uniforms"],
)
def test_the_training_prior_itself_gives_equal_weights_and_the_same_draws(spec):
    prior = parse_prior(spec, TOY, "same.yaml")
    draws = ToyPosterior().sample(X, 5000, seed=5)[0]
    found = reweight(draws, prior, TOY)
    assert found.weights == pytest.approx(np.full(5000, 1 / 5000), rel=1e-9)
    assert found.ess == pytest.approx(5000.0)
    assert found.log_evidence == pytest.approx(0.0, abs=1e-9)  # Z = E[r] = 1
    again = found.draws[resample(found.weights, 3000, seeding.rng(6, "test"))]
    assert stats.kstest(again[:, 0], truncated(2.0, S[0], 0).cdf).pvalue > 0.01


def test_resampling_never_takes_a_draw_of_zero_weight():
    weights = np.array([0.0, 0.5, 0.0, 0.5, 0.0])
    taken = resample(weights, 10000, seeding.rng(7, "test"))
    assert set(np.unique(taken)) == {1, 3}
    assert abs(np.mean(taken == 1) - 0.5) < 0.02


@pytest.mark.parametrize(
    "density",
    [
        Uniform(20.0, 30.0),
        TruncatedNormal(10.0, 25.0, 0.0, 100.0),
        TruncatedNormal(-20.0, 5.0, 0.0, 100.0),
        ScaledBeta(1.0, 8.0, 0.0, 100.0),
        ScaledBeta(0.5, 0.5, -90.0, 90.0),
        Mixture((0.7, 0.3), (ScaledBeta(1.0, 8.0, 0.0, 100.0), Uniform(0.0, 100.0))),
    ],
    ids=repr,
)
def test_each_density_integrates_to_one_on_its_range(density):
    low, high = (-90.0, 90.0) if isinstance(density, ScaledBeta) and density.low < 0 else (0.0, 100.0)
    points = [20.0, 30.0] if isinstance(density, Uniform) else None
    total, _ = integrate.quad(
        lambda t: float(np.exp(density.log_prob(np.array([t]))[0])), low, high, points=points, limit=200
    )
    assert total == pytest.approx(1.0, abs=1e-6)
    assert density.log_prob(np.array([low - 1.0, high + 1.0])).tolist() == [-math.inf, -math.inf]


def test_the_users_prior_is_a_product_and_parameters_not_named_keep_the_training_prior():
    box = weather.Box.full()
    prior = read_prior(DRY_WORLD, box)
    theta = box.sample(seeding.rng(8, "test"), 50)
    rain = Mixture((0.7, 0.3), (ScaledBeta(1.0, 8.0, 0.0, 100.0), Uniform(0.0, 100.0)))
    expected = (
        rain.log_prob(theta[:, 2])
        + ScaledBeta(1.0, 4.0, 0.0, 100.0).log_prob(theta[:, 5])
        + TruncatedNormal(30.0, 25.0, 0.0, 100.0).log_prob(theta[:, 0])
        - math.log(100.0) * 2  # fog, wind: uniform on [0, 100]
        - math.log(180.0)  # sun: uniform on [−90, 90]
    )
    assert prior.log_prob(theta) == pytest.approx(expected)
    assert list(prior.describe()) == ["cloudiness", "precipitation", "precipitation_deposits"]


@pytest.mark.parametrize(
    "text, message",
    [
        ("rain: {beta: [1, 8]}", "rain: unknown parameter; the model's are cloudiness, fog_density"),
        ("precipitation: {uniform: [0, 120]}", "precipitation: uniform [0, 120] lies outside the parameter's training"),
        ("sun_altitude_angle: {normal: [0, 30], range: [-100, 0]}", "sun_altitude_angle: range [-100, 0] lies outside"),
        ("precipitation: {uniform: [50, 10]}", "precipitation: uniform needs low < high, got [50, 10]"),
        ("precipitation: {beta: [0, 8]}", "precipitation: beta's a and b must be positive, got [0, 8]"),
        ("precipitation: {beta: [1, .nan]}", "precipitation: beta's b must be a finite number, got nan"),
        ("precipitation: {normal: [10, -1]}", "precipitation: normal's std must be positive, got -1"),
        ("precipitation: {normal: [ten, 1]}", "precipitation: normal's mean must be a finite number, got 'ten'"),
        ("precipitation: {beta: [yes, 1]}", "precipitation: beta's a must be a finite number, got True"),
        ("precipitation: {beta: [1, 2, 3]}", "precipitation: beta takes [a, b], got [1, 2, 3]"),
        (
            "precipitation: {mixture: [{weight: 0.7, beta: [1, 8]}, {weight: 0.2, uniform: [0, 100]}]}",
            "precipitation: mixture weights sum to 0.9, expected 1 (0.7 + 0.2)",
        ),
        ("precipitation: {mixture: [{weight: -1, beta: [1, 8]}]}", "mixture component 1: weight must be positive"),
        ("precipitation: {mixture: [{beta: [1, 8]}]}", "precipitation: mixture component 1: expected a mapping with"),
        ("precipitation: {normal: [1000, 1]}", "precipitation: normal(1000, 1) is zero on [0, 100] (its mass there"),
        ("precipitation: 0", "precipitation: a number (0) is a point mass: a point mass has no density with respect"),
        (
            "precipitation: {mixture: [{weight: 0.5, point: 0}, {weight: 0.5, uniform: [0, 100]}]}",
            "precipitation: mixture component 1: 'point': a point mass has no density with respect to the training",
        ),
        ("precipitation: {beta: [1, 8], mean: 3}", "precipitation: unknown key 'mean'; expected one of uniform"),
        ("precipitation: {beta: [1, 8], uniform: [0, 5]}", "precipitation: expected exactly one of uniform, normal"),
        ("precipitation: {uniform: [0, 5], range: [0, 3]}", "precipitation: range applies to normal and beta only"),
        ("precipitation: {beta: [1, 8]}\nprecipitation: {beta: [1, 2]}", "line 2: precipitation appears twice"),
        ("precipitation: [1, 2", "not valid YAML"),
        ("", "names no parameter"),
        ("- precipitation", "the top level must map parameter names to densities"),
    ],
)
def test_a_bad_prior_file_is_one_line_naming_the_file_and_the_parameter(tmp_path, text, message):
    path = tmp_path / "prior.yaml"
    path.write_text(text + "\n")
    with pytest.raises(PriorError) as caught:
        read_prior(path, weather.Box.full())
    line = str(caught.value)
    assert "\n" not in line and line.startswith(f"{path}: ") and message in line, line


def test_the_training_prior_is_read_from_the_card_and_never_assumed():
    card = {
        "theta": {"names": list(weather.PREDICTED), "units": ["%", "%", "%", "deg", "%", "%"]},
        "bijection": {"low": [0, 0, 0, -90, 0, 0], "high": [100, 100, 100, 0, 100, 100]},  # a night-only model
        "training_renders": {"simulator": "procedural", "height": 32, "width": 32},
    }
    box = training_prior(card, "m/card.json")
    assert box.high[3] == 0.0 and box.names == weather.PREDICTED
    # ranges are the model's: sun above 0° is outside its training prior
    with pytest.raises(PriorError, match=r"sun_altitude_angle: uniform \[0, 90\] lies outside .* \[-90, 0\] deg"):
        parse_prior({"sun_altitude_angle": {"uniform": [0, 90]}}, box, "day.yaml")
    with pytest.raises(PriorError, match="m/card.json: the card records no training box"):
        training_prior({k: v for k, v in card.items() if k != "bijection"}, "m/card.json")
    with pytest.raises(PriorError, match="does not say what data the model learned from"):
        training_prior({k: v for k, v in card.items() if k != "training_renders"}, "m/card.json")
    with pytest.raises(PriorError, match="learned from recorded data, whose weather is not drawn uniformly"):
        training_prior({**card, "training_renders": {"simulator": "recorded"}}, "m/card.json")


# --- the command line, on a small registry ------------------------------------------------------------------------

# weather boxes (cloud, fog, rain, sun, wind, deposits)
CLEAR = ([0, 0, 0, 50, 0, 0], [20, 10, 10, 90, 30, 10])
RAINY = ([60, 0, 55, 40, 30, 50], [100, 20, 85, 90, 80, 90])


def render_folder(folder: Path, box: tuple[list[float], list[float]], n: int, seed: int, prefix: str = "") -> Path:
    """n PNGs of 32×32 at weathers uniform in ``box``, named ``<prefix><i>.png``."""
    return tiny_registry.render_folder(folder, box, n, seed, prefix, stream="prior-folder")


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict[str, Path]:
    """A registry whose champion is a small NPE on the cues of 32×32 renders, and folders of images."""
    root = tmp_path_factory.mktemp("prior-registry")
    registry = tiny_registry.build_registry(root, "prior-registry")
    dry = root / "dry.yaml"  # the dry world: mostly dry days, some rain of any amount
    dry.write_text("precipitation: {mixture: [{weight: 0.7, beta: [1, 8]}, {weight: 0.3, uniform: [0, 100]}]}\n")
    return {
        "registry": registry,
        "dry": dry,
        "rainy": render_folder(root / "rainy", RAINY, 12, 21),
        "clear": render_folder(root / "clear", CLEAR, 12, 22),
        "mix": render_folder(render_folder(root / "mix", CLEAR, 4, 23, "c"), RAINY, 4, 24, "r"),
    }


def run(capsys, *args: object) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def rain_medians(path: Path) -> list[float]:
    report = json.loads(path.read_text())
    items = report["images"] if "images" in report and isinstance(report["images"], list) else [report]
    return [item["parameters"]["precipitation"]["median"] for item in items]


def test_characterize_with_a_dry_world_prior_moves_rain_toward_zero(world, capsys, tmp_path):
    images = sorted(world["rainy"].glob("*.png"))[:4]
    common = ["--registry", world["registry"], "--samples", 1000]
    code, _, _ = run(capsys, "characterize", *images, *common, "--json", tmp_path / "plain.json")
    assert code == 0
    code, out, err = run(
        capsys, "characterize", *images, *common, "--prior", world["dry"], "--json", tmp_path / "dry.json"
    )
    assert code == 0, err
    heads = [line for line in out.splitlines() if line.startswith("== ")]
    assert len(heads) == 4 and all(f"(prior {world['dry']}: effective sample size " in h for h in heads)
    assert f"prior {world['dry']} (importance weights from the training prior, uniform on the model's box)" in err
    plain, dry = rain_medians(tmp_path / "plain.json"), rain_medians(tmp_path / "dry.json")
    assert all(d < p - 10.0 for d, p in zip(dry, plain, strict=True)), (plain, dry)
    report = json.loads((tmp_path / "dry.json").read_text())
    prior = report["prior"]
    assert prior["file"] == str(world["dry"]) and prior["draws_per_image"] == 1000 and prior["min_ess"] == 100
    assert list(prior["parameters"]) == ["precipitation"]
    each = [item["ess"] for item in report["images"]]
    assert prior["ess"] == pytest.approx(
        {"images": 4, "min": min(each), "median": float(np.median(each)), "max": max(each)}
    )
    assert all(100 <= e < 1000 for e in each)


def test_a_prior_equal_to_the_training_prior_keeps_every_draw(world, capsys, tmp_path):
    same = tmp_path / "same.yaml"
    same.write_text("precipitation: {uniform: [0, 100]}\nsun_altitude_angle: {beta: [1, 1]}\n")
    image = sorted(world["rainy"].glob("*.png"))[0]
    code, out, _ = run(
        capsys, "characterize", image, "--registry", world["registry"], "--samples", 500, "--prior", same
    )
    assert code == 0 and "effective sample size 500.0 of 500)" in out


def test_too_small_an_effective_sample_size_is_one_line(world, capsys, tmp_path):
    sharp = tmp_path / "bone-dry.yaml"
    sharp.write_text("precipitation: {normal: [0, 1]}\n")
    image = sorted(world["rainy"].glob("*.png"))[0]
    code, out, err = run(
        capsys, "characterize", image, "--registry", world["registry"], "--samples", 200, "--prior", sharp
    )
    assert code == 2 and out == ""
    (line,) = [line for line in err.splitlines() if "error:" in line]  # one line (after the backbone's size note)
    assert line.startswith(f"pidc characterize: error: {image}: effective sample size "), line
    assert f"of 200 draws under --prior {sharp} is below --min-ess 100" in line and "use more --samples (about" in line
    # nothing the prior allows: ESS 0, said as such
    none = tmp_path / "clear-and-dry.yaml"  # the rainy image's posterior has no draw this clear and dry
    none.write_text("cloudiness: {uniform: [0, 1]}\nprecipitation_deposits: {uniform: [0, 1]}\n")
    code, _, err = run(capsys, "characterize", image, "--registry", world["registry"], "--prior", none)
    assert code == 2 and "no posterior draw of this image has a positive density under --prior" in err
    # and --min-ess beyond the draws, or without --prior
    code, _, err = run(capsys, "characterize", image, "--prior", world["dry"], "--samples", 200, "--min-ess", 300)
    assert code == 2 and "--min-ess must be in (0, 200]" in err
    code, _, err = run(capsys, "characterize", image, "--min-ess", 50)
    assert code == 2 and "--min-ess applies with --prior FILE only" in err
    code, _, err = run(capsys, "characterize", image, "--prior", tmp_path / "missing.yaml")
    assert code == 2 and f"--prior {tmp_path / 'missing.yaml'}: no such file" in err


def test_domain_with_a_prior_reweights_each_image(world, capsys, tmp_path):
    common = ["domain", world["rainy"], "--registry", world["registry"], "--samples", 1000]
    assert run(capsys, *common, "--json", tmp_path / "plain.json")[0] == 0
    code, out, _ = run(capsys, *common, "--prior", world["dry"], "--json", tmp_path / "dry.json")
    assert code == 0 and f"prior {world['dry']} (importance weights" in out and "median" in out
    (plain,), (dry,) = rain_medians(tmp_path / "plain.json"), rain_medians(tmp_path / "dry.json")
    assert dry < plain - 10.0, (plain, dry)
    assert json.loads((tmp_path / "dry.json").read_text())["prior"]["ess"]["images"] == 12


def test_relate_reweights_the_target_and_every_source_to_the_same_prior(world, capsys, tmp_path):
    code, out, err = run(
        capsys,
        "relate",
        world["mix"],
        world["clear"],
        world["rainy"],
        "--registry",
        world["registry"],
        "--calibration-targets",
        20,
        "--prior",
        world["dry"],
        "--json",
        tmp_path / "relate.json",
    )
    assert code == 0, err
    assert f"prior {world['dry']} (importance weights" in out and "of 1000 draws" in out
    report = json.loads((tmp_path / "relate.json").read_text())
    assert report["prior"]["ess"]["images"] == 8 + 12 + 12 and report["prior"]["draws_per_image"] == 1000
    assert sum(s["weight"] for s in report["sources"]) == pytest.approx(1.0)
    code, _, err = run(capsys, "relate", world["mix"], world["clear"], "--prior-draws", 500)
    assert code == 2 and "--prior-draws applies with --prior FILE only" in err
