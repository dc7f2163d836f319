"""pidc's posterior estimator against a standard NPE on four SBI problems with exact reference posteriors (C2ST).

Problems (``benchmarks/sbi_problems.py``, as in sbibm, Lueckmann et al. 2021): ``gaussian_linear_uniform`` (10-D),
``two_moons`` (2-D), ``gaussian_mixture`` (2-D) and ``slcp`` (5-D θ, 8-D x), each with a box-uniform prior and an
exactly sampled reference posterior; 10 observations per problem drawn from the prior with a fixed seed.

For every (problem, simulation budget) the estimator is trained ONCE (amortized) on ``budget`` simulations
(θ ~ prior, x ~ simulator, a fixed seed per problem and budget) and then sampled ``--samples`` times at each
observation; the metric is the classifier two-sample test accuracy (C2ST, 0.5 = perfect) against as many
reference draws, summarized over the observations by its median (sbibm's statistic) and mean ± std; against sbi's
column, each pidc column's difference paired by observation (mean ± standard error).

Estimators (``--estimator``):

* ``pidc`` — :class:`components.posterior.NPE` trained with :func:`components.posterior.train`. ``--settings
  default`` is the pipeline's: ``FlowConfig`` and ``TrainingConfig`` built from ``params.yaml``'s ``train:`` section by
  :mod:`components.posterior.settings` (as ``flows/train.py`` does); the other names of :data:`SETTINGS` are candidate
  changes of those defaults, applied here only. Validation = the last ``--val-fraction`` (10 %) of the budget
  (the training part is the rest), as sbi does; the pipeline itself validates on its separate val split.
* ``sbi`` — the sbi package's NPE with ALL its defaults (``NPE(prior, density_estimator="maf")``: a MAF of 5
  transforms with 50 hidden units, z-scored θ and x; ``train()``: Adam at 5e-4, batch 200, 10 % validation, stop after
  20 epochs without improvement, clip 5); samples from ``build_posterior`` (rejection of draws outside the prior box).
  Needs the sbi environment (``bench_sbi.py``'s docstring; this script also needs scikit-learn there).

C2ST (``--c2st``): ``sbibm`` is sbibm's exact protocol (MLP of two hidden layers of 10·d units, Adam, trained to
convergence, 5-fold CV, z-scored by the reference's mean/std); ``early-stopping`` (the default here) is the same
with scikit-learn's ``early_stopping=True`` (10 % of each training fold held out, stop after 10 epochs without
gain): ~25× cheaper on the 10-D problem, where the full protocol costs ~90 s per test on a shared 2-core machine.

Each (estimator, setting, problem, budget) writes one JSON file into ``--out`` (``benchmarks/results/sbi_problems``;
an existing file with the same protocol and, for pidc, the same flow and training settings is reused, ``--force``
recomputes); ``--report`` prints the table of all the
files there. Usage, from the repository root::

    nice .venv/bin/python benchmarks/bench_sbi_problems.py --estimator pidc [--settings default steps batch]
        [--problems gaussian_linear_uniform two_moons gaussian_mixture slcp] [--budgets 1000 10000]
        [--observations 10] [--samples 10000] [--c2st early-stopping|sbibm] [--threads 1]
    nice .venv-sbi/bin/python benchmarks/bench_sbi_problems.py --estimator sbi [same options]
    .venv/bin/python benchmarks/bench_sbi_problems.py --report

Prints a table (C2ST median and mean ± std over the observations, training seconds, epochs), the paired differences
from sbi when its files are there, and one JSON line with the settings, the machine and every figure. Figures of
2026-11-23 (``--samples 5000``) and the recommended change of the training defaults (``steps-small``, adopted as
``train.scale_to``): docs/studies/sbi-problems.md; the floor of epochs for few input features
(``train.few_features_epochs``): docs/studies/sbi-small-inputs.md; sbi's recipe below 300 training simulations per
parameter (``train.few_features_recipe``): docs/studies/few-features-recipe.md.
"""

from __future__ import annotations

