"""The code fingerprint that keys kept results (training checkpoints, kept evaluations): it changes exactly when the
source of a module the computation can import changes."""

from __future__ import annotations

import pytest

from components.core import code


@pytest.fixture
def package(tmp_path, monkeypatch):
    """A project of its own: ``components/{a,b,c}.py`` and ``components/sub/{__init__,d}.py``, where ``a`` imports
    ``b`` at the top, ``sub.d`` inside a function and ``.c`` relatively; nothing imports ``e``."""
    root = tmp_path / "project"
    (root / "components" / "sub").mkdir(parents=True)
    files = {
        "components/__init__.py": "",
        "components/a.py": "from components import b\nfrom . import c\n\ndef f():\n    import components.sub.d\n",
        "components/b.py": "X = 1\n",
        "components/c.py": "import math\n",
        "components/e.py": "Y = 2\n",
        "components/sub/__init__.py": "",
        "components/sub/d.py": "Z = 3\n",
    }
    for name, text in files.items():
        (root / name).write_text(text)
    monkeypatch.setattr(code, "ROOT", root)
    return root


def test_closure_follows_every_import(package):
    found = {p.relative_to(package).as_posix() for p in code.import_closure("components.a")}
    assert found == {
        "components/__init__.py",
        "components/a.py",
        "components/b.py",
        "components/c.py",
        "components/sub/__init__.py",
        "components/sub/d.py",
    }
    with pytest.raises(ValueError, match="'numpy' is not a module of the project packages components"):
        code.import_closure("numpy")


def test_fingerprint_changes_with_imported_code_only(package):
    before = code.code_fingerprint(["components.a"])
    assert code.code_fingerprint(["components.a"]) == before  # deterministic
    (package / "components/e.py").write_text("Y = 3\n")  # not imported by a
    assert code.code_fingerprint(["components.a"]) == before
    (package / "components/sub/d.py").write_text("Z = 4\n")  # imported inside a function
    edited = code.code_fingerprint(["components.a"])
    assert edited != before
    assert code.code_fingerprint(["components.a"], extra=["torch 2.9"]) != edited
    assert code.code_fingerprint(["components.a", "components.e"]) != edited


def test_training_code_covers_the_model_and_a_trained_backbone():
    from components.features.backbones import get_backbone
    from flows.train import training_code

    closure = {p.relative_to(code.ROOT).as_posix() for p in code.import_closure("components.posterior.train")}
    assert {
        "components/posterior/model.py",
        "components/posterior/loss.py",
        "components/posterior/bijection.py",
        "components/posterior/mixture.py",
    } <= closure
    cues, cnn = get_backbone("cues"), get_backbone("cnn")
    assert training_code(cues) == training_code(get_backbone("tiny")), "a frozen backbone enters by its features"
    assert training_code(cnn) != training_code(cues), "the cnn's network is part of the trained model"
