"""``pidc relate``: a target folder against source folders, each a kernel density of its images' posterior draws as in
the ``task3`` stage (or the paper's exact mixture): mixture weights λ̂, gaps, where the target differs, and the
out-of-ODD verdict with a threshold calibrated on in-ODD targets held out of the sources (Task III).

Used by the ``pidc`` CLI only.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from components.cli.errors import CLIError
from components.cli.outputs import check_not_input, check_outputs
from components.cli.reading import (
    ReadLog,
    check_figure_path,
    check_folder,
    check_json_path,
    check_prior,
    check_seed,
    count,
    folder_name,
    list_paths,
    load_model,
    load_prior,
    prior_json,
    prior_line,
    read_all,
    reweighted,
    write_json,
)
from components.core.seeding import derive_seed

__all__ = ["RELATE_DEFAULTS", "RELATE_PRIOR_DRAWS", "cmd_relate"]

#: ``pidc relate``'s defaults: the ``task3`` stage's defaults in params.yaml (``task3.n_points``, ``smoothing``,
#: ``draws_per_image``, ``bandwidth_scale``; a test holds them equal), so that the command relates folders as the stage
#: whose figures docs/results.md reports (docs/studies/task3-characterization.md)
RELATE_DEFAULTS: dict[str, Any] = {"n_points": 64, "smoothing": "scott", "draws_per_image": 64, "bandwidth_scale": 3.0}
#: relate refuses a verdict when the calibrated threshold (a relative gap) is within this of 1: where the folders'
#: densities do not overlap, every relative gap is 1 (δ = mean(b²): the sources are ≈ 0 at the target's points), so
#: in-ODD targets and targets the sources miss entirely look the same, and the verdict turns on rounding. It happens
#: when the kernels are too narrow: on 6-image folders ``--bandwidth-scale`` 0.3 gave 0.993 (two sources) and 1.014
#: (one source), 0.1 gave 1, where the default 3 gave 0.14 and 0.08. (With one source, heavy tails put thresholds far
#: above 1 at times, e.g. 4.6 with ``--smoothing none``: not saturation, and not refused.)
SATURATION_BAND = 0.02
#: ``--prior-draws``'s default: posterior draws per image reweighted to ``--prior`` (``--draws-per-image`` of them are
#: resampled), as ``characterize`` and ``domain`` draw ``--samples`` 1000 by default.
RELATE_PRIOR_DRAWS = 1000


def _fixed_draws(posterior: Any, bags: list[np.ndarray], m: int, seed: int) -> list[np.ndarray]:
    """``m`` posterior draws of each image of ``bags`` (one ``(Nₖ, m, d)`` array per bag), fixed once per image: an
    image in two folders (equal inputs) gets the same draws in both, as a kernel density of a subset or a
    reweighting of the same images needs. One sampling call over the distinct images, stream
    ``(seed, "relate", "kernel")``."""
    import hashlib

    union = np.concatenate(bags)
    first: dict[bytes, int] = {}
    index = np.array([first.setdefault(hashlib.sha256(row.tobytes()).digest(), len(first)) for row in union])
    distinct = np.unique(index, return_index=True)[1]  # the first row of each distinct input, in index order
    draws = np.asarray(posterior.sample(union[distinct], m, derive_seed(seed, "relate", "kernel")))[index]
    return np.split(draws, np.cumsum([len(b) for b in bags])[:-1])


def _print_differences(
    differences: Sequence[Any], levels: np.ndarray, outside: bool, draws_per_image: int, held: int, alpha: float
) -> None:
    """``pidc relate``'s table of where the target differs from the fitted mixture: per parameter the medians, W₁ and
    its in-ODD level (:mod:`components.domains.difference`), largest W₁ / level first; with an OUTSIDE verdict a * on
    the parameters beyond their level (what the alarm is about; docs/cli.md, "Where the target differs")."""
    print(
        f"where the target differs from the fitted mixture Σ λ̂ₖ sourceₖ (marginals of {draws_per_image} "
        "posterior draws an image):\n"
        "  medians and W₁ in the parameter's unit; in-ODD: the W₁ that in-ODD targets of "
        f"{count(held, 'image')} made from the sources\n"
        f"  (the calibration targets) exceed with probability {alpha:g}"
        + ("; *: beyond it, what the alarm is about" if outside else "")
    )
    print(f"{'parameter':<28}{'target':>9}{'mixture':>9}{'W₁':>9}{'in-ODD':>9}")
    for j in sorted(range(len(differences)), key=lambda i: -differences[i].wasserstein / levels[i]):
        diff, level = differences[j], levels[j]
        label = f"{diff.name} [{diff.unit}]"
        print(
            f"{label:<28}{diff.target_median:>9.2f}{diff.mixture_median:>9.2f}{diff.wasserstein:>9.2f}{level:>9.2f}"
            + (" *" if outside and diff.wasserstein > level else "")
        )


def _check_distinct_folders(folders: list[Path]) -> None:
    """A :class:`CLIError` when relate's target is also a source, or a source is given twice (the same folder after
    resolving links and ``..``): λ̂ and the verdict would compare a folder with itself."""
    first: dict[Path, int] = {}
    for i, f in enumerate(folders):
        j = first.setdefault(f.resolve(), i)
        if j == 0 and i > 0:
            also = "" if folders[0] == f else f" ({f})"
            raise CLIError(f"the target folder {folders[0]} is also given as a source{also}")
        if j != i:
            raise CLIError(f"source folder {f} is given twice" + ("" if folders[j] == f else f" (as {folders[j]})"))


def _bandwidth_scale(value: float | None, kernel: bool) -> float:
    """``--bandwidth-scale`` (default :data:`RELATE_DEFAULTS`), a positive finite number even where it is not used
    (``--smoothing none``, which a note says)."""
    scale = RELATE_DEFAULTS["bandwidth_scale"] if value is None else value
    if not (0.0 < scale < math.inf):
        raise CLIError(f"--bandwidth-scale must be a positive number, got {scale:g}")
    if value is not None and not kernel:
        print("pidc relate: note: --bandwidth-scale is ignored with --smoothing none (no kernel)", file=sys.stderr)
    return scale


def _check_calibration_sources(names: list[str], sources: Sequence[Any]) -> None:
    """A :class:`CLIError` when no source folder has two readable images: the threshold's in-ODD targets are images
    held out of the sources, at most half of a folder."""
    if max(len(s) for s in sources) >= 2:
        return
    each = ", ".join(f"{n}: {len(s)}" for n, s in zip(names, sources, strict=True))
    raise CLIError(
        f"every source folder has only 1 readable image ({each}); at least one source folder needs 2 or more images "
        "to calibrate the threshold (its in-ODD targets are images held out of the sources)"
    )


def _numeric(caught: list[warnings.WarningMessage]) -> list[str]:
    """The distinct messages of the RuntimeWarnings (numpy's overflow, invalid value, …) among ``caught``."""
    return list(dict.fromkeys(str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)))


