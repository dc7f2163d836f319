"""Posterior inference speed: the torch-free ONNX runtime vs the torch model (eager), on a trained model.

For each image, features → ``n`` posterior draws θ with their log-densities log q(θ | x):
``OnnxPosterior.sample_and_log_prob`` (onnxruntime, CPU) vs ``NPE.sample_and_log_prob`` (torch, no autograd).
Per-image latency (batch of one image, median over images) and throughput (batches of ``--batch`` images),
with the same thread count on both sides; the engines alternate call by call, so that a drifting machine load
affects them alike. The model is exported to a temporary folder first (not timed). For an ensemble a third engine,
"every member's density", draws as the runtime did before card format 2: each draw's log q from all K members'
density graphs, instead of the drawing member's from its inverse pass and the K − 1 others'
(:func:`draw_with_every_density`).

    .venv/bin/python benchmarks/bench_runtime.py --model models/cues-50000/model.pt --threads 1

Inputs are cached features (``--features``, an ``.npy`` of shape ``(N, F)``; default the first test shard of
``features/<backbone>/`` when present) or random features spread like the training set's. Prints a table and
one JSON line (``{"benchmark": "runtime", ...}``) with machine information.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from machine import machine_info  # benchmarks/machine.py (the script's folder is on sys.path)  # noqa: E402

from components.core import seeding, weather  # noqa: E402
from components.export.onnx import EXPORTERS, export_posterior  # noqa: E402
from components.export.runtime import OnnxPosterior  # noqa: E402
from components.posterior.store import load_npe  # noqa: E402


def _inputs(path: Path | None, model, count: int, seed: int) -> tuple[np.ndarray, str]:
    """``count`` feature vectors (float32) and a description of where they come from."""
    if path is not None and path.is_file():
        x = np.load(path, allow_pickle=False).astype(np.float32)
        if x.ndim != 2 or x.shape[1:] != tuple(model.input_shape):
            raise ValueError(f"{path}: features must have shape (N, {model.input_shape[0]}), got {x.shape}")
        reps = -(-count // len(x))
        return np.concatenate([x] * reps)[:count], str(path)
    rng = seeding.rng(seed, "benchmark", "runtime")
    mean, std = model.feature_mean.numpy(), model.feature_std.numpy()
    return (rng.standard_normal((count, *model.input_shape)) * std + mean).astype(np.float32), "random"


def draw_with_every_density(runtime: OnnxPosterior, x: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``runtime.sample_and_log_prob(x, n, seed)`` computed as before card format 2: the same draws, each one's
    mixture density from every member's density graph (the drawing member's inverse-pass density unused)."""
    context = runtime.context(x)
    eps, which = runtime._noise(x.shape[0], n, seed)
    b, _, d = eps.shape
    c_rows, e_rows, w_rows = np.repeat(context, n, axis=0), eps.reshape(b * n, 1, d), which.reshape(b * n)
    z64 = np.empty((b * n, d), dtype=np.float64)
    for k in range(runtime.ensemble):
        rows = np.flatnonzero(w_rows == k)
        if rows.size:
            zk, _ = runtime._invert(k, np.ascontiguousarray(c_rows[rows]), np.ascontiguousarray(e_rows[rows]))
            z64[rows] = zk[:, 0]
    members = np.stack([runtime._log_qz_member(k, c_rows, z64) for k in range(runtime.ensemble)], axis=1)
    log_q = runtime._log_qz_mixture(members) - weather.log_abs_det_jacobian(z64, runtime.box)
    return weather.to_physical(z64, runtime.box).reshape(b, n, d), log_q.reshape(b, n)


def _latency(calls: dict[str, Callable[[np.ndarray], object]], x: np.ndarray) -> dict[str, float]:
    """Median seconds per engine on one image at a time; engines alternate image by image (fair under drifting load)."""
    times: dict[str, list[float]] = {name: [] for name in calls}
    for call in calls.values():
        call(x[:1])  # warm-up
    for i in range(len(x)):
        for name, call in calls.items():
            t = time.perf_counter()
            call(x[i : i + 1])
            times[name].append(time.perf_counter() - t)
    return {name: statistics.median(ts) for name, ts in times.items()}


def _throughput(
    calls: dict[str, Callable[[np.ndarray], object]], x: np.ndarray, batch: int, repeats: int
) -> dict[str, float]:
    """Best images per second per engine over ``repeats`` passes over ``x`` in batches of ``batch`` (engines alternate)."""
    best = {name: 0.0 for name in calls}
    for call in calls.values():
        call(x[:batch])
    for _ in range(repeats):
        for name, call in calls.items():
            t = time.perf_counter()
            for i in range(0, len(x), batch):
                call(x[i : i + batch])
            best[name] = max(best[name], len(x) / (time.perf_counter() - t))
    return best


def flops_per_draw(model) -> float:
    """Floating-point operations of one posterior draw through the exported sampling graph (dense, as executed).

    Per autoregressive (coupling) transform, one hyper-network evaluation per draw: the first layer on θ's d inputs
    only (its context share runs once per image), then every other layer in full (2·in·out each, masks included: the
    graph multiplies dense matrices), plus the rational-quadratic spline (~30 operations per bin and parameter).
    For an ensemble a draw also evaluates the mixture's density under every member (one more pass each).
    """
    total = 0.0
    for flow in model.flows:
        per = 0.0
        for t in flow.transform.transforms:
            if not hasattr(t, "hyper"):
                continue
            linears = [m for m in t.hyper.modules() if isinstance(m, torch.nn.Linear)]
            first, rest = linears[0], linears[1:]
            per += 2.0 * model.dim * first.out_features + sum(2.0 * m.in_features * m.out_features for m in rest)
            per += 30.0 * model.config.bins * model.dim
        total += per
    return total / len(model.flows) * (1 if len(model.flows) == 1 else 1 + len(model.flows))


