"""The checks and moments of a model's training inputs before its first epoch: whole arrays against pieces.

Before training, ``train`` checks that every input is finite and ``NPE.fit_standardization`` takes the float64 mean and
standard deviation of every input element. For the cnn's 50 000 preprocessed images (3 × 64 × 64 float32, 2.5 GB) the
whole-array way makes a bool copy and a float64 copy (5 GB) and its squares. The project computes them in pieces
(:func:`components.posterior.model.finite_rows`: numpy's ``isfinite`` on 4 096 rows at a time; the moments of 256
elements at a time). Both ways run alternately on the same inputs, the results are compared to the bit, and the ratio
of the medians is printed.

    .venv/bin/python benchmarks/studies/bench_inputs.py --backbone cnn --size 50000 --repeats 3

Inputs: the pipeline's cached inputs of ``--backbone`` (``features/``, as the train stage reads them), or, without a
cache, uniform random inputs of the cnn's shape (``--synthetic``). Prints a table and one JSON line
(``{"benchmark": "inputs", ...}``) with machine information.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.features import cache  # noqa: E402
from components.features.backbones import get_backbone  # noqa: E402
from components.features.options import backbone_options  # noqa: E402
from components.posterior.model import NPE, FlowConfig, finite_rows  # noqa: E402
from components.simulate import dataset  # noqa: E402


def whole_finite(x: torch.Tensor) -> torch.Tensor:
    """The check as it was: one ``isfinite`` over the whole array."""
    return torch.isfinite(x.reshape(x.shape[0], -1)).all(dim=1)


def whole_moments(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The moments as they were: a float64 copy of the whole array (the zero-spread rule applied as in the model),
    stored as the model's float32 buffers."""
    assert bool(whole_finite(x).all())  # fit_standardization checks the inputs first, as it did
    x64 = x.to(torch.float64)
    mean = x64.mean(dim=0)
    std = x64.std(dim=0, unbiased=False)
    std = torch.where(std > 1e-8 * (1.0 + mean.abs()), std, torch.ones_like(std))
    return mean.float(), std.float()  # the model's float32 buffers


def piece_moments(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The project's way: :meth:`NPE.fit_standardization` (its finite check included)."""
    dim = int(x[0].numel())
    model = NPE(
        torch.nn.Flatten(),
        dim,
        load_params(ROOT / "params.yaml").box,
        FlowConfig(transforms=1),
        input_shape=tuple(x.shape[1:]),
    )
    model.fit_standardization(x)
    return model.feature_mean, model.feature_std


def inputs(args: argparse.Namespace) -> tuple[torch.Tensor, str]:
    if args.synthetic:
        g = torch.Generator().manual_seed(0)
        return torch.rand((args.size, 3, 64, 64), generator=g), "synthetic uniform (n, 3, 64, 64)"
    params = load_params(ROOT / "params.yaml")
    split = dataset.open_split(ROOT / params.data.root, "train")
    backbone = get_backbone(args.backbone, **backbone_options(args.backbone, params, ROOT))
    cached = cache.open_features(ROOT / "features", args.backbone, split, stop=args.size)
    return torch.from_numpy(cache.inputs_from_cached(backbone, cached)), f"features/{args.backbone} (train split)"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backbone", default="cnn")
    parser.add_argument("--size", type=int, default=50_000, help="training inputs (the train split's first ones)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--synthetic", action="store_true", help="random inputs of the cnn's shape, no cache needed")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    x, source = inputs(args)

    ways = {
        "finite check": {"whole array": lambda: whole_finite(x), "in pieces": lambda: finite_rows(x)},
        "check and float64 moments": {"whole array": lambda: whole_moments(x), "in pieces": lambda: piece_moments(x)},
    }
    rows: dict[str, dict] = {}
    for task, pair in ways.items():
        seconds: dict[str, list[float]] = {name: [] for name in pair}
        results = {}
        for _ in range(args.repeats):  # alternated, so that a drifting machine affects both alike
            for name, call in pair.items():
                t = time.perf_counter()
                results[name] = call()
                seconds[name].append(time.perf_counter() - t)
        a, b = results["whole array"], results["in pieces"]
        same = all(torch.equal(u, v) for u, v in zip(a, b, strict=True)) if isinstance(a, tuple) else torch.equal(a, b)
        if not same:
            raise SystemExit(
                f"{task}: the two ways disagree; the pieces must give the whole array's numbers to the bit"
            )
        med = {name: statistics.median(s) for name, s in seconds.items()}
        rows[task] = {**{f"{name} s": m for name, m in med.items()}, "ratio": med["in pieces"] / med["whole array"]}

    print(
        f"{source}: {tuple(x.shape)} float32 ({x.numel() * 4 / 1e9:.2f} GB), {args.threads} thread(s), median of {args.repeats}"
    )
    print(f"{'':<28}{'whole array s':>15}{'in pieces s':>13}{'ratio':>8}")
    for task, row in rows.items():
        print(f"{task:<28}{row['whole array s']:>15.2f}{row['in pieces s']:>13.2f}{row['ratio']:>7.2f}×")
    print("the same numbers to the bit: yes")
    record = {
        "benchmark": "inputs",
        "source": source,
        "shape": list(x.shape),
        "repeats": args.repeats,
        "results": rows,
        "machine": machine_info(threads=args.threads),
    }
    print(json.dumps(record))
    return record


if __name__ == "__main__":
    main()
