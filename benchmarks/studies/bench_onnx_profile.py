"""Where an exported sample graph spends its time: onnxruntime's profiler, kernel time per operator type.

The question behind it: the sample graph of the champion runs at a fraction of its floating-point bound
(``benchmarks/bench_runtime.py``: the draws a second at the CPU's dense float32 GEMM rate for the graph's FLOPs). If
the matrix products held the time, a faster GEMM would move it; if the element-wise spline arithmetic does, only a
fused spline kernel would. One thread, the runtime's own session settings (``ORT_ENABLE_ALL``), ``--batch`` images ×
``--draws`` draws per call, standard-normal inputs (the graph's arithmetic does not depend on their values).

    .venv/bin/python benchmarks/studies/bench_onnx_profile.py --graph registry/cues-50000/sample_0.onnx

Prints the share of kernel time per operator type and one JSON line. Record: docs/studies/onnx-draw-profile.md.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np
import onnxruntime


def op_shares(graph: Path, batch: int, draws: int, runs: int, seed: int) -> dict[str, float]:
    """Share of the summed kernel time per operator type over ``runs`` calls (after one warm-up call)."""
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
    with tempfile.TemporaryDirectory(prefix="pidc-ort-") as tmp:
        options.enable_profiling = True
        options.profile_file_prefix = str(Path(tmp) / "profile")
        try:
            session = onnxruntime.InferenceSession(str(graph), options, providers=["CPUExecutionProvider"])
        except Exception as err:  # onnxruntime raises its own exception types
            raise SystemExit(f"{graph}: onnxruntime cannot load it ({err})") from None
        g = np.random.default_rng(seed)
        feeds = {}
        for i in session.get_inputs():
            shape = [d if isinstance(d, int) else (batch if k == 0 else draws) for k, d in enumerate(i.shape)]
            feeds[i.name] = g.normal(size=shape).astype(np.float32)
        for _ in range(runs + 1):
            session.run(None, feeds)
        events = json.loads(Path(session.end_profiling()).read_text())
    kernel: dict[str, float] = defaultdict(float)
    for e in events:
        if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time"):
            kernel[e["args"]["op_name"]] += float(e["dur"])
    total = sum(kernel.values())
    return {op: t / total for op, t in sorted(kernel.items(), key=lambda kv: -kv[1])}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--graph", type=Path, default=Path("registry/cues-50000/sample_0.onnx"))
    ap.add_argument("--batch", type=int, default=32, help="images per call")
    ap.add_argument("--draws", type=int, default=1000, help="draws per image")
    ap.add_argument("--runs", type=int, default=3, help="profiled calls")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    for name in ("batch", "draws", "runs"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if not args.graph.is_file():
        ap.error(f"--graph {args.graph}: no such file (run the export stage: dvc repro export)")
    shares = op_shares(args.graph, args.batch, args.draws, args.runs, args.seed)
    gemm = sum(v for k, v in shares.items() if k in ("MatMul", "FusedMatMul", "Gemm"))
    for op, v in list(shares.items())[:15]:
        print(f"{op:<20}{v:7.1%}")
    print(f"matrix products (MatMul, FusedMatMul, Gemm): {gemm:.1%} of the kernel time")
    result = {"benchmark": "onnx_profile", "settings": {**vars(args), "graph": str(args.graph)}, "shares": shares}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
