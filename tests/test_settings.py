"""The few-features rule of ``components/posterior/settings.py``: small inputs train longer, the pipeline's do not.

A model of fewer than ``train.input_noise_min_features`` frozen features (the SBI problems' 2–10 inputs) gets no input
noise and at least ``train.few_features_epochs`` epochs (docs/studies/sbi-small-inputs.md). Every backbone of the
pipeline has at least 256 features, so its models must train exactly as before the rule: the first test rebuilds
their settings from the rule of many features written out here (an independent statement of it, not the code's
output) and compares them field by field. Deterministic: no training, no random draws.
"""

from __future__ import annotations

import dataclasses
import math

import pytest

from components.core.config import PROJECT_ROOT, load_params

PROFILES = ["default", *sorted(f.stem for f in (PROJECT_ROOT / "profiles").glob("*.yaml"))]


def _many_features_epochs(t, size: int, floor: int = 0) -> int:
    """The epochs of a frozen-feature model: min(max(⌈epochs·s⌉, floor), ⌈sample_budget / size⌉), s = max(1,
    scale_to / size); floor 0 = many features (the rule before few_features_epochs)."""
    s = max(1.0, t.scale_to / size)
    return max(1, min(max(math.ceil(t.epochs * s), floor), math.ceil(t.sample_budget / size)))


@pytest.mark.parametrize("profile", PROFILES)
def test_pipeline_models_train_as_without_the_rule(profile):
    """Every size of the grid (and a few more) with 64–2048 features: the epochs of the rule of many features, the
    same configs with the rules switched off (``few_features_epochs`` and ``few_features_recipe`` null), whatever the
    feature count."""
    from components.features.backbones import get_backbone
    from components.posterior.settings import epochs_for, flow_config, training_config

    params = load_params(PROJECT_ROOT / "params.yaml", profile=profile)
    t, parameters = params.train, len(params.box.names)
    off = t.model_copy(update={"few_features_epochs": None, "few_features_recipe": None})
    dims = {get_backbone(name).dim for name in ("cues", "tiny")} | {t.input_noise_min_features, 384, 1280, 2048}
    assert min(dims) >= t.input_noise_min_features
    for size in sorted({*t.sizes, 100, 1000, 3000, t.scale_to, 10 * t.scale_to}):
        for features in sorted(dims):
            for trainable in (False, True):
                on_cfg = training_config(
                    t, size=size, trainable=trainable, features=features, parameters=parameters, seed=3
                )
                off_cfg = training_config(
                    off, size=size, trainable=trainable, features=features, parameters=parameters, seed=3
                )
                assert on_cfg == off_cfg, (size, features, trainable)
                if not trainable:
                    assert on_cfg.epochs == _many_features_epochs(t, size) == epochs_for(t, size, trainable=False)
            assert flow_config(t, size=size, trainable=False) == flow_config(off, size=size, trainable=False)


def test_few_features_train_at_least_their_epochs():
    """Below the floor of features: at least few_features_epochs epochs, never above the sample budget's cap; sizes
    whose small-data rule already gives more epochs (1 000 images: ⌈60·10⌉) are unchanged; null switches it off."""
    from components.posterior.settings import epochs_for, few_features, training_config

    t = load_params(PROJECT_ROOT / "params.yaml").train
    floor, d = t.few_features_epochs, t.input_noise_min_features
    assert floor is not None and floor > t.epochs  # the rule is on and lengthens the 10k models
    assert [few_features(t, f) for f in (1, 2, 10, d - 1, d, 256)] == [True] * 4 + [False] * 2
    for size in (100, 900, 1000, 3000, 9000, 10_000, 20_000, 50_000, 10**6):
        few = epochs_for(t, size, trainable=False, features=2)
        many = epochs_for(t, size, trainable=False, features=d)
        assert few == _many_features_epochs(t, size, floor) and many == _many_features_epochs(t, size), size
        assert many <= few <= max(many, math.ceil(t.sample_budget / size))
    assert epochs_for(t, 1000, trainable=False, features=2) == epochs_for(t, 1000, trainable=False, features=d)
    assert epochs_for(t, 9000, trainable=False, features=2) == floor > epochs_for(t, 9000, trainable=False, features=d)
    assert epochs_for(t, 9000, trainable=True, features=2) == epochs_for(t, 9000, trainable=True, features=d)
    cfg = training_config(t, size=9000, trainable=False, features=2, parameters=6, seed=0)
    assert cfg.epochs == floor and cfg.input_noise == 0.0
    off = t.model_copy(update={"few_features_epochs": None})
    assert epochs_for(off, 9000, trainable=False, features=2) == epochs_for(t, 9000, trainable=False, features=d)
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="features must be a positive integer"):
            few_features(t, bad)


def test_the_benchmark_uses_the_rule():
    """``benchmarks/bench_sbi_problems.py`` builds its default settings through the rule: a 2-D problem's 9 000
    training simulations get the floor of epochs, its 900 the small-data rule's."""
    import sys

    sys.path.insert(0, str(PROJECT_ROOT / "benchmarks"))
    import bench_sbi_problems as bench

    params = load_params(PROJECT_ROOT / "params.yaml")
    t = params.train
    flow, training = bench.default_configs(params, 9000, 2, 2, seed=0)
    assert training.epochs == t.few_features_epochs and training.input_noise == 0.0
    assert dataclasses.replace(flow, regime_temperature=False) == flow
    assert bench.default_configs(params, 900, 2, 2, seed=0)[1].epochs == math.ceil(t.epochs * t.scale_to / 900)


