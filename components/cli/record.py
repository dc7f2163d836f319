"""``pidc record``: render the generate stage's plan into a recorded folder (images + labels) with any simulator.

The folder is what ``simulator.backend: recorded`` imports (:mod:`components.simulate.recorded`): a CARLA user records
on the CARLA server's machine (``--backend carla``) and trains anywhere. Resumable: run the same command again after a
kill and it renders only the images not yet written. The logic is :func:`components.simulate.recorded.record`.

Used by the ``pidc`` CLI only.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from components.cli.errors import CLIError

__all__ = ["add_record_command", "cmd_record"]

_SPLITS = ("train", "val", "test")


def cmd_record(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from components.core.config import ConfigError, load_params
    from components.simulate.base import make_simulator
    from components.simulate.labels import RecordedError
    from components.simulate.recorded import record, split_plans

    try:
        params = load_params(args.params)
    except ConfigError as e:
        raise CLIError(e.one_line()) from None
    backend = args.backend or params.simulator.backend
    if backend == "recorded":
        raise CLIError(
            f"{args.params}: simulator.backend is recorded, which renders nothing; record with --backend procedural "
            "or --backend carla"
        )
    if args.count is not None and args.count < 1:
        raise CLIError(f"--count must be a positive number of images, got {args.count}")
    splits = list(dict.fromkeys(args.split or _SPLITS))
    simulator = make_simulator(params.simulator.model_copy(update={"backend": backend}))
    try:
        plans = split_plans(params, splits, args.count, simulator.version)
        total = sum(len(p) for p in plans)
        with tqdm(total=total, desc="pidc record", unit="image") as bar:
            done = record(simulator, plans, args.out, progress=bar.update)
    except RecordedError as e:
        raise CLIError(str(e)) from None
    finally:
        close = getattr(simulator, "close", None)
        if callable(close):
            close()
    print(
        f"recorded {done['images']} images of {', '.join(splits)} into {args.out} ({done['rendered']} rendered, "
        f"{done['kept']} kept from an earlier run; {simulator.version}); labels: {done['labels']}"
    )
    return 0


def add_record_command(sub: Any) -> None:
    """Add ``record`` to the ``pidc`` subcommands ``sub``."""
    p = sub.add_parser(
        "record",
        help="render the generate stage's plan into a recorded folder (images + labels.csv) with any simulator",
    )
    p.add_argument("out", type=Path, metavar="OUT", help="the folder to write (new, or one to resume)")
    p.add_argument(
        "--params",
        type=Path,
        default=Path("params.yaml"),
        metavar="FILE",
        help="the params file whose plan, simulator and image size are used (default: params.yaml)",
    )
    p.add_argument(
        "--split",
        action="append",
        choices=_SPLITS,
        help="a split to record (repeatable; default: train, val and test)",
    )
    p.add_argument("--count", type=int, help="the first COUNT images of each split (default: its size in data.splits)")
    p.add_argument(
        "--backend",
        choices=("procedural", "carla"),
        help="the simulator (default: the params' simulator.backend; carla needs its server, simulator.carla)",
    )
    p.set_defaults(func=cmd_record)
