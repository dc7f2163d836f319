"""The splines' bin lookup in the exported graphs: one-hot sums (the export's) against zuko's gathers.

Exports member 0's sample graph (:class:`components.export.onnx._SampleGraph`; ``--graph log_prob``: its density
graph, :class:`components.export.onnx._LogProbGraph`) of a trained model twice — as the export stage does (bins read
by one-hot sums, :class:`components.export.onnx._OneHotRQS`) and with zuko's own spline (``torch.gather``,
GatherElements in ONNX) — checks that both give the same outputs to the bit, and times them in onnxruntime,
alternating call by call, one thread, on the test split's contexts (or random ones).

    .venv/bin/python benchmarks/studies/bench_spline_lookup.py [--graph sample|log_prob] [--model models/cues-50000/model.pt]

Prints µs per draw for each (median and best) and the median ratio of adjacent calls, and one JSON line
(``{"benchmark": "spline_lookup", ...}``) with machine information.
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
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import components.export.onnx as export_onnx  # noqa: E402
from benchmarks.machine import machine_info  # noqa: E402
from components.core import seeding  # noqa: E402
from components.posterior.store import load_npe  # noqa: E402

SAMPLE_AXES = {"context": ("batch",), "eps": ("batch", "draws"), "z": ("batch", "draws"), "log_qz": ("batch", "draws")}
LOG_PROB_AXES = {"context": ("batch",), "z": ("batch",), "log_qz": ("batch",)}


def _export(graph: str, flow: torch.nn.Module, context: torch.Tensor, d: int, path: Path, gathers: bool) -> None:
    """Member ``flow``'s ``graph`` (``sample`` or ``log_prob``) to ``path``; ``gathers``: with zuko's spline instead of
    the one-hot lookup."""
    swap = export_onnx._one_hot_univariate
    if gathers:
        export_onnx._one_hot_univariate = lambda univariate: univariate  # zuko's spline, as before the change
    try:
        with torch.no_grad():
            if graph == "sample":
                module, args = export_onnx._SampleGraph(flow), (context[:2], torch.zeros(2, 3, d))
                names, axes = (["context", "eps"], ["z", "log_qz"]), SAMPLE_AXES
            else:
                module, args = export_onnx._LogProbGraph(flow), (context[:2], torch.zeros(2, d))
                names, axes = (["context", "z"], ["log_qz"]), LOG_PROB_AXES
            export_onnx._export_graph(module, args, path, *names, "dynamo", axes)
    finally:
        export_onnx._one_hot_univariate = swap


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", type=Path, default=ROOT / "models" / "cues-50000" / "model.pt")
    p.add_argument("--batch", type=int, default=32, help="inputs per call")
    p.add_argument("--draws", type=int, default=500, help="draws per input")
    p.add_argument("--repeats", type=int, default=40, help="timed calls of each graph, alternating")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--graph",
        choices=["sample", "log_prob"],
        default="sample",
        help="sample: a member's draws (sample_<k>.onnx); log_prob: its density at batch × draws points, each with "
        "its input's context (log_prob_<k>.onnx, as the runtime asks an ensemble's other members)",
    )
    args = p.parse_args(argv)
    if min(args.batch, args.draws, args.repeats) < 1:
        p.error("--batch, --draws and --repeats must be at least 1")
    import onnxruntime

    model, header = load_npe(args.model)
    model.eval()
    flow = model.flows[0]
    rng = seeding.rng(args.seed, "benchmark", "spline-lookup")
    shard = ROOT / "features" / str(header["backbone"]) / "test" / "shard-00000.npy"
    if not header["trainable_backbone"] and shard.is_file():
        x = torch.from_numpy(np.load(shard, allow_pickle=False)[: args.batch].astype(np.float32))
        source = str(shard.relative_to(ROOT))
    else:
        x = torch.from_numpy((rng.standard_normal((args.batch, *model.input_shape))).astype(np.float32))
        source = "random"
    with torch.no_grad():
        context = export_onnx._ContextGraph(model)(x)
    d = len(model.box.names)
    eps = rng.standard_normal((len(x), args.draws, d)).astype(np.float32)
    if args.graph == "sample":
        feeds = {"context": context.numpy(), "eps": eps}
    else:
        feeds = {"context": np.repeat(context.numpy(), args.draws, axis=0), "z": eps.reshape(-1, d)}
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
    sessions, outputs = {}, {}
    with tempfile.TemporaryDirectory(prefix="spline-lookup-") as tmp:
        for name, gathers in (("one-hot", False), ("gather", True)):
            path = Path(tmp) / f"{name}.onnx"
            _export(args.graph, flow, context, d, path, gathers)
            sessions[name] = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
            outputs[name] = sessions[name].run(None, feeds)
    identical = all(np.array_equal(a, b) for a, b in zip(outputs["one-hot"], outputs["gather"], strict=True))
    times: dict[str, list[float]] = {name: [] for name in sessions}
    for _ in range(args.repeats):
        for name, session in sessions.items():
            start = time.perf_counter()
            session.run(None, feeds)
            times[name].append(time.perf_counter() - start)
    per_draw = {name: 1e6 * statistics.median(t) / (len(x) * args.draws) for name, t in times.items()}
    best = {name: 1e6 * min(t) / (len(x) * args.draws) for name, t in times.items()}
    # the ratio of each pair of adjacent calls, its median: robust to the machine's drift within the run
    ratio = statistics.median(g / o for g, o in zip(times["gather"], times["one-hot"], strict=True))
    print(f"{args.graph} graph of {args.model}, contexts {source}, {len(x)} inputs × {args.draws} draws, one thread")
    for name, us in per_draw.items():
        print(f"{name:8s} {us:7.2f} µs a draw (median; best {best[name]:.2f})")
    print(
        f"one-hot lookup: {ratio:.2f}× as fast (median of {args.repeats} paired calls); the same draws and "
        f"log-densities to the bit: {identical}"
    )
    record = {
        "benchmark": "spline_lookup",
        "graph": args.graph,
        "model": str(args.model),
        "contexts": source,
        "batch": len(x),
        "draws": args.draws,
        "us_per_draw": per_draw,
        "us_per_draw_best": best,
        "speedup": ratio,
        "bit_identical": identical,
        "machine": machine_info(threads=1),
    }
    print(json.dumps(record))
    if not identical:
        raise SystemExit("the two graphs disagree: the one-hot lookup must give zuko's draws to the bit")
    return record


if __name__ == "__main__":
    main()