def dense_peak_flops(threads: int, size: int = 1024, repeats: int = 5) -> float:
    """Measured float32 GEMM rate of this CPU (torch.mm, ``threads`` threads): the practical floating-point bound."""
    torch.set_num_threads(threads)
    a, b = torch.randn(size, size), torch.randn(size, size)
    torch.mm(a, b)
    best = 0.0
    for _ in range(repeats):
        t = time.perf_counter()
        torch.mm(a, b)
        best = max(best, 2.0 * size**3 / (time.perf_counter() - t))
    return best


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=ROOT / "models" / "cues-50000" / "model.pt")
    parser.add_argument("--features", type=Path, default=None, help="an .npy of cached features (N, F)")
    parser.add_argument("--samples", type=int, default=1000, help="posterior draws per image")
    parser.add_argument("--images", type=int, default=30, help="images timed one by one (latency)")
    parser.add_argument("--batch", type=int, default=32, help="images per call (throughput)")
    parser.add_argument("--batches", type=int, default=4, help="batches per throughput pass")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch threads = onnxruntime intra-op threads")
    parser.add_argument("--exporter", choices=EXPORTERS, default="dynamo")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    model, header = load_npe(args.model)
    if model.embedding is not None and not isinstance(model.embedding, torch.nn.Identity):
        raise SystemExit(
            f"{args.model}: this benchmark times feature models (frozen backbones); got a trainable embedding"
        )
    features = args.features
    if features is None:
        features = ROOT / "features" / header["backbone"] / "test" / "shard-00000.npy"
    x, source = _inputs(features, model, max(args.images, args.batch * args.batches), args.seed)

    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        folder = export_posterior(model, Path(tmp) / "posterior", card={"benchmark": True}, exporter=args.exporter)
        export_s = time.perf_counter() - t
        runtime = OnnxPosterior.load(folder, intra_op_num_threads=args.threads)

        def run_onnx(batch: np.ndarray) -> object:
            return runtime.sample_and_log_prob(batch, args.samples, seed=args.seed)

        def run_torch(batch: np.ndarray) -> object:
            with torch.no_grad():
                return model.sample_and_log_prob(torch.from_numpy(batch), args.samples, rng=args.seed)

        calls = {"onnxruntime": run_onnx, "torch eager": run_torch}
        if runtime.ensemble > 1:
            calls["every member's density"] = lambda batch: draw_with_every_density(
                runtime, batch, args.samples, args.seed
            )
            same, every = run_onnx(x[:4]), calls["every member's density"](x[:4])
            if not np.array_equal(same[0], every[0]) or np.abs(same[1] - every[1]).max() > 1e-2:
                raise SystemExit(
                    "the two ways of drawing disagree: not the same draws, or densities apart by > 0.01 nats"
                )
        latency = _latency(calls, x[: args.images])
        throughput = _throughput(calls, x[: args.batch * args.batches], args.batch, args.repeats)
        rows = {name: {"latency_ms": 1e3 * latency[name], "images_per_s": throughput[name]} for name in calls}

    onnx_row, torch_row = rows["onnxruntime"], rows["torch eager"]
    speedup_latency = torch_row["latency_ms"] / onnx_row["latency_ms"]
    speedup_throughput = onnx_row["images_per_s"] / torch_row["images_per_s"]
    print(f"model {args.model} ({source} features), {args.samples} draws + log q per image, {args.threads} thread(s)")
    print(f"{'engine':<24}{'latency ms/image':>18}{'images/s (batch ' + str(args.batch) + ')':>22}")
    for name, row in rows.items():
        print(f"{name:<24}{row['latency_ms']:>18.2f}{row['images_per_s']:>22.1f}")
    print(f"onnxruntime speed-up: latency {speedup_latency:.2f}×, throughput {speedup_throughput:.2f}×")
    if "every member's density" in rows:
        every = rows["every member's density"]
        print(
            f"the drawing member's density from its inverse pass: {onnx_row['images_per_s'] / every['images_per_s']:.2f}× "
            f"the throughput of every member's density graph ({every['images_per_s']:.1f} images/s), latency "
            f"{onnx_row['latency_ms'] / every['latency_ms']:.2f}× the time"
        )
    flops = flops_per_draw(model)
    peak = dense_peak_flops(args.threads)
    draws = onnx_row["images_per_s"] * args.samples
    bound = peak / flops
    print(
        f"sampling: {draws:,.0f} draws/s on onnxruntime; {flops / 1e3:.1f} kFLOP per draw; dense float32 peak "
        f"{peak / 1e9:.1f} GFLOP/s → bound {bound:,.0f} draws/s; achieved {draws / bound:.0%} of the bound"
    )
    record = {
        "benchmark": "runtime",
        "model": str(args.model),
        "features": source,
        "samples": args.samples,
        "batch": args.batch,
        "exporter": args.exporter,
        "export_seconds": export_s,
        "results": rows,
        "speedup_latency": speedup_latency,
        "speedup_throughput": speedup_throughput,
        "flops_per_draw": flops,
        "dense_peak_flops": peak,
        "draws_per_s": draws,
        "draws_bound_per_s": bound,
        "machine": machine_info(threads=args.threads),
    }
    print(json.dumps(record))
    return record


if __name__ == "__main__":
    main()
