"""Write the settings reference, ``docs/reference/settings.md``: every key of ``params.yaml`` with its type and allowed
values, its default, the profiles that change it, and its meaning, grouped by section.

    python scripts/settings_page.py            # rewrite docs/reference/settings.md
    python scripts/settings_page.py --check    # exit 1 when the page differs from what a fresh generation writes

A setting's meaning has one home: the docstring under its field in ``components/core/config.py`` (pydantic reads it
into the field's ``description``). Types and allowed values come from the fields' annotations and constraints,
defaults from ``params.yaml`` as written, and overrides from ``profiles/*.yaml`` merged over it as
:func:`components.core.config.load_params` merges them. The script fails, naming the key, when a key of the params
file is no field of the config, or a field has no meaning; ``tests/test_settings_docs.py`` runs both checks.

Key paths are dotted (``train.flow.context_layers``); ``<name>`` stands for an entry of a mapping whose keys the user
names (``task3.bags.<name>.box``), ``[]`` for an item of a list of sections (``task2.modes[].weight``); their
defaults are shown whole on the mapping's or list's own row.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# isort: off
import components  # noqa: E402,F401  first, before numpy: it pins numpy's SIMD kernels (the pipeline's images)

# isort: on
import argparse  # noqa: E402
import re  # noqa: E402
import types  # noqa: E402
import typing  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

import annotated_types as at  # noqa: E402
import yaml  # noqa: E402
from pydantic import BaseModel  # noqa: E402
from pydantic.fields import FieldInfo  # noqa: E402

from components.core import config  # noqa: E402

#: the page, relative to the project root
PAGE = Path("docs/reference/settings.md")

#: a key path segment standing for any entry of a mapping of user-named sections, and for any item of a list
NAMED, ITEM = "<name>", "[]"

_MISSING = object()


@dataclass
class Setting:
    """One row of the page: a key path, its type and allowed values, its default and the profiles' values, its
    meaning. ``default`` is ``params.yaml``'s value, or ``_MISSING`` under ``<name>``/``[]`` (shown on the parent)."""

    path: str
    kind: str
    meaning: str
    section: bool
    default: object = _MISSING
    overrides: dict[str, object] = field(default_factory=dict)


def _sections_in(annotation: object) -> list[type[BaseModel]]:
    """The section models of a field's annotation (``X``, ``X | None``)."""
    args = typing.get_args(annotation) if typing.get_origin(annotation) in (typing.Union, types.UnionType) else ()
    return [t for t in (annotation, *args) if isinstance(t, type) and issubclass(t, BaseModel)]


def _metadata(constraint: object) -> list[object]:
    """A constraint's parts: a ``Field(gt=0)`` inside an ``Annotated`` is its metadata, anything else itself."""
    return list(constraint.metadata) if isinstance(constraint, FieldInfo) else [constraint]


def _bounds(constraints: list[object]) -> str:
    """The numeric bounds and length or pattern constraints of a type, in words (`` > 0``, `` in [16, 2048]``)."""
    low = high = None
    words = []
    for c in constraints:
        for m in _metadata(c):
            if isinstance(m, at.Gt | at.Ge):
                low = ("(" if isinstance(m, at.Gt) else "[", m.gt if isinstance(m, at.Gt) else m.ge)
            elif isinstance(m, at.Lt | at.Le):
                high = (")" if isinstance(m, at.Lt) else "]", m.lt if isinstance(m, at.Lt) else m.le)
            elif isinstance(m, at.MinLen) and m.min_length:
                words.append(f"at least {m.min_length} item{'s' if m.min_length > 1 else ''}")
            elif getattr(m, "pattern", None):
                words.append(f"matching `{m.pattern}`")
    if low and high:
        words.insert(0, f"in {low[0]}{low[1]:g}, {high[1]:g}{high[0]}")
    elif low:
        words.insert(0, f"{'>' if low[0] == '(' else '≥'} {low[1]:g}")
    elif high:
        words.insert(0, f"{'<' if high[0] == ')' else '≤'} {high[1]:g}")
    return (" " + ", ".join(words)) if words else ""


