"""One base scale τ against one per regime, on the same trained flows: coverage of the marginals by day and by night.

The comparison of docs/studies/night-base-scale.md. Loads a trained model of the pipeline
(``models/<id>/model.pt``, frozen features: ``features/<backbone>/``), keeps its flows and refits the post-hoc
calibration both ways on the validation split: one τ for every input (``train.temperature_regime: null``), and one τ per
regime of ``params.yaml``'s ``train.temperature_regime`` blended by the gate fitted on the training split (the
pipeline's). Each is scored on the test split: test NLL, and per parameter the share of truths inside the central 68 %
interval of ``--samples`` seeded draws, for the day and night images (:func:`components.evaluate.marginals.
parameter_report`). Usage::

    python benchmarks/studies/bench_regime.py --model cues-50000 [--samples 400]

Prints a table and one JSON line with the figures and the machine's details.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from components.core.config import load_params  # noqa: E402
from components.evaluate.marginals import parameter_report  # noqa: E402
from components.features import cache as features  # noqa: E402
from components.features.backbones import get_backbone  # noqa: E402
from components.posterior.model import NPE  # noqa: E402
from components.posterior.settings import temperature_regime  # noqa: E402
from components.posterior.store import load_npe  # noqa: E402
from components.posterior.temperature import calibrate_post_hoc  # noqa: E402
from components.simulate import dataset  # noqa: E402

SHORT = ("cloud", "fog", "rain", "sun", "wind", "deposits")


def with_flows_of(model: NPE, regime: bool) -> NPE:
    """A model of ``model``'s weights whose last transform is one τ (``regime`` False) or one τ per regime (True),
    both unfitted (τ = 1)."""
    config = dataclasses.replace(model.config, regime_temperature=regime)
    out = NPE(None, model.features, model.box, config).eval()
    last = f"transform.transforms.{len(model.flows[0].transform.transforms) - 1}."
    weights = {k: v for k, v in model.state_dict().items() if last not in k}
    missing, unexpected = out.load_state_dict(weights, strict=False)
    if unexpected or not all(last in k for k in missing):
        raise ValueError(f"the weights do not fit: missing {missing}, unexpected {unexpected}")
    return out


def score(model: NPE, x: torch.Tensor, theta: torch.Tensor, samples: int, box) -> dict:
    """Test NLL and the central 68 % coverage per parameter, day and night."""
    draws, nll = [], []
    with torch.no_grad():
        for a in range(0, len(x), 100):
            draws.append(model.sample(x[a : a + 100], samples, rng=a).double().numpy())
            nll.append(-model.log_prob(theta[a : a + 100].double(), x[a : a + 100]).double().numpy())
    report = parameter_report(np.concatenate(draws), theta.double().numpy(), box)
    return {
        "test_nll": float(np.concatenate(nll).mean()),
        **{sub: [round(100 * report[sub][n]["coverage68"], 1) for n in box.names] for sub in ("night", "day")},
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="cues-50000", help="a trained model of the grid on frozen features")
    ap.add_argument("--samples", type=int, default=400, help="posterior draws per test image")
    args = ap.parse_args(argv)
    params = load_params(ROOT / "params.yaml")
    regime = temperature_regime(params.train, params.box)
    if regime is None:
        raise SystemExit(
            "params.yaml has no train.temperature_regime (or train.temperature is off): nothing to compare"
        )
    torch.set_num_threads(2)
    trained, header = load_npe(ROOT / "models" / args.model / "model.pt")
    if header["trainable_backbone"]:
        raise SystemExit(f"{args.model}: a backbone trained with the flow; this benchmark takes frozen features")
    backbone = get_backbone(header["backbone"], **header["backbone_options"])
    data = {}
    for split in dataset.SPLITS:
        s = dataset.open_split(ROOT / "data", split)
        stop = header["extra"]["size"] if split == "train" else None
        x = features.inputs_from_cached(
            backbone, features.open_features(ROOT / "features", header["backbone"], s, stop=stop)
        )
        data[split] = (torch.from_numpy(x), torch.from_numpy(s.theta[: len(x)].astype(np.float32)))
    rows = {}
    t0 = time.perf_counter()
    one = with_flows_of(trained, regime=False)
    rows["one τ"] = {
        **calibrate_post_hoc(one, None, data["val"], None),
        **score(one, *data["test"], args.samples, params.box),
    }
    per = with_flows_of(trained, regime=True)
    rows[f"τ per regime ({regime.name})"] = {
        **calibrate_post_hoc(per, data["train"], data["val"], regime),
        **score(per, *data["test"], args.samples, params.box),
    }
    print(f"{args.model}: central 68 % coverage (%) of {' / '.join(SHORT)}, {args.samples} draws per test image")
    for name, r in rows.items():
        print(f"  {name:24s} night {r['night']}  day {r['day']}  test NLL {r['test_nll']:.3f}")
    machine = {"machine": platform.processor() or platform.machine(), "torch": torch.__version__}
    print(json.dumps({"model": args.model, "seconds": round(time.perf_counter() - t0, 1), "rows": rows, **machine}))


if __name__ == "__main__":
    main()
