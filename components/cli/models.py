"""``pidc characterize``, ``pidc domain`` and ``pidc relate``: a registry model applied to image files.

* characterize — per image, the posterior's median and 68.27 % HDI per parameter (Task I), optionally the draws
  (CSV/Parquet) and a corner plot per image;
* domain — a folder of images as one weighted bag (equal weights, a weights CSV, or an exponentially decaying
  stream) → the domain's weather distribution (Task II);
* relate — a target folder against source folders, each a kernel density of its images' posterior draws as in the
  ``task3`` stage (or the paper's exact mixture): mixture weights λ̂, gaps, and the out-of-ODD verdict with a
  threshold calibrated on in-ODD targets held out of the sources (Task III).

Models come from the registry (:func:`components.export.lookup.load_registered`: ``champion``, a model id, or an
exported folder) or from the MLflow Model Registry by URI (``models:/pidc@champion``, downloaded with MLflow's
command line). Unreadable images are reported one line each on stderr and skipped. Heavy imports happen inside
commands.

Used by the ``pidc`` CLI only.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from components.cli.errors import CLIError
from components.core.files import atomic_write_bytes
from components.core.seeding import derive_seed

__all__ = ["add_model_commands", "read_weights_csv"]

#: Images read and turned into posterior inputs per batch (bounds memory for large folders).
READ_BATCH = 64
#: ``pidc relate``'s defaults: the ``task3`` stage's defaults in params.yaml (``task3.n_points``, ``smoothing``,
#: ``draws_per_image``, ``bandwidth_scale``; a test holds them equal), so that the command relates folders as the stage
#: whose figures the README reports (BENCHMARKS.md "Task III: the characterization")
RELATE_DEFAULTS: dict[str, Any] = {"n_points": 64, "smoothing": "scott", "draws_per_image": 64, "bandwidth_scale": 3.0}


# --- shared -----------------------------------------------------------------------------------------------------


def _download(uri: str, registry: Path) -> Path:
    """The exported folder of an MLflow registered model ``uri`` (e.g. ``models:/pidc@champion``), downloaded with
    MLflow's own command line (``mlflow artifacts download``), so that components import no MLflow. The tracking store
    is ``MLFLOW_TRACKING_URI`` or the project's ``mlflow.db`` beside ``registry``."""
    import os
    import subprocess
    import tempfile

    store = os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{registry.resolve().parent / 'mlflow.db'}"
    dest = Path(tempfile.mkdtemp(prefix="pidc-model-"))
    cmd = [sys.executable, "-m", "mlflow", "artifacts", "download", "--artifact-uri", uri, "--dst-path", str(dest)]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "MLFLOW_TRACKING_URI": store})
    except OSError as e:
        raise CLIError(f"{uri}: could not run `mlflow artifacts download` ({e})") from None
    if r.returncode != 0:
        lines = [line for line in r.stderr.strip().splitlines() if line.strip()]
        raise CLIError(f"{uri}: not found in the MLflow store {store}: {lines[-1] if lines else 'no message'}")
    folder = dest / "extra_files"
    if not (folder / "card.json").is_file():
        raise CLIError(f"{uri}: not a pidc model (no extra_files/card.json among its files)")
    return folder


def _load_model(args: argparse.Namespace) -> Any:
    """The model of ``--model``/``--registry`` (:class:`components.export.lookup.RegisteredPosterior`): a registry
    model (``champion``, a model id, a folder) or an MLflow registered model URI (``models:/pidc@champion``)."""
    from components.export.lookup import load_registered

    model = str(args.model)
    try:
        if model.startswith("models:/"):
            return load_registered(_download(model, Path(args.registry)))
        return load_registered(model, args.registry)
    except (FileNotFoundError, ValueError) as e:
        raise CLIError(str(e)) from None


def _list(paths: Sequence[str | Path]) -> list[Path]:
    from components.core.images import ImageError, list_images

    try:
        return list_images(paths)
    except ImageError as e:
        raise CLIError(str(e)) from None


