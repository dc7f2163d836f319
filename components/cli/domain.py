"""``pidc domain``: a folder of images as one weighted bag (equal weights, a weights CSV, or an exponentially decaying
stream) → the domain's weather distribution, the weighted mixture of the images' posteriors (Task II).

Used by the ``pidc`` CLI only.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections.abc import Collection
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
    check_samples,
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
    save_corner,
    write_json,
)
from components.core.seeding import derive_seed

__all__ = ["cmd_domain", "read_weights_csv"]


def _is_image_name(name: str, images: Collection[str]) -> bool:
    """Whether a weights file's first cell names an image: one of ``images`` or a name with an image extension."""
    from components.core.images import IMAGE_EXTENSIONS

    return name in images or Path(name).suffix.lower() in IMAGE_EXTENSIONS


def _csv_rows(path: Path) -> list[list[str]]:
    """The rows of a UTF-8 CSV file (a BOM allowed), cells stripped; ``ValueError`` naming the file otherwise."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            return [[c.strip() for c in row] for row in csv.reader(f)]
    except UnicodeDecodeError as e:
        raise ValueError(
            f"{path}: not a UTF-8 text CSV file (byte {e.object[e.start]:#04x} at position {e.start})"
        ) from None


def read_weights_csv(path: str | Path, images: Collection[str] = ()) -> dict[str, float]:
    """A weights file: rows ``<image file name>,<weight>``, an optional header row (e.g. ``image,weight``).

    Blank rows and rows whose first cell starts with ``#`` are skipped. The header is the first other row, when its
    weight is not a number and its first cell does not name an image (one of ``images``, e.g. the folder's file names,
    or a name with an image extension): ``a.png,abc`` on line 1 is a bad weight, not a header.

    Returns ``{name: weight}`` in file order. Raises ``ValueError`` naming the file and line for a row without
    exactly two cells, a weight that is not a finite non-negative number, a repeated name, or an empty table; and when
    all weights are zero, the file is not UTF-8 text, or the path is not a file.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder, not a weights file")
    if not path.exists():
        raise ValueError(f"{path}: no such weights file")
    if not path.is_file():
        raise ValueError(f"{path}: not a regular file")
    out: dict[str, float] = {}
    first = True  # the next row that is not blank or a comment is the header candidate
    for line, cells in enumerate(_csv_rows(path), start=1):
        if not any(cells) or cells[0].startswith("#"):
            continue
        header, first = first, False
        if len(cells) != 2:
            raise ValueError(f"{path} line {line}: expected 2 cells (image,weight), got {len(cells)}")
        name, text = cells
        try:
            w = float(text)
        except ValueError:
            if header and not _is_image_name(name, images):
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


def _relative(weights: dict[str, float]) -> dict[str, float]:
    """``weights`` divided by their largest: the same domain (only their ratios matter), and a sum that cannot
    overflow (two weights of 1e308 sum to inf)."""
    top = max(weights.values())
    return {name: w / top for name, w in weights.items()}


def _skipped_weight(given: dict[str, float], relative: dict[str, float], skipped: list[str]) -> dict | None:
    """What the ``skipped`` images (file names) weighed in a weights file (``given``; ``relative``, the same divided by
    the largest): ``weight`` and ``total`` in the file's units (None where their sum overflows), ``share`` of the total,
    and a ``line`` saying so; None when no image with a weight was skipped."""
    skipped = [name for name in skipped if name in relative]
    if not skipped:
        return None
    share = sum(relative[n] for n in skipped) / sum(relative.values())
    weight, total = sum(given[n] for n in skipped), sum(given.values())
    percent = f"{100 * share:.0f}" if share >= 0.01 else f"{100 * share:.2g}"
    finite = math.isfinite(weight) and math.isfinite(total)
    line = (
        f"weights of skipped images: {weight:g} of {total:g} ({percent} %)"
        if finite
        else f"weights of skipped images: {percent} % of the total"
    ) + f", left out of the domain with the {count(len(skipped), 'image')} skipped"
    return {
        "weight": weight if finite else None,
        "total": total if finite else None,
        "share": share,
        "images": len(skipped),
        "line": line,
    }