def _relate_error(error: ValueError, caught: list[warnings.WarningMessage], scale: float | None) -> str:
    """relate's one-line error for a ``ValueError`` of the computation; naming ``--bandwidth-scale`` (``scale``, None
    without kernels) when the kernel densities went out of float range (non-finite densities or gaps)."""
    text = str(error)
    numeric = _numeric(caught)
    if scale is None or not (numeric or any(word in text for word in ("finite", "NaN", "bandwidth"))):
        return text
    why = f"; numpy: {'; '.join(numeric)}" if numeric else ""
    return (
        f"--bandwidth-scale {scale:g} makes the kernel densities leave the range of floating-point numbers "
        f"({text}{why}); use a value near the default {RELATE_DEFAULTS['bandwidth_scale']:g}"
    )


def _say_warnings(caught: list[warnings.WarningMessage], scale: float | None) -> None:
    """The warnings of a computation that succeeded, as ``note:`` lines: numpy's numerical ones in one line (naming
    ``--bandwidth-scale`` with kernels), any other as it is."""
    numeric = _numeric(caught)
    if numeric:
        knob = f" with --bandwidth-scale {scale:g}" if scale is not None else ""
        print(
            f"pidc relate: note: numerical warnings while relating{knob} ({'; '.join(numeric)}): the densities may be "
            "unreliable",
            file=sys.stderr,
        )
    for message in dict.fromkeys(str(w.message) for w in caught if not issubclass(w.category, RuntimeWarning)):
        print(f"pidc relate: note: {message}", file=sys.stderr)


def _saturated(threshold: float, scale: float | None) -> str:
    """relate's error when the calibrated threshold is 1 within :data:`SATURATION_BAND`: in-ODD targets already look
    like targets the sources miss entirely, so no verdict can be given (``scale`` None without kernels)."""
    what = (
        f"so in-ODD targets held out of the sources already have relative gaps near 1 (threshold {threshold:.4g}), "
        "the gap of a target the sources miss entirely, and no verdict is possible"
    )
    default = RELATE_DEFAULTS["bandwidth_scale"]
    if scale is None:
        return (
            f"with --smoothing none the posteriors of the folders' images do not overlap, {what}; use --smoothing scott"
        )
    if scale < default:
        return (
            f"--bandwidth-scale {scale:g} is too small: the kernel densities of the folders do not overlap, {what}; "
            f"use a value near the default {default:g}"
        )
    return (
        f"with --bandwidth-scale {scale:g} the kernel densities of the folders do not overlap, {what}; the source "
        "folders may be too small or too unlike each other"
    )


