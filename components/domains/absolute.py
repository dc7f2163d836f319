"""Task II — absolute domain characterization: a weighted bag of observations → a distribution of weather.

A domain 𝒟 is characterized by the mixture of the per-observation posteriors over a bag 𝔅 (paper, Sec. Task II):

    p̂_𝒟(θ) = Σ_{x ∈ 𝔅} w(x) q(θ | x),      w(x) ≥ 0,  Σ w(x) = 1,

where q(θ | x) is the neural posterior estimator of Task I in physical units (θ ∈ ℝᵈ, d = 6 for pidc's weather) and
x is whatever that estimator takes (images, or backbone features). The mixture is a proper density whenever every
q(· | x) is, its log-density is a log-sum-exp over the bag, and drawing from it is "choose a member by weight, then
draw once from its posterior". A mixture of such domains is again one (:func:`mixture_of`), and exponentially
decaying weights give the linear temporal filter the paper mentions (:class:`ExponentialFilter`).

Everything here is numpy; the estimator is anything that satisfies :class:`Posterior` (the torch NPE wrapper or the
torch-free ONNX runtime).

Used by the ``task2`` and ``task3`` stages and the ``pidc`` CLI (``domain``, ``relate``).

References:
    Halin, Piérard et al., "Physically Interpretable Probabilistic Domain Characterization", Task II (the mixture of
    posteriors over a weighted bag, the linear temporal filter).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import Protocol, runtime_checkable

import numpy as np
from scipy.special import logsumexp

from components.core.checks import whole_number
from components.core.seeding import derive_seed, rng

__all__ = ["Posterior", "Domain", "mixture_of", "normalized_weights", "ExponentialFilter"]

_PAIRS_PER_CALL = 1 << 16  # (θ, x) pairs per posterior.log_prob call
_BYTES_PER_CALL = 64 << 20  # bytes of repeated observations per posterior call


@runtime_checkable
class Posterior(Protocol):
    """A conditional density estimator q(θ | x) in physical units, batched over inputs (numpy in, numpy out)."""

    def log_prob(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Row-wise ``log q(θᵢ | xᵢ)``: ``theta (n, d)``, ``x (n, ...)`` → ``(n,)`` (−inf where θᵢ has no mass)."""
        ...

    def sample(self, x: np.ndarray, n: int, seed: int) -> np.ndarray:
        """``n`` draws θ ~ q(θ | xᵢ) per input: ``x (b, ...)`` → ``(b, n, d)``, deterministic in ``seed``."""
        ...


def _check_posterior(posterior: object) -> None:
    if not isinstance(posterior, Posterior):
        raise TypeError(
            f"posterior must provide log_prob(theta, x) and sample(x, n, seed) (the Posterior protocol), "
            f"got {type(posterior).__name__}"
        )


def normalized_weights(weights: object, n: int, name: str = "weights") -> np.ndarray:
    """Validate non-negative weights for ``n`` members and normalize them.

    Arguments:
        weights: ``(n,)`` non-negative finite numbers, at least one positive.
        n: the number of members.
        name: what the weights are, for the messages.

    Returns:
        ``(n,)`` float64 weights summing to 1.

    Raises:
        ValueError: naming ``name``, when the length is not ``n``, a weight is not finite or is negative, or all
            weights are zero.
    """
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 1 or w.shape[0] != n:
        raise ValueError(f"{name} must have shape ({n},) (one weight per member), got shape {w.shape}")
    if not np.all(np.isfinite(w)):
        bad = int(np.flatnonzero(~np.isfinite(w))[0])
        raise ValueError(f"{name} must be finite, got {w[bad]} at index {bad}")
    if np.any(w < 0):
        bad = int(np.flatnonzero(w < 0)[0])
        raise ValueError(f"{name} must be non-negative, got {w[bad]} at index {bad}")
    total = float(w.sum())
    if total <= 0.0:
        raise ValueError(f"{name} are all zero: at least one member needs a positive weight")
    return w / total


