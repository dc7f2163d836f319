"""An ensemble's posterior draws: each member's draws packed per input (the runtime's) vs one row per draw (before).

``OnnxPosterior`` draws each θ from one member of an equal-weight ensemble. The member's inverse graph shares an
input's context (and the first inversion pass, at x = 0) among the draws given in one ``(B, n, d)`` block. The runtime
packs each member's draws of an input into such a block (padding the rest); before, every draw was a row of its own
(``(B·n, 1, d)``, its context repeated), which this script keeps as the alternative. Both then take the mixture's
density of the draws. Timed as the ``evaluate`` stage calls it (:func:`components.evaluate.task1.posterior_draws`: the
test split's cached features, 4 images per call, 500 draws each, one onnxruntime thread), alternated ``--repeats``
times; the draws and densities of the two are compared for equality.

    .venv/bin/python benchmarks/bench_draws.py --model registry/cues-50000 --images 200

Prints a table and one JSON line (``{"benchmark": "draws", ...}``) with machine information.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from machine import machine_info  # benchmarks/machine.py (the script's folder is on sys.path)  # noqa: E402

from components.core import seeding, weather  # noqa: E402
from components.export.runtime import OnnxPosterior  # noqa: E402
from components.features import cache  # noqa: E402
from components.simulate import dataset  # noqa: E402


def row_per_draw(p: OnnxPosterior, context: np.ndarray, eps: np.ndarray, which: np.ndarray):
    """The layout before: every draw a row of its own (its context repeated), then the mixture's density."""
    b, n, d = eps.shape
    c_rows = np.repeat(context, n, axis=0)
    e_rows = eps.reshape(b * n, 1, d)
    w_rows = which.reshape(b * n)
    z64 = np.empty((b * n, d), dtype=np.float64)
    for k in range(p.ensemble):
        rows = np.flatnonzero(w_rows == k)
        if rows.size:
            zk, _ = p._invert(k, np.ascontiguousarray(c_rows[rows]), np.ascontiguousarray(e_rows[rows]))
            z64[rows] = zk[:, 0]
    log_qz = p._log_qz_mixture(c_rows, z64)
    theta = weather.to_physical(z64, p.box)
    log_q = log_qz - weather.log_abs_det_jacobian(z64, p.box)
    return theta.reshape(b, n, d), log_q.reshape(b, n)


def draws(draw, context: np.ndarray, noise: list[tuple[np.ndarray, np.ndarray]], chunk: int):
    """All images' draws, ``chunk`` images per call, as ``posterior_draws`` does; and the seconds it took."""
    t0 = time.perf_counter()
    out = [
        draw(context[a : a + chunk], *[np.stack(v) for v in zip(*noise[a : a + chunk], strict=True)])
        for a in range(0, len(context), chunk)
    ]
    seconds = time.perf_counter() - t0
    return np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out]), seconds


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", type=Path, default=ROOT / "registry" / "cues-50000", help="an exported ensemble")
    p.add_argument("--images", type=int, default=200, help="the first images of the test split")
    p.add_argument("--draws", type=int, default=500)
    p.add_argument("--chunk", type=int, default=4, help="images per call (the evaluate stage's)")
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args(argv)
    posterior = OnnxPosterior.load(a.model, intra_op_num_threads=1)
    if posterior.ensemble < 2:
        p.error(f"{a.model}: a single flow ({posterior.card['model_id']}); the layouts differ for ensembles only")
    backbone = posterior.card["backbone"]
    split = dataset.open_split(ROOT / "data", "test")
    x = cache.open_features(ROOT / "features", backbone, split)[: a.images].astype(np.float32)
    context = posterior.context(x)
    noise = []
    for i in range(len(x)):  # the evaluate stage's streams
        rng = seeding.rng(0, "evaluate", i)
        eps = rng.standard_normal((a.draws, posterior.dim), dtype=np.float32)
        noise.append((eps, rng.integers(posterior.ensemble, size=a.draws)))
    layouts = {
        "packed per input (runtime)": posterior._draw,
        "one row per draw (before)": row_per_draw.__get__(posterior),
    }
    seconds: dict[str, list[float]] = {k: [] for k in layouts}
    results = {}
    for _ in range(a.repeats):  # alternated: a drifting load affects both alike
        for name, draw in layouts.items():
            theta, log_q, s = draws(draw, context, noise, a.chunk)
            seconds[name].append(s)
            results[name] = (theta, log_q)
    (t1, l1), (t2, l2) = results.values()
    same = bool(np.array_equal(t1, t2) and np.array_equal(l1, l2))
    diff = float(np.max(np.abs(t1 - t2) / posterior.box.width))
    base = statistics.median(seconds["one row per draw (before)"])
    print(f"{a.model.name}: {a.images} images × {a.draws} draws, {a.chunk} images per call; byte-identical: {same}")
    print("| layout | median s | ratio to before |")
    print("|---|---|---|")
    for name, s in seconds.items():
        print(f"| {name} | {statistics.median(s):.2f} | {statistics.median(s) / base:.2f} |")
    print(
        json.dumps(
            {
                "benchmark": "draws",
                "model": a.model.name,
                "images": a.images,
                "draws": a.draws,
                "chunk": a.chunk,
                "seconds": seconds,
                "identical": same,
                "max_theta_difference_share_of_range": diff,
                **machine_info(threads=1),
            }
        )
    )


if __name__ == "__main__":
    main()
