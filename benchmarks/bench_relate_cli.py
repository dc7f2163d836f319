"""``pidc relate`` on folders of the pipeline's test images: kernel densities (the default) against exact mixtures.

From the test split (``data/test``) and the ``task3`` stage's sub-boxes (``params.yaml`` ``task3.bags``; an image in
two boxes belongs to the first, b1 before b2 …, and b0 is the out-of-ODD weather), three source folders of the stage's
sizes (``max_images``) and, from the other images of the same boxes, ``--targets`` fresh in-ODD target folders of
``--size`` images (λ = ``task3.weights``, counts drawn per target) and as many out-of-ODD ones (the first half of an
in-ODD target, the rest images of b0). Each target runs through ``pidc relate`` (in-process, the registry's champion,
``--calibration-targets 100``) with ``--smoothing scott`` and ``none`` (at the command's other defaults). Prints per
smoothing the median d_E = ‖λ̂ − λ‖₂ of the in-ODD targets and how many of each kind were flagged, and one JSON line.

    .venv/bin/python benchmarks/bench_relate_cli.py --targets 6 --size 30
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import contextlib
import io
import json
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.stats import binomtest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from components.cli.main import main as pidc  # noqa: E402
from components.core import seeding  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.domains.task3 import bag_of  # noqa: E402
from components.simulate.dataset import open_split  # noqa: E402

SOURCES = ("b1", "b2", "b3")


def clopper_pearson(k: int, n: int) -> tuple[float, float]:
    """The 95 % Clopper–Pearson interval of a rate of ``k`` in ``n`` (scipy)."""
    ci = binomtest(k, n).proportion_ci(0.95, method="exact")
    return round(float(ci.low), 3), round(float(ci.high), 3)


def _write(folder: Path, images: np.ndarray, idx: np.ndarray) -> Path:
    folder.mkdir(parents=True)
    for i in idx:
        Image.fromarray(images[i]).save(folder / f"{i:05d}.png")
    return folder


def _relate(target: Path, sources: list[Path], smoothing: str, registry: Path) -> tuple[np.ndarray, bool]:
    """λ̂ and the verdict of one ``pidc relate`` run (its printed table parsed)."""
    out = io.StringIO()
    args = [str(target), *map(str, sources), "--registry", str(registry), "--smoothing", smoothing]
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        code = pidc(["relate", *args, "--calibration-targets", "100"])
    text = out.getvalue()
    if code != 0:
        raise RuntimeError(f"pidc relate {' '.join(args)} failed with exit code {code}:\n{text}")
    weights = dict(re.findall(r"^(b\d)\s+\d+\s+(\d\.\d{4})$", text, re.M))
    return np.array([float(weights[b]) for b in SOURCES]), "verdict: OUTSIDE the ODD" in text


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--targets", type=int, default=6, help="in-ODD and out-of-ODD target folders each (≥ 1)")
    ap.add_argument("--size", type=int, default=30, help="images per target folder (≥ 2)")
    ap.add_argument("--params", type=Path, default=ROOT / "params.yaml")
    args = ap.parse_args(argv)
    if args.targets < 1 or args.size < 2:
        ap.error(f"--targets must be ≥ 1 and --size ≥ 2, got {args.targets} and {args.size}")
    params = load_params(args.params)
    split = open_split(ROOT / params.data.root, "test")
    images, theta = split.images(), split.theta
    owner = bag_of(params.task3.bags, theta)  # each image's bag name, or "" (the stage's rule)
    lam = np.asarray(params.task3.weights, dtype=np.float64)
    r = seeding.rng(params.seed, "bench_relate_cli")
    t0 = time.perf_counter()
    rows: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        sources, pools = [], []
        for b in SOURCES:
            members = r.permutation(np.flatnonzero(owner == b))
            n = params.task3.bags[b].max_images
            if len(members) < n + args.size:
                raise SystemExit(f"bag {b}: {len(members)} test images, need {n} + {args.size} for its pool")
            sources.append(_write(root / b, images, members[:n]))
            pools.append(members[n:])
        outside = np.flatnonzero(owner == "b0")
        targets = []
        for t in range(args.targets):
            counts = r.multinomial(args.size, lam)
            idx = np.concatenate([r.choice(p, c, replace=False) for p, c in zip(pools, counts, strict=True)])
            half = args.size // 2
            out_idx = np.concatenate([idx[:half], r.choice(outside, args.size - half, replace=False)])
            targets += [
                ("in", _write(root / f"in{t}", images, idx)),
                ("out", _write(root / f"out{t}", images, out_idx)),
            ]
        for smoothing in ("scott", "none"):
            d_e, flagged = [], {"in": 0, "out": 0}
            for kind, folder in targets:
                weights, is_outside = _relate(folder, sources, smoothing, ROOT / "registry")
                flagged[kind] += is_outside
                if kind == "in":
                    d_e.append(float(np.linalg.norm(weights - lam)))
            rows[smoothing] = {
                "d_e_median_in_odd": round(float(np.median(d_e)), 3),
                "flagged_in_odd": flagged["in"],
                "flagged_out_of_odd": flagged["out"],
                "false_alarm_rate_ci": clopper_pearson(flagged["in"], args.targets),
                "detection_rate_ci": clopper_pearson(flagged["out"], args.targets),
            }
    print(f"pidc relate, {args.targets} in-ODD and {args.targets} out-of-ODD targets of {args.size} test images")
    for smoothing, row in rows.items():
        fa, det = row["false_alarm_rate_ci"], row["detection_rate_ci"]
        print(
            f"  --smoothing {smoothing:5s}: median d_E {row['d_e_median_in_odd']:.3f}; flagged: in-ODD "
            f"{row['flagged_in_odd']}/{args.targets} (95 % CI {fa[0]:.3f}–{fa[1]:.3f}), out-of-ODD "
            f"{row['flagged_out_of_odd']}/{args.targets} (95 % CI {det[0]:.3f}–{det[1]:.3f})"
        )
    print(
        json.dumps(
            {
                "benchmark": "relate_cli",
                "targets": args.targets,
                "size": args.size,
                "rows": rows,
                "seconds": round(time.perf_counter() - t0, 1),
                "machine": machine_info(),
            }
        )
    )


if __name__ == "__main__":
    main()