def describe(annotation: object, constraints: list[object] | None = None) -> str:
    """A field's type and allowed values in words, from its annotation and its constraints (``Field(gt=0)`` …).

    Arguments:
        annotation: the field's type (``FieldInfo.annotation``), possibly ``Annotated`` with constraints.
        constraints: constraints already split off the annotation (``FieldInfo.metadata``).

    Returns:
        e.g. ``integer > 0``, ``list of integer > 0``, ```cosine`, `plateau` or `constant```, ``number or null``.
    """
    constraints = list(constraints or [])
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Annotated:
        return describe(args[0], [*constraints, *args[1:]])
    if annotation is type(None):
        return "null"
    if origin in (typing.Union, types.UnionType):
        parts = [describe(a) for a in args if a is not type(None)]
        if type(None) in args:
            parts.append("null")
        return " or ".join(parts)
    if origin is typing.Literal:
        values = [f"`{v}`" for v in args]
        return values[0] if len(values) == 1 else f"{', '.join(values[:-1])} or {values[-1]}"
    if annotation is bool:
        return "`true` or `false`"
    if annotation is int:
        return "integer" + _bounds(constraints)
    if annotation is float:
        return "number" + _bounds(constraints)
    if annotation is str:
        min_length = [m for c in constraints for m in _metadata(c) if isinstance(m, at.MinLen) and m.min_length]
        rest = [m for c in constraints for m in _metadata(c) if m not in min_length]
        return ("non-empty text" if min_length else "text") + _bounds(rest)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            least = [m for c in constraints for m in _metadata(c) if isinstance(m, at.MinLen) and m.min_length]
            rest = [m for c in constraints for m in _metadata(c) if m not in least]
            items = f"list of {describe(args[0])}" + _bounds(rest)
            return f"non-empty {items}" if least and least[0].min_length == 1 else items + _bounds(least)
        return f"[{', '.join(describe(a) for a in args)}]"
    if origin is dict:
        return f"mapping: {describe(args[0])} → {describe(args[1])}"
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return "section"
    raise TypeError(f"no description of the type {annotation!r}: teach scripts/settings_page.py's describe()")


def _meaning(info: FieldInfo, sections: list[type[BaseModel]]) -> str:
    """A field's docstring on one line; for a section without one, its model's docstring (first paragraph)."""
    text = info.description or ""
    if not text and sections:
        text = (sections[0].__doc__ or "").split("\n\n")[0]
    return " ".join(text.split())


def collect(
    model: type[BaseModel], data: object, prefix: str = "", meanings: bool = True
) -> tuple[list[Setting], list[str]]:
    """The settings of ``model`` (and its sections, recursively) with the defaults of ``data``.

    Arguments:
        model: a section model of :mod:`components.core.config` (:class:`~components.core.config.Params` for all).
        data: the section's mapping in the params file (``_MISSING`` under ``<name>`` and ``[]`` paths).
        prefix: the dotted path of the section (``""`` for the top level, ``"train."`` …).
        meanings: report the fields without a meaning (once, under ``<name>``/``[]``, not per entry).

    Returns:
        The rows in the config's order, and the problems: keys of ``data`` that are no field of ``model`` and fields
        without a meaning, each naming its key path.
    """
    rows: list[Setting] = []
    problems: list[str] = []
    values = data if isinstance(data, dict) else {}
    for key in values:
        if key not in model.model_fields:
            problems.append(
                f"{prefix}{key}: a key of the params file but no field of {model.__name__} in components/core/config.py"
            )
    for name, info in model.model_fields.items():
        path = f"{prefix}{name}"
        sections = _sections_in(info.annotation)
        value = values.get(name, _MISSING) if data is not _MISSING else _MISSING
        row = Setting(path, describe(info.annotation, info.metadata), _meaning(info, sections), bool(sections))
        if not sections:
            row.default = value
        if meanings and not row.meaning:
            problems.append(
                f"{path}: no meaning (write it as the docstring under {model.__name__}.{name} in "
                "components/core/config.py)"
            )
        rows.append(row)
        origin, args = typing.get_origin(info.annotation), typing.get_args(info.annotation)
        if sections:
            sub = value if isinstance(value, dict) else _MISSING
            more, issues = collect(sections[0], sub, f"{path}.", meanings)
        elif origin is dict and _sections_in(args[1]):
            more, issues = collect(_sections_in(args[1])[0], _MISSING, f"{path}.{NAMED}.", meanings)
            for entry, sub in value.items() if isinstance(value, dict) else ():
                problems += collect(_sections_in(args[1])[0], sub, f"{path}.{entry}.", False)[1]
        elif origin is tuple and args and _sections_in(args[0]):
            more, issues = collect(_sections_in(args[0])[0], _MISSING, f"{path}{ITEM}.", meanings)
            for k, sub in enumerate(value if isinstance(value, list) else ()):
                problems += collect(_sections_in(args[0])[0], sub, f"{path}.{k}.", False)[1]
        else:
            more, issues = [], []
        rows += more
        problems += issues
    return rows, problems


def _get(data: object, path: str) -> object:
    for key in path.split("."):
        if not isinstance(data, dict) or key not in data:
            return _MISSING
        data = data[key]
    return data


def settings(params_path: Path | None = None) -> tuple[list[Setting], list[str], list[str]]:
    """Every setting of a params file (default: the project's ``params.yaml``) with each profile's changes.

    Returns:
        The rows, the problems (see :func:`collect`; a profile that does not validate is one too) and the profiles'
        names (those of ``profiles/*.yaml`` beside the file).
    """
    p = Path(params_path) if params_path is not None else config.PROJECT_ROOT / "params.yaml"
    data = yaml.safe_load(p.read_text(encoding="utf-8"))
    rows, problems = collect(config.Params, data)
    profiles = [n for n in config.profile_names(p) if n != config.DEFAULT_PROFILE]
    for name in profiles:
        try:
            config.load_params(p, profile=name)
        except config.ConfigError as e:
            problems.append(f"profile {name}: {e.one_line()}")
            continue
        overrides = yaml.safe_load((p.parent / "profiles" / f"{name}.yaml").read_text(encoding="utf-8")) or {}
        merged = config._merge(data, overrides, "", [])
        for row in rows:
            value = _get(merged, row.path)
            if row.section:  # a section is shown by its keys, unless a profile sets it to null
                if not isinstance(value, dict) and value is not _MISSING and value != _get(data, row.path):
                    row.overrides[name] = value
            elif row.default is not _MISSING and value != row.default:
                row.overrides[name] = value
    return rows, problems, profiles


