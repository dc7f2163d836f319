"""A local test of q(θ | x) at given images, L-C2ST, and the coverage of named weathers' intervals.

Expected coverage (:mod:`components.evaluate.diagnostics`) averages over the prior: a posterior can be calibrated on
average and wrong at the images a user tries. The local classifier two-sample test (L-C2ST; Linhart, Gramfort and
Rodrigues 2023) tests at one observation x_o the null hypothesis

    H₀(x_o): q(θ | x_o) = p(θ | x_o).

On a calibration set of n labelled images (θᵢ, xᵢ) ~ p(θ) p(x | θ) with one draw θ̃ᵢ ~ q(θ | xᵢ) each, a classifier
d(θ, x) learns to tell the posterior's pairs (θ̃ᵢ, xᵢ) (class 1) from the truths' (θᵢ, xᵢ) (class 0). Where q is
right both classes have the same joint law, so d ≈ ½; the statistic at x_o is the mean squared distance from chance
over m draws θ̃ⱼ ~ q(θ | x_o):

    T(x_o) = 1/m Σⱼ (d(θ̃ⱼ, x_o) − ½)².

Its null distribution: under H₀ (q = p at every x) the two members of a pair (θᵢ, θ̃ᵢ) are exchangeable, so the same
classifier trained after swapping the labels of a random half of the pairs has the same law as the observed one. Its
``null_trials`` = H copies, trained once on the calibration set, give the randomization p-value at any x_o

    p(x_o) = (1 + #{h : T_h(x_o) ≥ T(x_o)}) / (H + 1),

exact at every level k / (H + 1) (with H = 99: P(p ≤ 0.05) = 0.05 under H₀). This differs from sbi's
``sbi.diagnostics.lc2st.LC2ST`` in two ways: sbi permutes the 2n labelled points as one pool (which also separates
the pairs' shared x, so that its null is exchangeable only approximately) and counts ``T_h > T`` without the 1,
whose p-values run a little low; and the classifiers here are MLPs trained all at once, as one batched torch model,
full-batch Adam for a fixed number of steps, each from its own initial weights (sbi: scikit-learn's
``MLPClassifier`` with early stopping, trained one after another). sbi's normalizing-flow variant L-C2ST-NF, whose
null does not depend on q, needs the flow's inverse z = T⁻¹(θ; x) with a Gaussian base: pidc's posteriors are
equal-weight mixtures of K flows (and the exported graphs give densities and draws, not that inverse), so the
permutation null is the one that applies to them.

θ enters the classifier in the box's scaled-logit space when a box is given (:func:`components.core.weather.
to_unbounded`: draws piled against a face stay apart), then standardized with the pooled calibration moments; x is
standardized. Any fixed function of the image (e.g. a summary of its posterior, :func:`posterior_summary`) may stand
for x: the null stays exact, only the power changes.

:func:`named_coverage` counts how often the highest-density intervals of the images of one named weather cover its
truth, per parameter, with the exact binomial (Clopper–Pearson) interval of that rate. A named weather's value on a
face of the box (no rain: precipitation 0) can never lie strictly inside an interval of draws, so a truth on a face
counts as covered when the interval reaches within ``tolerance`` units of it. A correct posterior promises its
coverage on average over the prior, not at each fixed θ: near a face an exact posterior covers more than its mass.

Used by ``benchmarks/studies/bench_named_weathers.py``.

References:
    Linhart, Gramfort, Rodrigues (2023), "L-C2ST: Local diagnostics for posterior approximations in
    simulation-based inference", NeurIPS, https://arxiv.org/abs/2306.03580.
    Clopper, Pearson (1934), "The use of confidence or fiducial limits illustrated in the case of the binomial",
    Biometrika 26(4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.stats import beta

from components.core import seeding
from components.core.checks import whole_number
from components.core.weather import Box, to_unbounded

__all__ = ["LocalTest", "Rejections", "posterior_summary", "Coverage", "clopper_pearson", "named_coverage"]


def _matrix(name: str, a: object, n: int | None = None, d: int | None = None) -> np.ndarray:
    m = np.asarray(a, dtype=np.float64)
    if m.ndim != 2 or (n is not None and m.shape[0] != n) or (d is not None and m.shape[1] != d):
        want = f"({'n' if n is None else n}, {'d' if d is None else d})"
        raise ValueError(f"{name} must have shape {want}, got {m.shape}")
    if not np.isfinite(m).all():
        raise ValueError(f"{name} must be finite")
    return m


class _Classifiers:
    """B two-hidden-layer ReLU MLPs d_b(u) = σ(f_b(u)) on the same inputs u ``(N, k)``, trained at once.

    Weights ``(B, in, out)`` start as ``torch.nn.Linear``'s (uniform ±1/√fan_in) from one seeded generator; training
    is full-batch Adam on the mean binary cross-entropy of each classifier's own labels, plus ``weight_decay``·‖W‖².
    """

    def __init__(self, b: int, k: int, hidden: tuple[int, int], seed: int) -> None:
        gen = torch.Generator().manual_seed(seed)
        self.params: list[torch.Tensor] = []
        for fan_in, fan_out in ((k, hidden[0]), (hidden[0], hidden[1]), (hidden[1], 1)):
            bound = 1.0 / fan_in**0.5
            for shape in ((b, fan_in, fan_out), (b, 1, fan_out)):
                p = (torch.rand(shape, generator=gen, dtype=torch.float64) * 2 - 1) * bound
                self.params.append(p.float().requires_grad_(True))

    def logits(self, u: torch.Tensor) -> torch.Tensor:
        """f_b(u): ``(N, k)`` → ``(B, N)``."""
        w1, b1, w2, b2, w3, b3 = self.params
        h = torch.relu(torch.matmul(u, w1) + b1)
        h = torch.relu(torch.baddbmm(b2, h, w2))
        return torch.baddbmm(b3, h, w3).squeeze(-1)

    def train(self, u: torch.Tensor, labels: torch.Tensor, steps: int, lr: float, weight_decay: float) -> None:
        """``labels (B, N)`` in {0, 1}."""
        opt = torch.optim.Adam(self.params, lr=lr)
        loss_fn = torch.nn.BCEWithLogitsLoss(reduction="sum")
        weights = self.params[0::2]
        for _ in range(steps):
            opt.zero_grad(set_to_none=True)
            loss = loss_fn(self.logits(u), labels) / labels.shape[1]
            loss = loss + weight_decay * sum((w**2).sum() for w in weights)
            loss.backward()
            opt.step()


class LocalTest:
    """L-C2ST: a randomization test of H₀(x_o): q(θ | x_o) = p(θ | x_o), at any observation x_o.

    :meth:`fit` trains, on a calibration set, one classifier on the true labels and ``null_trials`` = H on labels
    swapped within a random half of the pairs (each trial's swaps and all initial weights from ``seed``); :meth:`test`
    then costs 1 + H evaluations of m draws.

    Arguments:
        box: θ's prior box; when given θ enters the classifier in its scaled-logit space (a d-dimensional box).
        hidden: the widths of the classifiers' two hidden layers.
        steps: full-batch Adam steps of the training.
        learning_rate: Adam's step size.
        weight_decay: the L2 penalty on the weights, per classifier.
        null_trials: H ≥ 1, the classifiers trained on swapped labels; the p-value takes the values k / (H + 1).
        seed: the root of the swaps' and the initial weights' streams (:mod:`components.core.seeding`).

    Example:
        A right posterior on a conjugate Gaussian: θ ~ N(0, 1), x = θ + ε, ε ~ N(0, 1), p(θ | x) = N(x/2, ½).

        >>> import numpy as np
        >>> g = np.random.default_rng(0)
        >>> theta = g.standard_normal((400, 1)); x = theta + g.standard_normal((400, 1))
        >>> exact = lambda x, m: x[:, None, :] / 2 + np.sqrt(0.5) * g.standard_normal((len(x), m, 1))
        >>> test = LocalTest(null_trials=19, steps=100, hidden=(8, 8), seed=1)
        >>> test = test.fit(theta, x, exact(x, 1)[:, 0])
        >>> statistic, p_value = test.test(np.array([0.3]), exact(np.array([[0.3]]), 200)[0])
        >>> 0.0 <= statistic <= 0.25 and p_value in {k / 20 for k in range(1, 21)}
        True
    """

    def __init__(
        self,
        *,
        box: Box | None = None,
        hidden: tuple[int, int] = (16, 16),
        steps: int = 200,
        learning_rate: float = 1e-2,
        weight_decay: float = 1e-4,
        null_trials: int = 99,
        seed: int = 0,
    ) -> None:
        if len(hidden) != 2:
            raise ValueError(f"hidden must name two layer widths, got {hidden!r}")
        self.hidden = tuple(whole_number("a hidden layer width", h, low=1) for h in hidden)
        self.steps = whole_number("steps", steps, low=1)
        self.null_trials = whole_number("null_trials", null_trials, low=1)
        self.seed = whole_number("seed", seed, low=0)
        if not learning_rate > 0 or not weight_decay >= 0:
            raise ValueError(f"learning_rate must be > 0 and weight_decay ≥ 0, got {learning_rate}, {weight_decay}")
        self.box, self.learning_rate, self.weight_decay = box, float(learning_rate), float(weight_decay)
        self._classifiers: _Classifiers | None = None

    def _theta(self, theta: np.ndarray) -> np.ndarray:
        return theta if self.box is None else to_unbounded(theta, self.box)

    def _inputs(self, theta: np.ndarray, x: np.ndarray) -> torch.Tensor:
        u = np.concatenate([(self._theta(theta) - self._t_mean) / self._t_std, (x - self._x_mean) / self._x_std], 1)
        return torch.from_numpy(u.astype(np.float32))

    def fit(self, theta_cal: np.ndarray, x_cal: np.ndarray, draws_cal: np.ndarray) -> LocalTest:
        """Train the 1 + H classifiers on a calibration set.

        Arguments:
            theta_cal: ``(n, d)`` truths θᵢ ~ p(θ), physical units (inside ``box`` when given).
            x_cal: ``(n, p)`` their observations xᵢ ~ p(x | θᵢ) (or a fixed function of them).
            draws_cal: ``(n, d)`` one draw θ̃ᵢ ~ q(θ | xᵢ) per observation, independent of θᵢ given xᵢ.

        Returns:
            ``self``, ready for :meth:`test`.
        """
        theta = _matrix("theta_cal", theta_cal, d=self.box.dim if self.box is not None else None)
        n, d = theta.shape
        x = _matrix("x_cal", x_cal, n=n)
        draws = _matrix("draws_cal", draws_cal, n=n, d=d)
        if n < 2:
            raise ValueError(f"the calibration set needs at least 2 pairs, got {n}")
        pooled = self._theta(np.concatenate([theta, draws]))
        self._d, self._p = d, x.shape[1]
        self._t_mean, self._t_std = pooled.mean(0), np.where(pooled.std(0) > 0, pooled.std(0), 1.0)
        self._x_mean, self._x_std = x.mean(0), np.where(x.std(0) > 0, x.std(0), 1.0)
        u = self._inputs(np.concatenate([theta, draws]), np.concatenate([x, x]))
        swap = seeding.rng(self.seed, "local-test", "swaps").random((self.null_trials, n)) < 0.5
        swap = np.concatenate([np.zeros((1, n), dtype=bool), swap])  # classifier 0: the true labels
        labels = torch.from_numpy(np.concatenate([swap, ~swap], 1).astype(np.float32))  # 1: "a draw of q"
        clf = _Classifiers(1 + self.null_trials, d + self._p, self.hidden, seeding.derive_seed(self.seed, "local-test"))
        clf.train(u, labels, self.steps, self.learning_rate, self.weight_decay)
        self._classifiers = clf
        return self

    def statistics(self, x_o: np.ndarray, draws_o: np.ndarray) -> np.ndarray:
        """T at each observation of the observed classifier (column 0) and of the H null ones, each in [0, ¼].

        Arguments:
            x_o: ``(p,)`` one observation (as ``x_cal`` was given), or ``(k, p)`` k of them.
            draws_o: ``(m, d)`` draws θ̃ⱼ ~ q(θ | x_o), physical units; ``(k, m, d)`` for k observations.

        Returns:
            ``(1 + H,)`` for one observation, ``(k, 1 + H)`` for k.
        """
        if self._classifiers is None:
            raise RuntimeError("LocalTest.fit must be called before testing")
        one = np.ndim(x_o) == 1
        x = _matrix("x_o", np.atleast_2d(np.asarray(x_o, dtype=np.float64)), d=self._p)
        draws = np.asarray(draws_o, dtype=np.float64)
        draws = draws[None] if one else draws
        if draws.ndim != 3 or draws.shape[0] != len(x) or draws.shape[2] != self._d or draws.shape[1] == 0:
            raise ValueError(
                f"draws_o must have shape {'(m, d)' if one else '(k, m, d)'} with d = {self._d}, "
                f"m ≥ 1 and k = {len(x)} observations, got {np.shape(draws_o)}"
            )
        if not np.isfinite(draws).all():
            raise ValueError("draws_o must be finite")
        k, m = draws.shape[:2]
        out = np.empty((k, 1 + self.null_trials))
        step = max(1, _EVAL_ROWS // m)
        for a in range(0, k, step):
            b = min(k, a + step)
            u = self._inputs(draws[a:b].reshape(-1, self._d), np.repeat(x[a:b], m, 0))
            with torch.no_grad():
                prob = torch.sigmoid(self._classifiers.logits(u)).double().reshape(-1, b - a, m)
            out[a:b] = ((prob - 0.5) ** 2).mean(2).T.numpy()
        return out[0] if one else out

    def test(self, x_o: np.ndarray, draws_o: np.ndarray) -> tuple[float, float]:
        """The statistic T(x_o) and its randomization p-value (1 + #{T_h ≥ T}) / (H + 1).

        Arguments and shapes as :meth:`statistics` for one observation; reject H₀(x_o) at level α when
        ``p_value ≤ α``.
        """
        t = self.statistics(x_o, draws_o)
        if t.ndim != 1:
            raise ValueError("LocalTest.test takes one observation; use LocalTest.rejections for many")
        return float(t[0]), float(_ranks(t[None])[0, 0])

    def rejections(self, x_o: np.ndarray, draws_o: np.ndarray, level: float = 0.05) -> Rejections:
        """The test at each of k observations, and what the same count gives under H₀ for the set as a whole.

        The k tests share the classifiers, so under H₀ their rejections are correlated and their count is not
        binomial. Each null classifier is, under H₀, exchangeable with the observed one: counted the same way (its
        p-value against the other H), its rejection rate is a draw of the set's rate under H₀, so the H null rates
        give the set's range and its exact p-value.

        Arguments:
            x_o: ``(k, p)`` the observations.
            draws_o: ``(k, m, d)`` m draws of q(θ | x_o) for each, physical units.
            level: α in (0, 1): H₀(x_o) is rejected when the p-value ≤ α.

        Returns:
            :class:`Rejections`.
        """
        if not 0.0 < level < 1.0:
            raise ValueError(f"level must be in (0, 1), got {level!r}")
        t = self.statistics(x_o, draws_o)
        if t.ndim != 2:
            raise ValueError("LocalTest.rejections takes (k, p) observations and (k, m, d) draws")
        p = _ranks(t)
        rates = (p <= level + 1e-12).mean(0)
        return Rejections(float(level), p[:, 0], rates[1:], float(rates[0]))


#: Classifier inputs per evaluation call of :meth:`LocalTest.statistics` (bounds its working memory).
_EVAL_ROWS = 20000


def _ranks(t: np.ndarray) -> np.ndarray:
    """Each classifier's randomization p-value among all 1 + H at each observation: ``(k, 1 + H)`` → ``(k, 1 + H)``,
    #{b′ : T_b′ ≥ T_b} / (1 + H) (b′ = b counted)."""
    return (t[:, None, :] >= t[:, :, None]).sum(2) / t.shape[1]


@dataclass(frozen=True)
class Rejections:
    """The local test at k observations (:meth:`LocalTest.rejections`).

    Attributes:
        level: α.
        p_values: ``(k,)`` the test's p-value at each observation.
        null_rates: ``(H,)`` each null classifier's rejection rate on the same observations: the set's rate under H₀.
        rate: the share of the k observations where H₀(x_o) is rejected (p ≤ α).
    """

    level: float
    p_values: np.ndarray
    null_rates: np.ndarray
    rate: float

    @property
    def p_value(self) -> float:
        """The set's randomization p-value: (1 + #{null rates ≥ rate}) / (1 + H); under H₀, P(p ≤ j / (1 + H)) ≤
        j / (1 + H)."""
        return float((1 + np.count_nonzero(self.null_rates >= self.rate - 1e-12)) / (1 + self.null_rates.size))

    def null_range(self, confidence: float = 0.95) -> tuple[float, float]:
        """The central ``confidence`` range of the set's rejection rate under H₀ (quantiles of the null rates)."""
        tail = (1.0 - confidence) / 2
        lo, hi = np.quantile(self.null_rates, (tail, 1.0 - tail), method="inverted_cdf")
        return float(lo), float(hi)


def posterior_summary(draws: np.ndarray, box: Box) -> np.ndarray:
    """A low-dimensional stand-in for x: each parameter's median and log interquartile range of q(θ | x)'s draws in
    the box's scaled-logit space.

    Arguments:
        draws: ``(n, m, d)`` m draws of q(θ | xᵢ) per image, physical units.
        box: θ's prior box (d parameters).

    Returns:
        ``(n, 2d)``: d medians, then d log interquartile ranges (logit units).
    """
    a = np.asarray(draws, dtype=np.float64)
    if a.ndim != 3 or a.shape[2] != box.dim or a.shape[1] < 2:
        raise ValueError(f"draws must have shape (n, m ≥ 2, {box.dim}), got {a.shape}")
    z = to_unbounded(a, box)
    q1, med, q3 = np.quantile(z, (0.25, 0.5, 0.75), axis=1)
    return np.concatenate([med, np.log(np.maximum(q3 - q1, 1e-6))], axis=1)


@dataclass(frozen=True)
class Coverage:
    """How often one set of intervals covered its truths, per parameter (every array ``(d,)``).

    Attributes:
        mass: the intervals' credible mass (e.g. 0.6827), or None when not stated.
        images: n, the images counted.
        covered: the number of images whose interval covered the truth.
        rate: covered / n.
        low: the lower Clopper–Pearson limit of the rate at ``confidence``.
        high: the upper limit.
        confidence: the intervals' confidence level (e.g. 0.95).
    """

    mass: float | None
    images: int
    covered: np.ndarray
    rate: np.ndarray
    low: np.ndarray
    high: np.ndarray
    confidence: float

    def to_dict(self, box: Box) -> dict:
        """``{"mass", "images", "confidence", "parameters": {name: {"covered", "rate", "low", "high"}}}`` (JSON)."""
        return {
            "mass": self.mass,
            "images": self.images,
            "confidence": self.confidence,
            "parameters": {
                name: {
                    "covered": int(self.covered[j]),
                    "rate": float(self.rate[j]),
                    "low": float(self.low[j]),
                    "high": float(self.high[j]),
                }
                for j, name in enumerate(box.names)
            },
        }


def clopper_pearson(covered: np.ndarray | int, n: int, confidence: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """The exact binomial interval of a rate k / n: the Beta quantiles of Clopper and Pearson.

    Arguments:
        covered: k, successes (an int or an array of them), 0 ≤ k ≤ n.
        n: trials, n ≥ 1.
        confidence: the interval's level in (0, 1); each tail holds at most (1 − confidence) / 2.

    Returns:
        ``(low, high)`` shaped like ``covered``: low = B⁻¹(α/2; k, n − k + 1) (0 when k = 0), high = B⁻¹(1 − α/2;
        k + 1, n − k) (1 when k = n).

    Example:
        >>> low, high = clopper_pearson(17, 24)
        >>> round(float(low), 3), round(float(high), 3)
        (0.489, 0.874)
    """
    n = whole_number("n", n, low=1)
    k = np.asarray(covered, dtype=np.float64)
    if np.any((k < 0) | (k > n)) or np.any(k != np.round(k)):
        raise ValueError(f"covered must be whole numbers in [0, {n}], got {covered!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    tail = (1.0 - confidence) / 2
    with np.errstate(invalid="ignore"):
        low = np.where(k == 0, 0.0, beta.ppf(tail, k, n - k + 1))
        high = np.where(k == n, 1.0, beta.ppf(1.0 - tail, k + 1, n - k))
    return low, high


def named_coverage(
    truth: np.ndarray,
    hdi_low: np.ndarray,
    hdi_high: np.ndarray,
    box: Box,
    tolerance: float = 0.5,
    *,
    mass: float | None = None,
    confidence: float = 0.95,
) -> Coverage:
    """Per parameter, the share of images whose interval covers the truth, with its Clopper–Pearson interval.

    A truth inside the box is covered when ``hdi_low ≤ truth ≤ hdi_high``; a truth on a face of the box (e.g. no
    rain: precipitation = 0) when the interval reaches within ``tolerance`` units of it (``hdi_low ≤ low +
    tolerance`` on the lower face, ``hdi_high ≥ high − tolerance`` on the upper one), as draws never sit on a face.

    Arguments:
        truth: ``(n, d)`` each image's true θ, physical units, inside ``box`` (one named weather: n equal rows).
        hdi_low: ``(n, d)`` the intervals' lower ends (e.g. :func:`components.evaluate.summary.hdi` of each image).
        hdi_high: ``(n, d)`` their upper ends.
        box: the prior box (d parameters; its faces are where ``tolerance`` applies).
        tolerance: in θ's units (% or degrees), ≥ 0.
        mass: the intervals' credible mass, recorded in the result (e.g. 0.6827 or 0.95).
        confidence: the level of the Clopper–Pearson intervals.

    Returns:
        :class:`Coverage`, arrays ``(d,)``.
    """
    t = _matrix("truth", truth, d=box.dim)
    lo = _matrix("hdi_low", hdi_low, n=t.shape[0], d=box.dim)
    hi = _matrix("hdi_high", hdi_high, n=t.shape[0], d=box.dim)
    if t.shape[0] == 0:
        raise ValueError("named_coverage needs at least one image")
    if not tolerance >= 0:
        raise ValueError(f"tolerance must be ≥ 0 (θ's units), got {tolerance!r}")
    box.check(t, what="truth")
    covered = (lo <= t) & (t <= hi)
    on_low, on_high = t == box.low, t == box.high
    covered = np.where(on_low, lo <= box.low + tolerance, covered)
    covered = np.where(on_high, hi >= box.high - tolerance, covered)
    k = covered.sum(0)
    low, high = clopper_pearson(k, t.shape[0], confidence)
    return Coverage(mass, int(t.shape[0]), k, k / t.shape[0], low, high, float(confidence))