def cmd_relate(args: argparse.Namespace) -> int:
    """Each folder an equally weighted bag, characterized as the ``task3`` stage does by default (``--smoothing
    scott``: the :class:`components.domains.kernel.KernelDomain` of ``--draws-per-image`` fixed posterior draws per
    image, with ``--bandwidth-scale`` × the sources' Scott bandwidth) or by the paper's exact mixture (``none``:
    :class:`components.domains.absolute.Domain`); the verdict is
    :func:`components.domains.relative.calibrate_on_sources`'s detector on :attr:`Relation.relative_gap`."""
    seed = check_seed(args.seed)
    folders = [check_folder(Path(f), "relate") for f in (args.target, *args.sources)]
    _check_distinct_folders(folders)
    alpha, scale = _check_options(args)
    proposals = _prior_draws(args)
    min_ess = check_prior(args, proposals, "--prior-draws")
    check_json_path(args.json)
    check_figure_path(args.plot, "--plot")
    listed = [list_paths([f]) for f in folders]
    outputs = [("--json", args.json), ("--plot", args.plot)]
    check_not_input(outputs, [p for paths in listed for p in paths])
    check_outputs(outputs)
    model = load_model(args)
    log = ReadLog("relate")  # the skips, notes and caveats of all folders, said once for the whole command
    bags = [
        read_all(model, paths, "relate", f"read {folder_name(f)}", f, log)
        for f, paths in zip(folders, listed, strict=True)
    ]
    log.finish(model, each=True)
    prior = load_prior(args, model, min_ess, "--prior-draws")
    if prior is not None:  # the target and the sources under the same prior: their kernels live under it
        posterior, ess = reweighted(
            prior, model.posterior, [(b.paths, b.x) for b in bags], proposals, derive_seed(seed, "relate"), "relate"
        )
        model = dataclasses.replace(model, posterior=posterior)
    found = _relate_folders(args, model, folders, [b.x for b in bags], seed, alpha, scale)
    _print_relation(args, model, found, seed, alpha, scale)
    if prior is not None:
        print(prior_line(prior, ess, proposals))
    if args.json is not None:
        report = _relation_json(args, model, found, seed, alpha)
        if prior is not None:
            report |= prior_json(prior, ess, proposals)
        write_json(args.json, report | log.to_json() | found.parameters())
    if args.plot is not None:
        _plot_relation(args.plot, model, found, alpha)
    return 0


def _check_options(args: argparse.Namespace) -> tuple[float, float]:
    """``(--false-alarm-rate, --bandwidth-scale)``, after a :class:`CLIError` for any option out of its range."""
    k = len(args.sources)
    if args.points < k:
        raise CLIError(f"--points {args.points} cannot determine {k} mixture weights: need --points ≥ {k}")
    alpha = args.false_alarm_rate
    if not (0.0 < alpha < 1.0):
        raise CLIError(f"--false-alarm-rate must be in (0, 1), got {alpha:g}")
    need = math.ceil((1.0 - alpha) / alpha - 1e-9)
    if args.calibration_targets < need:
        raise CLIError(
            f"--calibration-targets must be ≥ {need} for --false-alarm-rate {alpha:g}, got {args.calibration_targets}"
        )
    if args.draws_per_image < 2:
        raise CLIError(f"--draws-per-image must be at least 2 (a bag's spread), got {args.draws_per_image}")
    return alpha, _bandwidth_scale(args.bandwidth_scale, args.smoothing == "scott")


def _prior_draws(args: argparse.Namespace) -> int:
    """``--prior-draws`` (default :data:`RELATE_PRIOR_DRAWS`), with ``--prior`` at least ``--draws-per-image``, which
    are resampled from them (without ``--prior``, :func:`check_prior` refuses it when it is given)."""
    draws = RELATE_PRIOR_DRAWS if args.prior_draws is None else args.prior_draws
    if args.prior is not None and draws < args.draws_per_image:
        raise CLIError(
            f"--prior-draws must be at least --draws-per-image {args.draws_per_image} (the draws resampled from "
            f"them), got {draws}"
        )
    return draws


