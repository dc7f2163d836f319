"""The ``pidc`` command line: thin over :mod:`components`, heavy imports only inside commands.

The ``pidc`` CLI's entry point (``[project.scripts]`` in ``pyproject.toml``); no pipeline stage imports it.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from components.cli.errors import CLIError
from components.cli.outputs import check_output, memory_error_line, os_error_line
from components.core import presets, weather
from components.core.images import RENDER_SIDES


def _parse_assignments(items: Sequence[str]) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise CLIError(f"--set expects NAME=VALUE, got {item!r}")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise CLIError(f"--set {name}: {value!r} is not a number") from None
    return out


def _cmd_weather(args: argparse.Namespace) -> int:
    print(f"{'parameter':<28}{'role':<11}{'range / value':<22}short")
    for p in weather.PARAMETERS.values():
        rng = f"{p.fixed:g}" if p.role == "fixed" else p.describe_range()
        print(f"{p.name:<28}{p.role:<11}{rng:<22}{p.short}")
    _print_presets()
    return 0


def _print_presets() -> None:
    """CARLA's presets: the usable ones with their values, the refused ones with the field that differs."""
    print(
        f"\nCARLA {presets.CARLA_VERSION}'s presets for `pidc render --preset`, as CARLA sets them; CARLA leaves the sun "
        f"azimuth\nunchanged, pidc renders it at {presets.PRESET_SUN_AZIMUTH:g} deg (--set sun_azimuth_angle=A for another):"
    )
    print(f"{'preset':<18}" + "".join(f"{s:>9}" for s in (*weather.SHORT_NAMES, "azimuth")))
    for name in presets.USABLE:
        w = presets.preset_weather(name)
        print(f"{name:<18}" + "".join(f"{w[n]:>9g}" for n in (*weather.PREDICTED, "sun_azimuth_angle")))
    print("\nrefused (a parameter pidc holds fixed, or does not model, differs):")
    for reason in presets.REFUSED.values():
        print(f"  {reason}")


def _cmd_render(args: argparse.Namespace) -> int:
    w: dict[str, float] = {}
    if args.preset:
        try:
            w = presets.preset_weather(args.preset)
        except ValueError as e:
            raise CLIError(f"--preset {e} (`pidc weather` lists the presets pidc renders)") from None
    w.update(_parse_assignments(args.set or []))
    if args.seed is None:
        raise CLIError("--seed is required: it picks the scene (map, camera, traffic); e.g. --seed 0")
    if args.seed < 0:
        raise CLIError(f"--seed must be a non-negative integer, got {args.seed}")
    try:
        w = weather.complete_weather(w)
    except ValueError as e:
        raise CLIError(f"{e} (set it with --set NAME=VALUE or start from --preset)") from None
    low, high = RENDER_SIDES
    if not (low <= args.height <= high and low <= args.width <= high):
        raise CLIError(
            f"--height and --width must be within {low}..{high} pixels (the renderer's sizes), got --height "
            f"{args.height} --width {args.width}"
        )
    if args.out.suffix.lower() != ".png":
        raise CLIError(f"-o {args.out}: pidc render writes PNG; use a .png file name")
    check_output(args.out, "-o")

    from components.simulate.contact_sheet import save_png
    from components.simulate.procedural import ProceduralSimulator

    sim = ProceduralSimulator(args.height, args.width)
    image = sim.render(w, args.seed)
    save_png(args.out, image)
    print(f"wrote {args.out} ({args.width}×{args.height}, scene seed {args.seed}, {sim.version})")
    return 0


def _cmd_config_check(args: argparse.Namespace) -> int:
    import yaml

    from components.core.config import ConfigError, load_params

    check_output(args.write, "--write")
    try:
        params = load_params(args.params, profile=args.profile)
    except ConfigError as e:
        raise CLIError(e.one_line()) from None
    overrides = (
        "" if params.profile == "default" else f" (overrides: {args.params.parent / 'profiles' / params.profile}.yaml)"
    )
    header = f"# {args.params}, profile {params.profile}{overrides}: valid; the resolved config:"
    text = yaml.safe_dump(params.model_dump(mode="json"), sort_keys=False, allow_unicode=True)
    if args.write is not None:  # the whole resolved config, e.g. params.yaml for `dvc repro` on another profile
        from components.core.files import atomic_write_bytes

        atomic_write_bytes(args.write, f"{header}\n{text}".encode())
        print(f"{args.params}, profile {params.profile}: valid; the resolved config written to {args.write}")
    else:
        print(header)
        print(text, end="")
    print("\n".join(_plan_lines(params)))
    return 0


