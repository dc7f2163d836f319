"""dvc.yaml's code deps follow the imports: every stage declares exactly the project modules its flow can import.

A stage's command runs ``python -m flows.<name>``; its import closure is that module and every ``components`` /
``flows`` module it reaches through ``import`` statements anywhere in a file (function-level imports included),
with the ``__init__.py`` of every package on the way. Each module of the closure must be declared as a dep of the
stage (the file or a parent folder), and each declared code dep must hold only modules of the closure — so editing a
module re-runs exactly the stages that import it. The stages are read through DVC's own API (foreach and matrix
expanded).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from components.core import code
from components.core.code import ROOT, import_closure

PACKAGES = ("components", "flows")


def closure(module: str) -> set[Path]:
    """Every project file that running ``python -m <module>`` can import (the closure the checkpoints' and the kept
    evaluations' code fingerprints hash, over the flows too)."""
    return import_closure(module, PACKAGES)


def direct_imports(path: Path) -> frozenset[Path]:
    """Project files (components and flows) that ``path`` imports anywhere in it."""
    return code.direct_imports(path, PACKAGES)


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
