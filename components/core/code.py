"""The project code a computation depends on: its import closure and a fingerprint of it (standard library only).

A result kept between runs — a finished training checkpoint, a model's Task I evaluation — is valid only for the code
that made it. DVC re-runs a stage when a module it imports changes, but a stage that finds a kept result keyed by its
settings alone would return the old code's result. :func:`code_fingerprint` keys such results by the source of every
project module the computation can import (:func:`import_closure`: ``import`` statements anywhere in a file,
function-level and relative ones included, with the ``__init__.py`` of every package on the way), so an edit redoes
the work and an unchanged code reuses it.

Used by the ``train`` stage (checkpoints), the ``evaluate`` stage (kept evaluations) and the test of ``dvc.yaml``'s
code deps (the same closure).
"""

from __future__ import annotations

import ast
import hashlib
from collections.abc import Iterable
from functools import cache
from pathlib import Path

__all__ = ["ROOT", "module_file", "direct_imports", "import_closure", "code_fingerprint"]

#: The project root: the folder that holds the ``components`` package.
ROOT = Path(__file__).resolve().parents[2]

#: The packages whose modules count as project code (``flows`` only for the test of ``dvc.yaml``).
LIBRARY = ("components",)


def module_file(module: str, packages: tuple[str, ...] = LIBRARY) -> Path | None:
    """The project file of a dotted module name, or None if it is not a module of ``packages``."""
    if module.split(".")[0] not in packages:
        return None
    base = ROOT.joinpath(*module.split("."))
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    if base.with_suffix(".py").is_file():
        return base.with_suffix(".py")
    return None


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def direct_imports(path: Path, packages: tuple[str, ...] = LIBRARY) -> frozenset[Path]:
    """Files of ``packages`` that ``path`` imports anywhere in it (relative imports resolved; importing ``a.b.c``
    runs ``a/__init__.py`` and ``a/b/__init__.py`` too)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = _module_name(path) if path.name == "__init__.py" else _module_name(path).rpartition(".")[0]
    found: set[Path] = set()
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            names = [mod] + [f"{mod}.{a.name}" for a in node.names]  # `from pkg import submodule`
        for name in names:
            parts = name.split(".")
            for i in range(1, len(parts) + 1):
                f = module_file(".".join(parts[:i]), packages)
                if f is not None:
                    found.add(f)
    return frozenset(found)


def import_closure(module: str, packages: tuple[str, ...] = LIBRARY) -> set[Path]:
    """Every file of ``packages`` that importing (or running) ``module`` can import, the module's own included.

    Raises ``ValueError`` naming the module if it is not a module of ``packages``."""
    start = module_file(module, packages)
    if start is None:
        raise ValueError(f"{module!r} is not a module of the project packages {', '.join(packages)}")
    parts = module.split(".")
    todo = [start] + [f for i in range(1, len(parts)) if (f := module_file(".".join(parts[:i]), packages))]
    seen: set[Path] = set()
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        todo.extend(direct_imports(f, packages))
    return seen


def code_fingerprint(modules: Iterable[str], extra: Iterable[str] = ()) -> str:
    """SHA-256 (hex) of the source of every project module that ``modules`` can import (their files' paths relative
    to the project and their bytes, in path order) and of the strings ``extra`` (e.g. library versions)."""
    files = set().union(*(import_closure(m) for m in modules))
    digest = hashlib.sha256()
    for f in sorted(files):
        digest.update(f.relative_to(ROOT).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    for e in extra:
        digest.update(str(e).encode() + b"\0")
    return digest.hexdigest()
