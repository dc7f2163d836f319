"""The layout's two import rules (docs/pipeline.md, the design card): the library imports no orchestration, and the
flows stay independent.

* No module of ``components/`` imports Prefect, prefect-dask, DVC or MLflow — anywhere in the file, function-level
  imports and ``importlib.import_module("…")`` included — so every piece is testable and reusable alone; checked by
  parsing every file, and by importing every module in a fresh interpreter and looking at ``sys.modules``.
* No flow imports another flow: ``flows/stage.py`` (what every flow does first), ``flows/tracking.py`` (every MLflow
  call) and ``flows/__init__.py`` are the shared helpers, not flows.

The checkers are tested on small packages written to a temporary folder, with the bad imports they must catch.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

from components.core.code import ROOT

#: the orchestration and tracking packages the library must not import (top-level module names)
FORBIDDEN = frozenset({"prefect", "prefect_dask", "dvc", "mlflow"})
#: the modules of flows/ that every flow may import: they are helpers, not flows
SHARED_FLOW_MODULES = frozenset({"flows", "flows.stage", "flows.tracking"})


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _resolve(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    """The absolute module an ``ImportFrom`` names (relative imports resolved against ``module``)."""
    if node.level == 0:
        return node.module or ""
    base = module.split(".")
    base = base if is_package else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


def imported_modules(path: Path, root: Path) -> set[str]:
    """Every module ``path`` (a file under ``root``) imports anywhere in it: ``import a.b`` gives ``a.b``; ``from a
    import b`` gives ``a`` and ``a.b`` (``b`` may be a module); ``importlib.import_module("x")`` and
    ``__import__("x")`` with a constant name give ``x``."""
    module, is_package = _module_name(path, root), path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(node, module, is_package)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names if alias.name != "*")
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            if name in {"import_module", "__import__"} and isinstance(node.args[0].value, str):
                found.add(node.args[0].value)
    return found


def python_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*.py") if "__pycache__" not in p.parts)


def forbidden_imports(package: Path, root: Path, forbidden: frozenset[str] = FORBIDDEN) -> list[str]:
    """``"<file>: <module>"`` for every import of a ``forbidden`` package (or one of its submodules) in ``package``."""
    bad = []
    for path in python_files(package):
        for name in sorted(imported_modules(path, root)):
            if name.split(".")[0] in forbidden:
                bad.append(f"{path.relative_to(root)}: {name}")
    return bad


def flows_importing_flows(flows: Path, root: Path, shared: frozenset[str] = SHARED_FLOW_MODULES) -> list[str]:
    """``"<flow> imports <flow>"`` for every flow module of ``flows`` that imports another (helpers aside)."""
    package = flows.name
    modules = {_module_name(p, root) for p in python_files(flows)}
    bad = []
    for path in python_files(flows):
        me = _module_name(path, root)
        if me in shared:
            continue
        for name in sorted(imported_modules(path, root)):
            if name.split(".")[0] == package and name in modules and name not in shared and name != me:
                bad.append(f"{me} imports {name}")
    return bad


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")


# --- the checkers catch what they must -----------------------------------------------------------------------------


def test_the_import_checker_finds_every_form_of_a_forbidden_import(tmp_path):
    _write(
        tmp_path,
        {
            "lib/__init__.py": "",
            "lib/clean.py": "import numpy as np\nfrom lib import clean\nimport prefecture\n",
            "lib/top.py": "import mlflow.tracking\n",
            "lib/late.py": "def f():\n    from prefect import flow\n    return flow\n",
            "lib/sub/__init__.py": "",
            "lib/sub/dynamic.py": "import importlib\n\ndef g():\n    return importlib.import_module('dvc.repo')\n",
            "lib/sub/dunder.py": "x = __import__('prefect_dask')\n",
        },
    )
    assert forbidden_imports(tmp_path / "lib", tmp_path) == [
        "lib/late.py: prefect",
        "lib/late.py: prefect.flow",
        "lib/sub/dunder.py: prefect_dask",
        "lib/sub/dynamic.py: dvc.repo",
        "lib/top.py: mlflow.tracking",
    ]


def test_the_flow_checker_finds_a_flow_importing_a_flow_but_not_the_helpers(tmp_path):
    _write(
        tmp_path,
        {
            "flows/__init__.py": "",
            "flows/stage.py": "from flows import tracking\n",
            "flows/tracking.py": "import mlflow\n",
            "flows/train.py": "from flows.stage import run\nfrom flows import tracking\nfrom . import stage\n",
            "flows/evaluate.py": "from flows import train\n",
            "flows/task2.py": "def f():\n    from .evaluate import evaluate\n",
            "flows/task3.py": "import flows.task2\nfrom components.core import paths\n",
        },
    )
    assert flows_importing_flows(tmp_path / "flows", tmp_path) == [
        "flows.evaluate imports flows.train",
        "flows.task2 imports flows.evaluate",
        "flows.task3 imports flows.task2",
    ]


def test_relative_imports_resolve_against_the_module(tmp_path):
    _write(tmp_path, {"a/__init__.py": "from .b import c\n", "a/b/__init__.py": "", "a/b/d.py": "from ..e import f\n"})
    assert imported_modules(tmp_path / "a/__init__.py", tmp_path) == {"a.b", "a.b.c"}
    assert imported_modules(tmp_path / "a/b/d.py", tmp_path) == {"a.e", "a.e.f"}


# --- the rules hold ------------------------------------------------------------------------------------------------


def test_components_import_no_prefect_dvc_or_mlflow_anywhere_in_a_file():
    assert (ROOT / "components").is_dir()
    assert not forbidden_imports(ROOT / "components", ROOT), "components/ must stay free of orchestration"


def test_no_flow_imports_another_flow():
    flows = python_files(ROOT / "flows")
    assert len(flows) > len(SHARED_FLOW_MODULES), "flows/ holds no flow"
    assert not flows_importing_flows(ROOT / "flows", ROOT)


_IMPORT_ALL = """
import importlib, json, pathlib, sys
root = pathlib.Path(sys.argv[1])
names = []
for p in sorted((root / "components").rglob("*.py")):
    if "__pycache__" in p.parts:
        continue
    parts = list(p.relative_to(root).with_suffix("").parts)
    names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
