"""Throughput of the posterior estimator: training (samples/s), log_prob and sampling (θ/s).

A 6-D NSF over the weather box conditioned on 64- or 128-dim synthetic features (a random linear map of the
normalized θ plus noise). Prints a table and one JSON line with the machine's description.

    .venv/bin/python benchmarks/bench_training.py [--threads 2] [--steps 30] [--passes 2]
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import os
import platform
import time

import torch

from components.core import seeding, weather
from components.posterior.loss import npe_loss
from components.posterior.model import NPE, FlowConfig


def synthetic(n: int, features: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    box = weather.Box.full()
    rng = seeding.rng(seed, "bench", "data", features)
    theta = box.sample(rng, n)
    u = (theta - box.low) / box.width
    x = u @ rng.normal(size=(6, features)) + 0.1 * rng.normal(size=(n, features))
    return torch.tensor(x, dtype=torch.float32), torch.tensor(theta)


def timed(fn, repeat: int) -> float:  # type: ignore[no-untyped-def]
    fn()  # warm-up
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat


def bench(features: int, args: argparse.Namespace) -> dict[str, float]:
    cfg = FlowConfig(transforms=args.transforms, hidden_features=(128, 128), bins=8, passes=args.passes)
    model = NPE(None, features, weather.Box.full(), cfg, seed=0)
    x, theta = synthetic(args.batch_size * args.steps, features, 0)
    model.fit_standardization(x)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    batches = list(zip(torch.split(x, args.batch_size), torch.split(theta, args.batch_size), strict=False))

    def epoch() -> None:
        for xb, tb in batches:
            loss = npe_loss(model, tb, xb, balance=args.balance).loss
            opt.zero_grad()
            loss.backward()
            opt.step()

    train_s = timed(epoch, 1)
    xe, te = synthetic(10_000, features, 1)
    with torch.no_grad():
        lp_s = timed(lambda: model.log_prob(te, xe), 3)
        xs = xe[: args.sample_batch]
        sample_s = timed(lambda: model.sample(xs, args.sample_n, rng=0), 3)
    return {
        "features": features,
        "train_samples_per_s": len(x) / train_s,
        "log_prob_per_s": 10_000 / lp_s,
        "sample_per_s": args.sample_batch * args.sample_n / sample_s,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--steps", type=int, default=20, help="training steps timed")
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--transforms", type=int, default=3)
    p.add_argument("--passes", type=int, default=2, help="2 = coupling; 0 = fully autoregressive")
    p.add_argument("--balance", type=float, default=0.0)
    p.add_argument("--sample-batch", type=int, default=100)
    p.add_argument("--sample-n", type=int, default=1000)
    args = p.parse_args()
    args.passes = None if args.passes == 0 else args.passes
    torch.set_num_threads(args.threads)
    rows = [bench(f, args) for f in (64, 128)]
    print(f"{'features':>8} {'train samples/s':>16} {'log_prob θ/s':>14} {'sample θ/s':>12}")
    for r in rows:
        print(
            f"{r['features']:>8} {r['train_samples_per_s']:>16,.0f} {r['log_prob_per_s']:>14,.0f} {r['sample_per_s']:>12,.0f}"
        )
    machine = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "threads": torch.get_num_threads(),
        "load_avg_1m": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }
    settings = {k: v for k, v in vars(args).items()}
    print(
        json.dumps(
            {
                "benchmark": "posterior_training",
                "settings": settings,
                "machine": machine,
                "results": [
                    {k: (int(v) if k == "features" else round(float(v), 1)) for k, v in r.items()} for r in rows
                ],
            }
        )
    )


if __name__ == "__main__":
    main()
