"""``pidc watch``: a drive (a video or a folder of frames) followed frame by frame against source domains: per frame the
posterior's median and 68.27 % HDI, per window its domain (Task II), λ̂ over the sources and the ODD decision (Task
III), a sequential rule whose false alarms per hour are measured on windows held out of the sources, the alarm segments
and their causes; a timeline figure, tables and a JSON summary. The logic is :mod:`components.watch`.

Used by the ``pidc`` CLI only.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from components.cli.errors import CLIError
from components.cli.outputs import check_not_input, check_outputs
from components.cli.reading import MIN_SAMPLES, check_seed, folder_name, load_model
from components.watch.settings import WATCH_DEFAULTS

__all__ = ["add_watch_command", "cmd_watch"]


def _options(args: argparse.Namespace, seed: int) -> Any:
    from components.watch.errors import WatchError
    from components.watch.settings import WatchOptions

    if args.samples < MIN_SAMPLES:
        raise CLIError(
            f"--samples must be at least {MIN_SAMPLES} for a 68.27 % HDI that rests on more than a handful of draws, "
            f"got {args.samples}"
        )
    try:
        return WatchOptions(
            samples=args.samples,
            draws_per_image=args.draws_per_image,
            window=WATCH_DEFAULTS["window"] if args.window is None else args.window,
            stride=args.stride,
            decay=args.decay,
            block=args.block,
            n_points=args.points,
            bandwidth_scale=args.bandwidth_scale,
            source_centres=args.source_centres,
            false_alarm_rate=args.false_alarm_rate,
            consecutive=args.consecutive,
            batch=args.batch,
            seed=seed,
        )
    except WatchError as e:
        raise CLIError(str(e)) from None


def _names(paths: list[Path]) -> list[str]:
    """The sources' names: their folder names (a video's stem), or their paths where two share one."""
    names = [folder_name(p) if p.is_dir() else p.stem for p in paths]
    return names if len(set(names)) == len(names) else [str(p) for p in paths]


def _check_distinct(drive: Path, sources: list[Path]) -> None:
    first: dict[Path, Path] = {drive.resolve(): drive}
    for s in sources:
        key = s.resolve()
        if key in first:
            if first[key] is drive:
                raise CLIError(f"the drive {drive} is also given as a source ({s})")
            raise CLIError(f"source {s} is given twice")
        first[key] = s


def _outputs(out: Path, fmt: str) -> dict[str, Path]:
    from components.watch.report import TABLE_FORMATS

    suffix = TABLE_FORMATS[fmt]
    return {
        "timeline": out / "timeline.png",
        "frames": out / f"frames{suffix}",
        "windows": out / f"windows{suffix}",
        "summary": out / "summary.json",
    }


def _check_out(out: Path, fmt: str, inputs: list[Path]) -> dict[str, Path]:
    """The output files in ``--out`` after the checks: a folder (or a new one), not a drive's or source's folder of
    frames (its figure would become a frame), no output an input file, every output writable; Parquet needs
    pyarrow."""
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {out}: is a file; give a folder (made if missing)")
    if out.exists() and any(out.resolve() == p.resolve() for p in inputs if p.is_dir()):
        raise CLIError(f"--out {out} is the folder of the drive or a source: its outputs would be read as frames")
    if fmt == "parquet":
        try:
            import pyarrow  # noqa: F401
        except ImportError:
            raise CLIError("--table-format parquet needs pyarrow (pip install pyarrow), or use csv") from None
    outputs = _outputs(out, fmt)
    named = [(f"--out {out}:", p) for p in outputs.values()]
    files = [p for p in inputs if not p.is_dir()]
    for folder in (p for p in inputs if p.is_dir()):
        files.extend(f for f in folder.iterdir() if f.is_file())
    check_not_input(named, files)
    check_outputs(named)
    return outputs


def cmd_watch(args: argparse.Namespace) -> int:
    """Watch the drive (:func:`components.watch.run.watch`) and write ``--out``."""
    from components.watch.errors import WatchError
    from components.watch.frames import open_frames
    from components.watch.plot import timeline_figure
    from components.watch.report import report_lines, write_summary, write_table
    from components.watch.run import watch

    seed = check_seed(args.seed)
    options = _options(args, seed)
    drive_path, source_paths = Path(args.drive), [Path(s) for s in args.sources]
    try:
        drive = open_frames(drive_path, args.fps)
        sources = [open_frames(p, timed=False) for p in source_paths]
    except WatchError as e:
        raise CLIError(str(e)) from None
    _check_distinct(drive_path, source_paths)
    outputs = _check_out(Path(args.out), args.table_format, [drive_path, *source_paths])
    model = load_model(args)
    try:
        result = watch(model, drive, sources, _names(source_paths), options, progress=True)
    except WatchError as e:
        raise CLIError(str(e)) from None
    for note in result.notes:
        print(f"pidc watch: note: {note}", file=sys.stderr)
    write_table(outputs["frames"], result.frames, args.table_format)
    write_table(outputs["windows"], result.windows, args.table_format)
    write_summary(outputs["summary"], result)
    from components.plots.canvas import save_figure

    save_figure(timeline_figure(result), outputs["timeline"])
    print("\n".join(report_lines(result)))
    print(f"wrote {', '.join(str(p) for p in outputs.values())}", file=sys.stderr)
    return 0


def add_watch_command(sub: Any) -> None:
    """Add ``watch`` to the ``pidc`` subcommands ``sub``."""
    d = WATCH_DEFAULTS
    p = sub.add_parser(
        "watch",
        help="follow a drive (video or folder of frames) frame by frame against source domains: alarms when it leaves "
        "their ODD",
    )
    p.add_argument("drive", metavar="DRIVE", help="a video file (any format OpenCV reads) or a folder of frames")
    p.add_argument(
        "--sources",
        nargs="+",
        required=True,
        metavar="SOURCE",
        help="the source domains: folders of frames in name order (ideally drives) or videos",
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="the folder to write the outputs into")
    p.add_argument(
        "--table-format",
        choices=("csv", "parquet"),
        default="csv",
        help="format of frames.* and windows.* (default csv)",
    )
    p.add_argument(
        "--fps",
        type=float,
        help="frames per second: a video's instead of its stated rate; a folder's without times.csv",
    )
    p.add_argument("--model", default="champion", help="as for `pidc relate` (default: champion)")
    p.add_argument("--registry", type=Path, default=Path("registry"), help="the registry folder (default: registry)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random draw (default 0)")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--window", type=int, help=f"frames per window, equally weighted (default {d['window']})")
    how.add_argument(
        "--decay",
        type=float,
        metavar="RATE",
        help="exponentially decaying windows instead: weights × RATE ∈ (0, 1) per frame of age (Task II's filter), "
        f"over the frames above {d['decay_tolerance']:g} of the newest's weight",
    )
    p.add_argument("--stride", type=int, default=d["stride"], help="frames between windows (default %(default)s)")
    p.add_argument(
        "--block",
        type=int,
        default=d["block"],
        help="frames per block of the sources (density, calibration, density, evaluation; default %(default)s)",
    )
    p.add_argument(
        "--false-alarm-rate",
        type=float,
        default=d["false_alarm_rate"],
        help="share of in-ODD windows above the threshold (default %(default)s)",
    )
    p.add_argument(
        "--consecutive",
        type=int,
        default=d["consecutive"],
        help="the rule: alarm after this many consecutive flagged windows (default %(default)s)",
    )
    p.add_argument(
        "--samples",
        type=int,
        default=d["samples"],
        help=f"posterior draws per frame for its median and HDI (default %(default)s, at least {MIN_SAMPLES})",
    )
    p.add_argument(
        "--draws-per-image",
        type=int,
        default=d["draws_per_image"],
        help="the first of them: each frame's fixed draws for the kernel densities (default %(default)s)",
    )
    p.add_argument("--points", type=int, default=d["n_points"], help="n_W per window (default %(default)s)")
    p.add_argument(
        "--bandwidth-scale",
        type=float,
        default=d["bandwidth_scale"],
        help="kernel bandwidth in units of Scott's rule on the sources (default %(default)s)",
    )
    p.add_argument(
        "--source-centres",
        type=int,
        default=d["source_centres"],
        help="kernel centres kept per source (default %(default)s)",
    )
    p.add_argument("--batch", type=int, default=d["batch"], help="frames read at once (default %(default)s)")
    p.set_defaults(func=cmd_watch)
