"""Task II: the mixture of posteriors beside two deconvolutions of the same bag, scored by the same metrics.

Renders the ``task2`` stage's bag (:func:`components.domains.task2.render_bag`, the paper's setting), computes the
registry model's contexts once, and scores with :func:`components.domains.task2.task2_metrics` (same seeds for all):

* ``mixture`` — p̂ = Σᵢ wᵢ q(θ | xᵢ), the paper's estimate (``task2.estimate: mixture``);
* ``em`` — the nonparametric maximum-likelihood weather distribution on the pooled posterior draws, EM steps and
  kernel bandwidth cross-validated (:mod:`components.domains.deconvolution`, ``task2.estimate: deconvolved``);
* ``xd`` / ``xd-prior`` — extreme deconvolution (Bovy, Hogg & Roweis 2011): each image's posterior approximated by a
  Gaussian (mean and covariance of 64 draws) taken as its likelihood (``xd``), or divided by the Gaussian of the
  uniform prior first (``xd-prior``: information form, precision S⁻¹ − P⁻¹ clipped at 0, so an uninformative posterior
  becomes a flat likelihood); a Gaussian mixture G fitted by XD's EM in physical units with 1…6 components chosen by
  5-fold held-out likelihood, components kept inside the box and no broader than the prior, truncated to the box.

Then the **width floor** of the mixture (:func:`components.domains.task2.width_floor`, as the stage reports it): each
image's posterior draws moved so that their median is the image's true θ (no bias left, only the posteriors' widths),
their deviations scaled by ``task2.width_floor.scales``; the W₁ ratio of that mixture says how sharp the per-image
posteriors must be for the W₁ target even without any bias (``--no-floor`` skips it).

Needs the pipeline's registry/ (``dvc repro evaluate`` at least).

    .venv/bin/python benchmarks/studies/bench_task2.py [--params params.yaml] [--model champion] [--estimates mixture em xd xd-prior]

Prints a table (W₁ estimate/prior per parameter, energy-distance ratios over all six and the two free parameters, the
true mass in the joint 95 % HDR, seconds) and one JSON line (``{"benchmark": "task2", ...}``) with machine information.
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
from pathlib import Path

import numpy as np
from scipy.special import logsumexp

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import machine_info  # noqa: E402
from components.core import seeding  # noqa: E402
from components.core.config import load_params  # noqa: E402
from components.domains import task2 as task2_  # noqa: E402
from components.domains.absolute import Domain  # noqa: E402
from components.export.lookup import load_registered, read_champion  # noqa: E402
from components.simulate.base import make_simulator  # noqa: E402

ESTIMATES = ("mixture", "em", "xd", "xd-prior")
XD_COMPONENTS = (1, 2, 3, 4, 6)
XD_STEPS = 150
POSTERIOR_DRAWS = 64


def _log_normal(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    chol = np.linalg.cholesky(cov)
    sol = np.linalg.solve(chol, (x - mean)[..., None])[..., 0]
    half_logdet = np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1)
    return -0.5 * np.sum(sol * sol, -1) - half_logdet - 0.5 * x.shape[-1] * math.log(2 * math.pi)


def _components(precision, info, mean, cov):
    """log ∫ 𝒩(θ; mⱼ, Vⱼ) exp(−½θᵀΛᵢθ + ηᵢᵀθ) dθ (up to a constant of i), posterior means and covariances (N, J)."""
    cov_inv = np.linalg.inv(cov)
    a = cov_inv[None] + precision[:, None]
    a_inv = np.linalg.inv(a)
    h = (cov_inv @ mean[..., None])[..., 0][None] + info[:, None]
    b = (a_inv @ h[..., None])[..., 0]
    quad = np.einsum("jd,jd->j", mean, (cov_inv @ mean[..., None])[..., 0])
    log_z = -0.5 * quad[None] + 0.5 * np.einsum("njd,njd->nj", h, b)
    log_z -= 0.5 * np.linalg.slogdet(cov)[1][None] + 0.5 * np.linalg.slogdet(a)[1]
    return log_z, b, a_inv


def xd_fit(precision, info, start, weights, k, prior_mean, prior_sd, seed):
    """XD's EM for a k-component Gaussian mixture G given Gaussian likelihoods in information form."""
    n, d = info.shape
    alpha = np.full(k, 1.0 / k)
    mean = start[np.random.default_rng(seed).choice(n, k, replace=False)]
    cov = np.repeat(np.diag(prior_sd**2)[None], k, 0) * 0.5
    lo, hi = prior_mean - math.sqrt(3) * prior_sd, prior_mean + math.sqrt(3) * prior_sd
    scale, unscale = np.diag(prior_sd), np.diag(1.0 / prior_sd)
    for _ in range(XD_STEPS):
        log_z, b, post_cov = _components(precision, info, mean, cov)
        log_p = np.log(np.maximum(alpha, 1e-300))[None] + log_z
        resp = weights[:, None] * np.exp(log_p - logsumexp(log_p, 1)[:, None])
        total = resp.sum(0)
        alive = total > 1e-9
        alpha = np.where(alive, total, 0.0) / total[alive].sum()
        t = np.where(alive, total, 1.0)
        new_mean = np.clip((resp[..., None] * b).sum(0) / t[:, None], lo, hi)
        dev = b - new_mean[None]
        new_cov = (resp[..., None, None] * (dev[..., :, None] * dev[..., None, :] + post_cov)).sum(0) / t[:, None, None]
        ev, u = np.linalg.eigh(unscale[None] @ (new_cov + 1e-2 * np.eye(d)) @ unscale[None])
        new_cov = scale[None] @ ((u * np.minimum(ev, 1.0)[:, None, :]) @ np.swapaxes(u, 1, 2)) @ scale[None]
        mean = np.where(alive[:, None], new_mean, mean)
        cov = np.where(alive[:, None, None], new_cov, cov)
    return alpha, mean, cov


