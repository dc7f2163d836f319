"""The command lines of ``pidc characterize``, ``pidc domain`` and ``pidc relate``: a registry model applied to image
files (each command in its own module, what they share in :mod:`~components.cli.reading`).

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
from pathlib import Path
from typing import Any

from components.cli.characterize import cmd_characterize
from components.cli.domain import cmd_domain
from components.cli.reading import MIN_ESS, MIN_SAMPLES
from components.cli.relate import RELATE_DEFAULTS, RELATE_PRIOR_DRAWS, cmd_relate

__all__ = ["add_model_commands"]


def _model_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--model",
        default="champion",
        help="'champion' (the model reports/task1/champion.json names), a model id under the registry, "
        "an exported folder, or an MLflow registered model URI such as models:/pidc@champion (default: champion)",
    )
    p.add_argument("--registry", type=Path, default=Path("registry"), help="the registry folder (default: registry)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random draw (default 0)")


def _prior_options(p: argparse.ArgumentParser, draws: str) -> None:
    p.add_argument(
        "--prior",
        type=Path,
        metavar="FILE.yaml",
        help="your own prior, a density per parameter (docs/cli.md, 'Your own prior'): the posterior draws are "
        "reweighted from the training prior (uniform on the model's box) to it; others keep the training prior",
    )
    p.add_argument(
        "--min-ess",
        type=float,
        metavar="N",
        help=f"with --prior: the fewest effective draws (of {draws} per image) an image's reweighted posterior may "
        f"rest on; below, an error naming the image (default {MIN_ESS})",
    )


def add_model_commands(sub: Any) -> None:
    """Add ``characterize``, ``domain`` and ``relate`` to the ``pidc`` subcommands ``sub``."""
    _add_characterize(sub)
    _add_domain(sub)
    _add_relate(sub)


def _add_characterize(sub: Any) -> None:
    p = sub.add_parser("characterize", help="per image: the posterior's median and 68.27 %% HDI per parameter")
    p.add_argument("images", nargs="+", metavar="IMAGE_OR_FOLDER", help="image files and/or folders of images")
    _model_options(p)
    p.add_argument(
        "--samples", type=int, default=1000, help=f"posterior draws per image (default 1000, at least {MIN_SAMPLES})"
    )
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
    _prior_options(p, "--samples")
    p.set_defaults(func=cmd_characterize)


def _add_domain(sub: Any) -> None:
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
    p.add_argument(
        "--samples",
        type=int,
        default=1000,
        help=f"draws from the domain's distribution (default 1000, at least {MIN_SAMPLES})",
    )
    p.add_argument("--corner", type=Path, metavar="FILE.png", help="corner plot of the domain's distribution")
    p.add_argument(
        "--json", type=Path, metavar="FILE.json", help="write the domain's summary (median, HDI, mean, std) as JSON"
    )
    _prior_options(p, "--samples")
    p.set_defaults(func=cmd_domain)


def _add_relate(sub: Any) -> None:
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
        help="the kernel's bandwidth in units of Scott's rule on the sources (default "
        f"{RELATE_DEFAULTS['bandwidth_scale']:g}; --smoothing scott only)",
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
    _prior_options(p, "--prior-draws")
    p.add_argument(
        "--prior-draws",
        type=int,
        metavar="N",
        help=f"with --prior: posterior draws per image reweighted to it, of which --draws-per-image are resampled "
        f"(default {RELATE_PRIOR_DRAWS})",
    )
    p.set_defaults(func=cmd_relate)