# isort: off
import components  # noqa: F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine import machine_info  # benchmarks/machine.py
from sbi_problems import PROBLEMS, Problem, c2st, get_problem, observations, problem_rng

#: training samples of the 10k budget (10 % validation): the rules of :data:`SETTINGS` leave this size unchanged.
N_REF = 9000
DEFAULT_OUT = ROOT / "benchmarks" / "results" / "sbi_problems"


# --- data ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Simulations:
    """``budget`` simulations of a problem: θ ``(n, d)`` float64 inside the box and x ``(n, x_dim)`` float64."""

    theta: np.ndarray
    x: np.ndarray

    def split(self, val_fraction: float) -> tuple[Simulations, Simulations]:
        """(train, val): the last ``int(val_fraction · n)`` simulations validate (they are i.i.d.: no shuffle needed)."""
        n_val = max(1, int(val_fraction * len(self.theta)))
        cut = len(self.theta) - n_val
        return Simulations(self.theta[:cut], self.x[:cut]), Simulations(self.theta[cut:], self.x[cut:])


def simulate(problem: Problem, budget: int, seed: int) -> Simulations:
    """The training simulations of one (problem, budget): the same in every environment and for every estimator."""
    rng = problem_rng(problem, seed, "simulations", budget)
    theta = problem.prior(budget, rng)
    return Simulations(theta, problem.simulate(theta, rng))


# --- pidc ----------------------------------------------------------------------------------------------


#: candidate settings: name → (what it changes, rule). A rule maps (n_train, flow, training) → (flow, training).
Rule = Callable[[int, Any, Any], tuple[Any, Any]]


def _scale(n_train: int) -> float:
    """How many times smaller than the 10k budget's training part the training set is (≥ 1)."""
    return max(1.0, N_REF / n_train)