def xd_log_likelihood(precision, info, alpha, mean, cov) -> np.ndarray:
    log_z, _, _ = _components(precision, info, mean, cov)
    return logsumexp(np.log(np.maximum(alpha, 1e-300))[None] + log_z, 1)


class BoxedMixture:
    """A Gaussian mixture truncated to the prior box: ``sample`` by rejection, ``log_prob`` up to the truncation's
    constant (−inf outside; HDR membership and energy distances do not need the constant)."""

    def __init__(self, alpha, mean, cov, low, high):
        self.alpha, self.mean, self.cov, self.low, self.high = alpha, mean, cov, low, high

    def sample(self, n: int, seed: int) -> np.ndarray:
        r = seeding.rng(seed, "bench_task2", "xd")
        chol = np.linalg.cholesky(self.cov)
        parts, got = [], 0
        while got < n:
            j = r.choice(len(self.alpha), 2 * n, p=self.alpha / self.alpha.sum())
            x = self.mean[j] + (chol[j] @ r.standard_normal((2 * n, self.mean.shape[1]))[..., None])[..., 0]
            x = x[np.all((x >= self.low) & (x <= self.high), 1)]
            parts.append(x)
            got += len(x)
        return np.concatenate(parts)[:n]

    def log_prob(self, theta: np.ndarray) -> np.ndarray:
        lp = logsumexp(
            np.log(np.maximum(self.alpha, 1e-300))[None]
            + _log_normal(theta[:, None, :], self.mean[None], self.cov[None]),
            1,
        )
        return np.where(np.all((theta >= self.low) & (theta <= self.high), 1), lp, -np.inf)


