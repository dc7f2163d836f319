"""Do the renders depend on the CPU through BLAS? The pipeline's first test images under each OpenBLAS kernel.

numpy's ``@`` hands matrix products to its bundled OpenBLAS, which picks its kernels by CPU (``SkylakeX`` with AVX-512
fuses the multiply-adds, ``Haswell``/``Zen`` with AVX2 and ``Prescott`` with SSE3 do not). This study renders the first
``--images`` images of the test split's first shard exactly as the ``generate`` stage does, once per
``OPENBLAS_CORETYPE`` (each in a fresh process, the kernels this CPU can run), and counts the images and the linear
radiances whose bytes differ from the default process's. Record: docs/studies/openblas-kernels.md. ~1 min:

    .venv/bin/python benchmarks/studies/bench_blas_kernels.py --images 200
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402

#: OpenBLAS kernels by the CPU flag they need (``OPENBLAS_CORETYPE``), oldest first
KERNELS = {"Prescott": "sse2", "Haswell": "avx2", "SkylakeX": "avx512f"}

PROBE = """
import components, hashlib, json, sys
from components.core import weather
from components.core.config import load_params
from components.simulate.base import make_simulator
from flows.generate import plans
params = load_params("params.yaml")
sim = make_simulator(params.simulator)
plan = next(p for p in plans(params, sim.version) if p.name == "test")
rows = plan.rows(plan.shards()[0])
out = []
for j in range(int(sys.argv[1])):
    w = {n: float(v) for n, v in zip(weather.ALL_NAMES, rows.weather[j], strict=True)}
    seed = int(rows.scene_seed[j])
    out.append([hashlib.sha256(sim.render(w, seed).tobytes()).hexdigest(),
                hashlib.sha256(sim.radiance(w, seed).tobytes()).hexdigest()])
print(json.dumps({"digests": out}))
"""


def digests(images: int, coretype: str | None) -> list[list[str]]:
    """The (image, radiance) SHA-256 of the first ``images`` test renders in a fresh process under ``coretype``."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
    if coretype is not None:
        env["OPENBLAS_CORETYPE"] = coretype
    out = subprocess.run([sys.executable, "-c", PROBE, str(images)], capture_output=True, text=True, env=env, cwd=ROOT)
    if out.returncode != 0:
        raise SystemExit(f"the render probe failed under OPENBLAS_CORETYPE={coretype}: {out.stderr.strip()[-400:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])["digests"]


def cpu_flags() -> set[str]:
    """The CPU flags of this Linux machine (``/proc/cpuinfo``), empty elsewhere."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    line = next((line for line in text.splitlines() if line.startswith("flags")), "")
    return set(line.partition(":")[2].split())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=200, help="test images to render per kernel (default 200)")
    args = parser.parse_args()
    if args.images < 1:
        parser.error(f"--images must be a positive integer, got {args.images}")
    flags = cpu_flags()
    default = digests(args.images, None)
    rows = []
    for coretype, flag in KERNELS.items():
        if flag not in flags:
            continue
        other = digests(args.images, coretype)
        images = sum(a[0] != b[0] for a, b in zip(default, other, strict=True))
        radiances = sum(a[1] != b[1] for a, b in zip(default, other, strict=True))
        rows.append({"coretype": coretype, "images_differ": images, "radiances_differ": radiances})
        print(f"{coretype:>9}: {images} of {args.images} images and {radiances} radiances differ from the default's")
    print(json.dumps({"images": args.images, "kernels": rows, "machine": machine_info()}))


if __name__ == "__main__":
    main()
