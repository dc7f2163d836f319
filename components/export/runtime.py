"""The torch-free posterior q(θ | x): the graphs written by :mod:`components.export.onnx`, run with onnxruntime.

Only numpy, onnxruntime and json are needed (no torch anywhere in the import chain), so that the posterior can
run where torch is not installed (e.g. in a vehicle). Notation as in :mod:`components.posterior.model`:
θ ∈ [low, high]ᵈ physical units, z = scaled logit of θ (:func:`components.core.weather.to_unbounded`), c = context.
The graphs give z-space log-densities ``log qₖ(z | c)`` of the K ensemble members; this module adds the
mixture and the change of variables in float64:

    log q(θ | x) = logsumexp_k (log qₖ(z | c) − log K) − log |det ∂θ/∂z|        (−inf outside the closed box)

Sampling pushes base noise ε ~ N(0, I), drawn from ``numpy.random.Generator(PCG64)`` seeded through
:mod:`components.core.seeding` (stream ``(seed, "posterior", "sample")``), through member k's inverse graph; the member
of each draw is chosen uniformly by the same generator. θ = :func:`components.core.weather.to_physical` (z) never
leaves the box.

:class:`OnnxPosterior` satisfies :class:`components.domains.absolute.Posterior` (numpy in, numpy out).

Used by the ``evaluate``, ``task2`` and ``task3`` stages and the ``pidc`` CLI.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime

from components.core import seeding, weather
from components.core.checks import whole_number
from components.core.files import sha256_file

__all__ = ["OnnxPosterior", "CARD_FORMAT", "CARD_KIND"]

#: The card format this runtime reads (:data:`components.export.onnx.CARD_FORMAT`; repeated here to keep torch out).
CARD_FORMAT: int = 2
#: The card's ``kind``.
CARD_KIND: str = "pidc-onnx-posterior"
#: Rows per onnxruntime call when sampling or evaluating many points (bounds the graphs' working memory).
_CHUNK_ROWS: int = 65536


def _read_card(folder: Path) -> dict[str, Any]:
    path = folder / "card.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no model card; is {folder} an exported posterior (components.export.onnx)?")
    try:
        card = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not a valid JSON model card ({e})") from None
    if not isinstance(card, dict) or card.get("kind") != CARD_KIND:
        kind = card.get("kind") if isinstance(card, dict) else None
        raise ValueError(f"{path}: not a pidc ONNX posterior card (kind {kind!r}, expected {CARD_KIND!r})")
    if card.get("format") != CARD_FORMAT:
        raise ValueError(
            f"{path}: card format {card.get('format')!r}, this runtime reads format {CARD_FORMAT}; re-export the model"
        )
    for key, kind in (
        ("theta", dict),
        ("bijection", dict),
        ("ensemble", int),
        ("features", int),
        ("input", dict),
        ("files", dict),
    ):
        if not isinstance(card.get(key), kind):
            raise ValueError(f"{path}: the model card lacks {key!r} (a {kind.__name__})")
    return card


def _even_blocks(rows: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The rows ``(m,)`` (ascending; row ``b·n + j`` is input b's draw j) with each input's last row repeated where it
    has an odd number of them, and the mask ``(m',)`` of the rows that are not such repeats.

    onnxruntime's CPU kernels compute rows in pairs, and a row's last digit depends on whether it sits at an even or an
    odd position of the call (measured on the graphs of an ensemble: every mismatch between two chunkings was a row
    whose position changed parity). With each input's rows an even block, an input's draws sit at the same parities
    however the inputs are grouped into calls: its draws and densities depend on the input only (``evaluate.images``
    and the evaluation's chunking are a matter of speed).
    """
    if rows.size == 0:
        return rows, np.ones(0, dtype=bool)
    counts = np.bincount(rows // n)
    last = np.cumsum(counts)[counts % 2 == 1] - 1  # the position of each odd block's last row
    padded = np.insert(rows, last + 1, rows[last])
    real = np.ones(padded.size, dtype=bool)
    real[last + 1 + np.arange(last.size)] = False
    return padded, real


class OnnxPosterior:
    """q(θ | x) from an exported folder, on onnxruntime (CPU). Build it with :meth:`load`.

    Attributes:
        card: the model card (dict).
        box: the prior box (:class:`components.core.weather.Box`), θ names and units in order.
        ensemble: K, the number of flows of the equal-weight mixture.
        input_shape: one input's shape (features ``(F,)``, or the preprocessed image tensor's ``(C, H, W)``).
        features: the context size.

    Examples:
        An (untrained) torch posterior exported, then read back without torch: the same density to float32
        precision.

        >>> import tempfile
        >>> from pathlib import Path
        >>> import numpy as np, torch
        >>> from components.core.weather import Box
        >>> from components.export.onnx import export_posterior
        >>> from components.posterior import NPE, FlowConfig
        >>> box = Box(np.array([0.0, -90.0]), np.array([100.0, 90.0]), names=("cloudiness", "sun_altitude_angle"))
        >>> model = NPE(None, features=3, box=box, config=FlowConfig(transforms=1, hidden_features=(16,)))
        >>> folder = export_posterior(model, Path(tempfile.mkdtemp()) / "toy", card={}, exporter="torchscript")
        >>> posterior = OnnxPosterior.load(folder)
        >>> x = np.random.default_rng(0).standard_normal((4, 3)).astype(np.float32)  # 4 inputs of 3 features
        >>> theta = posterior.sample(x, 10, seed=1)  # 10 draws per input, physical units
        >>> theta.shape, theta.dtype
        ((4, 10, 2), dtype('float64'))
        >>> torch_log_q = model.log_prob(torch.from_numpy(theta).float(), torch.from_numpy(x)).detach().numpy()
        >>> bool(np.allclose(posterior.log_prob(theta, x), torch_log_q, atol=1e-3))
        True
    """

    def __init__(self, folder: Path, card: dict[str, Any], sessions: dict[str, onnxruntime.InferenceSession]) -> None:
        self.folder = folder
        self.card = card
        b = card["bijection"]
        if b.get("name") != "scaled_logit" or not math.isclose(float(b.get("edge_eps", -1.0)), weather.EDGE_EPS):
            raise ValueError(
                f"{folder}: bijection {b.get('name')!r} with edge_eps {b.get('edge_eps')!r}; this runtime implements "
                f"'scaled_logit' with EDGE_EPS = {weather.EDGE_EPS}"
            )
        self.box = weather.Box(
            np.array(b["low"]), np.array(b["high"]), tuple(card["theta"]["names"]), tuple(card["theta"]["units"])
        )
        self.ensemble = int(card["ensemble"])
        self.features = int(card["features"])
        self.input_shape: tuple[int, ...] = tuple(int(s) for s in card["input"]["shape"][1:])
        self._context = sessions["context"]
        self._log_prob = [sessions[f"log_prob_{k}"] for k in range(self.ensemble)]
        self._sample = [sessions[f"sample_{k}"] for k in range(self.ensemble)]

    # --- loading -----------------------------------------------------------------------------------------

    @classmethod
    def load(cls, folder: str | Path, *, intra_op_num_threads: int = 1) -> OnnxPosterior:
        """Open the exported posterior in ``folder`` (``card.json`` + ONNX graphs), checking every file's sha256.

        Arguments:
            folder: an exported folder (e.g. ``registry/<backbone>-<size>``).
            intra_op_num_threads: onnxruntime threads per graph call (≥ 1; default 1).

        Raises:
            FileNotFoundError: no folder, no card, or a graph file named by the card is missing.
            ValueError: unreadable card, wrong card kind/format, a file whose sha256 differs from the card's
                (corrupt or modified), or a graph onnxruntime cannot load.
        """
        folder = Path(folder)
        if not folder.is_dir():
            raise FileNotFoundError(f"{folder}: no such exported posterior folder (run the export stage)")
        intra_op_num_threads = whole_number("intra_op_num_threads", intra_op_num_threads, low=1)
        card = _read_card(folder)
        ensemble = card["ensemble"]
        whole_number(f"{folder / 'card.json'}: ensemble", ensemble, low=1)
        roles = ["context", *(f"{g}_{k}" for g in ("log_prob", "sample") for k in range(ensemble))]
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = intra_op_num_threads
        options.inter_op_num_threads = 1
        options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
        sessions: dict[str, onnxruntime.InferenceSession] = {}
        for role in roles:
            entry = card["files"].get(role)
            if not isinstance(entry, dict) or "name" not in entry or "sha256" not in entry:
                raise ValueError(f"{folder / 'card.json'}: the card names no file for the {role!r} graph")
            path = folder / str(entry["name"])
            if not path.is_file():
                raise FileNotFoundError(f"{path}: the {role!r} graph named by the card is missing")
            digest = sha256_file(path)
            if digest != entry["sha256"]:
                raise ValueError(
                    f"{path}: sha256 {digest[:16]}… differs from the card's {str(entry['sha256'])[:16]}… "
                    "(corrupt or modified file; re-export the model)"
                )
            try:
                sessions[role] = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
            except Exception as e:  # onnxruntime raises its own exception types
                raise ValueError(
                    f"{path}: onnxruntime cannot load the {role!r} graph ({type(e).__name__}: {e})"
                ) from None
        try:
            return cls(folder, card, sessions)
        except (KeyError, TypeError, IndexError) as e:
            raise ValueError(f"{folder / 'card.json'}: malformed model card ({type(e).__name__}: {e})") from None

    def on_context(self) -> OnnxPosterior:
        """The same posterior taking the context ``c = self.context(x)`` as its input ``x`` (shape ``(B, features)``).

        For bags evaluated many times (Task III): compute each image's context once, then every ``log_prob`` and
        ``sample`` call skips the context graph (for a CNN embedding, the costly part). Shares the sessions.
        """
        view = copy.copy(self)
        view.input_shape = (self.features,)
        view._context_of = lambda x32: x32  # type: ignore[method-assign]
        return view

    # --- inputs ------------------------------------------------------------------------------------------

    @property
    def dim(self) -> int:
        """d, the number of parameters θ."""
        return self.box.dim

    def _inputs(self, x: np.ndarray) -> np.ndarray:
        """Check ``x (B, *input_shape)`` (floating point, finite) and return it as contiguous float32."""
        x = np.asarray(x)
        expected = f"(batch, {', '.join(map(str, self.input_shape))})"
        if x.ndim != 1 + len(self.input_shape) or tuple(x.shape[1:]) != self.input_shape:
            raise ValueError(
                f"x must have shape {expected} ({self.card['input'].get('preprocessing', '')}), got {x.shape}"
            )
        if x.shape[0] == 0:
            raise ValueError(f"x must be a non-empty batch of shape {expected}, got {x.shape}")
        if not np.issubdtype(x.dtype, np.floating):
            raise TypeError(
                f"x must be a float32 array of shape {expected} (e.g. backbone.preprocess output), got dtype {x.dtype}"
            )
        if not np.all(np.isfinite(x)):
            raise ValueError("x contains NaN or infinite values")
        return np.ascontiguousarray(x, dtype=np.float32)

    def _check_n(self, n: int) -> int:
        return whole_number("the number of posterior samples n", n, low=1)

    # --- graphs ------------------------------------------------------------------------------------------

    def context(self, x: np.ndarray) -> np.ndarray:
        """The flow's context ``c``: ``x (B, *input_shape) → (B, features)`` float32."""
        return self._context_of(self._inputs(x))

    def _context_of(self, x32: np.ndarray) -> np.ndarray:
        out = [self._context.run(None, {"x": x32[i : i + _CHUNK_ROWS]})[0] for i in range(0, x32.shape[0], _CHUNK_ROWS)]
        return np.concatenate(out, axis=0)

    def _log_qz_member(self, k: int, context: np.ndarray, z: np.ndarray) -> np.ndarray:
        """``(N, features), (N, d) → (N,)`` float64: member k's log qₖ(z | c)."""
        z32 = np.ascontiguousarray(z, dtype=np.float32)
        out = [
            self._log_prob[k].run(None, {"context": context[i : i + _CHUNK_ROWS], "z": z32[i : i + _CHUNK_ROWS]})[0]
            for i in range(0, z32.shape[0], _CHUNK_ROWS)
        ]
        return np.concatenate(out, axis=0).astype(np.float64)

    def _log_qz_mixture(self, members: np.ndarray) -> np.ndarray:
        """log q(z | c) of the equal-weight mixture from its members' ``(N, K)`` log qₖ, ``(N,)`` float64."""
        if self.ensemble == 1:
            return members[:, 0]
        # numpy's log-sum-exp (−inf where every member is −inf); no scipy here, to keep the runtime's dependencies few
        return np.logaddexp.reduce(members, axis=1) - math.log(self.ensemble)

    def _invert(self, k: int, context: np.ndarray, eps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Member k's inverse pass: ``(B, features), (B, n, d) → z (B, n, d), log qₖ(z | c) (B, n)``."""
        step = max(1, _CHUNK_ROWS // eps.shape[1])
        zs, lqs = [], []
        for i in range(0, eps.shape[0], step):
            z, lq = self._sample[k].run(None, {"context": context[i : i + step], "eps": eps[i : i + step]})
            zs.append(z)
            lqs.append(lq)
        return np.concatenate(zs, axis=0), np.concatenate(lqs, axis=0).astype(np.float64)

    # --- densities ---------------------------------------------------------------------------------------

    def log_prob(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        """log q(θ | x) in physical units (per unit of each parameter's unit), float64.

        Arguments:
            theta: ``(B, d)`` (one θ per input) or ``(B, m, d)`` (m θ's per input), physical units.
            x: ``(B, *input_shape)``.

        Returns:
            ``(B,)`` or ``(B, m)``; exactly ``-inf`` outside the closed box.
        """
        x32 = self._inputs(x)
        b = x32.shape[0]
        t = np.asarray(theta, dtype=np.float64)
        if t.ndim not in (2, 3) or t.shape[0] != b or t.shape[-1] != self.dim:
            raise ValueError(
                f"θ must have shape ({b}, {self.dim}) or ({b}, m, {self.dim}) ({', '.join(self.box.names)}), got {t.shape}"
            )
        if not np.all(np.isfinite(t)):
            raise ValueError("θ contains NaN or infinite values")
        context = self._context_of(x32)
        m = 1 if t.ndim == 2 else t.shape[1]
        flat = t.reshape(b * m, self.dim)
        z = weather.to_unbounded(flat, self.box)
        c_rows = np.repeat(context, m, axis=0)
        log_qz = self._log_qz_mixture(np.stack([self._log_qz_member(k, c_rows, z) for k in range(self.ensemble)], 1))
        log_q = log_qz - weather.log_abs_det_jacobian(z, self.box)
        log_q = np.where(self.box.contains(flat), log_q, -np.inf)
        return log_q.reshape(t.shape[:-1])

    # --- sampling ----------------------------------------------------------------------------------------

    def _noise(self, b: int, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Base noise ε ``(b, n, d)`` float32 and members ``(b, n)`` from the stream ``(seed, "posterior", "sample")``."""
        rng = seeding.rng(seed, "posterior", "sample")
        eps = rng.standard_normal((b, n, self.dim)).astype(np.float32)
        members = rng.integers(self.ensemble, size=(b, n)) if self.ensemble > 1 else np.zeros((b, n), dtype=np.int64)
        return eps, members

    def sample_from_noise(
        self, x: np.ndarray, eps: np.ndarray, members: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Push given base noise through the flow: draws θ and log q(θ | x), physical units.

        Arguments:
            x: ``(B, *input_shape)``.
            eps: ``(B, n, d)`` standard-normal base noise ε.
            members: ``(B, n)`` integers in [0, K): the ensemble member of each draw (may be omitted when K = 1).

        Returns:
            θ ``(B, n, d)`` float64 inside the closed box, and log q(θ | x) ``(B, n)`` float64 (the mixture's density
            of the drawn z, Jacobian included).
        """
        x32 = self._inputs(x)
        b = x32.shape[0]
        e = np.asarray(eps)
        if e.ndim != 3 or e.shape[0] != b or e.shape[2] != self.dim or e.shape[1] == 0:
            raise ValueError(f"eps must have shape ({b}, n, {self.dim}) with n >= 1, got {e.shape}")
        if not np.all(np.isfinite(e)):
            raise ValueError("eps contains NaN or infinite values")
        n = e.shape[1]
        if members is None:
            if self.ensemble > 1:
                raise ValueError(
                    f"members ({b}, {n}) is required: this posterior is an ensemble of {self.ensemble} flows"
                )
            which = np.zeros((b, n), dtype=np.int64)
        else:
            which = np.asarray(members)
            if which.shape != (b, n) or not np.issubdtype(which.dtype, np.integer):
                raise ValueError(
                    f"members must be an integer array of shape ({b}, {n}), got {which.dtype} {which.shape}"
                )
            if which.min() < 0 or which.max() >= self.ensemble:
                raise ValueError(
                    f"members must lie in [0, {self.ensemble}), got values in [{which.min()}, {which.max()}]"
                )
        return self._draw(self._context_of(x32), np.ascontiguousarray(e, dtype=np.float32), which)

    def _draw(self, context: np.ndarray, eps: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """θ ``(b, n, d)`` and log q(θ | x) ``(b, n)`` from contexts ``(b, F)``, ε ``(b, n, d)``, members ``(b, n)``."""
        b, n, d = eps.shape
        if self.ensemble == 1:  # one graph call: the context is shared by the n draws of an input
            z, log_qz = self._invert(0, context, eps)
            z64 = z.astype(np.float64).reshape(b * n, d)
            log_qz = log_qz.reshape(b * n)
        else:  # each draw goes through its member (rows of one draw each), then the other members' densities
            c_rows = np.repeat(context, n, axis=0)  # row b·n + j ↔ (input b, draw j)
            e_rows = eps.reshape(b * n, 1, d)
            w_rows = which.reshape(b * n)
            z64 = np.empty((b * n, d), dtype=np.float64)
            members = np.empty((b * n, self.ensemble), dtype=np.float64)
            for k in range(self.ensemble):
                rows, real = _even_blocks(np.flatnonzero(w_rows == k), n)
                if rows.size:
                    c_k = np.ascontiguousarray(c_rows[rows])
                    zk, log_qk = self._invert(k, c_k, np.ascontiguousarray(e_rows[rows]))
                    z_k, kept = zk[:, 0], rows[real]
                    z64[kept] = z_k[real]
                    members[kept, k] = log_qk[real, 0]  # the drawing member's density from its inverse pass
                    for j in range(self.ensemble):
                        if j != k:
                            members[kept, j] = self._log_qz_member(j, c_k, z_k)[real]
            log_qz = self._log_qz_mixture(members)
        theta = weather.to_physical(z64, self.box)
        log_q = log_qz - weather.log_abs_det_jacobian(z64, self.box)
        return theta.reshape(b, n, d), log_q.reshape(b, n)

    def sample_and_log_prob(self, x: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """n draws θ ~ q(θ | xᵢ) per input and their log q(θ | xᵢ). Deterministic in ``seed`` (same seed, same draws).

        Arguments:
            x: ``(B, *input_shape)`` inputs.
            n: draws per input, ≥ 1.
            seed: root of the stream ``(seed, "posterior", "sample")`` of the base noise and the members.

        Returns:
            θ ``(B, n, d)`` float64 in physical units, inside the closed box, and log q(θ | x) ``(B, n)`` float64.
        """
        n = self._check_n(n)
        x32 = self._inputs(x)
        eps, which = self._noise(x32.shape[0], n, seed)
        return self._draw(self._context_of(x32), eps, which)

    def sample(self, x: np.ndarray, n: int, seed: int) -> np.ndarray:
        """n draws θ ~ q(θ | xᵢ) per input, deterministic in ``seed`` (the θ of :meth:`sample_and_log_prob`).

        Arguments:
            x: ``(B, *input_shape)`` inputs.
            n: draws per input, ≥ 1.
            seed: root of the draws' stream.

        Returns:
            θ ``(B, n, d)`` float64 in physical units, inside the closed box.
        """
        return self.sample_and_log_prob(x, n, seed)[0]

    def __repr__(self) -> str:
        return (
            f"OnnxPosterior({str(self.folder)!r}, d={self.dim}, ensemble={self.ensemble}, "
            f"input_shape={self.input_shape}, features={self.features})"
        )