def _weighted_paths(
    weights_csv: Path | None, folder: Path, paths: list[Path]
) -> tuple[list[Path], dict[str, float] | None, dict[str, float]]:
    """``(paths to read, relative weights by file name, the weights as the file gives them)``: with ``--weights``
    the images it lists with a positive weight (a note says how many images it leaves out); without, ``paths``, None
    and no weights."""
    if weights_csv is None:
        return paths, None, {}
    by_name = {p.name: p for p in paths}
    try:
        given = read_weights_csv(weights_csv, by_name)  # as the file gives them, to say what skipped images weighed
        weights = _relative(given)
    except ValueError as e:
        raise CLIError(f"--weights {e}") from None
    missing = [name for name in weights if name not in by_name]
    if missing:
        raise CLIError(
            f"--weights {weights_csv}: {len(missing)} listed image(s) not found among the images of "
            f"{folder}, e.g. {missing[0]!r}"
        )
    ignored = len(paths) - len(weights)
    if ignored:
        print(
            f"pidc domain: note: {ignored} image(s) of {folder} are not in {weights_csv}: left out",
            file=sys.stderr,
        )
    return [by_name[name] for name in weights if weights[name] > 0], weights, given


def _weighted_domain(
    args: argparse.Namespace, posterior: Any, bag: Any, weights: dict[str, float] | None
) -> tuple[Any, str]:
    """``(the domain of the bag's images, how they are weighted)``: by ``weights``, as an exponentially decaying
    stream in file-name order (``--decay``), or equally."""
    from components.domains.absolute import Domain, ExponentialFilter

    if weights is not None:
        return Domain(posterior, bag.x, [weights[p.name] for p in bag.paths]), f"weights from {args.weights}"
    if args.decay is not None:
        stream = ExponentialFilter(posterior, decay=args.decay)
        for i in range(len(bag.paths)):
            stream.update(bag.x[i : i + 1])
        how = f"a stream in file-name order, weight × {args.decay:g} per image of age (newest last)"
        return stream.domain(), how
    return Domain(posterior, bag.x), "equal weights"


def cmd_domain(args: argparse.Namespace) -> int:
    """The folder's images as one :class:`components.domains.absolute.Domain`; skipped images do not count as stream steps."""
    from components.evaluate.summary import format_summary, summarize

    n = check_samples(args.samples)
    seed = check_seed(args.seed)
    check_figure_path(args.corner)
    check_json_path(args.json)
    folder = check_folder(Path(args.folder), "domain")
    if args.decay is not None and not (0.0 < args.decay <= 1.0):
        raise CLIError(f"--decay must be in (0, 1] (the weight factor per image of age), got {args.decay:g}")
    min_ess = check_prior(args, n, "--samples")
    paths = list_paths([folder])
    outputs = [("--json", args.json), ("--corner", args.corner)]
    check_not_input(outputs, paths)
    check_outputs(outputs)
    paths, weights, given = _weighted_paths(args.weights, folder, paths)
    model = load_model(args)
    prior = load_prior(args, model, min_ess, "--samples")
    name = folder_name(folder)
    log = ReadLog("domain")
    bag = read_all(model, paths, "domain", f"domain {name}", folder, log)
    log.finish(model, each=True)
    lost = _skipped_weight(given, weights, [Path(p).name for p, _ in log.skipped]) if weights else None
    if lost is not None:
        print(f"pidc domain: note: {lost['line']}", file=sys.stderr)
    posterior, ess = model.posterior, None
    if prior is not None:  # each image's posterior under --prior: n draws reweighted
        posterior, ess = reweighted(prior, posterior, [(bag.paths, bag.x)], n, derive_seed(seed, "domain"), name)
    domain, how = _weighted_domain(args, posterior, bag, weights)
    draws = domain.sample(n, derive_seed(seed, "domain"))
    box = model.posterior.box
    size = _effective_size(domain.weights)
    print(f"domain {folder}: {count(len(bag.paths), 'image')}, {how}; effective size {size:.1f}")
    print(f"model {model.name}; {count(n, 'draw')} from the mixture of the posteriors (seed {seed})")
    if prior is not None:
        print(prior_line(prior, ess, n))
    summary = summarize(draws)
    print(format_summary(summary, box, moments=True))
    if args.json is not None:
        report = {
            "folder": str(folder),
            "name": name,
            "images": len(bag.paths),
            "weighting": how,
            "effective_size": _effective_size(domain.weights),
            "model": model.name,
            "seed": seed,
            **(prior_json(prior, ess, n) if prior is not None else {}),
            **log.to_json(),
        }
        if lost is not None:
            report["skipped_weight"] = {k: v for k, v in lost.items() if k != "line"}
        write_json(args.json, report | summary.to_dict(box))
    if args.corner is not None:
        save_corner(draws, box, f"domain {name} — {model.name}", args.corner)
        print(f"wrote {args.corner}", file=sys.stderr)
    return 0