def test_few_features_recipe_applies_below_its_images_per_parameter():
    """``train.few_features_recipe`` replaces batch, rate, weight decay, schedule and patience exactly when the model
    has few frozen features and fewer than ``size_per_parameter`` × d training images: the 10-D Gaussian's 900 and
    1 800 (d = 10), not two_moons' 900 (d = 2) nor anything at 9 000; never a trainable backbone or many features.
    The patience is the recipe's (not × s), the epochs stay the cap of :func:`epochs_for`, the compile decision
    counts the recipe's batches; null switches it off."""
    from components.posterior.settings import compile_for, epochs_for, recipe_for, training_config

    t = load_params(PROJECT_ROOT / "params.yaml").train
    r = t.few_features_recipe
    assert r is not None and r.schedule == "constant" and r.patience is not None
    few, many = 10, t.input_noise_min_features
    limit = r.size_per_parameter * 10
    for size, features, d, trainable, applies in [
        (900, few, 10, False, True),
        (1800, few, 10, False, True),
        (limit - 1, few, 10, False, True),
        (limit, few, 10, False, False),
        (900, 2, 2, False, False),
        (9000, few, 10, False, False),
        (900, many, 10, False, False),
        (900, few, 10, True, False),
    ]:
        cfg = training_config(t, size=size, trainable=trainable, features=features, parameters=d, seed=0)
        assert (recipe_for(t, size, trainable=trainable, features=features, parameters=d) is not None) == applies
        if applies:
            assert (cfg.batch_size, cfg.lr, cfg.weight_decay, cfg.schedule, cfg.patience) == (
                r.batch_size,
                r.lr,
                r.weight_decay,
                r.schedule,
                r.patience,
            )
            steps = epochs_for(t, size, trainable=False, features=features) * math.ceil(size / r.batch_size)
            assert cfg.compile == (steps >= t.compile_min_steps)
        else:
            assert (cfg.batch_size, cfg.lr, cfg.weight_decay, cfg.schedule) == (
                t.batch_size,
                t.lr,
                t.weight_decay,
                t.schedule,
            )
        assert cfg.epochs == epochs_for(t, size, trainable=trainable, features=features)
    off = t.model_copy(update={"few_features_recipe": None})
    assert recipe_for(off, 900, trainable=False, features=few, parameters=10) is None
    assert training_config(off, size=900, trainable=False, features=few, parameters=10, seed=0).lr == t.lr
    assert compile_for(t, 900, trainable=False, features=few, batch_size=r.batch_size) == (
        epochs_for(t, 900, trainable=False, features=few) * math.ceil(900 / r.batch_size) >= t.compile_min_steps
    )
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="parameters must be a positive integer"):
            recipe_for(t, 900, trainable=False, features=few, parameters=bad)


def test_the_benchmark_gets_the_recipe_on_the_10d_gaussian_at_1k():
    """``bench_sbi_problems.py``'s defaults for gaussian_linear_uniform at 1 000 simulations (900 to train, x and θ of
    10 dimensions) are the recipe's; two_moons' (2 and 2) are ``train``'s."""
    import sys

    sys.path.insert(0, str(PROJECT_ROOT / "benchmarks"))
    import bench_sbi_problems as bench

    params = load_params(PROJECT_ROOT / "params.yaml")
    r = params.train.few_features_recipe
    glu = bench.default_configs(params, 900, 10, 10, seed=0)[1]
    moons = bench.default_configs(params, 900, 2, 2, seed=0)[1]
    assert (glu.lr, glu.schedule, glu.patience, glu.batch_size) == (r.lr, r.schedule, r.patience, r.batch_size)
    assert (moons.lr, moons.schedule, moons.batch_size) == (
        params.train.lr,
        params.train.schedule,
        params.train.batch_size,
    )


def test_spared_features_get_their_share_of_the_noise():
    """The cues' sun head (μ and log σ, the last two cues) is the training config's ``spared``, its noise
    ``train.input_noise_spared`` of the others'; a trainable backbone (no input noise) spares none; a backbone
    without such features (the tiny) has none to name."""
    from components.features.backbones import get_backbone
    from components.features.backbones.cues import FEATURE_NAMES
    from components.posterior.settings import training_config

    t = load_params(PROJECT_ROOT / "params.yaml").train
    cues, tiny = get_backbone("cues"), get_backbone("tiny")
    spared = cues.spared_index()
    assert [FEATURE_NAMES[i] for i in spared] == ["reader_sun_head_mean", "reader_sun_head_log_sd"]
    assert spared == (cues.dim - 2, cues.dim - 1) and tiny.spared_index() == ()
    for share in (0.0, 0.5, 1.0):
        tt = t.model_copy(update={"input_noise_spared": share})
        common = dict(size=5000, features=cues.dim, parameters=6, seed=0, spared=spared)
        frozen = training_config(tt, trainable=False, **common)
        assert frozen.input_noise > 0 and frozen.spared == spared and frozen.spared_noise == share
        assert training_config(tt, trainable=True, **common).spared == ()
