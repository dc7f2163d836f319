"""``pidc drive``: render a simulated drive whose weather over time is known (a folder of frames or a video).

The weather θ(t) walks inside a box (``--box``, the others held by ``--set``) with scripted events over it
(``--event fog:… / rain:… / dusk:…``), a new scene every ``--scene-seconds``; the truth is written beside the frames.
The logic is :mod:`components.simulate.drive`.

Used by the ``pidc`` CLI only.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

from components.cli.errors import CLIError

__all__ = ["add_drive_command", "cmd_drive", "EVENT_KEYS"]

#: The keys of ``--event KIND:key=value,…`` → the event's fields (start, over and to are required).
EVENT_KEYS: dict[str, str] = {
    "start": "start_s",
    "over": "duration_s",
    "to": "target",
    "lag": "lag_s",
    "deposits": "deposits_target",
    "clouds": "cloudiness_target",
}
_RAIN_ONLY = ("lag", "deposits", "clouds")


def _number(option: str, item: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise CLIError(f"{option} {item}: {text!r} is not a number") from None


def _pairs(option: str, items: list[str], form: str) -> dict[str, str]:
    """``NAME=VALUE`` items → {name: value text}; each name once."""
    out: dict[str, str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise CLIError(f"{option} expects {form}, got {item!r}")
        if name in out:
            raise CLIError(f"{option} {name}: given twice")
        out[name] = value.strip()
    return out


def parse_box(items: list[str]) -> dict[str, tuple[float, float]]:
    """``--box NAME=LOW:HIGH`` items → the checked box (:func:`components.simulate.drive.check_box`)."""
    from components.simulate.drive import check_box

    box: dict[str, tuple[float, float]] = {}
    for name, text in _pairs("--box", items, "NAME=LOW:HIGH").items():
        low, sep, high = text.partition(":")
        if not sep:
            raise CLIError(f"--box expects NAME=LOW:HIGH, got {name}={text!r}")
        box[name] = (_number("--box", name, low), _number("--box", name, high))
    try:
        return check_box(box, what="--box")
    except ValueError as e:
        raise CLIError(str(e)) from None


def parse_held(items: list[str], box: dict[str, tuple[float, float]]) -> dict[str, float]:
    """``--set NAME=VALUE`` items → held values, none walked in ``box``."""
    from components.simulate.drive import check_held

    held = {name: _number("--set", name, text) for name, text in _pairs("--set", items, "NAME=VALUE").items()}
    both = [n for n in held if n in box]
    if both:
        raise CLIError(f"--set {both[0]}: it is walked by --box {both[0]}=…; hold it or walk it, not both")
    try:
        return check_held(held, what="--set")
    except ValueError as e:
        raise CLIError(str(e)) from None


def parse_event(spec: str) -> Any:
    """``KIND:start=S,over=D,to=T[,lag=L,deposits=P,clouds=C]`` → a :class:`~components.simulate.drive.Fog`,
    ``Rain`` or ``Dusk`` (seconds and the parameter's units; lag/deposits/clouds are rain's)."""
    from components.simulate.drive import EVENTS

    kind, sep, rest = spec.partition(":")
    kind = kind.strip()
    if kind not in EVENTS:
        raise CLIError(
            f"--event {spec}: unknown event {kind!r}; known: {', '.join(EVENTS)} (e.g. fog:start=60,over=60,to=80)"
        )
    if not sep or not rest.strip():
        raise CLIError(f"--event {spec}: expects {kind}:start=S,over=D,to=T")
    values: dict[str, float] = {}
    for part in rest.split(","):
        key, eq, text = part.partition("=")
        key = key.strip()
        allowed = [k for k in EVENT_KEYS if kind == "rain" or k not in _RAIN_ONLY]
        if not eq or key not in allowed:
            raise CLIError(f"--event {spec}: unknown key {key!r}; {kind} takes {', '.join(allowed)}")
        if EVENT_KEYS[key] in values:
            raise CLIError(f"--event {spec}: {key} given twice")
        values[EVENT_KEYS[key]] = _number("--event", spec + ":", text)
    missing = [k for k in ("start", "over", "to") if EVENT_KEYS[k] not in values]
    if missing:
        raise CLIError(f"--event {spec}: missing {', '.join(missing)}")
    try:
        return EVENTS[kind](**values)
    except ValueError as e:
        raise CLIError(f"--event {spec}: {e}") from None


def _check_scalars(args: argparse.Namespace) -> None:
    from components.core.images import RENDER_SIDES

    if args.seed is None:
        raise CLIError("--seed is required: it picks the walk and the scenes; e.g. --seed 0")
    if args.seed < 0:
        raise CLIError(f"--seed must be a non-negative integer, got {args.seed}")
    for option, value, unit in (
        ("--seconds", args.seconds, "s"),
        ("--fps", args.fps, "frames/s"),
        ("--correlation-seconds", args.correlation_seconds, "s"),
        ("--scene-seconds", args.scene_seconds, "s"),
    ):
        if not value > 0 or value == float("inf"):
            raise CLIError(f"{option} must be a positive, finite number of {unit}, got {value:g}")
    low, high = RENDER_SIDES
    if not low <= args.size <= high:
        raise CLIError(f"--size must be within {low}..{high} pixels (the renderer's sizes), got {args.size}")


def _check_out(out: Path) -> str:
    """``"video"`` or ``"folder"`` for ``-o OUT``, after checking it can be written."""
    from components.cli.outputs import check_outputs
    from components.simulate.drive import VIDEO_CODECS, video_sidecars

    suffix = out.suffix.lower()
    if suffix in VIDEO_CODECS:
        sidecars = video_sidecars(out)
        check_outputs([("-o", out), ("-o", sidecars[0]), ("-o", sidecars[1])])
        return "video"
    if suffix and not out.is_dir():
        raise CLIError(
            f"-o {out}: a drive is a folder (a name without extension) or a video ({', '.join(VIDEO_CODECS)}), "
            f"got {out.suffix!r}"
        )
    if out.exists():
        if not out.is_dir():
            raise CLIError(f"-o {out}: is a file; give a new or empty folder, or a video name")
        if any(out.iterdir()):
            raise CLIError(f"-o {out}: the folder is not empty; give a new or empty folder")
    parent = out.absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise CLIError(f"-o {out}: cannot write in {parent}")
    return "folder"


def cmd_drive(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from components.simulate.drive import DEFAULT_BOX, Drive, write_folder, write_video

    _check_scalars(args)
    box = parse_box(args.box or [])
    held = parse_held(args.set or [], box)
    box = {n: v for n, v in {**DEFAULT_BOX, **box}.items() if n not in held}
    events = tuple(parse_event(spec) for spec in args.event or [])
    try:
        drive = Drive(
            seconds=args.seconds,
            seed=args.seed,
            fps=args.fps,
            size=args.size,
            box=box,
            held=held,
            correlation_s=args.correlation_seconds,
            events=events,
            scene_seconds=args.scene_seconds,
        )
    except ValueError as e:
        raise CLIError(f"--event: {e}" if "event" in str(e) else str(e)) from None
    kind = _check_out(args.out)
    write = write_video if kind == "video" else write_folder
    with tqdm(total=drive.n_frames, desc="pidc drive", unit="frame") as bar:
        write(drive, args.out, progress=bar.update)
    info = drive.to_dict()
    beside = "OUT.weather.csv, OUT.drive.json" if kind == "video" else "times.csv, weather.csv, drive.json"
    print(
        f"wrote {drive.n_frames} frames ({drive.seconds:g} s at {drive.fps:g} frames/s, {drive.size}×{drive.size}, "
        f"seed {drive.seed}) to {args.out} ({beside.replace('OUT', str(args.out.with_suffix('')))})"
    )
    walked = ", ".join(f"{n} {lo:g}..{hi:g}" for n, (lo, hi) in drive.box.items()) or "nothing"
    print(
        f"walk (τ = {drive.correlation_s:g} s): {walked}; held: "
        + ", ".join(f"{n} {v:g}" for n, v in drive.held.items())
    )
    if info["exits"]:
        print(
            "leaves its box and held values: "
            + ", ".join(f"{n} at {t:g} s" for n, t in sorted(info["exits"].items(), key=lambda kv: kv[1]))
        )
    else:
        print("stays within its box and held values throughout")
    return 0


def add_drive_command(sub: Any) -> None:
    """Add ``drive`` to the ``pidc`` subcommands ``sub``."""
    from components.simulate.drive import DEFAULT_BOX, DRIVE_DEFAULTS

    default_box = ", ".join(f"{n}={lo:g}:{hi:g}" for n, (lo, hi) in DEFAULT_BOX.items())
    p = sub.add_parser(
        "drive",
        help="render a simulated drive (weather walking in a box, scripted fog/rain/dusk) as frames or a video",
    )
    p.add_argument(
        "-o",
        "--out",
        type=Path,
        required=True,
        metavar="OUT",
        help="a new or empty folder (OUT/000000.png…, times.csv, weather.csv, drive.json), or a video OUT.avi "
        "(MJPG), .mp4 (mp4v) or .mkv (FFV1, lossless) with OUT.weather.csv and OUT.drive.json beside it",
    )
    p.add_argument("--seconds", type=float, default=60.0, help="the drive's length, seconds (default %(default)g)")
    p.add_argument("--fps", type=float, default=DRIVE_DEFAULTS["fps"], help="frames per second (default %(default)g)")
    p.add_argument("--seed", type=int, help="seed (required) of the walk and the scenes: same seed, same drive")
    p.add_argument(
        "--size", type=int, default=int(DRIVE_DEFAULTS["size"]), help="image side, pixels (default %(default)s)"
    )
    p.add_argument(
        "--box",
        action="append",
        metavar="NAME=LOW:HIGH",
        help=f"a walked parameter's range (repeatable; added to the default box {default_box})",
    )
    p.add_argument(
        "--set",
        action="append",
        metavar="NAME=VALUE",
        help="hold a parameter at a value (repeatable; takes it out of the default box; the unwalked ones default "
        "to no rain, dry road, azimuth 135)",
    )
    p.add_argument(
        "--correlation-seconds",
        type=float,
        default=DRIVE_DEFAULTS["correlation_s"],
        metavar="TAU",
        help="the walk's correlation time, seconds (default %(default)g)",
    )
    p.add_argument(
        "--event",
        action="append",
        metavar="KIND:start=S,over=D,to=T",
        help="a scripted event (repeatable, applied in order): fog (fog_density), dusk (sun_altitude_angle), rain "
        "(precipitation; also lag=L s for the puddles, deposits=P, clouds=C), e.g. fog:start=60,over=60,to=80",
    )
    p.add_argument(
        "--scene-seconds",
        type=float,
        default=DRIVE_DEFAULTS["scene_seconds"],
        metavar="S",
        help="seconds per scene: the car reaches a new scene (map, camera, traffic) every S seconds (default %(default)g)",
    )
    p.set_defaults(func=cmd_drive)
