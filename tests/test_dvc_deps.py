"""dvc.yaml's code deps follow the imports: every stage declares exactly the project modules its flow can import.

A stage's command runs ``python -m flows.<name>``; its import closure is that module and every ``components`` /
``flows`` module it reaches through ``import`` statements anywhere in a file (function-level imports included),
with the ``__init__.py`` of every package on the way. Each module of the closure must be declared as a dep of the
stage (the file or a parent folder), and each declared code dep must hold only modules of the closure — so editing a
module re-runs exactly the stages that import it. The stages are read through DVC's own API (foreach and matrix
expanded).
"""

from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("components", "flows")


def module_file(module: str) -> Path | None:
    """The project file of a dotted module name, or None if it is not a project module."""
    if module.split(".")[0] not in PACKAGES:
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
def direct_imports(path: Path) -> frozenset[Path]:
    """Project files that ``path`` imports anywhere in it (relative imports resolved)."""
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
            for i in range(1, len(parts) + 1):  # importing a.b.c runs a/__init__, a/b/__init__, …
                f = module_file(".".join(parts[:i]))
                if f is not None:
                    found.add(f)
    return frozenset(found)


def closure(module: str) -> set[Path]:
    """Every project file that running ``python -m <module>`` can import."""
    start = module_file(module)
    assert start is not None, module
    todo, seen = [start], set()
    parts = module.split(".")
    todo += [f for i in range(1, len(parts)) if (f := module_file(".".join(parts[:i])))]
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        todo.extend(direct_imports(f))
    return seen


def code_files(dep: Path) -> set[Path]:
    """The Python files a declared dep covers (the file, or every file below the folder)."""
    if dep.is_file():
        return {dep} if dep.suffix == ".py" else set()
    return {p for p in dep.rglob("*.py") if "__pycache__" not in p.parts}


def stages() -> list[tuple[str, str, list[Path]]]:
    """``(stage name, flow module, declared deps)`` of every stage of dvc.yaml, through DVC's API."""
    from dvc.repo import Repo

    repo = Repo(str(ROOT))
    try:
        out = []
        for stage in repo.index.stages:
            m = re.search(r"python -m (flows\.\w+)", stage.cmd)
            assert m, f"stage {stage.addressing}: its command {stage.cmd!r} does not run a flow module"
            out.append((stage.addressing, m.group(1), [Path(d.fs_path) for d in stage.deps]))
        return out
    finally:
        repo.close()


STAGES = stages()


def test_every_stage_is_checked():
    names = {s for s, _, _ in STAGES}
    assert {"generate", "train", "export", "evaluate", "task2", "task3"} <= names


@pytest.mark.parametrize("name, module, deps", STAGES, ids=[s for s, _, _ in STAGES])
def test_stage_declares_exactly_its_imports(name, module, deps):
    needed = closure(module)
    declared = set().union(*(code_files(d) for d in deps))
    missing = sorted(str(p.relative_to(ROOT)) for p in needed - declared)
    assert not missing, f"dvc.yaml stage {name!r} runs {module} but does not declare: {', '.join(missing)}"
    extra = sorted(str(p.relative_to(ROOT)) for p in declared - needed)
    assert not extra, (
        f"dvc.yaml stage {name!r} declares code that {module} never imports (editing it would re-run "
        f"the stage for nothing): {', '.join(extra)}"
    )


def test_closure_follows_function_level_and_relative_imports(tmp_path):
    # the simulator's factory imports the renderers inside a function; the renderer imports its physics relatively
    files = {str(p.relative_to(ROOT)) for p in closure("flows.generate")}
    assert "components/simulate/carla.py" in files  # function-level import in make_simulator
    assert "components/simulate/procedural/shadows.py" in files  # relative import in the renderer
    assert "components/__init__.py" in files and "flows/__init__.py" in files


def test_no_flow_imports_another_flow():
    helpers = {ROOT / "flows" / "__init__.py", ROOT / "flows" / "stage.py", ROOT / "flows" / "tracking.py"}
    for flow_file in sorted((ROOT / "flows").glob("*.py")):
        if flow_file in helpers:
            continue
        others = {f for f in direct_imports(flow_file) if f.parent == ROOT / "flows"} - helpers
        assert not others, f"{flow_file.name} imports the flow(s) {[f.name for f in others]}"


def test_no_import_circle():
    files = [p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py") if "__pycache__" not in p.parts]
    graph = {f: {g for g in direct_imports(f) if g.name != "__init__.py" and g != f} for f in files}
    # a package's __init__ re-exporting its modules is not a circle; module ↔ module is
    index, low, stack, on, circles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                circles.append(sorted(str(p.relative_to(ROOT)) for p in comp))

    for f in files:
        if f not in index:
            visit(f)
    assert not circles, f"import circles: {circles}"


def test_training_stages_declare_every_training_setting():
    """The train stage trains every model of the grid and its variants: changing any ``train`` setting in params.yaml
    (and the backbones trained) must re-run it."""
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    from components.core.config import TrainConfig

    wanted = {f"train.{k}" for k in TrainConfig.model_fields} | {"backbones.names"}
    repo = Repo(str(ROOT))
    try:
        training = [s for s in repo.index.stages if s.addressing == "train"]
        assert training, "dvc.yaml has no train stage"
        for stage in training:
            declared = {key for d in stage.deps if isinstance(d, ParamsDependency) for key in d.params}
            missing = sorted(k for k in wanted if k not in declared and "train" not in declared)
            assert not missing, f"dvc.yaml stage {stage.addressing!r} does not declare the params {missing}"
    finally:
        repo.close()
