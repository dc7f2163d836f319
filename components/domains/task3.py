"""Task III (paper): the source and out-of-ODD bags of the test split, the sweep over η, and its metrics.

Used by the ``task3`` stage and its benchmark. The bags are the test images whose weather lies in a sub-box
(``task3.bags``); every image is characterized once by the registry model (its context), and the sweep
(:class:`~components.domains.sweep.NoiseSweep`) mixes them into targets at each noise level η.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from components.core.config import Params
from components.core.paths import ProjectPaths
from components.domains.relative import OddDetector
from components.domains.scenarios import in_sub_box
from components.domains.sweep import Experiment, NoiseSweep, summarize_sweep
from components.export.lookup import load_registered
from components.features import cache as features
from components.simulate import dataset

__all__ = ["bag_members", "build_sweep", "task3_metrics"]


def bag_members(params: Params, theta: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Indices of the test images of each bag (the first ``max_images`` inside its sub-box), and of each source's
    fresh pool (the other test images inside its sub-box), for the test split's true weathers ``theta (N, 6)``."""
    members, pools = {}, {}
    for name, bag in params.task3.bags.items():
        inside = np.flatnonzero(in_sub_box(theta, bag.box))
        if inside.size == 0:
            raise ValueError(
                f"task3.bags.{name}: no test image lies in its sub-box {dict(bag.box)}; widen the box or "
                "grow data.splits.test"
            )
        members[name], pools[name] = inside[: bag.max_images], inside[bag.max_images :]
        if name != "b0" and params.task3.fresh_targets and pools[name].size < members[name].size:
            raise ValueError(
                f"task3.bags.{name}: {inside.size} test images in its sub-box, too few for a fresh bag of "
                f"{members[name].size} beside the source bag; lower max_images, grow data.splits.test, "
                "or set task3.fresh_targets: false"
            )
    return members, pools


def build_sweep(params: Params, paths: ProjectPaths) -> tuple[NoiseSweep, dict[str, np.ndarray], str]:
    """The sweep of the project: the registry model's contexts of the bags' test images (from the feature cache).
    Returns the sweep, the bags' test-image indices and the model's name."""
    t = params.task3
    model = load_registered(t.model, paths.registry)  # one thread: many small calls
    test = dataset.open_split(paths.data, "test")
    members, pools = bag_members(params, test.theta)
    cached = features.open_features(paths.features, model.backbone.name, test)

    def contexts(idx: np.ndarray) -> np.ndarray:
        return model.posterior.context(features.inputs_from_cached(model.backbone, cached[idx]))

    fresh = [contexts(pools[s]) for s in t.sources] if t.fresh_targets else None
    sweep = NoiseSweep(
        model.posterior.on_context(),
        contexts(members["b0"]),
        [contexts(members[s]) for s in t.sources],
        t.weights,
        t.n_points,
        fresh_pools=fresh,
    )
    return sweep, members, model.name


def task3_metrics(
    params: Params,
    model_name: str,
    members: dict[str, np.ndarray],
    experiments: Sequence[Experiment],
    fresh_experiments: Sequence[Experiment],
    detector: OddDetector,
    seconds: float,
) -> dict:
    """The per-η medians, AUCs and flagged rates of the paper's targets (and of the fresh ones, which the ODD
    decision is judged on when ``task3.fresh_targets``), with the decision's threshold and observed false-alarm rate."""
    t = params.task3
    fresh = t.fresh_targets
    decided = fresh_experiments if fresh else experiments
    paper, judged = summarize_sweep(experiments, detector), summarize_sweep(decided, detector)
    per_eta = {}
    for key, row in paper.items():
        per_eta[key] = {
            **{
                k: row[k]
                for k in (
                    "d_e_median",
                    "gap_median",
                    "baseline_gap_median",
                    "relative_gap_median",
                    "baseline_relative_gap_median",
                )
            },
            **({"auc": judged[key]["auc"], "auc_same_images": row["auc"]} if "auc" in row else {}),
            "flagged_rate": judged[key]["flagged_rate"],
        }
        if fresh:
            per_eta[key]["fresh"] = {k: judged[key][k] for k in ("d_e_median", "gap_median", "relative_gap_median")}
    return {
        "model": model_name,
        "bags": {n: int(i.size) for n, i in members.items()},
        "n_points": t.n_points,
        "odd": {
            "statistic": "relative_gap",
            "targets": "fresh" if fresh else "paper",
            "threshold": detector.threshold,
            "false_alarm_rate": t.false_alarm_rate,
            "calibration_targets": detector.n_calibration,
            "observed_false_alarm_rate": per_eta["0"]["flagged_rate"],
        },
        "experiments": len(experiments) + len(fresh_experiments),
        "sweep_seconds": seconds,
        "eta": per_eta,
    }
