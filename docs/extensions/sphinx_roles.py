"""A griffe extension for the API reference (mkdocs.yml): the Sphinx roles of pidc's docstrings as links.

The docstrings name other objects the Sphinx way, ``:class:`~components.domains.absolute.Domain``` or
``:func:`relate```, which Markdown would show as the raw role. This extension rewrites each role, before the
docstrings are parsed, into the object's name in code, linked to its entry of the API reference when the name resolves
to an object of the ``components`` package (full paths, or names relative to the object whose docstring it is and its
parents). A link to an object that no page renders stays plain code: the links are optional, so they never fail the
strict build.
"""

from __future__ import annotations

import html
import re
from typing import Any

import griffe

_ROLE = re.compile(
    r":(?:py:)?(?P<role>mod|class|func|meth|attr|data|exc|obj|const):`(?P<tilde>~?)(?P<target>[\w.]+)(?:\(\))?`"
)
_PACKAGE = "components"


class SphinxRoles(griffe.Extension):
    """Rewrite ``:role:`target``` in every docstring of the package into linked inline code."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        if pkg.name != _PACKAGE:
            return
        for obj in _objects(pkg):
            if obj.docstring is not None and ":" in obj.docstring.value:
                obj.docstring.value = _ROLE.sub(lambda m, o=obj: _replace(m, o, pkg), obj.docstring.value)


def _objects(obj: griffe.Object) -> list[griffe.Object]:
    """``obj`` and every object defined under it (aliases, i.e. re-exports, are documented where they are defined)."""
    found = [obj]
    for member in obj.members.values():
        if not member.is_alias:
            found += _objects(member)  # type: ignore[arg-type]
    return found


def _lookup(pkg: griffe.Module, path: str) -> str | None:
    """The canonical path of the package's object ``path`` (dotted, from the package's name), or None."""
    if path == _PACKAGE:
        return path
    if not path.startswith(_PACKAGE + "."):
        return None
    try:
        return pkg[path[len(_PACKAGE) + 1 :]].canonical_path
    except (KeyError, griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None


def _resolve(target: str, obj: griffe.Object, pkg: griffe.Module) -> str | None:
    """The canonical path that ``target`` names, seen from the docstring of ``obj``: itself, or relative to ``obj``
    and each of its parents (a method's ``:meth:`sample``` is its class's ``sample``)."""
    if target.startswith(_PACKAGE + ".") or target == _PACKAGE:
        return _lookup(pkg, target)
    scope: griffe.Object | None = obj
    while scope is not None:
        found = _lookup(pkg, f"{scope.path}.{target}")
        if found is not None:
            return found
        scope = scope.parent
    return None


def _replace(match: re.Match[str], obj: griffe.Object, pkg: griffe.Module) -> str:
    target = match["target"]
    title = target.rsplit(".", 1)[-1] if match["tilde"] else target
    if match["role"] in ("func", "meth"):
        title += "()"
    code = f"<code>{html.escape(title)}</code>"
    identifier = _resolve(target, obj, pkg)
    if identifier is None:
        return code
    return f'<autoref identifier="{html.escape(identifier)}" optional>{code}</autoref>'