@dataclass(frozen=True)
class _Found:
    """What ``pidc relate`` found. ``target`` and ``sources``: the folders' :class:`components.domains.absolute.Domain`
    bags (``names``: the sources' names); ``rel``: the relation of the target to the sources; ``detector``: the
    calibrated :class:`components.domains.relative.OddDetector`; ``bandwidth``: the kernels' ``(d,)``, None with
    ``--smoothing none``; ``pooled``: each folder's posterior draws ``(Nₖ·m, d)``; ``differences`` and ``levels``:
    per parameter where the target differs from the fitted mixture, and the W₁ in-ODD targets exceed with probability
    α; ``held``: the images of each calibration target."""

    folders: list[Path]
    names: list[str]
    target: Any
    sources: list[Any]
    rel: Any
    detector: Any
    bandwidth: np.ndarray | None
    pooled: list[np.ndarray]
    differences: list[Any]
    levels: np.ndarray
    held: int

    @property
    def outside(self) -> bool:
        """The verdict: the target is outside the ODD the sources span."""
        return bool(self.detector.decide(self.rel.relative_gap))

    def parameters(self) -> dict[str, Any]:
        """The ``parameters`` entry of ``--json``: per parameter its difference and in-ODD level."""
        return {
            "parameters": {
                diff.name: {
                    **diff.to_dict(),
                    "in_odd_level": level,
                    "exceeds_in_odd_level": bool(diff.wasserstein > level),
                }
                for diff, level in zip(self.differences, self.levels, strict=True)
            }
        }