def yaml_value(v: object) -> str:
    """A value as YAML writes it on one line (flow style): ``null``, ``true``, ``[256, 256, 128]``, ``{b: 1}``."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list | tuple):
        return f"[{', '.join(yaml_value(x) for x in v)}]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {yaml_value(x)}" for k, x in v.items()) + "}"
    return str(v)


def _cell(text: str) -> str:
    """``text`` for a table cell: a ``|`` outside code spans escaped (one inside a code span cannot be)."""
    parts = re.split(r"(`+[^`]*`+)", text)
    if any("|" in part for part in parts[1::2]):
        raise ValueError(f"a table cell cannot hold '|' in a code span: {text!r} (write 'or' in the docstring)")
    return "".join(part if k % 2 else part.replace("|", "\\|") for k, part in enumerate(parts))


def _links(text: str, docs: Path) -> str:
    """``text`` with each ``docs/<page>.md`` it names made a link from the page (``../<page>.md``); a page that
    does not exist is an error (the site's strict build would fail on the link)."""

    def link(m: re.Match[str]) -> str:
        page = m.group(1)
        if not (docs / page).is_file():
            raise ValueError(f"{m.group(0)} is named in a setting's meaning but does not exist")
        return f"[{page.removesuffix('.md')}](../{page})"

    return re.sub(r"\bdocs/([\w/-]+\.md)\b", link, text)


def _row(s: Setting) -> str:
    if s.section:
        default = "(section)"
    elif s.default is _MISSING:
        default = "(per entry)" if NAMED in s.path or ITEM in s.path else "—"
    else:
        default = f"`{yaml_value(s.default)}`"
    for name, value in s.overrides.items():
        default += f"<br>*{name}:* `{yaml_value(value)}`"
    meaning = _links(_cell(s.meaning), ROOT / "docs")
    return f"| `{s.path}` | {_cell(s.kind)} | {_cell(default)} | {meaning} |"


_HEADER = """\
# Settings

<!-- Generated by scripts/settings_page.py from components/core/config.py, params.yaml and profiles/: do not edit.
     Rewrite it with `python scripts/settings_page.py`; tests/test_settings_docs.py fails on a stale page. -->

Every setting of the pipeline is a key of `params.yaml`, and every key is listed here: its type and allowed values,
its default (the value in `params.yaml`), the value each profile gives it where the profile changes it, and its
meaning. The meanings are the docstrings of the fields of `components/core/config.py`, the code that parses the file;
an unknown key, a missing key or a bad value is an error naming the key. Check a params file and a profile without
running anything with `pidc config check [--params FILE] [--profile NAME]`; profiles are described in
[Profiles and scaling](../profiles.md).

Key paths are dotted; `<name>` stands for any entry of a mapping whose keys you choose (`task3.bags.<name>.box`) and
`[]` for any item of a list (`task2.modes[].weight`): their defaults are shown whole on the mapping's or the list's
own row.
"""


def render(rows: list[Setting], profiles: list[str]) -> str:
    """The page: an introduction, then one table per top-level section of ``params.yaml``."""
    out = [_HEADER]
    if profiles:
        out.append(f"Profiles: {', '.join(f'`{n}` (`profiles/{n}.yaml`)' for n in profiles)}.\n")
    table = "| Key | Type and allowed values | Default | Meaning |\n| --- | --- | --- | --- |"
    top = [s for s in rows if "." not in s.path and not s.section]
    out += ["## Top level\n", table, *(_row(s) for s in top), ""]
    for s in rows:
        if "." in s.path or not s.section:
            continue
        out += [f"## `{s.path}`\n", s.meaning + "\n", table]
        out += [_row(r) for r in rows if r.path.startswith(f"{s.path}.")]
        out.append("")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when the page is stale; write nothing")
    parser.add_argument("--params", type=Path, default=None, help="the params file (default: the project's)")
    parser.add_argument("--page", type=Path, default=ROOT / PAGE, help=f"the page (default: {PAGE})")
    args = parser.parse_args(argv)
    rows, problems, profiles = settings(args.params)
    if problems:
        print("settings without documentation:\n  " + "\n  ".join(problems), file=sys.stderr)
        return 1
    text = render(rows, profiles)
    if args.check:
        current = args.page.read_text(encoding="utf-8") if args.page.is_file() else None
        if current != text:
            print(f"{args.page} is stale: rewrite it with python scripts/settings_page.py", file=sys.stderr)
            return 1
        print(f"{args.page}: up to date ({len(rows)} settings)")
        return 0
    args.page.parent.mkdir(parents=True, exist_ok=True)
    args.page.write_text(text, encoding="utf-8")
    print(f"wrote {args.page} ({len(rows)} settings)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
