"""The threshold of the windows' relative gap and the per-parameter in-ODD levels, calibrated on windows held out of
the sources.

In-ODD calibration windows must look like the drive's windows: L *consecutive* frames of one drive, a narrow
distribution, not a random bag of a source's images. So each source (frames in name order, ideally a recorded or
simulated drive) is cut into blocks of B frames whose roles cycle

    density, calibration, density, evaluation, density, calibration, …

(:data:`BLOCK_ROLES`): the density blocks make the source's kernel density (the drive is related to these alone), and
the windows inside each calibration or evaluation block — contiguous runs of L frames every s frames, never across a
block's edge — are in-ODD windows of frames no density holds, related exactly as the drive's windows are
(:func:`components.watch.relation.relate_window`).

- The **threshold** is the split-conformal rank of the calibration windows' relative gaps at α
  (:meth:`components.domains.relative.OddDetector.calibrate`): a fresh in-ODD window is above it with probability
  ≤ α (overlapping windows are dependent, so this holds per window, on average, not for each window independently).
- Each parameter's **in-ODD level** is the same rank of the calibration windows' W₁ (as
  :class:`components.domains.difference.InOddDifferences` sets relate's levels): the W₁ an in-ODD window exceeds
  with probability ≤ α; a parameter beyond it is what an alarm is about.
- The **evaluation** windows, used for neither, give the rule's stated false alarms per hour
  (:mod:`components.watch.sequential`), block by block as a drive would meet them.

Used by :mod:`components.watch.run`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from components.core.seeding import derive_seed
from components.domains.relative import OddDetector
from components.watch.errors import WatchError
from components.watch.relation import SourceDensities, relate_window
from components.watch.timeline import WindowShape

__all__ = [
    "BLOCK_ROLES",
    "SATURATION_BAND",
    "block_roles",
    "check_sources",
    "density_draws",
    "HeldOut",
    "Calibration",
    "calibrate",
]

#: The roles of a source's consecutive blocks, cycled: half its frames make its density, a quarter calibrate the
#: threshold and the levels, a quarter evaluate the rule.
BLOCK_ROLES: tuple[str, ...] = ("density", "calibration", "density", "evaluation")
#: A threshold within this of 1 gives no decision: in-ODD windows already have the relative gap of windows the sources
#: miss entirely (``pidc relate``'s :data:`components.cli.relate.SATURATION_BAND`, for the same reason).
SATURATION_BAND = 0.02


def block_roles(n_frames: int, block: int) -> np.ndarray:
    """The role of each of a source's ``n_frames`` frames (``(n,)`` of :data:`BLOCK_ROLES`' names): frame i is in
    block ⌊i / B⌋, whose role is ``BLOCK_ROLES[⌊i / B⌋ mod 4]``.

    Examples:
        >>> block_roles(9, 2).tolist()
        ['density', 'density', 'calibration', 'calibration', 'density', 'density', 'evaluation', 'evaluation', 'density']
    """
    blocks = np.arange(n_frames) // block
    return np.asarray(BLOCK_ROLES)[blocks % len(BLOCK_ROLES)]


def _blocks(n_frames: int, block: int, role: str) -> list[tuple[int, int]]:
    """The ``[start, stop)`` frames of a source's blocks of ``role``."""
    out = []
    for b, start in enumerate(range(0, n_frames, block)):
        if BLOCK_ROLES[b % len(BLOCK_ROLES)] == role:
            out.append((start, min(start + block, n_frames)))
    return out


@dataclass(frozen=True)
class HeldOut:
    """The windows of one held-out block of a source, in time order.

    Attributes:
        source: the source's index k.
        role: ``"calibration"`` or ``"evaluation"``.
        start: the block's first frame in the source.
        ends: ``(w,)`` the windows' last frames in the source.
        gaps: ``(w,)`` their relative gaps.
        wasserstein: ``(w, d)`` their W₁ per parameter.
    """

    source: int
    role: str
    start: int
    ends: np.ndarray
    gaps: np.ndarray
    wasserstein: np.ndarray


@dataclass(frozen=True)
class Calibration:
    """What the held-out windows of the sources give.

    Attributes:
        detector: the :class:`~components.domains.relative.OddDetector` on the relative gap at α.
        levels: ``(d,)`` each parameter's in-ODD level of W₁, physical units.
        calibration: the calibration blocks' :class:`HeldOut` windows.
        evaluation: the evaluation blocks' :class:`HeldOut` windows.
        density_frames: per source, the frames in its density.
    """

    detector: OddDetector
    levels: np.ndarray
    calibration: list[HeldOut]
    evaluation: list[HeldOut]
    density_frames: list[int]

    @property
    def calibration_windows(self) -> int:
        return int(sum(h.ends.size for h in self.calibration))

    @property
    def evaluation_windows(self) -> int:
        return int(sum(h.ends.size for h in self.evaluation))


def _count(sizes: Sequence[int], block: int, shape: WindowShape, role: str) -> int:
    return sum(shape.ends(a, b).size for n in sizes for a, b in _blocks(n, block, role))