def _plan_lines(params) -> list[str]:
    """The stages' plan on this machine (``components.core.hardware``), as YAML comments: per stage its runner's kind,
    workers, threads per worker and device (``—``: no torch model, or onnxruntime on the CPU). A stage whose workers
    or device this machine cannot give is a line naming the key and what was found (the stage would stop with it at
    its start); the file is valid all the same: a profile for another machine is checked here too."""
    from components.core.hardware import STAGES, cuda_devices_without_torch, stage_plan, usable_cores

    cores, gpus = usable_cores(), cuda_devices_without_torch()  # without torch: the check stays fast
    lines = [f"# the plan on this machine ({cores} usable core{'s' if cores != 1 else ''}, {gpus} CUDA device(s)):"]
    for stage, *_ in STAGES:
        try:
            plan = stage_plan(params, stage, cores, gpus)
        except ValueError as e:
            lines.append(f"#   {stage:<9} cannot run here: {e}")
            continue
        lines.append(
            f"#   {stage:<9} {plan.kind}, {plan.workers} worker{'s' if plan.workers != 1 else ''} × "
            f"{plan.threads} thread{'s' if plan.threads != 1 else ''}, device {plan.device or '—'}"
        )
    return lines


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pidc", description="Physically interpretable, probabilistic domain characterization."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("weather", help="list the weather parameters, their ranges and the presets")
    p.set_defaults(func=_cmd_weather)

    p = sub.add_parser("render", help="render one image of a scene under a weather (embedded simulator)")
    p.add_argument(
        "--preset",
        choices=presets.PRESETS,
        metavar="NAME",
        help="one of CARLA's presets, e.g. ClearNoon (`pidc weather` lists them); then --set overrides",
    )
    p.add_argument(
        "--set", action="append", metavar="NAME=VALUE", help="a weather parameter, e.g. --set fog_density=40"
    )
    p.add_argument("--seed", type=int, help="scene seed (required): same seed, same scene")
    # the default profile's image size (simulator.height/width): the size its models learned from; a model's card
    # names its own (training_renders), and `pidc characterize` says when it resizes other sizes
    p.add_argument("--height", type=int, default=128, help="pixels (default 128: the default profile's models' images)")
    p.add_argument("--width", type=int, default=128, help="pixels (default 128)")
    p.add_argument("-o", "--out", type=Path, default=Path("render.png"), help="PNG path (default: render.png)")
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser("config", help="the pipeline's params file")
    config = p.add_subparsers(dest="config_command", required=True)
    c = config.add_parser("check", help="validate a params file and print its resolved config (runs nothing)")
    c.add_argument(
        "--params",
        type=Path,
        default=Path("params.yaml"),
        metavar="FILE",
        help="the params file (default: params.yaml in the current folder)",
    )
    c.add_argument(
        "--profile",
        metavar="NAME",
        help="the profile to resolve (default: the file's `profile` key); NAME = default or a "
        "file name of profiles/ beside FILE",
    )
    c.add_argument(
        "--write",
        type=Path,
        metavar="OUT",
        help="write the resolved config to OUT instead of printing it (e.g. --profile paper --write "
        "params.yaml switches the pipeline to the paper profile; `git checkout params.yaml` switches back)",
    )
    c.set_defaults(func=_cmd_config_check)

    from components.cli.models import add_model_commands

    add_model_commands(sub)
    from components.cli.record import add_record_command

    add_record_command(sub)
    from components.cli.drive import add_drive_command

    add_drive_command(sub)
    from components.cli.watch import add_watch_command

    add_watch_command(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except CLIError as e:
        print(f"pidc {args.command}: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. `pidc characterize … | head`: the reader left; not an error of ours
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's recipe: no flush error at exit
        return 0
    except MemoryError as e:  # e.g. --samples 500000000: numpy cannot allocate the draws
        print(f"pidc {args.command}: error: {memory_error_line(args, e)}", file=sys.stderr)
        return 2
    except OSError as e:  # a write the early checks could not foresee (a full disk, a folder made meanwhile, …)
        print(f"pidc {args.command}: error: {os_error_line(args, e)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
