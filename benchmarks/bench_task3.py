"""The Task III sweep on the project's registry model: 330 experiments (11 η × 30) and the ODD calibration.

Builds the sweep exactly as the ``task3`` stage does (:func:`components.domains.task3.build_sweep`: the bags' contexts computed
once, then every experiment = a target drawn and related to the three sources with n_W points, CVXPY solve, chance
baseline) and times (a) the contexts, (b) the calibration targets, (c) the 330 experiments. Needs the pipeline's
registry/ and features/ (``dvc repro evaluate`` at least).

    .venv/bin/python benchmarks/bench_task3.py [--params params.yaml] [--model cnn-3000]

Prints a table and one JSON line (``{"benchmark": "task3", ...}``) with machine information.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import yaml  # noqa: E402
from machine import machine_info  # noqa: E402

from components.core.config import load_params  # noqa: E402
from components.core.paths import ProjectPaths  # noqa: E402
from components.domains.task3 import build_sweep  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", type=Path, default=ROOT / "params.yaml")
    parser.add_argument("--model", help="registry model id (default: task3.model of the params file)")
    args = parser.parse_args()
    params_file = args.params
    if args.model:  # a copy of the params with another model, beside the original (same project folder)
        data = yaml.safe_load(params_file.read_text())
        data["task3"]["model"] = args.model
        params_file = params_file.resolve().parent / f".bench-task3-{args.model}.yaml"
        params_file.write_text(yaml.safe_dump(data))
    try:
        params = load_params(params_file)
        t = params.task3
        t0 = time.perf_counter()
        sweep, members, model = build_sweep(params, ProjectPaths.of(params, params_file))
        t_build = time.perf_counter() - t0
        t0 = time.perf_counter()
        sweep.calibrate(t.calibration_targets, t.false_alarm_rate, params.seed, fresh=t.fresh_targets)
        t_cal = time.perf_counter() - t0
        timed = {}
        for fresh in (False, True) if t.fresh_targets else (False,):
            t0 = time.perf_counter()
            n = 0
            for eta in t.etas:
                for r in range(t.repetitions):
                    sweep.run(eta, r, params.seed, fresh)
                    n += 1
            timed["fresh" if fresh else "paper"] = time.perf_counter() - t0
        t_sweep = timed["paper"]
    finally:
        if args.model:
            params_file.unlink(missing_ok=True)
    print(f"model {model}, bags {sweep.sizes}, n_W = {t.n_points}")
    print("| part | seconds |\n|---|---|")
    print(f"| bags' contexts (registry model, {sum(sweep.sizes)} images) | {t_build:.2f} |")
    print(f"| ODD calibration ({t.calibration_targets} in-ODD targets) | {t_cal:.2f} |")
    print(f"| sweep, the paper's targets ({n} experiments) | {t_sweep:.2f} |")
    if "fresh" in timed:
        print(f"| sweep, fresh targets ({n} experiments) | {timed['fresh']:.2f} |")
    print(f"| per experiment (paper) | {1000 * t_sweep / n:.1f} ms |")
    print(
        json.dumps(
            {
                "benchmark": "task3",
                "model": model,
                "bags": sweep.sizes,
                "experiments": n,
                "contexts_s": t_build,
                "calibration_s": t_cal,
                "sweep_s": t_sweep,
                "fresh_sweep_s": timed.get("fresh"),
                **machine_info(),
            }
        )
    )


if __name__ == "__main__":
    main()