def _progress(total: int, desc: str) -> Any:
    """A tqdm bar on stderr over ``total`` images (shown on a terminal and for more than one image)."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="image", file=sys.stderr, disable=True if total < 2 else None)


def _say(bar: Any, text: str, err: bool = False) -> None:
    """Print ``text`` without breaking the progress bar."""
    bar.write(text, file=sys.stderr if err else sys.stdout)


@dataclass(frozen=True)
class _Read:
    """Posterior inputs of readable images: ``paths[i]``, ``notes[i]`` and ``x[i]`` (the model's input)."""

    paths: list[Path]
    notes: list[str | None]
    x: np.ndarray


def _resize_caveat(model: Any, sizes: set[tuple[int, int]], converted: bool) -> str | None:
    """What a posterior of a resized image is worth, for images of ``sizes`` (H, W): a note when a size is not one the
    model learned from (the card's ``training_renders``), or, for a card that does not name them (exported before pidc
    recorded it), when the backbone ``converted`` the images to its input; for a model of resized renders
    (``simulator.render_sizes``), also when images come at its input size, which it takes as frames already shrunk;
    None otherwise."""
    renders = model.training_renders
    other = sorted(s for s in sizes if not model.learned_size(s)) if renders else (sorted(sizes) if converted else [])
    shown = ", ".join(f"{w}×{h}" for h, w in other[:3]) + (" …" if len(other) > 3 else "")
    if renders is not None and renders[2] is not None:  # a model of resized renders
        notes = [f"images of {shown} are outside them"] if other else []
        if renders[:2] in sizes:
            notes.append(
                f"images of {renders[1]}×{renders[0]} are taken as frames already shrunk to it, not as the renderer's "
                "own renders of that size"
            )
        if not notes:
            return None
        return (
            f"{model.name} learned from {model.learned_from}; {'; '.join(notes)}: the calibration measured in the "
            'pipeline covers only what it learned (BENCHMARKS.md, "Camera-like renders in the pipeline")'
        )
    if not other:
        return None
    learned = model.learned_from or "renders of a size its card does not name (re-export it)"
    return (
        f"{model.name} learned from {learned}; images of {shown} are area-resized, and the calibration measured in "
        "the pipeline does not cover them: the simulator's own renders made larger and resized gave overconfident "
        'posteriors (BENCHMARKS.md, "Images of another resolution")'
    )


def _inputs(model: Any, images: list[np.ndarray], bar: Any, command: str, said: set[str]) -> np.ndarray:
    """uint8 images of any sizes → the model's inputs ``x (n, …)`` in the same order (one batch per size).

    The backbone's one-time "converting H×W images" warning becomes a ``note:`` line on stderr, and so does, once per
    command (``said``), the caveat of images not of the model's training size (:func:`_resize_caveat`).
    """
    from components.core.images import map_by_size

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        out = map_by_size(images, model.inputs)
    for message in dict.fromkeys(str(w.message) for w in caught):
        _say(bar, f"pidc {command}: note: {message}", err=True)
    if "resized" not in said and (caveat := _resize_caveat(model, {im.shape[:2] for im in images}, bool(caught))):
        said.add("resized")
        _say(bar, f"pidc {command}: note: {caveat}", err=True)
    return out


def _read_batches(
    model: Any, paths: list[Path], command: str, desc: str, said: set[str] | None = None
) -> Iterator[tuple[_Read, Any]]:
    """Read ``paths`` in batches of :data:`READ_BATCH`: yields the readable ones' inputs (and the progress bar).

    Bad files are reported on stderr (``pidc <command>: skipped <path>: <reason>``) and left out. Notes said once per
    command are recorded in ``said`` (shared by the calls of one command; a new set when None).
    """
    from components.core.images import ImageError, read_image

    said = set() if said is None else said

    with _progress(len(paths), desc) as bar:
        for start in range(0, len(paths), READ_BATCH):
            good: list[Path] = []
            notes: list[str | None] = []
            images: list[np.ndarray] = []
            for path in paths[start : start + READ_BATCH]:
                try:
                    image, note = read_image(path)
                except ImageError as e:
                    _say(bar, f"pidc {command}: skipped {e}", err=True)
                else:
                    good.append(path)
                    notes.append(note)
                    images.append(image)
                bar.update(1)
            if good:
                yield _Read(good, notes, _inputs(model, images, bar, command, said)), bar


def _read_all(model: Any, paths: list[Path], command: str, desc: str, said: set[str] | None = None) -> _Read:
    """All readable images' inputs at once (the bag of a domain); CLIError when none is readable."""
    parts = [read for read, _ in _read_batches(model, paths, command, desc, said)]
    if not parts:
        raise CLIError(f"none of the {len(paths)} images could be read")
    return _Read(
        [p for r in parts for p in r.paths], [n for r in parts for n in r.notes], np.concatenate([r.x for r in parts])
    )


def _check_figure_path(path: Path | None, option: str = "--corner") -> None:
    """A figure file name whose type matplotlib writes (PNG, PDF, SVG, …), else a one-line error naming ``option``."""
    if path is None:
        return
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fmt = path.suffix.lstrip(".").lower()
    if fmt not in FigureCanvasAgg.get_supported_filetypes():
        raise CLIError(f"{option} {path}: unknown image type {path.suffix!r}; use e.g. a .png file")


def _corner(draws: np.ndarray, box: Any, title: str, path: Path) -> None:
    from components.plots import corner_plot, save_figure

    save_figure(corner_plot(draws, box=box, title=title), path)


def _positive(value: int, option: str) -> int:
    if value < 1:
        raise CLIError(f"{option} must be a positive integer, got {value}")
    return value


def _check_json_path(path: Path | None) -> None:
    if path is not None and path.suffix.lower() != ".json":
        raise CLIError(f"--json {path}: expected a .json file name")


def _write_json(path: Path, report: dict) -> None:
    """``report`` as indented JSON at ``path`` (atomically; its folder made), and a line on stderr saying so."""
    atomic_write_bytes(path, (json.dumps(report, indent=1) + "\n").encode())
    print(f"wrote {path}", file=sys.stderr)


def _seed(value: int) -> int:
    if value < 0:
        raise CLIError(f"--seed must be a non-negative integer, got {value}")
    return value


# --- characterize ---------------------------------------------------------------------------------------------


def _corner_paths(base: Path, paths: list[Path]) -> dict[Path, Path]:
    """One corner file per image: ``base`` itself for one image, else ``<stem>-<image stem><suffix>`` (unique)."""
    if len(paths) == 1:
        return {paths[0]: base}
    out: dict[Path, Path] = {}
    used: set[str] = set()
    for p in paths:
        name = f"{base.stem}-{p.stem}"
        k = 2
        while name in used:
            name = f"{base.stem}-{p.stem}-{k}"
            k += 1
        used.add(name)
        out[p] = base.with_name(name + base.suffix)
    return out


def _cmd_characterize(args: argparse.Namespace) -> int:
    """Per image a table block (median, HDI); the draws of an image are seeded by (``--seed``, its path), so they do
    not depend on the other images given."""
    from components.cli.drawsfile import DrawsWriter, check_draws_path
    from components.evaluate.summary import format_summary, summarize

    n = _positive(args.samples, "--samples")
    seed = _seed(args.seed)
    _check_figure_path(args.corner)
    _check_json_path(args.json)
    if args.samples_out is not None:
        try:
            check_draws_path(args.samples_out)
        except (ValueError, ImportError) as e:
            raise CLIError(f"--samples-out {e}") from None
    paths = _list(args.images)
    model = _load_model(args)
    post = model.posterior
    writer = None if args.samples_out is None else DrawsWriter(args.samples_out, post.box.names)
    corners = _corner_paths(args.corner, paths) if args.corner is not None else {}
    done = 0
    summaries: list[dict] = []  # for --json
    try:
        for read, bar in _read_batches(model, paths, "characterize", "characterize"):
            for i, path in enumerate(read.paths):
                draws = post.sample(read.x[i : i + 1], n, derive_seed(seed, "characterize", str(path)))[0]
                head = f"== {path}" + (f"  (note: {read.notes[i]})" if read.notes[i] else "")
                summary = summarize(draws)
                _say(bar, f"{head}\n{format_summary(summary, post.box)}\n")
                summaries.append({"image": str(path), "note": read.notes[i] or None, **summary.to_dict(post.box)})
                if writer is not None:
                    writer.write(str(path), draws)
                if path in corners:
                    _corner(draws, post.box, f"{path.name} — {model.name}", corners[path])
                done += 1
    except BaseException:
        if writer is not None:
            writer.discard()
        raise
    if done == 0:
        if writer is not None:
            writer.discard()
        raise CLIError(f"none of the {len(paths)} images could be read")
    if writer is not None:
        writer.close()
        print(f"wrote {writer.rows} draws of {done} images to {writer.path}", file=sys.stderr)
    skipped = len(paths) - done
    if args.json is not None:
        _write_json(
            args.json,
            {"model": model.name, "seed": seed, "samples": n, "skipped": skipped, "images": summaries},
        )
    print(
        f"characterized {done} image{'s' * (done != 1)} with {model.name} ({n} draws each, seed {seed})"
        + (f"; skipped {skipped}" if skipped else ""),
        file=sys.stderr,
    )
    return 0


# --- domain ---------------------------------------------------------------------------------------------------


def read_weights_csv(path: str | Path) -> dict[str, float]:
    """A weights file: rows ``<image file name>,<weight>``, an optional header row (e.g. ``image,weight``).

    Returns ``{name: weight}`` in file order. Raises ``ValueError`` naming the file and line for a row without
    exactly two cells, a weight that is not a finite non-negative number, a repeated name, or an empty table; and when
    all weights are zero.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such weights file")
    out: dict[str, float] = {}
    with open(path, newline="", encoding="utf-8") as f:
        for line, row in enumerate(csv.reader(f), start=1):
            cells = [c.strip() for c in row]
            if not any(cells) or cells[0].startswith("#"):
                continue
            if len(cells) != 2:
                raise ValueError(f"{path} line {line}: expected 2 cells (image,weight), got {len(cells)}")
            name, text = cells
            try:
                w = float(text)
            except ValueError:
                if not out and line == 1:  # a header row
                    continue
                raise ValueError(f"{path} line {line}: weight {text!r} of {name!r} is not a number") from None
            if not math.isfinite(w) or w < 0:
                raise ValueError(f"{path} line {line}: weight of {name!r} must be finite and non-negative, got {text}")
            if name in out:
                raise ValueError(f"{path} line {line}: {name!r} is listed twice")
            out[name] = w
    if not out:
        raise ValueError(f"{path}: no weights (expected rows image,weight)")
    if not any(w > 0 for w in out.values()):
        raise ValueError(f"{path}: all weights are zero; at least one image needs a positive weight")
    return out


def _effective_size(weights: np.ndarray) -> float:
    """Kish's effective number of members, (Σw)²/Σw²."""
    w = np.asarray(weights, dtype=np.float64)
    return float(w.sum() ** 2 / np.sum(w**2))


def _cmd_domain(args: argparse.Namespace) -> int:
    """The folder's images as one :class:`components.domains.absolute.Domain`; skipped images do not count as stream steps."""
    from components.domains.absolute import Domain, ExponentialFilter
    from components.evaluate.summary import format_summary, summarize

    n = _positive(args.samples, "--samples")
    seed = _seed(args.seed)
    _check_figure_path(args.corner)
    _check_json_path(args.json)
    folder = Path(args.folder)
    if not folder.is_dir():
        raise CLIError(f"{folder}: not a folder (pidc domain takes a folder of images)")
    if args.decay is not None and not (0.0 < args.decay <= 1.0):
        raise CLIError(f"--decay must be in (0, 1] (the weight factor per image of age), got {args.decay:g}")
    paths = _list([folder])
    weights: dict[str, float] | None = None
    if args.weights is not None:
        try:
            weights = read_weights_csv(args.weights)
        except ValueError as e:
            raise CLIError(f"--weights {e}") from None
        by_name = {p.name: p for p in paths}
        missing = [name for name in weights if name not in by_name]
        if missing:
            raise CLIError(
                f"--weights {args.weights}: {len(missing)} listed image(s) not found among the images of "
                f"{folder}, e.g. {missing[0]!r}"
            )
        ignored = len(paths) - len(weights)
        if ignored:
            print(
                f"pidc domain: note: {ignored} image(s) of {folder} are not in {args.weights}: left out",
                file=sys.stderr,
            )
        paths = [by_name[name] for name in weights if weights[name] > 0]
    model = _load_model(args)
    bag = _read_all(model, paths, "domain", f"domain {folder.name}")
    if weights is not None:
        how = f"weights from {args.weights}"
        domain = Domain(model.posterior, bag.x, [weights[p.name] for p in bag.paths])
    elif args.decay is not None:
        how = f"a stream in file-name order, weight × {args.decay:g} per image of age (newest last)"
        stream = ExponentialFilter(model.posterior, decay=args.decay)
        for i in range(len(bag.paths)):
            stream.update(bag.x[i : i + 1])
        domain = stream.domain()
    else:
        how = "equal weights"
        domain = Domain(model.posterior, bag.x)
    draws = domain.sample(n, derive_seed(seed, "domain"))
    box = model.posterior.box
    print(f"domain {folder}: {len(bag.paths)} images, {how}; effective size {_effective_size(domain.weights):.1f}")
    print(f"model {model.name}; {n} draws from the mixture of the posteriors (seed {seed})")
    summary = summarize(draws)
    print(format_summary(summary, box, moments=True))
    if args.json is not None:
        report = {
            "folder": str(folder),
            "images": len(bag.paths),
            "weighting": how,
            "effective_size": _effective_size(domain.weights),
            "model": model.name,
            "seed": seed,
        }
        _write_json(args.json, report | summary.to_dict(box))
    if args.corner is not None:
        _corner(draws, box, f"domain {folder.name} — {model.name}", args.corner)
        print(f"wrote {args.corner}", file=sys.stderr)
    return 0


# --- relate ---------------------------------------------------------------------------------------------------


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
    the parameters beyond their level (what the alarm is about; README "Where the target differs")."""
    print(
        f"where the target differs from the fitted mixture Σ λ̂ₖ sourceₖ (marginals of {draws_per_image} "
        "posterior draws an image):\n"
        "  medians and W₁ in the parameter's unit; in-ODD: the W₁ that in-ODD targets of "
        f"{held} images made from the sources\n"
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


def _cmd_relate(args: argparse.Namespace) -> int:
    """Each folder an equally weighted bag, characterized as the ``task3`` stage does by default (``--smoothing
    scott``: the :class:`components.domains.kernel.KernelDomain` of ``--draws-per-image`` fixed posterior draws per
    image, with ``--bandwidth-scale`` × the sources' Scott bandwidth) or by the paper's exact mixture (``none``:
    :class:`components.domains.absolute.Domain`); the verdict is
    :func:`components.domains.relative.calibrate_on_sources`'s detector on :attr:`Relation.relative_gap`."""
    from components.domains.absolute import Domain
    from components.domains.difference import InOddDifferences, parameter_differences
    from components.domains.kernel import KernelDomain, sources_bandwidth
    from components.domains.relative import calibrate_on_sources, relate

    seed = _seed(args.seed)
    folders = [Path(args.target), *map(Path, args.sources)]
    for f in folders:
        if not f.is_dir():
            raise CLIError(f"{f}: not a folder (pidc relate takes folders of images)")
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
    kernel = args.smoothing == "scott"
    if args.draws_per_image < 2:
        raise CLIError(f"--draws-per-image must be at least 2 (a bag's spread), got {args.draws_per_image}")
    if kernel and not (0.0 < args.bandwidth_scale < math.inf):
        raise CLIError(f"--bandwidth-scale must be a positive number, got {args.bandwidth_scale:g}")
    _check_json_path(args.json)
    _check_figure_path(args.plot, "--plot")
    listed = [_list([f]) for f in folders]
    model = _load_model(args)
    said: set[str] = set()  # notes said once for the whole command
    bags = [
        _read_all(model, paths, "relate", f"read {f.name}", said) for f, paths in zip(folders, listed, strict=False)
    ]
    target, *sources = [Domain(model.posterior, b.x) for b in bags]
    names = [f.name for f in folders[1:]]
    if len(set(names)) < len(names):
        names = [str(f) for f in folders[1:]]
    # fixed posterior draws of every image: the kernel densities' support (--smoothing scott) and, for either
    # smoothing, the marginals that say where the target differs from the sources' fitted mixture
    draws = _fixed_draws(model.posterior, [b.x for b in bags], args.draws_per_image, seed)
    bandwidth = None
    box = model.posterior.box
    pooled = [d.reshape(-1, d.shape[-1]) for d in draws]
    in_odd = InOddDifferences(draws[1:], box)  # each parameter's W₁ on the calibration's in-ODD targets

    try:
        if kernel:
            bandwidth = args.bandwidth_scale * sources_bandwidth(draws[1:])
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
        raise CLIError(str(e)) from None
    outside = detector.decide(rel.relative_gap)
    differences = parameter_differences(pooled[0], pooled[1:], rel.weights, box)
    levels = in_odd.levels(alpha)  # the W₁ that in-ODD targets of this size exceed with probability α
    print(f"target {folders[0]}: {len(target)} images; model {model.name}; {args.points} points (seed {seed})")
    if bandwidth is None:
        print("each folder: the exact mixture of its images' posteriors (--smoothing none)")
    else:
        print(
            f"each folder: a kernel density of {args.draws_per_image} posterior draws per image, bandwidth "
            f"{args.bandwidth_scale:g} × the sources' Scott rule = "
            + ", ".join(f"{n} {h:.3g}" for n, h in zip(model.posterior.box.names, bandwidth, strict=False))
        )
    width = max(len("source"), *map(len, names))
    print(f"{'source':<{width}}  {'images':>6}  {'weight λ̂':>9}")
    for name, s, lam in zip(names, sources, rel.weights, strict=False):
        print(f"{name:<{width}}  {len(s):>6}  {lam:>9.4f}")
    print(f"mean squared gap δ: {rel.gap:.4g} (density², physical units)")
    print(f"relative gap δ/mean(b²): {rel.relative_gap:.4g}")
    if rel.degenerate:
        print(
            "degenerate: yes — the sources are linearly dependent (e.g. the same images): λ̂ is not unique; "
            "shown is the minimum-norm one"
        )
    else:
        print("degenerate: no")
    held = min(len(target), sum(len(s) // 2 for s in sources))  # calibrate_on_sources holds out ≤ half a source
    print(
        f"threshold: {detector.threshold:.4g} (relative gap; {detector.n_calibration} in-ODD targets of "
        f"{held} images held out of the sources; false-alarm rate {alpha:g})"
    )
    if k == 1:
        print("note: one source, so λ̂ = 1; the verdict says whether the target looks like that source")
    _print_differences(differences, levels, outside, args.draws_per_image, held, alpha)
    verdict = "OUTSIDE the ODD" if outside else "inside the ODD"
    print(f"verdict: {verdict} (relative gap {'>' if outside else '≤'} threshold; false-alarm rate {alpha:g})")
    if args.json is not None:
        report = {
            "target": {"folder": str(folders[0]), "images": len(target)},
            "sources": [
                {"name": n, "folder": str(f), "images": len(src), "weight": float(lam)}
                for n, f, src, lam in zip(names, folders[1:], sources, rel.weights, strict=True)
            ],
            "model": model.name,
            "seed": seed,
            "points": args.points,
            "smoothing": args.smoothing,
            "draws_per_image": args.draws_per_image,
            "bandwidth": None if bandwidth is None else dict(zip(box.names, map(float, bandwidth), strict=True)),
            "gap": float(rel.gap),
            "relative_gap": float(rel.relative_gap),
            "degenerate": bool(rel.degenerate),
            "threshold": float(detector.threshold),
            "calibration_targets": detector.n_calibration,
            "calibration_target_images": held,
            "false_alarm_rate": alpha,
            "outside": bool(outside),
            "parameters": {
                diff.name: {
                    **diff.to_dict(),
                    "in_odd_level": level,
                    "exceeds_in_odd_level": bool(diff.wasserstein > level),
                }
                for diff, level in zip(differences, levels, strict=True)
            },
        }
        _write_json(args.json, report)
    if args.plot is not None:
        from components.plots import relation_marginals, save_figure

        notes = [
            f"W₁ {q.wasserstein:.3g} {q.unit}{' *' if outside and q.wasserstein > level else ''} (in-ODD ≤ {level:.3g} "
            f"with prob. {1 - alpha:g})"
            for q, level in zip(differences, levels, strict=True)
        ]
        title = (
            f"{folders[0].name} against {', '.join(names)} ({model.name}): {verdict} "
            f"(relative gap {rel.relative_gap:.3g}, threshold {detector.threshold:.3g})"
        )
        save_figure(relation_marginals(pooled[0], pooled[1:], rel.weights, names, box, notes, title), args.plot)
        print(f"wrote {args.plot}", file=sys.stderr)
    return 0


# --- parser ---------------------------------------------------------------------------------------------------


def _model_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--model",
        default="champion",
        help="'champion' (the model reports/task1/champion.json names), a model id under the registry, "
        "an exported folder, or an MLflow registered model URI such as models:/pidc@champion (default: champion)",
    )
    p.add_argument("--registry", type=Path, default=Path("registry"), help="the registry folder (default: registry)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random draw (default 0)")


def add_model_commands(sub: Any) -> None:
    """Add ``characterize``, ``domain`` and ``relate`` to the ``pidc`` subcommands ``sub``."""
    p = sub.add_parser("characterize", help="per image: the posterior's median and 68.27 %% HDI per parameter")
    p.add_argument("images", nargs="+", metavar="IMAGE_OR_FOLDER", help="image files and/or folders of images")
    _model_options(p)
    p.add_argument("--samples", type=int, default=1000, help="posterior draws per image (default 1000)")
    p.add_argument("--samples-out", type=Path, metavar="FILE", help="write the draws: FILE.csv or FILE.parquet")
    p.add_argument(
        "--corner",
        type=Path,
        metavar="FILE.png",
        help="corner plot; for several images one per image, named FILE-<image stem>.png",
    )
    p.add_argument(
        "--json", type=Path, metavar="FILE.json", help="write each image's summary (median, HDI, mean, std) as JSON"
    )
    p.set_defaults(func=_cmd_characterize)

    p = sub.add_parser("domain", help="a folder of images as one weighted bag: the domain's weather distribution")
    p.add_argument("folder", metavar="FOLDER")
    how = p.add_mutually_exclusive_group()
    how.add_argument(
        "--weights",
        type=Path,
        metavar="FILE.csv",
        help="rows <image file name>,<weight> (header optional); images not listed are left out",
    )
    how.add_argument(
        "--decay",
        type=float,
        metavar="RATE",
        help="the images in file-name order are a stream; weights × RATE ∈ (0, 1] per image of age",
    )
    _model_options(p)
    p.add_argument("--samples", type=int, default=1000, help="draws from the domain's distribution (default 1000)")
    p.add_argument("--corner", type=Path, metavar="FILE.png", help="corner plot of the domain's distribution")
    p.add_argument(
        "--json", type=Path, metavar="FILE.json", help="write the domain's summary (median, HDI, mean, std) as JSON"
    )
    p.set_defaults(func=_cmd_domain)

    p = sub.add_parser("relate", help="a target folder as a mixture of source folders, and the out-of-ODD verdict")
    p.add_argument("target", metavar="TARGET_FOLDER")
    p.add_argument(
        "sources",
        nargs="+",
        metavar="SOURCE_FOLDER",
        help="source domains (one folder each); with one source λ̂ = 1 and the verdict tests likeness",
    )
    _model_options(p)
    p.add_argument(
        "--points",
        type=int,
        default=RELATE_DEFAULTS["n_points"],
        help="n_W, points drawn from the target (default %(default)s)",
    )
    p.add_argument(
        "--smoothing",
        choices=("scott", "none"),
        default=RELATE_DEFAULTS["smoothing"],
        help="how a folder's weather is characterized: scott, a kernel density of its images' posterior draws (the "
        "task3 stage's); none, the paper's exact mixture of posteriors, isolated peaks for a sharp model and "
        "folders of tens of images (default %(default)s)",
    )
    p.add_argument(
        "--draws-per-image",
        type=int,
        default=RELATE_DEFAULTS["draws_per_image"],
        help="posterior draws per image: the kernel density's support (--smoothing scott) and the marginals of the "
        "per-parameter differences (default %(default)s)",
    )
    p.add_argument(
        "--bandwidth-scale",
        type=float,
        default=RELATE_DEFAULTS["bandwidth_scale"],
        help="the kernel's bandwidth in units of Scott's rule on the sources (default %(default)s)",
    )
    p.add_argument(
        "--false-alarm-rate",
        type=float,
        default=0.05,
        help="rate at which in-ODD targets are declared outside (default 0.05)",
    )
    p.add_argument(
        "--calibration-targets",
        type=int,
        default=100,
        help="in-ODD targets held out of the sources to set the threshold (default 100)",
    )
    p.add_argument(
        "--json",
        type=Path,
        metavar="FILE.json",
        help="write the result: λ̂, the gaps, the threshold, the verdict and the per-parameter differences",
    )
    p.add_argument(
        "--plot",
        type=Path,
        metavar="FILE.png",
        help="the target's marginals beside the fitted mixture's and each source's",
    )
    p.set_defaults(func=_cmd_relate)