def _relate_folders(
    args: argparse.Namespace,
    model: Any,
    folders: list[Path],
    inputs: list[np.ndarray],
    seed: int,
    alpha: float,
    scale: float,
) -> _Found:
    """The target (``inputs[0]``) related to the sources (the rest), the detector calibrated on targets held out of
    them, and where the target differs; a :class:`CLIError` where no verdict can be given."""
    from components.domains.absolute import Domain
    from components.domains.difference import InOddDifferences, parameter_differences
    from components.domains.kernel import KernelDomain, sources_bandwidth
    from components.domains.relative import calibrate_on_sources, relate

    kernel = args.smoothing == "scott"
    target, *sources = [Domain(model.posterior, x) for x in inputs]
    names = [folder_name(f) for f in folders[1:]]
    if len(set(names)) < len(names):
        names = [str(f) for f in folders[1:]]
    _check_calibration_sources(names, sources)
    # fixed posterior draws of every image: the kernel densities' support (--smoothing scott) and, for either
    # smoothing, the marginals that say where the target differs from the sources' fitted mixture
    draws = _fixed_draws(model.posterior, inputs, args.draws_per_image, seed)
    bandwidth = None
    box = model.posterior.box
    pooled = [d.reshape(-1, d.shape[-1]) for d in draws]
    in_odd = InOddDifferences(draws[1:], box)  # each parameter's W₁ on the calibration's in-ODD targets

    with warnings.catch_warnings(record=True) as caught:  # numpy's overflow/invalid-value warnings: said below
        warnings.simplefilter("always", RuntimeWarning)
        try:
            if kernel:
                bandwidth = scale * sources_bandwidth(draws[1:])
                rel = relate(
                    KernelDomain(draws[0], None, bandwidth),
                    [KernelDomain(d, None, bandwidth) for d in draws[1:]],
                    args.points,
                    derive_seed(seed, "relate"),
                )
            else:
                rel = relate(target, sources, args.points, derive_seed(seed, "relate"))
            detector = calibrate_on_sources(
                sources,
                args.calibration_targets,
                args.points,
                alpha,
                derive_seed(seed, "calibrate"),
                target_size=len(target),
                progress=sys.stderr.isatty(),
                draws=draws[1:] if kernel else None,
                bandwidth=bandwidth,
                on_target=in_odd,
            )
        except ValueError as e:
            raise CLIError(_relate_error(e, caught, scale if kernel else None)) from None
    _say_warnings(caught, scale if kernel else None)
    if abs(detector.threshold - 1.0) <= SATURATION_BAND:
        raise CLIError(_saturated(detector.threshold, scale if kernel else None))
    differences = parameter_differences(pooled[0], pooled[1:], rel.weights, box)
    levels = in_odd.levels(alpha)  # the W₁ that in-ODD targets of this size exceed with probability α
    held = min(len(target), sum(len(s) // 2 for s in sources))  # calibrate_on_sources holds out ≤ half a source
    return _Found(folders, names, target, sources, rel, detector, bandwidth, pooled, differences, levels, held)


def _print_relation(args: argparse.Namespace, model: Any, found: _Found, seed: int, alpha: float, scale: float) -> None:
    """``pidc relate``'s report on stdout: the folders, λ̂, the gaps, the threshold, the differences, the verdict."""
    rel, detector, bandwidth, outside = found.rel, found.detector, found.bandwidth, found.outside
    print(
        f"target {found.folders[0]}: {count(len(found.target), 'image')}; model {model.name}; {args.points} points "
        f"(seed {seed})"
    )
    if bandwidth is None:
        print("each folder: the exact mixture of its images' posteriors (--smoothing none)")
    else:
        print(
            f"each folder: a kernel density of {args.draws_per_image} posterior draws per image, bandwidth "
            f"{scale:g} × the sources' Scott rule = "
            + ", ".join(f"{n} {h:.3g}" for n, h in zip(model.posterior.box.names, bandwidth, strict=False))
        )
    width = max(len("source"), *map(len, found.names))
    print(f"{'source':<{width}}  {'images':>6}  {'weight λ̂':>9}")
    for name, s, lam in zip(found.names, found.sources, rel.weights, strict=False):
        print(f"{name:<{width}}  {len(s):>6}  {lam:>9.4f}")
    print(f"mean squared gap δ: {rel.gap:.4g} (density², physical units)")
    print(f"relative gap δ/mean(b²): {rel.relative_gap:.4g}")
    if rel.degenerate:
        print(
            "degenerate: yes — λ̂ is not unique: the sources' densities at the target's points are linearly dependent "
            "(folders of the same images, or densities that do not reach the target's points); shown is the "
            "minimum-norm one"
        )
    else:
        print("degenerate: no")
    print(
        f"threshold: {detector.threshold:.4g} (relative gap; {detector.n_calibration} in-ODD targets of "
        f"{count(found.held, 'image')} held out of the sources; false-alarm rate {alpha:g})"
    )
    if len(found.sources) == 1:
        print("note: one source, so λ̂ = 1; the verdict says whether the target looks like that source")
    _print_differences(found.differences, found.levels, outside, args.draws_per_image, found.held, alpha)
    verdict = "OUTSIDE the ODD" if outside else "inside the ODD"
    print(f"verdict: {verdict} (relative gap {'>' if outside else '≤'} threshold; false-alarm rate {alpha:g})")


def _relation_json(args: argparse.Namespace, model: Any, found: _Found, seed: int, alpha: float) -> dict[str, Any]:
    """The fields of ``--json`` up to the read log (which :meth:`ReadLog.to_json` adds, then the parameters)."""
    rel, folders, box = found.rel, found.folders, model.posterior.box
    return {
        "target": {"name": folder_name(folders[0]), "folder": str(folders[0]), "images": len(found.target)},
        "sources": [
            {"name": n, "folder": str(f), "images": len(src), "weight": float(lam)}
            for n, f, src, lam in zip(found.names, folders[1:], found.sources, rel.weights, strict=True)
        ],
        "model": model.name,
        "seed": seed,
        "points": args.points,
        "smoothing": args.smoothing,
        "draws_per_image": args.draws_per_image,
        "bandwidth": None
        if found.bandwidth is None
        else dict(zip(box.names, map(float, found.bandwidth), strict=True)),
        "gap": float(rel.gap),
        "relative_gap": float(rel.relative_gap),
        "degenerate": bool(rel.degenerate),
        "threshold": float(found.detector.threshold),
        "calibration_targets": found.detector.n_calibration,
        "calibration_target_images": found.held,
        "false_alarm_rate": alpha,
        "outside": found.outside,
    }


def _plot_relation(path: Path, model: Any, found: _Found, alpha: float) -> None:
    """``--plot``: the target's marginals against the fitted mixture's, each parameter's W₁ and in-ODD level noted."""
    from components.plots import relation_marginals, save_figure

    outside, rel = found.outside, found.rel
    notes = [
        f"W₁ {q.wasserstein:.3g} {q.unit}{' *' if outside and q.wasserstein > level else ''} (in-ODD ≤ {level:.3g} "
        f"with prob. {1 - alpha:g})"
        for q, level in zip(found.differences, found.levels, strict=True)
    ]
    verdict = "OUTSIDE the ODD" if outside else "inside the ODD"
    title = (
        f"{folder_name(found.folders[0])} against {', '.join(found.names)} ({model.name}): {verdict} "
        f"(relative gap {rel.relative_gap:.3g}, threshold {found.detector.threshold:.3g})"
    )
    pooled = found.pooled
    save_figure(
        relation_marginals(pooled[0], pooled[1:], rel.weights, found.names, model.posterior.box, notes, title), path
    )
    print(f"wrote {path}", file=sys.stderr)