for name in names:
    importlib.import_module(name)
loaded = sorted({m.split(".")[0] for m in sys.modules} & set(sys.argv[2].split(",")))
print(json.dumps({"modules": len(names), "loaded": loaded}))
"""


def test_importing_every_component_module_loads_no_prefect_dvc_or_mlflow():
    """Catches what parsing cannot: a third-party package that imports one of them on the library's behalf."""
    out = subprocess.run(
        [sys.executable, "-c", _IMPORT_ALL, str(ROOT), ",".join(sorted(FORBIDDEN))],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert out.returncode == 0, out.stderr[-4000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["modules"] == len(python_files(ROOT / "components"))
    assert result["loaded"] == [], f"importing components/ loaded {result['loaded']}"


def test_the_import_probe_sees_a_forbidden_package_loaded_on_the_librarys_behalf(tmp_path):
    """The subprocess probe can fail: in a components-like tree whose module imports a third-party package that
    imports a forbidden one (stand-ins, so the test stays fast), the forbidden package shows as loaded."""
    _write(
        tmp_path,
        {
            "components/__init__.py": "",
            "components/sub/__init__.py": "",
            "components/sub/bad.py": "def f():\n    return 1\n\nimport thirdparty\n",
            "site/thirdparty.py": "import orchestra.tracking\n",
            "site/orchestra/__init__.py": "",
            "site/orchestra/tracking.py": "",
        },
    )
    out = subprocess.run(
        [sys.executable, "-c", _IMPORT_ALL, str(tmp_path), "orchestra,prefect"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        env={"PYTHONPATH": f"{tmp_path}:{tmp_path / 'site'}", "PATH": "/usr/bin:/bin"},
    )
    assert out.returncode == 0, out.stderr[-4000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == {"modules": 3, "loaded": ["orchestra"]}