def _as_theta(theta: object) -> np.ndarray:
    t = np.asarray(theta, dtype=np.float64)
    if t.ndim != 2 or t.shape[0] == 0 or t.shape[1] == 0:
        raise ValueError(f"theta must have shape (m, d) with m ≥ 1 and d ≥ 1, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("theta must be finite (physical units)")
    return t


def _check_count(n: object, name: str = "n") -> int:
    return whole_number(name, n, low=1)


class Domain:
    """The estimated weather distribution of a domain, p̂_𝒟(θ) = Σᵢ wᵢ q(θ | xᵢ), from a weighted bag.

    Members with zero weight are kept in :attr:`bag` but never evaluated nor drawn. ``bag_x`` is not copied: do not
    modify it afterwards.

    Arguments:
        posterior: the estimator q(θ | x) (see :class:`Posterior`), in physical units.
        bag_x: the bag 𝔅 of observations, shape ``(N, ...)`` (images or features, what ``posterior`` takes).
        weights: non-negative weights w(xᵢ), shape ``(N,)``; normalized here. ``None``: equal weights 1/N.

    Examples:
        A toy estimator q(θ | x) = N(θ; x, 1) in 1-D and a bag of two observations weighted 3 : 1:

        >>> import numpy as np
        >>> from scipy import stats
        >>> class Shifted:  # a Posterior: log_prob(θ, x) and sample(x, n, seed), numpy in and out
        ...     def log_prob(self, theta, x):
        ...         return stats.norm.logpdf(theta[:, 0], loc=x[:, 0])
        ...     def sample(self, x, n, seed):
        ...         return x[:, None, :] + np.random.default_rng(seed).standard_normal((len(x), n, 1))
        >>> domain = Domain(Shifted(), np.array([[-2.0], [2.0]]), weights=[3, 1])
        >>> domain.weights.tolist()
        [0.75, 0.25]
        >>> round(float(np.exp(domain.log_prob(np.array([[-2.0]]))[0])), 4)  # 0.75 φ(0) + 0.25 φ(4)
        0.2992
        >>> domain.sample(1000, seed=0).shape
        (1000, 1)
    """

    def __init__(self, posterior: Posterior, bag_x: np.ndarray, weights: np.ndarray | Sequence[float] | None = None):
        _check_posterior(posterior)
        bag = np.asarray(bag_x)
        if bag.ndim == 0:
            raise ValueError("bag_x must be an array of observations with shape (N, ...), got a scalar")
        if bag.shape[0] == 0:
            raise ValueError("the bag is empty: a domain needs at least one observation")
        n = bag.shape[0]
        w = np.full(n, 1.0 / n) if weights is None else normalized_weights(weights, n)
        self.posterior = posterior
        self._bag = bag
        self._weights = w
        self._weights.setflags(write=False)
        self._active = np.flatnonzero(w > 0)
        self._log_w = np.log(w[self._active])

    @property
    def bag(self) -> np.ndarray:
        """The observations, shape ``(N, ...)``."""
        return self._bag

    @property
    def weights(self) -> np.ndarray:
        """Normalized weights w(xᵢ), shape ``(N,)``, read-only, summing to 1."""
        return self._weights

    def __len__(self) -> int:
        return int(self._bag.shape[0])

    def __repr__(self) -> str:
        return f"Domain(N={len(self)}, observation shape={self._bag.shape[1:]})"

    def _members_per_call(self) -> int:
        item = max(1, int(self._bag[0].nbytes))
        return max(1, min(_PAIRS_PER_CALL, _BYTES_PER_CALL // item))

    def _member_blocks(self, t: np.ndarray) -> Iterator[tuple[int, int, np.ndarray]]:
        """Yield ``(t0, i0, lq)``: log q(θⱼ | xᵢ) for rows t0… of the checked ``t`` (:func:`_as_theta`) and active
        members i0…, ``lq (members, rows)``; every (θⱼ, xᵢ) pair once, in calls of a bounded number of pairs and bytes."""
        pairs = self._members_per_call()
        for t0 in range(0, t.shape[0], pairs):
            tb = t[t0 : t0 + pairs]
            mb = tb.shape[0]
            per_call = max(1, pairs // mb)
            for i0 in range(0, self._active.size, per_call):
                idx = self._active[i0 : i0 + per_call]
                x_rep = np.repeat(self._bag[idx], mb, axis=0)  # member-major: row i*mb + j is (θⱼ, x_idx[i])
                t_rep = np.tile(tb, (idx.size, 1))
                lq = np.asarray(self.posterior.log_prob(t_rep, x_rep), dtype=np.float64)
                if lq.shape != (idx.size * mb,):
                    raise ValueError(
                        f"posterior.log_prob returned shape {lq.shape}, expected ({idx.size * mb},) for that many pairs"
                    )
                if np.any(np.isnan(lq)) or np.any(lq == np.inf):
                    raise ValueError("posterior.log_prob returned NaN or +inf: the estimator is not a proper density")
                yield t0, i0, lq.reshape(idx.size, mb)

    def log_prob(self, theta: np.ndarray) -> np.ndarray:
        """log p̂_𝒟(θⱼ) = logsumexpᵢ [log wᵢ + log q(θⱼ | xᵢ)].

        All (θⱼ, xᵢ) pairs are evaluated, in calls of a bounded number of pairs and bytes.

        Arguments:
            theta: ``(m, d)`` points in physical units.

        Returns:
            ``(m,)`` log-densities per unit of θ; −inf where no member has mass.
        """
        t = _as_theta(theta)
        out = np.full(t.shape[0], -np.inf)
        for t0, i0, lq in self._member_blocks(t):
            part = lq + self._log_w[i0 : i0 + lq.shape[0], None]
            sl = slice(t0, t0 + lq.shape[1])
            out[sl] = np.logaddexp(out[sl], logsumexp(part, axis=0))  # −inf where a column is all −inf
        return out

    def member_log_prob(self, theta: np.ndarray) -> np.ndarray:
        """log q(θⱼ | xᵢ) for every member with positive weight (bag order) and every row of ``theta (m, d)`` →
        ``(members, m)``, physical units."""
        t = _as_theta(theta)
        out = np.empty((self._active.size, t.shape[0]))
        for t0, i0, lq in self._member_blocks(t):
            out[i0 : i0 + lq.shape[0], t0 : t0 + lq.shape[1]] = lq
        return out

    def sample(self, n: int, seed: int) -> np.ndarray:
        """``n`` draws θ ~ p̂_𝒟: members chosen i.i.d. by weight, one posterior draw each.

        Deterministic in ``seed``: the member choice uses stream ``(seed, "domain", "members")``, and the draws of
        the k-th batch of chosen members use the posterior seed ``derive_seed(seed, "domain", "draws", k)``.

        Arguments:
            n: the number of draws, ≥ 1.
            seed: root of the draws' streams.

        Returns:
            θ ``(n, d)``, float64 in physical units.
        """
        n = _check_count(n)
        chosen = rng(seed, "domain", "members").choice(len(self), size=n, p=self._weights)
        per_call = self._members_per_call()
        parts = []
        for k, c0 in enumerate(range(0, n, per_call)):
            idx = chosen[c0 : c0 + per_call]
            draws = np.asarray(self.posterior.sample(self._bag[idx], 1, derive_seed(seed, "domain", "draws", k)))
            if draws.ndim != 3 or draws.shape[:2] != (idx.size, 1):
                raise ValueError(f"posterior.sample returned shape {draws.shape}, expected ({idx.size}, 1, d)")
            parts.append(draws[:, 0, :])
        return np.concatenate(parts, axis=0).astype(np.float64, copy=False)


def mixture_of(domains: Sequence[Domain], weights: np.ndarray | Sequence[float]) -> Domain:
    """The domain Σₖ λₖ p̂_𝒟ₖ as one :class:`Domain` (mixtures of mixtures are mixtures).

    The bag is the concatenation of the domains' bags and member i of domain k gets weight λₖ·wₖᵢ.

    Arguments:
        domains: K ≥ 1 domains sharing the same posterior object and observation shape.
        weights: λ ``(K,)``, non-negative; validated and normalized like any weights.

    Returns:
        One :class:`Domain` over the concatenated bags.
    """
    domains = list(domains)
    if not domains:
        raise ValueError("mixture_of needs at least one domain")
    for k, d in enumerate(domains):
        if not isinstance(d, Domain):
            raise TypeError(f"domains[{k}] must be a Domain, got {type(d).__name__}")
    lam = normalized_weights(weights, len(domains), "mixture weights")
    first = domains[0]
    for k, d in enumerate(domains[1:], start=1):
        if d.posterior is not first.posterior:
            raise ValueError(f"domains[{k}] uses another posterior: a single Domain needs one shared estimator")
        if d.bag.shape[1:] != first.bag.shape[1:]:
            raise ValueError(
                f"domains[{k}] has observations of shape {d.bag.shape[1:]}, domains[0] has {first.bag.shape[1:]}"
            )
    bag = np.concatenate([d.bag for d in domains], axis=0)
    w = np.concatenate([lk * d.weights for lk, d in zip(lam, domains, strict=False)])
    return Domain(first.posterior, bag, w)


class ExponentialFilter:
    """A stream of observations weighted by age: w(x) ∝ decay^age, the linear temporal filter of Task II.

    Time advances by one step per :meth:`update`; the observations of one update share their age (0 for the newest
    batch). Exactly one of ``half_life`` (in updates, weights halve every ``half_life`` updates: decay = 2^(−1/h))
    and ``decay`` ∈ (0, 1] is given. decay = 1 gives the equally weighted bag of everything seen.

    Incremental: each member stores its log-weight relative to a running log-scale s (s decreases by −log decay per
    update), so an update costs O(batch) amortized; older weights are never recomputed, only rescaled when the
    scale is folded back into the stored values (rarely, to keep them bounded).

    Arguments:
        posterior: the estimator q(θ | x).
        half_life: half-life in updates (> 0), or
        decay: the per-update decay factor in (0, 1].
        tolerance: members whose weight relative to the newest falls below it are dropped (0: never).
        max_size: at most this many members are kept; the oldest are dropped first (None: no limit).
    """

    _FOLD = 256.0  # fold the running log-scale into the stored log-weights once it exceeds this (or 64 updates' worth)

    def __init__(
        self,
        posterior: Posterior,
        *,
        half_life: float | None = None,
        decay: float | None = None,
        tolerance: float = 0.0,
        max_size: int | None = None,
    ) -> None:
        _check_posterior(posterior)
        if (half_life is None) == (decay is None):
            raise ValueError("give exactly one of half_life (updates) and decay (per update)")
        if half_life is not None:
            h = float(half_life)
            if not (math.isfinite(h) and h > 0):
                raise ValueError(f"half_life must be a positive finite number of updates, got {half_life!r}")
            decay = 0.5 ** (1.0 / h)
        decay = float(decay)
        if not (0.0 < decay <= 1.0):
            raise ValueError(f"decay must be in (0, 1], got {decay!r}")
        tol = float(tolerance)
        if not (0.0 <= tol < 1.0):
            raise ValueError(f"tolerance must be in [0, 1), got {tolerance!r}")
        if max_size is not None:
            max_size = _check_count(max_size, "max_size")
        self.posterior = posterior
        self.decay = decay
        self.tolerance = tol
        self.max_size = max_size
        self._log_decay = math.log(decay)
        self._log_tol = math.log(tol) if tol > 0 else -math.inf
        self._scale = 0.0  # running log-scale s: current log-weight of member i = stored_i + s
        self._steps = 0
        self._start = 0  # live members are buffer rows [start, stop)
        self._stop = 0
        self._stored = np.empty(0)
        self._bag: np.ndarray | None = None
        self._birth = np.empty(0, dtype=np.int64)

    @property
    def steps(self) -> int:
        """Number of updates so far."""
        return self._steps

    def __len__(self) -> int:
        return self._stop - self._start

    def _grow(self, extra: int, example: np.ndarray) -> None:
        live = len(self)
        if self._bag is None:
            cap = max(16, extra)
            self._bag = np.empty((cap, *example.shape[1:]), dtype=example.dtype)
            self._stored = np.empty(cap)
            self._birth = np.empty(cap, dtype=np.int64)
            return
        if self._stop + extra <= self._stored.size:
            return
        cap = self._stored.size if live + extra <= self._stored.size // 2 else 2 * (live + extra)
        sl = slice(self._start, self._stop)
        bag = np.empty((cap, *self._bag.shape[1:]), dtype=self._bag.dtype)
        stored = np.empty(cap)
        birth = np.empty(cap, dtype=np.int64)
        bag[:live], stored[:live], birth[:live] = self._bag[sl], self._stored[sl], self._birth[sl]
        self._bag, self._stored, self._birth = bag, stored, birth
        self._start, self._stop = 0, live

    def update(self, x_batch: np.ndarray) -> None:
        """Age everything by one update and add ``x_batch (b, ...)`` (b ≥ 1) with age 0."""
        x = np.asarray(x_batch)
        if x.ndim == 0 or x.shape[0] == 0:
            raise ValueError(f"x_batch must be a non-empty batch of observations (b, ...), got shape {x.shape}")
        if self._bag is not None and x.shape[1:] != self._bag.shape[1:]:
            raise ValueError(f"x_batch has observations of shape {x.shape[1:]}, the stream has {self._bag.shape[1:]}")
        self._steps += 1
        self._scale += self._log_decay
        if abs(self._scale) > max(self._FOLD, 64.0 * abs(self._log_decay)):
            self._stored[self._start : self._stop] += self._scale
            self._scale = 0.0
        b = x.shape[0]
        self._grow(b, x)
        assert self._bag is not None
        self._bag[self._stop : self._stop + b] = x
        self._stored[self._stop : self._stop + b] = -self._scale
        self._birth[self._stop : self._stop + b] = self._steps
        self._stop += b
        self._prune()

    def _prune(self) -> None:
        # the newest weight is stored + s = 0; oldest members come first and have the smallest weights
        if self._log_tol > -math.inf:
            while self._start < self._stop and self._stored[self._start] + self._scale < self._log_tol:
                self._start += 1
        if self.max_size is not None and len(self) > self.max_size:
            self._start = self._stop - self.max_size

    @property
    def ages(self) -> np.ndarray:
        """Age (in updates, 0 = newest batch) of each live member, oldest first, shape ``(N,)``."""
        return self._steps - self._birth[self._start : self._stop]

    @property
    def weights(self) -> np.ndarray:
        """Normalized current weights ∝ decay^age, oldest member first, shape ``(N,)``."""
        if len(self) == 0:
            raise ValueError("the filter has seen no observation yet: call update() first")
        lw = self._stored[self._start : self._stop] + self._scale
        w = np.exp(lw - lw.max())
        return w / w.sum()

    def domain(self) -> Domain:
        """The current characterization: a :class:`Domain` over the live members (a copy) with :attr:`weights`."""
        w = self.weights
        assert self._bag is not None
        return Domain(self.posterior, self._bag[self._start : self._stop].copy(), w)
