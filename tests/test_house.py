"""The house rules of the repository's front pages (CONTRIBUTING.md): the README is a front door (small, no run
history), BENCHMARKS.md indexes every re-runnable benchmark, and every study record is reachable from its index."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# marks of a lab notebook: an ISO date, a commit hash (7-40 hex digits with a letter and a digit), an issue number
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
COMMIT = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
ISSUE = re.compile(r"(?<![\w&/])#\d+\b")


def notebook_marks(text: str) -> list[str]:
    """The dates, commit hashes, issue numbers and ``../shared`` paths in ``text``, in order."""
    marks = [m.group() for pattern in (DATE, COMMIT, ISSUE) for m in pattern.finditer(text)]
    return marks + ["../shared"] * text.count("../shared")


def test_notebook_marks_are_found() -> None:
    text = "run of 2026-12-01 at commit 9643f5a (issue #54) with ../shared/paper; 1280 features, colour #fff"
    assert notebook_marks(text) == ["2026-12-01", "9643f5a", "#54", "../shared"]
    assert notebook_marks("ResNet-50 reads 1280-dimensional features at 128 px") == []


def test_readme_is_a_front_door() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.encode()) <= 15 * 1024
    assert notebook_marks(readme) == []
    for command in ("bash run.sh", "bash .ci/run"):
        assert command in readme


def test_benchmarks_index_names_every_benchmark() -> None:
    index = (ROOT / "BENCHMARKS.md").read_text(encoding="utf-8")
    assert len(index.encode()) <= 40 * 1024
    scripts = sorted((ROOT / "benchmarks").glob("*.py"))
    assert scripts
    missing = [p.name for p in scripts if f"benchmarks/{p.name}" not in index]
    assert missing == []


@pytest.mark.parametrize("folder", ["benchmarks/studies", "docs/studies"])
def test_studies_are_apart(folder: str) -> None:
    assert any((ROOT / folder).iterdir())


def test_every_study_record_is_in_the_index() -> None:
    studies = ROOT / "docs" / "studies"
    index = (studies / "index.md").read_text(encoding="utf-8")
    linked = set(re.findall(r"\]\(([\w.-]+\.md)\)", index))
    records = {p.name for p in studies.glob("*.md")} - {"index.md"}
    assert records - linked == set()
    assert linked - records == set()


def test_scripts_named_by_the_docs_exist() -> None:
    named = set()
    for page in [*(ROOT / "docs").rglob("*.md"), ROOT / "BENCHMARKS.md", ROOT / "README.md"]:
        named |= set(re.findall(r"\bbenchmarks/(?:studies/)?[\w-]+\.py\b", page.read_text(encoding="utf-8")))
    assert named
    assert sorted(p for p in named if not (ROOT / p).is_file()) == []
