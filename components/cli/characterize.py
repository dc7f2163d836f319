"""``pidc characterize``: per image, the posterior's median and 68.27 % HDI per parameter (Task I), optionally the
draws (CSV/Parquet), a corner plot per image and a JSON summary.

Used by the ``pidc`` CLI only.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from components.cli.errors import CLIError
from components.cli.outputs import check_not_input, check_outputs
from components.cli.reading import (
    ReadLog,
    check_figure_path,
    check_inputs,
    check_json_path,
    check_prior,
    check_samples,
    check_seed,
    count,
    list_paths,
    load_model,
    load_prior,
    none_read,
    prior_json,
    prior_line,
    read_batches,
    reweighted,
    save_corner,
    say,
    write_json,
)
from components.core.seeding import derive_seed

__all__ = ["cmd_characterize"]


def _distinct(paths: list[Path], command: str) -> list[Path]:
    """``paths`` without repeats of one file (the same path after resolving links and ``..``, e.g. ``good good/a.png``),
    each repeat said in a ``note:`` line: an image is characterized once."""
    first: dict[Path, Path] = {}
    for p in paths:
        key = p.resolve()
        if key in first:
            same = "" if first[key] == p else f" (as {first[key]})"
            print(f"pidc {command}: note: {p} is given twice{same}: taken once", file=sys.stderr)
        else:
            first[key] = p
    return list(first.values())


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


def cmd_characterize(args: argparse.Namespace) -> int:
    """Per image a table block (median, HDI); the draws of an image are seeded by (``--seed``, its path), so they do
    not depend on the other images given."""
    from components.cli.drawsfile import DrawsWriter, check_draws_path
    from components.evaluate.summary import format_summary, summarize

    n = check_samples(args.samples)
    seed = check_seed(args.seed)
    check_figure_path(args.corner)
    check_json_path(args.json)
    if args.samples_out is not None:
        try:
            check_draws_path(args.samples_out)
        except (ValueError, ImportError) as e:
            raise CLIError(f"--samples-out {e}") from None
    min_ess = check_prior(args, n, "--samples")
    check_inputs(args.images)
    paths = _distinct(list_paths(args.images), "characterize")
    corners = _corner_paths(args.corner, paths) if args.corner is not None else {}
    outputs = [("--samples-out", args.samples_out), ("--json", args.json), *(("--corner", c) for c in corners.values())]
    check_not_input(outputs, paths)
    check_outputs(outputs)
    model = load_model(args)
    post = model.posterior
    prior = load_prior(args, model, min_ess, "--samples")
    ess: list[float] = []  # each image's ESS under --prior
    writer = None if args.samples_out is None else DrawsWriter(args.samples_out, post.box.names)
    done = 0
    summaries: list[dict] = []  # for --json
    log = ReadLog("characterize")  # the skips, notes and caveats, for stderr and --json
    try:
        for read, bar in read_batches(model, paths, "characterize", "characterize", log):
            for i, path in enumerate(read.paths):
                x, image_seed = read.x[i : i + 1], derive_seed(seed, "characterize", str(path))
                head = f"== {path}" + (f"  (note: {read.notes[i]})" if read.notes[i] else "")
                extra = {}
                if prior is None:
                    draws = post.sample(x, n, image_seed)[0]
                else:  # resampled from n draws reweighted to --prior
                    user, found = reweighted(prior, post, [([path], x)], n, image_seed, str(path))
                    draws, extra = user.sample(x, n, image_seed)[0], {"ess": float(found[0])}
                    ess.append(extra["ess"])
                    head += f"  (prior {prior.path}: effective sample size {found[0]:.1f} of {n})"
                summary = summarize(draws)
                say(bar, f"{head}\n{format_summary(summary, post.box)}\n")
                summaries.append(
                    {"image": str(path), "note": read.notes[i] or None, **extra, **summary.to_dict(post.box)}
                )
                if writer is not None:
                    writer.write(str(path), draws)
                if path in corners:
                    save_corner(draws, post.box, f"{path.name} — {model.name}", corners[path])
                done += 1
    except BaseException:
        if writer is not None:
            writer.discard()
        raise
    if done == 0:
        if writer is not None:
            writer.discard()
        raise CLIError(none_read(len(paths)))
    log.finish(model, each=False)  # each image's notes are in its table's head
    if writer is not None:
        writer.close()
        print(f"wrote {count(writer.rows, 'draw')} of {count(done, 'image')} to {writer.path}", file=sys.stderr)
    skipped = len(paths) - done
    if prior is not None:
        print(prior_line(prior, ess, n), file=sys.stderr)
    if args.json is not None:
        write_json(
            args.json,
            {
                "model": model.name,
                "seed": seed,
                "samples": n,
                **(prior_json(prior, ess, n) if prior is not None else {}),
                **log.to_json(),
                "images": summaries,
            },
        )
    print(
        f"characterized {count(done, 'image')} with {model.name} ({count(n, 'draw')} each, seed {seed})"
        + (f"; skipped {skipped}" if skipped else ""),
        file=sys.stderr,
    )
    return 0
