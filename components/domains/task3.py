"""Task III (paper): the source and out-of-ODD bags of the test split, the sweep over η, and its metrics.

Used by the ``task3`` stage, its benchmark and the scheduled monitoring (``flows/monitor.py``). The bags are the
test images whose weather lies in a sub-box (``task3.bags``); every image is characterized once by the registry
model (its context), and the sweep (:class:`~components.domains.sweep.NoiseSweep`) mixes them into targets at each
noise level η.

Each bag's weather is characterized as ``task3.smoothing`` says: the kernel density of ``task3.draws_per_image``
posterior draws per image with one bandwidth, ``task3.bandwidth_scale`` × Scott's rule
(:mod:`components.domains.kernel`, the default), or the paper's exact mixture of posteriors.

Bags share no image, by construction (:func:`split_bags`): every test image belongs to at most one bag — the first,
in the order b0, b1, b2, …, whose sub-box holds it (b0's box is disjoint from the sources' by the config) — so an
image inside two source sub-boxes is given to the lower-numbered source and is neither in the other's bag nor in its
fresh pool. A source's bag is the first ``max_images`` of its own images, its fresh pool the rest of them: bag and
pool follow the same weather (the sub-box less the earlier sources' boxes), and a fresh target holds no image of any
bag. A configuration where that cannot hold (a sub-box with no image of its own, a pool smaller than its bag) is
refused with an error naming the bags and the key of params.yaml.

The metrics name every per-η figure by the kind of target it was measured on: ``<figure>_paper`` (the paper's
targets, whose in-ODD part reuses the sources' images) and ``<figure>_fresh`` (other images of the sources' weather),
in ``metrics.json`` (``eta``), in the rows of ``eta.json`` and, at step 100·η, in MLflow.

References:
    Halin, Piérard et al., "Physically Interpretable Probabilistic Domain Characterization", Task III (the source and
    out-of-ODD bags, the targets at noise level η, d_E and the mean squared gap against η).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from components.core.config import BagConfig, Params
from components.core.paths import ProjectPaths
from components.domains.relative import OddDetector
from components.domains.scenarios import in_sub_box
from components.domains.sweep import Experiment, FalseAlarmCheck, NoiseSweep, experiments_by_eta, summarize_sweep
from components.evaluate.diagnostics import roc_curve
from components.export.lookup import RegisteredPosterior
from components.features import cache as features
from components.simulate import dataset

__all__ = [
    "KINDS",
    "PER_ETA",
    "BagSplit",
    "bag_of",
    "split_bags",
    "bag_members",
    "build_sweep",
    "DETECTED",
    "detection_floor",
    "task3_metrics",
    "eta_rows",
    "eta_series",
    "roc_rows",
]

#: the target kinds: the paper's (in-ODD part = the sources' own images) and fresh ones (other images of their weather)
KINDS = ("paper", "fresh")
#: the per-η figures of each kind (medians over the repetitions, the share flagged, AUCs against η = 0; the last two
#: with their 95 % intervals)
PER_ETA = (
    "d_e_median",
    "gap_median",
    "baseline_gap_median",
    "relative_gap_median",
    "baseline_relative_gap_median",
    "flagged_rate",
    "flagged_rate_ci_low",
    "flagged_rate_ci_high",
    "auc",
    "auc_ci_low",
    "auc_ci_high",
    "auc_gap",
    "auc_gap_ci_low",
    "auc_gap_ci_high",
)


@dataclass(frozen=True)
class BagSplit:
    """Test-image indices of every bag and of every source's fresh pool, pairwise disjoint.

    Attributes:
        members: bag name (b0, b1, …) → indices ``(Nₖ,)`` into the test split.
        pools: source name (b1, …) → the indices of its fresh pool (its own images beyond the bag).
        in_sub_box: bag name → test images inside its sub-box, before any was given to an earlier bag.
        given_to: bag name → {earlier bag: images of this bag's sub-box that belong to that bag} (overlaps only).
    """

    members: dict[str, np.ndarray]
    pools: dict[str, np.ndarray]
    in_sub_box: dict[str, int]
    given_to: dict[str, dict[str, int]]

    def sizes(self) -> dict[str, int]:
        """Bag name → images in the bag."""
        return {n: int(i.size) for n, i in self.members.items()}

    def check_disjoint(self) -> None:
        """``ValueError`` naming the two sets when a bag or pool shares an image with another."""
        sets = [(f"bag {n}", i) for n, i in self.members.items()]
        sets += [(f"the fresh pool of {n}", i) for n, i in self.pools.items()]
        for a in range(len(sets)):
            for b in range(a + 1, len(sets)):
                shared = np.intersect1d(sets[a][1], sets[b][1])
                if shared.size:
                    raise ValueError(
                        f"{sets[a][0]} and {sets[b][0]} share {shared.size} test image(s) (e.g. {int(shared[0])}): "
                        "bags and fresh pools must be disjoint"
                    )


def _bag_order(names: Sequence[str]) -> list[str]:
    return sorted(names, key=lambda n: int(n[1:]))


def bag_of(bags: Mapping[str, BagConfig], theta: np.ndarray) -> np.ndarray:
    """The bag each weather of ``theta (N, 6)`` belongs to: the first of b0, b1, b2, … (``task3.bags``) whose sub-box
    holds it, ``""`` for none; ``(N,)`` of names."""
    owner = np.full(np.asarray(theta).shape[0], "", dtype=object)
    for name in reversed(_bag_order(bags)):  # the first bag in order is written last
        owner[in_sub_box(theta, bags[name].box)] = name
    return owner


def split_bags(bags: Mapping[str, BagConfig], theta: np.ndarray, fresh: bool) -> BagSplit:
    """The disjoint bags and fresh pools of the test images (the rules of the module's description).

    Arguments:
        bags: ``task3.bags``: b0 (out of the ODD) first, then the sources b1, b2, …
        theta: the test images' true weathers ``(N, 6)``, physical units.
        fresh: whether fresh targets are run, so every source needs a pool at least as large as its bag.

    Returns:
        The :class:`BagSplit`: per bag its test-image indices, per source its fresh pool.

    Raises:
        ValueError: naming ``task3.bags.<name>…``, for a sub-box without an image of its own or a pool smaller than
            its bag.

    Examples:
        1 000 test weathers from the prior; b2's fog range overlaps b1's, whose images it leaves to b1:

        >>> import numpy as np
        >>> from components.core.config import BagConfig
        >>> from components.core.weather import Box
        >>> theta = Box.full().sample(np.random.default_rng(0), 1000)
        >>> bags = {
        ...     "b0": BagConfig(box={"fog_density": (80, 100)}, max_images=50),
        ...     "b1": BagConfig(box={"fog_density": (0, 20)}, max_images=50),
        ...     "b2": BagConfig(box={"fog_density": (10, 40)}, max_images=50),
        ... }
        >>> split = split_bags(bags, theta, fresh=True)
        >>> split.sizes(), {name: pool.size for name, pool in split.pools.items()}
        ({'b0': 50, 'b1': 50, 'b2': 50}, {'b1': 153, 'b2': 149})
        >>> split.given_to  # b2's sub-box holds 96 images of b1
        {'b2': {'b1': 96}}
    """
    owner = bag_of(bags, theta)
    members, pools, counts, given = {}, {}, {}, {}
    for name in _bag_order(bags):
        cfg = bags[name]
        inside = in_sub_box(theta, cfg.box)
        counts[name] = int(inside.sum())
        if counts[name] == 0:
            raise ValueError(
                f"task3.bags.{name}.box: no test image lies in its sub-box {dict(cfg.box)}; widen the box or grow "
                "data.splits.test"
            )
        taken = owner[inside & (owner != name)]  # images of its sub-box that belong to an earlier bag
        given[name] = {b: int(np.sum(taken == b)) for b in _bag_order(set(taken))}
        own = np.flatnonzero(owner == name)
        if own.size == 0:
            raise ValueError(
                f"task3.bags.{name}.box: all {counts[name]} test images of its sub-box also lie in the sub-box of "
                f"{', '.join(given[name])}, which comes first (an image in two sub-boxes belongs to the first bag): "
                f"bags {name} and {', '.join(given[name])} cannot be disjoint; make {name}'s box overlap theirs less"
            )
        size = min(cfg.max_images, own.size)
        members[name] = own[:size]
        if name == "b0":
            continue
        pools[name] = own[size:]
        if fresh and pools[name].size < size:
            lost = f" ({sum(given[name].values())} more of its sub-box belong to {', '.join(given[name])})"
            raise ValueError(
                f"task3.bags.{name}.max_images: bag {name} has {own.size} test images of its own"
                f"{lost if given[name] else ''}, too few for a source bag of {size} and a fresh pool of at least as "
                "many beside it; lower max_images, widen or separate the boxes, grow data.splits.test, or set "
                "task3.fresh_targets: false"
            )
    split = BagSplit(members, pools, counts, {n: g for n, g in given.items() if g})
    split.check_disjoint()
    return split


def bag_members(params: Params, theta: np.ndarray) -> BagSplit:
    """:func:`split_bags` with the project's ``task3`` settings."""
    return split_bags(params.task3.bags, theta, params.task3.fresh_targets)


def build_sweep(
    params: Params, paths: ProjectPaths, model: RegisteredPosterior, fresh_inputs: Sequence[np.ndarray] | None = None
) -> tuple[NoiseSweep, BagSplit, str]:
    """The sweep of the project: ``model``'s contexts of the bags' test images, from the feature cache.

    Arguments:
        params: the configuration (``task3``, the seed).
        paths: where the test split and its feature cache are.
        model: the registry model; open it with one onnxruntime thread (many small calls).
        fresh_inputs: the posterior inputs of other images of each source's weather (b1, b2, … in order), the fresh
            pools instead of the test split's (scheduled monitoring: new images); ``None``: the test split's.

    Returns:
        The :class:`~components.domains.sweep.NoiseSweep`, the bags' test-image indices (:class:`BagSplit`) and the
            model's name.
    """
    t = params.task3
    test = dataset.open_split(paths.data, "test")
    split = bag_members(params, test.theta)
    cached = features.open_features(paths.features, model.backbone.name, test)

    def contexts(idx: np.ndarray) -> np.ndarray:
        return model.posterior.context(features.inputs_from_cached(model.backbone, cached[idx]))

    if fresh_inputs is not None:
        fresh = [model.posterior.context(x) for x in fresh_inputs]
    else:
        fresh = [contexts(split.pools[s]) for s in t.sources] if t.fresh_targets else None
    sweep = NoiseSweep(
        model.posterior.on_context(),
        contexts(split.members["b0"]),
        [contexts(split.members[s]) for s in t.sources],
        t.weights,
        t.n_points,
        fresh_pools=fresh,
        smoothing=t.smoothing,
        draws_per_image=t.draws_per_image,
        bandwidth_scale=t.bandwidth_scale,
        seed=params.seed,
    )
    return sweep, split, model.name


def _eta_key(eta: float) -> str:
    return f"{eta:g}"


#: the ODD decision detects an out-of-ODD share η when it flags at least this share of the targets at η
DETECTED = 0.5


def detection_floor(flagged_rates: Mapping[float, float]) -> float | None:
    """The power of the ODD decision in one number: the smallest out-of-ODD share η it detects.

    With α the false-alarm rate at η = 0, targets with an out-of-ODD share of at least this η are flagged more often
    than not. ``None`` is the warning a user needs: the decision keeps its false-alarm promise but detects nothing.

    Arguments:
        flagged_rates: η → the share of the targets at η that the decision flags.

    Returns:
        The smallest η > 0 from which the decision flags ≥ :data:`DETECTED` of the targets at that η and at every
            larger one, or ``None`` when not even the largest η qualifies.

    Examples:
        >>> detection_floor({0.0: 0.05, 0.2: 0.3, 0.4: 0.6, 0.6: 0.9, 0.8: 1.0})
        0.4
        >>> detection_floor({0.0: 0.05, 1.0: 0.4}) is None
        True
    """
    floor = None
    for eta in sorted((e for e in flagged_rates if e > 0), reverse=True):
        if flagged_rates[eta] < DETECTED:
            break
        floor = float(eta)
    return floor


def task3_metrics(
    model_name: str,
    n_points: int,
    weights: Sequence[float],
    split: BagSplit,
    experiments: Mapping[str, Sequence[Experiment]],
    detector: OddDetector,
    calibrated_on: str,
    check: FalseAlarmCheck,
    seconds: float,
) -> dict:
    """``reports/task3/metrics.json``: the setting, the ODD decision and, per η, every figure of :data:`PER_ETA`.

    Arguments:
        model_name: the registry model's id.
        n_points: n_W, the draws of each target where the densities were compared.
        weights: the true λ of the sources in the targets.
        split: the bags and fresh pools (their sizes are reported).
        experiments: target kind (``paper``, ``fresh``) → the sweep's experiments of that kind.
        detector: the ODD decision, calibrated on the relative gap.
        calibrated_on: the target kind the decision was calibrated on.
        check: the decision's false alarms on in-ODD targets of new seeds.
        seconds: the sweep's wall time.

    Returns:
        A JSON-ready dict: the setting (n_W, the true λ, bag and pool sizes), the ODD decision (the target kind it
            was calibrated on, α, rank, threshold; its false-alarm rate on the sweep's η = 0 targets and on
            ``check``'s targets of new seeds, each with its Clopper–Pearson interval; its power,
            :func:`detection_floor` on the same kind) and, per η, every figure for each target kind as
            ``<figure>_<kind>``.

    Raises:
        ValueError: when the sweep did not run the kind the decision was calibrated on.
    """
    if calibrated_on not in experiments:
        raise ValueError(f"the detector was calibrated on {calibrated_on} targets, which the sweep did not run")
    summaries = {kind: summarize_sweep(es, detector) for kind, es in experiments.items()}
    per_eta: dict[str, dict] = {}
    for eta in sorted({e.eta for es in experiments.values() for e in es}):
        key = _eta_key(eta)
        row: dict = {"repetitions": min(summaries[k][key]["repetitions"] for k in summaries)}
        for kind, summary in summaries.items():
            row |= {f"{f}_{kind}": summary[key].get(f) for f in PER_ETA}
        per_eta[key] = row
    rates = {float(key): row[f"flagged_rate_{calibrated_on}"] for key, row in per_eta.items()}
    in_sweep = FalseAlarmCheck.of(
        detector.decide_many([e.relative_gap for e in experiments[calibrated_on] if e.eta == 0.0]),
        detector,
        calibrated_on,
    )
    return {
        "model": model_name,
        "n_points": int(n_points),
        "weights": [float(w) for w in weights],
        "bags": {
            name: {
                "images": int(idx.size),
                "in_sub_box": split.in_sub_box[name],
                "given_to_earlier_bags": sum(split.given_to.get(name, {}).values()),
                **({"fresh_pool": int(split.pools[name].size)} if name in split.pools else {}),
            }
            for name, idx in split.members.items()
        },
        "experiments": {kind: len(es) for kind, es in experiments.items()},
        "odd": {
            "statistic": "relative_gap",
            "calibrated_on": calibrated_on,
            "false_alarm_rate": detector.false_alarm_rate,
            "calibration_targets": detector.n_calibration,
            "rank": detector.rank,
            "threshold": detector.threshold,
            "false_alarms_sweep": in_sweep.to_dict(),
            "false_alarms_new_seeds": check.to_dict(),
            # power: the smallest out-of-ODD share flagged in most targets (null: the decision detects nothing)
            "detects_from_eta": detection_floor(rates),
        },
        "sweep_seconds": seconds,
        "eta": per_eta,
    }


def eta_rows(metrics: Mapping) -> list[dict]:
    """``reports/task3/eta.json``: one row per η, ``{"eta": η, "repetitions": r, "<figure>_<kind>": …}`` (the
    figures of ``metrics["eta"]``; null where undefined: the AUCs at η = 0)."""
    return [{"eta": float(key), **row} for key, row in metrics["eta"].items()]


def eta_series(rows: Sequence[Mapping]) -> dict[str, dict[int, float]]:
    """The per-η figures as series ``"<figure>_<kind>" → {round(100·η): value}`` (MLflow metrics at step 100·η)."""
    out: dict[str, dict[int, float]] = {}
    for row in rows:
        step = round(100 * float(row["eta"]))
        for name, value in row.items():
            if name not in ("eta", "repetitions") and value is not None:
                out.setdefault(name, {})[step] = float(value)
    return out


def roc_rows(experiments: Mapping[str, Sequence[Experiment]]) -> list[dict]:
    """``reports/task3/roc.json``: the ROC curves of the relative gap, η > 0 against η = 0, per target kind, on the
    false-positive rates the η = 0 repetitions allow (j/m, j = 0…m): rows ``{"fpr": j/m, "<kind> η=<η>": TPR}``,
    the TPR the best threshold reaches at that false-positive rate or below."""
    by_kind = {kind: experiments_by_eta(es, "relative_gap") for kind, es in experiments.items()}
    m = max(len(rel[0.0]) for rel in by_kind.values())
    grid = np.linspace(0.0, 1.0, m + 1)
    rows = [{"fpr": float(x)} for x in grid]
    for kind, rel in by_kind.items():
        for eta, scores in rel.items():
            if eta == 0.0:
                continue
            fpr, tpr, _ = roc_curve(rel[0.0], scores)
            best = [float(tpr[fpr <= x + 1e-12].max()) for x in grid]
            for row, value in zip(rows, best, strict=True):
                row[f"{kind} η={_eta_key(eta)}"] = value
    return rows
