"""Task III solve time: 330 ``relate`` calls (n_W = 16, K = 3) with the reused parametrized CVXPY problem vs a
problem rebuilt (and recompiled) for every call.

The workload is the paper's protocol (11 noise levels η × 30 targets, target = (1 − η)·Σₖ λₖ 𝒮ₖ + η·𝒟_out with
λ = (0.2, 0.3, 0.5)) on bags of 27, 21, 26 and 176 members under a closed-form 6-D Gaussian posterior
q(θ | x) = N(θ; x, σ²I), so the posterior costs little and the QP dominates. Two timings per mode: the whole
``relate`` (draws, densities, solve) and the solve alone on the same (A, b).

    .venv/bin/python benchmarks/bench_relative.py --repeats 3

Prints a table and one JSON line (``{"benchmark": "relative", ...}``) with machine information.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from components.core import seeding  # noqa: E402
from components.domains.absolute import Domain, mixture_of  # noqa: E402
from components.domains.relative import SimplexLeastSquares, relate  # noqa: E402


class GaussianPosterior:
    """q(θ | x) = N(θ; x, σ²I) in physical units (a closed-form stand-in for the NPE)."""

    def __init__(self, sigma: float) -> None:
        self.sigma = sigma

    def log_prob(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        d = theta.shape[1]
        z = (theta - x) / self.sigma
        return -0.5 * np.sum(z**2, axis=1) - d * np.log(self.sigma) - 0.5 * d * np.log(2 * np.pi)

    def sample(self, x: np.ndarray, n: int, seed: int) -> np.ndarray:
        eps = seeding.rng(seed, "benchmark", "posterior").standard_normal((x.shape[0], n, x.shape[1]))
        return x[:, None, :] + self.sigma * eps


def _targets(seed: int) -> tuple[list[Domain], list[Domain]]:
    post = GaussianPosterior(5.0)
    g = seeding.rng(seed, "benchmark", "relative", "bags")
    sources = [Domain(post, g.uniform(lo, lo + 20, size=(n, 6))) for lo, n in ((0, 27), (30, 21), (60, 26))]
    outside = g.uniform(90, 100, size=(176, 6))
    in_odd = mixture_of(sources, [0.2, 0.3, 0.5])
    targets = []
    for eta in np.linspace(0.0, 1.0, 11):
        for _ in range(30):
            out = Domain(post, outside, g.random(176))
            targets.append(mixture_of([in_odd, out], [1 - eta, eta]))
    return sources, targets


def _time_relate(sources, targets, reuse: bool) -> tuple[float, list]:
    shared = SimplexLeastSquares()
    t0 = time.perf_counter()
    rels = [
        relate(t, sources, 16, seed=i, solver=shared if reuse else SimplexLeastSquares()) for i, t in enumerate(targets)
    ]
    return time.perf_counter() - t0, rels


def _time_solve(rels, reuse: bool) -> float:
    shared = SimplexLeastSquares()
    t0 = time.perf_counter()
    for rel in rels:
        (shared if reuse else SimplexLeastSquares()).solve(rel.A, rel.b)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3, help="timings per mode; the best is reported")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    sources, targets = _targets(args.seed)
    _time_relate(sources, targets[:5], True)  # import/JIT warm-up of cvxpy and the solver
    best: dict[str, float] = {}
    for mode, reuse in (("reused", True), ("rebuilt", False)):
        runs = [_time_relate(sources, targets, reuse) for _ in range(args.repeats)]
        best[f"relate_{mode}_s"] = min(t for t, _ in runs)
        rels = runs[0][1]
        best[f"solve_{mode}_s"] = min(_time_solve(rels, reuse) for _ in range(args.repeats))
    n = len(targets)
    print(f"{'mode':<10}{'relate total s':>16}{'relate ms/call':>16}{'solve total s':>15}{'solve ms/call':>15}")
    for mode in ("reused", "rebuilt"):
        r, s = best[f"relate_{mode}_s"], best[f"solve_{mode}_s"]
        print(f"{mode:<10}{r:>16.3f}{1e3 * r / n:>16.2f}{s:>15.3f}{1e3 * s / n:>15.2f}")
    ratio_relate = best["relate_rebuilt_s"] / best["relate_reused_s"]
    ratio_solve = best["solve_rebuilt_s"] / best["solve_reused_s"]
    print(f"rebuilt / reused: relate ×{ratio_relate:.2f}, solve ×{ratio_solve:.2f}  (n = {n} solves, n_W = 16, K = 3)")
    print(
        json.dumps(
            {
                "benchmark": "relative",
                "n_solves": n,
                "n_points": 16,
                "n_sources": 3,
                "solver": "CLARABEL",
                **{k: round(v, 4) for k, v in best.items()},
                "ratio_relate_rebuilt_over_reused": round(ratio_relate, 3),
                "ratio_solve_rebuilt_over_reused": round(ratio_solve, 3),
                "python": platform.python_version(),
                "machine": platform.machine(),
                "cpus": os.cpu_count(),
                "load_avg_1min": round(os.getloadavg()[0], 2),
            }
        )
    )


if __name__ == "__main__":
    main()