def extreme_deconvolution(domain: Domain, params, divide_prior: bool, seed: int) -> tuple[BoxedMixture, dict]:
    box = params.box
    draws = np.asarray(domain.posterior.sample(domain.bag, POSTERIOR_DRAWS, seed), dtype=np.float64)
    mu = draws.mean(1)
    dev = draws - mu[:, None]
    cov = np.einsum("nkd,nke->nde", dev, dev) / (POSTERIOR_DRAWS - 1)
    prior_mean, prior_sd = (box.low + box.high) / 2, box.width / math.sqrt(12)
    precision = np.linalg.inv(cov)
    if divide_prior:
        ev, u = np.linalg.eigh(precision - np.diag(1.0 / prior_sd**2)[None])
        precision = (u * np.maximum(ev, 0.0)[:, None, :]) @ np.swapaxes(u, 1, 2)
        info = (np.linalg.inv(cov) @ mu[..., None])[..., 0] - (prior_mean / prior_sd**2)[None]
    else:
        info = (precision @ mu[..., None])[..., 0]
    n = len(mu)
    w = domain.weights
    fold = seeding.rng(seed, "bench_task2", "folds").permutation(n) % 5
    held_out = {}
    for k in XD_COMPONENTS:
        total = 0.0
        for f in range(5):
            tr, te = fold != f, fold == f
            fit = xd_fit(precision[tr], info[tr], mu[tr], w[tr] / w[tr].sum(), k, prior_mean, prior_sd, seed)
            total += float(w[te] @ xd_log_likelihood(precision[te], info[te], *fit))
        held_out[k] = total
    best = max(held_out, key=held_out.get)
    fit = xd_fit(precision, info, mu, w, best, prior_mean, prior_sd, seed)
    return BoxedMixture(*fit, box.low, box.high), {"components": best, "held_out": held_out}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--params", default=str(ROOT / "params.yaml"))
    ap.add_argument("--model", default="champion")
    ap.add_argument("--estimates", nargs="+", choices=ESTIMATES, default=list(ESTIMATES))
    ap.add_argument("--no-floor", action="store_true", help="skip the width floor of the mixture")
    args = ap.parse_args(argv)
    params = load_params(args.params)
    registry = ROOT / "registry"
    name = read_champion(registry)["model"] if args.model == "champion" else args.model
    model = load_registered(name, registry, threads=2)
    theta, images = task2_.render_bag(params, make_simulator(params.simulator))
    domain = Domain(model.posterior.on_context(), model.posterior.context(model.inputs(images)))
    seed = seeding.derive_seed(params.seed, "task2")
    rows = {}
    for est in args.estimates:
        t0 = time.perf_counter()
        info: dict = {}
        if est == "mixture":
            characterization = domain
        elif est == "em":
            characterization, info = task2_.characterize(
                domain, params.model_copy(update={"task2": params.task2.model_copy(update={"estimate": "deconvolved"})})
            )
            info = {k: v for k, v in info.items() if k in ("steps", "kernel_scale", "effective_support")}
        else:
            characterization, info = extreme_deconvolution(domain, params, est == "xd-prior", seed)
        metrics, *_ = task2_.task2_metrics(characterization, params, name)
        rows[est] = {
            "seconds": round(time.perf_counter() - t0, 1),
            "wasserstein_ratio": {k: round(v["wasserstein_ratio"], 3) for k, v in metrics["parameters"].items()},
            "median": {k: round(v["estimate_median"], 1) for k, v in metrics["parameters"].items()},
            "energy_ratio_all": round(metrics["energy_distance_sq"]["all"]["ratio"], 3),
            "energy_ratio_free": round(metrics["energy_distance_sq"]["free"]["ratio"], 4),
            "true_mass_in_hdr": round(metrics["true_mass_in_hdr"], 3),
            **info,
        }
    names = params.box.names
    print(
        f"Task II, {name}, {params.task2.images} images; W₁ estimate/prior per parameter; true values {params.task2.fixed}"
    )
    print(f"{'estimate':10s} " + " ".join(f"{n[:12]:>12s}" for n in names) + "  energy all / free  HDR mass  seconds")
    for est, r in rows.items():
        cells = " ".join(f"{r['wasserstein_ratio'][n]:12.3f}" for n in names)
        print(
            f"{est:10s} {cells}  {r['energy_ratio_all']:.3f} / {r['energy_ratio_free']:.4f}  {r['true_mass_in_hdr']:.3f}  {r['seconds']}"
        )
        print(f"{'':10s} " + " ".join(f"{r['median'][n]:12.1f}" for n in names) + "  (medians)")
    floor = None
    if not args.no_floor:
        floor = task2_.width_floor(domain.posterior, domain.bag, theta, params)
        print("width floor: the mixture with each posterior moved onto its image's truth, deviations × s (W₁ ratio)")
        for s, r in floor["wasserstein_ratio"].items():
            print(f"{'s = ' + str(s):10s} " + " ".join(f"{r[n]:12.3f}" for n in names))
        sd = floor["posterior_sd_median"]
        print(f"{'sd (s=1)':10s} " + " ".join(f"{sd[n]:12.2f}" for n in names) + "  (median posterior sd)")
    print(
        json.dumps(
            {"benchmark": "task2", "model": name, "machine": machine_info(), "rows": rows, "width_floor": floor},
            default=str,
        )
    )


if __name__ == "__main__":
    main()