def check_sources(names: Sequence[str], sizes: Sequence[int], block: int, shape: WindowShape, alpha: float) -> None:
    """A :class:`WatchError` naming the source and the options when a source holds no calibration or no evaluation
    window (it needs 3 blocks and a window: density, calibration, density, and a window of evaluation), or naming
    them all when their calibration windows are fewer than a threshold at α needs."""
    least = 3 * block + shape.length
    for name, n in zip(names, sizes, strict=True):
        if _count([n], block, shape, "calibration") == 0 or _count([n], block, shape, "evaluation") == 0:
            raise WatchError(
                f"source {name}: {n} frames are too few to calibrate: in blocks of --block {block} frames (density, "
                f"calibration, density, evaluation) a source needs {least} frames or more to hold out a window of "
                f"{shape.length} frames for the threshold and one for the rule's false-alarm rate; give a longer "
                "source or a smaller --block"
            )
    need = int(np.ceil((1.0 - alpha) / alpha - 1e-9))
    have = _count(sizes, block, shape, "calibration")
    if have >= need:
        return
    each = ", ".join(f"{n}: {s} frames" for n, s in zip(names, sizes, strict=True))
    raise WatchError(
        f"the sources are too short to calibrate ({each}): in blocks of --block {block} frames (density, calibration, "
        f"density, evaluation) their held-out blocks hold {have} calibration windows of {shape.length} frames every "
        f"--stride {shape.stride}, and --false-alarm-rate {alpha:g} needs at least {need}; give longer sources, or a "
        "smaller --block, --stride or window, or a larger --false-alarm-rate"
    )


def density_draws(draws: Sequence[np.ndarray], block: int) -> list[np.ndarray]:
    """Per source, the fixed draws ``(N_k, m, d)`` of its density frames (:func:`block_roles`)."""
    return [np.asarray(d)[block_roles(len(d), block) == "density"] for d in draws]


def calibrate(
    names: Sequence[str],
    draws: Sequence[np.ndarray],
    sources: SourceDensities,
    shape: WindowShape,
    block: int,
    n_points: int,
    alpha: float,
    seed: int,
    progress: bool = False,
) -> Calibration:
    """The threshold, the levels and the evaluation windows from the sources' held-out blocks (module docstring).

    Arguments:
        names: the sources' names (for errors).
        draws: per source its frames' fixed draws ``(N_k, m, d)``, in name order.
        sources: the :class:`~components.watch.relation.SourceDensities` of their density frames.
        shape: the windows' :class:`~components.watch.timeline.WindowShape`.
        block: B, frames per block.
        n_points: n_W of each window's relation.
        alpha: α, the share of in-ODD windows above the threshold.
        seed: the root of the windows' streams ``(seed, "watch", "held-out", k, end)``.
        progress: show a tqdm bar over the held-out windows.

    Raises:
        WatchError: too few calibration windows for α or no evaluation window (naming the sources and options), or
            a threshold within :data:`SATURATION_BAND` of 1 (naming ``--bandwidth-scale``).
    """
    sizes = [len(d) for d in draws]
    check_sources(names, sizes, block, shape, alpha)
    weights = shape.weights
    plan = [
        (k, role, a, b)
        for role in ("calibration", "evaluation")
        for k, n in enumerate(sizes)
        for a, b in _blocks(n, block, role)
    ]
    bar = None
    if progress:
        from tqdm.auto import tqdm

        total = sum(shape.ends(a, b).size for _, _, a, b in plan)
        bar = tqdm(total=total, desc="pidc watch: calibrating on held-out windows", unit="window", disable=None)
    held: dict[str, list[HeldOut]] = {"calibration": [], "evaluation": []}
    try:
        for k, role, a, b in plan:
            ends = shape.ends(a, b)
            if ends.size == 0:
                continue
            gaps, w1 = np.empty(ends.size), np.empty((ends.size, sources.bandwidth.size))
            for i, e in enumerate(ends):
                window = draws[k][e - shape.length + 1 : e + 1]
                rel = relate_window(
                    window, weights, sources, n_points, derive_seed(seed, "watch", "held-out", k, int(e))
                )
                gaps[i], w1[i] = rel.relative_gap, rel.wasserstein
                if bar is not None:
                    bar.update(1)
            held[role].append(HeldOut(k, role, a, ends, gaps, w1))
    finally:
        if bar is not None:
            bar.close()
    cal_gaps = np.concatenate([h.gaps for h in held["calibration"]])
    cal_w1 = np.concatenate([h.wasserstein for h in held["calibration"]])
    detector = OddDetector.calibrate(cal_gaps, alpha)
    if abs(detector.threshold - 1.0) <= SATURATION_BAND:
        raise WatchError(
            f"the threshold is {detector.threshold:.4g}, within {SATURATION_BAND:g} of 1: held-out in-ODD windows "
            "already have the relative gap of windows the sources miss entirely, so no decision is possible; the "
            "kernels are too narrow for windows this short: use a larger --bandwidth-scale or --window"
        )
    levels = np.array([OddDetector.calibrate(cal_w1[:, j], alpha).threshold for j in range(cal_w1.shape[1])])
    density = [int(np.count_nonzero(block_roles(n, block) == "density")) for n in sizes]
    return Calibration(detector, levels, held["calibration"], held["evaluation"], density)
