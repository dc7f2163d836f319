"""``pidc relate`` on folders of the pipeline's test images: kernel densities (the default) against exact mixtures.

From the test split (``data/test``) and the ``task3`` stage's sub-boxes (``params.yaml`` ``task3.bags``; an image in
two boxes belongs to the first, b1 before b2 …, and b0 is the out-of-ODD weather), three source folders of the stage's
sizes (``max_images``) and, from the other images of the same boxes, ``--targets`` fresh in-ODD target folders of
``--size`` images (λ = ``task3.weights``, counts drawn per target) and as many out-of-ODD ones (the first half of an
in-ODD target, the rest images of b0). Each target runs through ``pidc relate`` (in-process, the registry's champion,
``--calibration-targets 100``) with ``--smoothing scott`` and ``none`` (at the command's other defaults). Prints per
smoothing the median d_E = ‖λ̂ − λ‖₂ of the in-ODD targets, how many of each kind were flagged, and per parameter how
many targets of each kind had its W₁ beyond its in-ODD level (the command's table of where the target differs, from
its ``--json``), and one JSON line. ``--source-draws N`` repeats it for N splits of the bags into source folders and
fresh pools (the levels' guarantee is over the sources' draws).

    .venv/bin/python benchmarks/studies/bench_relate_cli.py --targets 6 --size 30 [--smoothings scott none] [--source-draws 1]
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.stats import binomtest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from components.cli.main import main as pidc  # noqa: E402
from components.core import seeding  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.domains.task3 import bag_of  # noqa: E402
from components.simulate.dataset import open_split  # noqa: E402

SOURCES = ("b1", "b2", "b3")


def clopper_pearson(k: int, n: int) -> tuple[float, float]:
    """The 95 % Clopper–Pearson interval of a rate of ``k`` in ``n`` (scipy); [0, 1] when n = 0 (nothing known)."""
    if n == 0:
        return 0.0, 1.0
    ci = binomtest(k, n).proportion_ci(0.95, method="exact")
    return round(float(ci.low), 3), round(float(ci.high), 3)


def _write(folder: Path, images: np.ndarray, idx: np.ndarray) -> Path:
    folder.mkdir(parents=True)
    for i in idx:
        Image.fromarray(images[i]).save(folder / f"{i:05d}.png")
    return folder


def _relate(
    target: Path, sources: list[Path], smoothing: str, registry: Path
) -> tuple[np.ndarray, bool, set[str]] | None:
    """λ̂, the verdict and the parameters whose W₁ exceeds their in-ODD level (whatever the verdict) of one
    ``pidc relate`` run (its ``--json`` report); None when the command refuses a verdict (its calibrated threshold
    saturated at 1: the folders' densities do not overlap)."""
    report_path = target.with_suffix(f".{smoothing}.json")
    args = [str(target), *map(str, sources), "--registry", str(registry), "--smoothing", smoothing]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = pidc(["relate", *args, "--calibration-targets", "100", "--json", str(report_path)])
    if code != 0 and "no verdict is possible" in err.getvalue():
        return None
    if code != 0:
        raise RuntimeError(
            f"pidc relate {' '.join(args)} failed with exit code {code}:\n{out.getvalue()}{err.getvalue()}"
        )
    report = json.loads(report_path.read_text())
    weights = {s["name"]: s["weight"] for s in report["sources"]}
    exceeded = {name for name, p in report["parameters"].items() if p["exceeds_in_odd_level"]}
    return np.array([float(weights[b]) for b in SOURCES]), report["outside"], exceeded


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--targets", type=int, default=6, help="in-ODD and out-of-ODD target folders each (≥ 1)")
    ap.add_argument("--size", type=int, default=30, help="images per target folder (≥ 2)")
    ap.add_argument("--params", type=Path, default=ROOT / "params.yaml")
    ap.add_argument("--smoothings", nargs="+", choices=("scott", "none"), default=["scott", "none"])
    ap.add_argument(
        "--source-draws", type=int, default=1, help="draws of the source folders, --targets of each kind for each (≥ 1)"
    )
    args = ap.parse_args(argv)
    if args.targets < 1 or args.size < 2 or args.source_draws < 1:
        ap.error(
            f"--targets and --source-draws must be ≥ 1 and --size ≥ 2, got {args.targets}, {args.source_draws}, {args.size}"
        )
    params = load_params(args.params)
    split = open_split(ROOT / params.data.root, "test")
    images, theta = split.images(), split.theta
    owner = bag_of(params.task3.bags, theta)  # each image's bag name, or "" (the stage's rule)
    lam = np.asarray(params.task3.weights, dtype=np.float64)
    r = seeding.rng(params.seed, "bench_relate_cli")
    t0 = time.perf_counter()
    rows: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        outside = np.flatnonzero(owner == "b0")
        targets = []  # (kind, folder, its source folders)
        for draw in range(args.source_draws):  # a new split of each bag into source folder and fresh pool
            root = Path(tmp) / f"draw{draw}"
            sources, pools = [], []
            for b in SOURCES:
                members = r.permutation(np.flatnonzero(owner == b))
                n = params.task3.bags[b].max_images
                if len(members) < n + args.size:
                    raise SystemExit(f"bag {b}: {len(members)} test images, need {n} + {args.size} for its pool")
                sources.append(_write(root / b, images, members[:n]))
                pools.append(members[n:])
            for t in range(args.targets):
                counts = r.multinomial(args.size, lam)
                idx = np.concatenate([r.choice(p, c, replace=False) for p, c in zip(pools, counts, strict=True)])
                half = args.size // 2
                out_idx = np.concatenate([idx[:half], r.choice(outside, args.size - half, replace=False)])
                targets += [
                    ("in", _write(root / f"in{t}", images, idx), sources),
                    ("out", _write(root / f"out{t}", images, out_idx), sources),
                ]
        names = params.box.names
        total = args.targets * args.source_draws
        for smoothing in args.smoothings:
            d_e, flagged, refused = [], {"in": 0, "out": 0}, {"in": 0, "out": 0}
            marks = {kind: dict.fromkeys(names, 0) for kind in ("in", "out")}
            any_mark = {"in": 0, "out": 0}
            for kind, folder, sources in targets:
                result = _relate(folder, sources, smoothing, ROOT / "registry")
                if result is None:  # no verdict: counted apart, neither flagged nor passed
                    refused[kind] += 1
                    continue
                weights, is_outside, marked = result
                flagged[kind] += is_outside
                any_mark[kind] += bool(marked)
                for name in marked:
                    marks[kind][name] += 1
                if kind == "in":
                    d_e.append(float(np.linalg.norm(weights - lam)))
            rows[smoothing] = {
                "refused_in_odd": refused["in"],
                "refused_out_of_odd": refused["out"],
                "d_e_median_in_odd": round(float(np.median(d_e)), 3) if d_e else None,
                "flagged_in_odd": flagged["in"],
                "flagged_out_of_odd": flagged["out"],
                # rates among the targets given a verdict
                "false_alarm_rate_ci": clopper_pearson(flagged["in"], total - refused["in"]),
                "detection_rate_ci": clopper_pearson(flagged["out"], total - refused["out"]),
                # the per-parameter table: how many targets had each parameter's W₁ beyond its in-ODD level
                "exceeded_in_odd": marks["in"],
                "exceeded_out_of_odd": marks["out"],
                "exceeded_in_odd_rate_ci": clopper_pearson(
                    sum(marks["in"].values()), (total - refused["in"]) * len(names)
                ),
                "any_exceeded_in_odd": any_mark["in"],
                "any_exceeded_out_of_odd": any_mark["out"],
            }
    print(
        f"pidc relate, {total} in-ODD and {total} out-of-ODD targets of {args.size} test images "
        f"({args.targets} each for {args.source_draws} draws of the source folders)"
    )
    for smoothing, row in rows.items():
        fa, det = row["false_alarm_rate_ci"], row["detection_rate_ci"]
        given = {kind: total - row[f"refused_{kind}"] for kind in ("in_odd", "out_of_odd")}
        d_e = "–" if row["d_e_median_in_odd"] is None else f"{row['d_e_median_in_odd']:.3f}"
        print(
            f"  --smoothing {smoothing:5s}: no verdict (threshold saturated): in-ODD {row['refused_in_odd']}/{total}, "
            f"out-of-ODD {row['refused_out_of_odd']}/{total}; of the others: median d_E {d_e}; flagged: in-ODD "
            f"{row['flagged_in_odd']}/{given['in_odd']} (95 % CI {fa[0]:.3f}–{fa[1]:.3f}), out-of-ODD "
            f"{row['flagged_out_of_odd']}/{given['out_of_odd']} (95 % CI {det[0]:.3f}–{det[1]:.3f})"
        )
        for kind in ("in_odd", "out_of_odd"):
            counts = ", ".join(f"{n} {c}" for n, c in row[f"exceeded_{kind}"].items())
            print(f"      W₁ beyond the in-ODD level, {kind} targets: {counts}; any: {row[f'any_exceeded_{kind}']}")
        low, high = row["exceeded_in_odd_rate_ci"]
        print(f"      in-ODD rate per parameter and target: {low:.3f}–{high:.3f} (95 % CI)")
    print(
        json.dumps(
            {
                "benchmark": "relate_cli",
                "targets": args.targets,
                "source_draws": args.source_draws,
                "size": args.size,
                "rows": rows,
                "seconds": round(time.perf_counter() - t0, 1),
                "machine": machine_info(),
            }
        )
    )


if __name__ == "__main__":
    main()