def _steps(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    s = _scale(n)
    return f, replace(
        t, epochs=math.ceil(t.epochs * s), patience=None if t.patience is None else math.ceil(t.patience * s)
    )


def _batch(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    return f, replace(t, batch_size=int(min(t.batch_size, max(32, n // 35))))


def _batch_small(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    return _width(n, f), _batch(n, f, t)[1]


def _width(n: int, f: Any) -> Any:
    """Hidden widths / sqrt(9000/n_train), rounded to a multiple of 16, at least 32."""
    return replace(
        f, hidden_features=tuple(max(32, int(round(h / math.sqrt(_scale(n)) / 16) * 16)) for h in f.hidden_features)
    )


def _steps_small(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    return _width(n, f), _steps(n, f, t)[1]


def _wd(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    return f, replace(t, weight_decay=t.weight_decay * _scale(n))


def _patience(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    return f, replace(t, epochs=max(t.epochs, 200), patience=None if t.patience is None else max(t.patience, 20))


def _sbi_train(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    return f, replace(t, epochs=2000, patience=20, batch_size=200, lr=5e-4, schedule="constant", weight_decay=0.0)


def _no_context(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    return replace(f, context_layers=()), t


def _early_stop(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    return f, replace(t, patience=math.ceil(10 * max(1.0, 10_000 / n)))


def _epochs_x3(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    return f, replace(t, epochs=3 * t.epochs)


def _full_width(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    return replace(f, hidden_features=(128, 128)), t


def _epochs_x3_no_context(n: int, f: Any, t: Any) -> tuple[Any, Any]:
    return _no_context(n, *_epochs_x3(n, f, t))


SETTINGS: dict[str, tuple[str, Rule]] = {
    "default": ("params.yaml train: as it is", lambda n, f, t: (f, t)),
    "steps": ("epochs and patience × max(1, 9000/n_train): the 10k run's optimizer steps at every budget", _steps),
    "batch": ("batch_size = clamp(n_train // 35, 32, 256): ≥ 35 steps an epoch, as at 10k", _batch),
    "batch-small": ("batch rule + hidden widths / sqrt(9000/n_train) (rounded to 16, ≥ 32)", _batch_small),
    "steps-small": ("steps rule + hidden widths / sqrt(9000/n_train) (rounded to 16, ≥ 32)", _steps_small),
    "wd": ("weight_decay × max(1, 9000/n_train)", _wd),
    "patience": ("epochs 60 → 200 and patience 10 → 20 at every budget", _patience),
    # issue #57 part 5: the levers of a few-feature input, one at a time (docs/studies/sbi-small-inputs.md)
    "no-context": ("no context network (features straight into the flows)", _no_context),
    "early-stop": (
        "early stopping, patience ⌈10 · max(1, 10000/n_train)⌉ epochs (best epoch kept as always)",
        _early_stop,
    ),
    "epochs-x3": ("3 × the epochs of the defaults (the cosine schedule stretches)", _epochs_x3),
    "full-width": ("hidden widths 128 × 128 at every size (no ÷√s)", _full_width),
    "epochs-x3-no-context": ("epochs-x3 and no context network", _epochs_x3_no_context),
    "sbi-train": (
        "sbi's training: constant lr 5e-4, batch 200, patience 20, no weight decay (pidc's flow)",
        _sbi_train,
    ),
}


def default_configs(params: Any, n_train: int, x_dim: int, theta_dim: int, seed: int) -> tuple[Any, Any]:
    """The pipeline's ``(FlowConfig, TrainingConfig)`` for ``n_train`` training simulations of ``x_dim``-dimensional
    observations and ``theta_dim``-dimensional parameters: ``params.yaml``'s
    ``train:`` section (``params``, a loaded :class:`components.core.config.Params`) through
    :mod:`components.posterior.settings`, as ``flows/train.py`` builds them for cached features of ``n_train`` images
    (the small-data rule of ``train.scale_to`` included)."""
    import dataclasses

    from components.posterior.settings import flow_config, training_config

    # no temperature is fitted on these problems (they have no validation split of the pipeline's kind), so no regime
    flow = dataclasses.replace(flow_config(params.train, size=n_train, trainable=False), regime_temperature=False)
    return flow, training_config(
        params.train, size=n_train, trainable=False, features=x_dim, parameters=theta_dim, seed=seed
    )


def pidc_configs(setting: str, n_train: int, base: tuple[Any, Any]) -> tuple[Any, Any]:
    """``(FlowConfig, TrainingConfig)`` of a setting: its rule applied to the defaults ``base`` for ``n_train``
    training simulations."""
    return SETTINGS[setting][1](n_train, *base)


def pidc_setting_configs(problem: Problem, n_train: int, args: argparse.Namespace, setting: str) -> tuple[Any, Any]:
    """``(FlowConfig, TrainingConfig)`` of pidc's ``setting`` on ``problem`` with ``n_train`` training simulations:
    the defaults of ``params.yaml`` (:func:`default_configs`) through the setting's rule."""
    base = default_configs(args.pidc_params, n_train, problem.x_dim, problem.dim, args.seed)
    return pidc_configs(setting, n_train, base)


def run_pidc(
    problem: Problem, sims: Simulations, x_obs: np.ndarray, args: argparse.Namespace, setting: str
) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Train pidc's NPE on the budget and draw ``args.samples`` θ at each observation: ``[(samples, d)] × n_obs``."""
    import torch

    from components.core import weather
    from components.posterior import NPE, train

    train_set, val_set = sims.split(args.val_fraction)
    flow_cfg, train_cfg = pidc_setting_configs(problem, len(train_set.theta), args, setting)
    box = weather.Box(problem.low, problem.high)
    model = NPE(None, problem.x_dim, box, flow_cfg, seed=args.seed)
    t0 = time.perf_counter()
    history = train(
        model,
        (torch.as_tensor(train_set.x, dtype=torch.float32), torch.as_tensor(train_set.theta)),
        (torch.as_tensor(val_set.x, dtype=torch.float32), torch.as_tensor(val_set.theta)),
        train_cfg,
        progress=False,
    )
    train_s = time.perf_counter() - t0
    draws = model.sample(torch.as_tensor(x_obs, dtype=torch.float32), args.samples, rng=args.seed)
    info = {
        "train_s": train_s,
        "epochs": len(history.records),
        "best_epoch": history.best_epoch + 1,
        "steps": len(history.records) * math.ceil(len(train_set.theta) / train_cfg.batch_size),
        "n_train": len(train_set.theta),
        "n_val": len(val_set.theta),
        "best_val_nll": history.records[history.best_epoch].val_nll,
        "parameters": sum(p.numel() for p in model.parameters()),
        "flow": asdict(flow_cfg),
        "training": asdict(train_cfg),
        "versions": {"torch": torch.__version__},
    }
    return [d.double().numpy() for d in draws], info


# --- sbi -----------------------------------------------------------------------------------------------


class _NullTracker:
    """sbi's ``Tracker`` protocol doing nothing (sbi would otherwise write TensorBoard files to ``sbi-logs/``)."""

    log_dir = None

    def log_metric(self, name: str, value: float, step: int | None = None) -> None:
        return None

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        return None

    def log_params(self, params: dict[str, Any]) -> None:
        return None

    def add_figure(self, name: str, figure: Any, step: int | None = None) -> None:
        return None

    def flush(self) -> None:
        return None


def run_sbi(
    problem: Problem, sims: Simulations, x_obs: np.ndarray, args: argparse.Namespace, setting: str
) -> tuple[list[np.ndarray], dict[str, Any]]:
    """sbi's NPE with its defaults on the whole budget (it holds out its own 10 %); draws at each observation."""
    import torch

    try:
        import sbi
        from sbi.inference import NPE as SbiNPE
        from sbi.utils import BoxUniform
    except ImportError as err:
        raise SystemExit(
            f"bench_sbi_problems: cannot import sbi ({err}); run --estimator sbi with .venv-sbi/bin/python "
            "(set-up: benchmarks/bench_sbi.py's docstring, plus scikit-learn)"
        ) from None
    prior = BoxUniform(
        torch.as_tensor(problem.low, dtype=torch.float32), torch.as_tensor(problem.high, dtype=torch.float32)
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(args.seed)
        inference = SbiNPE(prior=prior, tracker=_NullTracker(), show_progress_bars=False)
        inference.append_simulations(
            torch.as_tensor(sims.theta, dtype=torch.float32), torch.as_tensor(sims.x, dtype=torch.float32)
        )
        t0 = time.perf_counter()
        net = inference.train()
        train_s = time.perf_counter() - t0
        posterior = inference.build_posterior(net)
        draws = [
            posterior.sample((args.samples,), x=torch.as_tensor(x, dtype=torch.float32), show_progress_bars=False)
            for x in x_obs
        ]
    summary = inference._summary
    info = {
        "train_s": train_s,
        "epochs": int(summary["epochs_trained"][-1]),
        "best_epoch": int(np.argmin(summary["validation_loss"])) + 1,
        "n_train": len(sims.theta) - int(0.1 * len(sims.theta)),
        "n_val": int(0.1 * len(sims.theta)),
        "best_val_nll": float(summary["best_validation_loss"][-1]),
        "parameters": sum(p.numel() for p in net.parameters()),
        "flow": "sbi NPE default: density_estimator='maf' (5 transforms, 50 hidden)",
        "training": "sbi NPE.train() defaults: batch 200, lr 5e-4, validation 0.1, stop after 20 epochs, clip 5",
        "versions": {"torch": torch.__version__, "sbi": sbi.__version__},
    }
    return [d.double().numpy() for d in draws], info


# --- one cell of the table -----------------------------------------------------------------------------


def label(estimator: str, setting: str) -> str:
    """The column name of an estimator and setting, e.g. ``pidc-default`` or ``sbi``."""
    return "sbi" if estimator == "sbi" else f"pidc-{setting}"


def protocol(args: argparse.Namespace) -> dict[str, Any]:
    """What makes two result files comparable (a file written under another protocol is recomputed)."""
    return {
        "c2st": args.c2st,
        "samples": args.samples,
        "observations": args.observations,
        "seed": args.seed,
        "val_fraction": args.val_fraction,
    }


def same_settings(
    record: dict[str, Any],
    problem: Problem,
    sims: Simulations,
    estimator: str,
    setting: str,
    args: argparse.Namespace,
) -> bool:
    """Whether a result file was trained with the flow and training settings a run would use now: for pidc, its
    recorded configs against ``params.yaml``'s through the setting (a file from before a change of defaults is
    recomputed, not reused); sbi's NPE has no settings of ours."""
    if estimator == "sbi":
        return True
    n_train = len(sims.split(args.val_fraction)[0].theta)
    flow_cfg, train_cfg = pidc_setting_configs(problem, n_train, args, setting)
    now = json.loads(json.dumps({"flow": asdict(flow_cfg), "training": asdict(train_cfg)}))
    return {"flow": record.get("flow"), "training": record.get("training")} == now


def run_cell(problem: Problem, budget: int, estimator: str, setting: str, args: argparse.Namespace) -> dict[str, Any]:
    """Train one estimator on one (problem, budget), score it at every observation, write and return the record."""
    path = args.out / f"{label(estimator, setting)}__{problem.name}__{budget}.json"
    sims = simulate(problem, budget, args.seed)
    if path.is_file() and not args.force:
        old = json.loads(path.read_text())
        if old.get("protocol") == protocol(args) and same_settings(old, problem, sims, estimator, setting, args):
            print(f"  {path.name}: reused", flush=True)
            return old
    theta_obs, x_obs = observations(problem, args.observations, args.seed)
    runner = run_sbi if estimator == "sbi" else run_pidc
    draws, info = runner(problem, sims, x_obs, args, setting)
    t0 = time.perf_counter()
    scores = []
    for i, (x, q) in enumerate(zip(x_obs, draws, strict=True)):
        ref = problem.reference_posterior(x, args.samples, problem_rng(problem, args.seed, "reference", i))
        scores.append(c2st(ref, q, early_stopping=args.c2st == "early-stopping"))
    record = {
        "estimator": estimator,
        "setting": setting,
        "label": label(estimator, setting),
        "problem": problem.name,
        "budget": budget,
        "protocol": protocol(args),
        "c2st": scores,
        "c2st_mean": float(np.mean(scores)),
        "c2st_median": float(np.median(scores)),
        "c2st_std": float(np.std(scores)),
        "c2st_s": time.perf_counter() - t0,
        "theta_obs": theta_obs.tolist(),
        **info,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1))
    print(
        f"  {record['label']:<18} {problem.name:<24} {budget:>6}: C2ST {record['c2st_mean']:.3f} ± {record['c2st_std']:.3f}"
        f"  train {info['train_s']:.1f} s ({info['epochs']} epochs)  C2ST {record['c2st_s']:.0f} s",
        flush=True,
    )
    return record


# --- report --------------------------------------------------------------------------------------------


def load_records(out: Path) -> list[dict[str, Any]]:
    """Every result file in ``out``."""
    return [json.loads(p.read_text()) for p in sorted(out.glob("*__*__*.json"))]


def paired_difference(record: dict[str, Any], other: dict[str, Any]) -> tuple[float, float]:
    """Mean and standard error over the observations of ``record``'s C2ST minus ``other``'s, observation by
    observation (both scored at the same observations; < 0: ``record`` better)."""
    d = np.asarray(record["c2st"]) - np.asarray(other["c2st"])
    return float(d.mean()), float(d.std(ddof=1) / math.sqrt(len(d))) if len(d) > 1 else math.nan


def print_table(records: list[dict[str, Any]]) -> None:
    """One row per (problem, budget), one column per estimator/setting: C2ST median, mean ± std [training s, epochs];
    then, when sbi's column is there, each pidc column's paired difference from it (mean ± standard error)."""
    labels = sorted({r["label"] for r in records}, key=lambda s: (s != "sbi", s != "pidc-default", s))
    cells = {(r["problem"], r["budget"], r["label"]): r for r in records}
    rows = [
        (name, budget)
        for name in PROBLEMS
        for budget in sorted({r["budget"] for r in records})
        if any((name, budget, lab) in cells for lab in labels)
    ]
    print("\nC2ST accuracy over observations (0.5 = perfect): median | mean ± std [training s / epochs run]")
    print(f"{'problem':<24} {'budget':>6} " + " ".join(f"{lab:>34}" for lab in labels))
    for name, budget in rows:
        text = [
            "—"
            if (r := cells.get((name, budget, lab))) is None
            else f"{np.median(r['c2st']):.3f} | {r['c2st_mean']:.3f} ± {r['c2st_std']:.3f} [{r['train_s']:.0f}s/{r['epochs']}]"
            for lab in labels
        ]
        print(f"{name:<24} {budget:>6} " + " ".join(f"{t:>34}" for t in text))
    others = [lab for lab in labels if lab != "sbi"]
    if "sbi" not in labels or not others:
        return
    print("\nC2ST minus sbi's, paired by observation: mean ± standard error (< 0: better than sbi)")
    print(f"{'problem':<24} {'budget':>6} " + " ".join(f"{lab:>20}" for lab in others))
    for name, budget in rows:
        ref = cells.get((name, budget, "sbi"))
        text = []
        for lab in others:
            r = cells.get((name, budget, lab))
            if r is None or ref is None or len(r["c2st"]) != len(ref["c2st"]):
                text.append("—")
            else:
                text.append("{:+.3f} ± {:.3f}".format(*paired_difference(r, ref)))
        print(f"{name:<24} {budget:>6} " + " ".join(f"{t:>20}" for t in text))


# --- main ----------------------------------------------------------------------------------------------


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--estimator", choices=["pidc", "sbi"], default="pidc")
    p.add_argument("--settings", nargs="+", default=["default"], choices=list(SETTINGS), help="pidc only")
    p.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=list(PROBLEMS))
    p.add_argument("--budgets", nargs="+", type=int, default=[1000, 10_000])
    p.add_argument("--observations", type=int, default=10)
    p.add_argument("--samples", type=int, default=10_000, help="posterior and reference draws per observation")
    p.add_argument("--c2st", choices=["early-stopping", "sbibm"], default="early-stopping")
    p.add_argument("--val-fraction", type=float, default=0.1, help="pidc: share of the budget held out to validate")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--params", type=Path, default=None, help="pidc's params file (default: params.yaml)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--force", action="store_true", help="recompute cells whose result file exists")
    p.add_argument("--report", action="store_true", help="only print the table of the result files in --out")
    args = p.parse_args()
    if args.observations < 1 or args.samples < 10 or args.threads < 1:
        p.error("--observations, --threads must be >= 1 and --samples >= 10")
    if not 0 < args.val_fraction < 0.5:
        p.error(f"--val-fraction must be in (0, 0.5), got {args.val_fraction}")
    if any(b < 100 for b in args.budgets):
        p.error("--budgets must be >= 100")
    return args


def main() -> None:
    args = parse_args()
    if args.report:
        records = load_records(args.out)
        print_table(records)
        print(json.dumps({"benchmark": "sbi_problems", "out": str(args.out), "records": records}))
        return
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(args.threads)
    threadpool_limits(args.threads)
    settings = ["sbi"] if args.estimator == "sbi" else args.settings
    if args.estimator == "pidc":  # read once: params.yaml may change while the benchmark runs
        from components.core.config import load_params

        args.pidc_params = load_params(args.params)
    wall0 = time.perf_counter()
    load0 = machine_info()["load_avg_1min"]
    records = [
        run_cell(get_problem(name), budget, args.estimator, setting, args)
        for setting in settings
        for name in args.problems
        for budget in args.budgets
    ]
    print_table(records)
    import sklearn

    machine = machine_info(
        torch_threads=torch.get_num_threads(),
        sklearn=sklearn.__version__,
        load_avg_1min_start=load0,
        wall_s=round(time.perf_counter() - wall0, 1),
    )
    settings_json = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items() if k != "pidc_params"}
    print(json.dumps({"benchmark": "sbi_problems", "settings": settings_json, "machine": machine, "records": records}))


if __name__ == "__main__":
    main()
