"""Task III on the project's registry model, side by side for each way of characterizing a bag (``task3.smoothing``).

Builds the sweep exactly as the ``task3`` stage does (:func:`components.domains.task3.build_sweep`: the bags'
contexts computed once, then every experiment = a target drawn and related to the sources with n_W points, CVXPY
solve, chance baseline), once per smoothing (``none``: the paper's exact mixture of posteriors; ``scott``: the kernel
density of :mod:`components.domains.kernel`), on the same bags, images and seeds. For each: median d_E at η = 0 for
the paper's and for fresh targets, the fresh targets' ODD AUC at each η, the false-alarm rate of the decision
calibrated on fresh in-ODD targets measured on new seeds (Clopper–Pearson interval), and the seconds each part took.
Needs the pipeline's registry/ and features/ (``dvc repro evaluate`` at least).

    .venv/bin/python benchmarks/studies/bench_task3.py [--params params.yaml] [--model champion] [--smoothing none scott]
        [--bandwidth-scale 0.5 1 2 3 4] [--n-points 16 64] [--block-pairs 1048576 131072]

``--bandwidth-scale`` and ``--n-points`` replace ``task3.bandwidth_scale`` and ``task3.n_points``: every combination
is measured (the scale only matters for ``scott``). ``--block-pairs`` times the kernel density's (θ, centre) pairs per
block of ``log_prob`` (``components.domains.kernel._CENTRES_PER_CALL``; ``scott`` only), each in turn.

Prints a table and one JSON line (``{"benchmark": "task3", ...}``) with machine information.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.core.paths import ProjectPaths  # noqa: E402
from components.domains import kernel  # noqa: E402
from components.domains.sweep import SMOOTHINGS, summarize_sweep  # noqa: E402
from components.domains.task3 import build_sweep  # noqa: E402
from components.export.lookup import load_registered, read_champion  # noqa: E402


def measure(params, paths, model, smoothing: str, scale: float, n_points: int) -> dict:
    t = params.task3
    changes = {"smoothing": smoothing, "fresh_targets": True, "bandwidth_scale": scale, "n_points": n_points}
    p = params.model_copy(update={"task3": t.model_copy(update=changes)})
    t0 = time.perf_counter()
    sweep, _, name = build_sweep(p, paths, model)
    out: dict = {"smoothing": smoothing, "bandwidth_scale": scale, "n_points": n_points, "model": name}
    out["block_pairs"] = kernel._CENTRES_PER_CALL if smoothing == "scott" else None
    out |= {"bags": sweep.sizes, "build_s": time.perf_counter() - t0}
    t0 = time.perf_counter()
    detector, _ = sweep.calibrate(t.calibration_targets, t.false_alarm_rate, params.seed, fresh=True)
    check, _ = sweep.check_false_alarms(detector, t.false_alarm_targets, params.seed, fresh=True)
    out["calibration_s"] = time.perf_counter() - t0
    out["false_alarms"] = check.to_dict()
    for kind in ("paper", "fresh"):
        t0 = time.perf_counter()
        experiments = [sweep.run(eta, r, params.seed, kind == "fresh") for eta in t.etas for r in range(t.repetitions)]
        out[f"{kind}_s"] = time.perf_counter() - t0
        summary = summarize_sweep(experiments, detector)
        out[kind] = {
            eta: {k: row[k] for k in ("d_e_median", "flagged_rate", "auc") if k in row} for eta, row in summary.items()
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", type=Path, default=ROOT / "params.yaml")
    parser.add_argument("--model", default="champion", help="registry model id, or champion (default)")
    parser.add_argument("--smoothing", nargs="+", choices=SMOOTHINGS, default=list(SMOOTHINGS))
    parser.add_argument("--bandwidth-scale", nargs="+", type=float, help="default: task3.bandwidth_scale")
    parser.add_argument("--n-points", nargs="+", type=int, help="default: task3.n_points")
    parser.add_argument("--block-pairs", nargs="+", type=int, help=f"default: the library's {kernel._CENTRES_PER_CALL}")
    args = parser.parse_args()
    params = load_params(args.params)
    paths = ProjectPaths.of(params, args.params)
    model_id = read_champion(paths.registry)["model"] if args.model == "champion" else args.model
    model = load_registered(model_id, paths.registry)
    t = params.task3
    scales, points = args.bandwidth_scale or [t.bandwidth_scale], args.n_points or [t.n_points]
    blocks = args.block_pairs or [kernel._CENTRES_PER_CALL]
    if min(blocks) < 1:
        parser.error("--block-pairs must be positive")
    results = []
    for s in args.smoothing:
        for block in blocks if s == "scott" else blocks[:1]:
            kernel._CENTRES_PER_CALL = block
            for scale in scales if s == "scott" else scales[:1]:
                results += [measure(params, paths, model, s, scale, n) for n in points]
    etas = [f"{e:g}" for e in t.etas if e > 0]
    print(f"model {model_id}, bags {results[0]['bags']}, {t.repetitions} targets per η")
    print(
        "| smoothing | block pairs | bandwidth scale | n_W | d_E η=0 paper | d_E η=0 fresh | fresh AUC at η = "
        + " / ".join(etas)
        + " | false alarms (new seeds) | seconds |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        fa = r["false_alarms"]
        auc = " / ".join(f"{r['fresh'][e]['auc']:.2f}" for e in etas)
        seconds = r["build_s"] + r["calibration_s"] + r["paper_s"] + r["fresh_s"]
        print(
            f"| {r['smoothing']} | {r['block_pairs'] or '–'} | {r['bandwidth_scale']:g} | {r['n_points']} | {r['paper']['0']['d_e_median']:.3g} | "
            f"{r['fresh']['0']['d_e_median']:.3f} | {auc} | "
            f"{fa['flagged']}/{fa['n']} = {fa['rate']:.3f} [{fa['ci_low']:.3f}, {fa['ci_high']:.3f}] | {seconds:.0f} |"
        )
    print(json.dumps({"benchmark": "task3", "results": results, **machine_info()}))


if __name__ == "__main__":
    main()
