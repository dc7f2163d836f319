"""The training step compiled (``TrainingConfig.compile``, torch.compile) against eager torch, side by side.

The cues models' flow (273 input features, the ``train.flow`` of ``params.yaml`` at ≥ ``scale_to`` images) trained
with :func:`components.posterior.train` on synthetic features (a random linear map of the normalized θ plus noise),
in fresh processes on ``--threads`` torch threads, alternating eager and compiled runs ``--repeats`` times. A
compiled run's first epoch includes the compilation: with an empty inductor cache (``cold``, a new temporary
``TORCHINDUCTOR_CACHE_DIR``) and with the cache the cold run left (``warm``, as a later model of the same shape in the
train stage). Prints a table and one JSON line with the machine's details.

    .venv/bin/python benchmarks/bench_compile.py [--threads 1] [--size 20000] [--epochs 4] [--repeats 2]
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def worker(args: argparse.Namespace) -> None:
    """One training run; prints its per-epoch wall times as JSON."""
    import dataclasses

    import torch

    from benchmarks.bench_training import synthetic
    from components.core.config import load_params
    from components.posterior import NPE, train
    from components.posterior.settings import flow_config, training_config

    torch.set_num_threads(args.threads)
    params = load_params(ROOT / "params.yaml")
    size = args.size
    x, theta = synthetic(size + 2000, args.features, 0)
    config = dataclasses.replace(
        training_config(
            params.train, size=size, trainable=False, features=args.features, parameters=len(params.box.names), seed=0
        ),
        epochs=args.epochs,
        compile=args.worker != "eager",
    )
    model = NPE(
        None,
        args.features,
        params.box,
        flow_config(params.train, size=size, trainable=False),
        parameters=len(params.box.names),
        seed=0,
    )
    history = train(model, (x[:size], theta[:size]), (x[size:], theta[size:]), config, progress=False)
    print(json.dumps({"epochs": history.wall_time, "steps_per_epoch": -(-size // config.batch_size)}))


def run(mode: str, args: argparse.Namespace, cache: str) -> dict:
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache}
    cmd = [sys.executable, __file__, "--worker", mode, "--threads", str(args.threads), "--size", str(args.size)]
    cmd += ["--epochs", str(args.epochs), "--features", str(args.features)]
    out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--size", type=int, default=20000, help="training images (synthetic)")
    p.add_argument("--features", type=int, default=273, help="input features (the cues: 273)")
    p.add_argument("--epochs", type=int, default=4, help="≥ 2: the first compiles, the others are timed")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--worker", choices=["eager", "cold", "warm"], help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.epochs < 2:
        p.error(f"--epochs must be at least 2 (the first epoch compiles; the others are timed), got {args.epochs}")
    if args.repeats < 1 or args.size < 1 or args.threads < 1:
        p.error("--repeats, --size and --threads must be at least 1")
    if args.worker:
        worker(args)
        return
    from benchmarks.machine import machine_info

    rows: dict[str, list[dict]] = {"eager": [], "cold": [], "warm": []}
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory(prefix="inductor-") as cache:
            for mode in ("eager", "cold", "warm"):
                rows[mode].append(run(mode, args, cache))
    steps = rows["eager"][0]["steps_per_epoch"]
    epoch = {m: statistics.median(e for r in rs for e in r["epochs"][1:]) for m, rs in rows.items()}
    compiled = statistics.median([epoch["cold"], epoch["warm"]])
    first = {m: statistics.median(r["epochs"][0] for r in rs) for m, rs in rows.items()}
    result = {
        "size": args.size,
        "features": args.features,
        "threads": args.threads,
        "steps_per_epoch": steps,
        "eager_ms_per_step": 1000 * epoch["eager"] / steps,
        "compiled_ms_per_step": 1000 * compiled / steps,
        "speedup": epoch["eager"] / compiled,
        "compile_s_cold": first["cold"] - compiled,
        "compile_s_warm": first["warm"] - compiled,
        "break_even_steps_cold": (first["cold"] - compiled) / ((epoch["eager"] - compiled) / steps),
    }
    print("| | ms per step | first epoch's extra s |\n|---|---|---|")
    print(f"| eager | {result['eager_ms_per_step']:.1f} | — |")
    print(f"| compiled, empty cache | {result['compiled_ms_per_step']:.1f} | {result['compile_s_cold']:.1f} |")
    print(f"| compiled, warm cache | {result['compiled_ms_per_step']:.1f} | {result['compile_s_warm']:.1f} |")
    print(
        f"speed-up {result['speedup']:.2f}×; a cold compilation pays after {result['break_even_steps_cold']:.0f} steps"
    )
    print(json.dumps({**result, "machine": machine_info(threads=args.threads)}))


if __name__ == "__main__":
    main()
