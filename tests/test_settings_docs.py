"""One home per setting's meaning: every key of params.yaml is documented by the docstring of its field in
components/core/config.py, and the settings page (docs/reference/settings.md, written by scripts/settings_page.py)
lists every key with its type, its default and the profiles' values. A key added without documentation fails here,
and so does a page that was not regenerated."""

import subprocess
import sys
import typing
from pathlib import Path

import pytest
import yaml

from components.core import config
from components.core.config import PROJECT_ROOT, PositiveInt

sys.path.insert(0, str(PROJECT_ROOT / "scripts"))
import settings_page  # noqa: E402

PAGE = PROJECT_ROOT / settings_page.PAGE
PARAMS_FILES = [PROJECT_ROOT / "params.yaml", *sorted((PROJECT_ROOT / "profiles").glob("*.yaml"))]


def _keys(d: object, where: str = "") -> dict[str, object]:
    """Every key path of nested mappings, the intermediate ones too; the items of a list of mappings are ``[]``."""
    out: dict[str, object] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            key = f"{where}.{k}" if where else str(k)
            out[key] = v
            out |= _keys(v, key)
    elif isinstance(d, list) and d and all(isinstance(x, dict) for x in d):
        for x in d:
            out |= {k: v for k, v in _keys(x, f"{where}[]").items() if k not in out}
    return out


def _segments(path: str) -> list[str]:
    return path.replace("[]", ".[]").split(".")


def _matches(row_path: str, key: str) -> bool:
    """Whether a row's path (``<name>`` for any entry, ``[]`` for any item) is the key's path."""
    a, b = _segments(row_path), _segments(key)
    return len(a) == len(b) and all(x == y or x == settings_page.NAMED for x, y in zip(a, b, strict=True))


def _row_for(rows: list[settings_page.Setting], key: str) -> tuple[settings_page.Setting, list[str]]:
    """The row documenting ``key``: its own, or the row of the mapping it lies in (``prior`` for
    ``prior.cloudiness``), with the segments of the key below that row."""
    segments = _segments(key)
    for n in range(len(segments), 0, -1):
        head = ".".join(segments[:n]).replace(".[]", "[]")
        found = [r for r in rows if _matches(r.path, head)]
        if found:
            row = found[0]
            assert n == len(segments) or not row.section, f"{key}: under section {row.path} but no row of its own"
            return row, segments[n:]
    raise AssertionError(f"{key}: no row of the settings page documents it")


def _line(page: str, path: str) -> str:
    """The page's row of a key; for a top-level section, its heading."""
    lines = [line for line in page.splitlines() if line.startswith((f"| `{path}` |", f"## `{path}`"))]
    assert len(lines) == 1, f"{path}: {len(lines)} rows on the page"
    return lines[0]


@pytest.fixture(scope="module")
def generated() -> tuple[list[settings_page.Setting], list[str], list[str], str]:
    rows, problems, profiles = settings_page.settings()
    return rows, problems, profiles, settings_page.render(rows, profiles)


def test_every_key_of_params_is_documented_and_on_the_page(generated):
    rows, problems, _profiles, page = generated
    assert problems == []
    data = yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())
    keys = _keys(data)
    assert {"train.flow.context_layers", "task3.bags.b0.box", "task2.modes[].weight", "prior.cloudiness"} <= set(keys)
    for key, value in keys.items():
        row, below = _row_for(rows, key)
        assert row.meaning.strip(), f"{key}: documented without a meaning"
        line = _line(page, row.path)
        if not below and not row.section and settings_page.NAMED not in row.path and "[]" not in row.path:
            assert f"`{settings_page.yaml_value(value)}`" in line, f"{key}: its default is not on its row"
        # a key inside a mapping (or an entry, or a list's item) shows in the default of the nearest concrete row
        concrete = [
            r for r in rows if not r.section and (key == r.path or key.startswith((f"{r.path}.", f"{r.path}[")))
        ]
        if below or settings_page.NAMED in row.path or "[]" in row.path:
            assert concrete, f"{key}: no row shows its value"
            shown = _line(page, max(concrete, key=lambda r: len(r.path)).path)
            nearest = max(concrete, key=lambda r: len(r.path)).path
            for segment in _segments(key)[len(_segments(nearest)) :]:
                assert segment == "[]" or f"{segment}:" in shown, f"{key}: {segment} not in the row of {nearest}"


def test_every_field_of_the_config_has_a_meaning(generated):
    rows, _problems, _profiles, page = generated
    assert len(rows) > 100
    for row in rows:
        assert row.meaning.strip(), row.path
        assert _line(page, row.path)
    # the meaning is the field's docstring, read by pydantic
    assert "AdamW" in config.TrainConfig.model_fields["lr"].description


def test_each_profiles_changes_are_shown_on_their_rows(generated):
    rows, _problems, profiles, page = generated
    assert set(profiles) == {p.stem for p in (PROJECT_ROOT / "profiles").glob("*.yaml")} >= {"paper", "camera"}
    default = yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())
    for name in profiles:
        overrides = yaml.safe_load((PROJECT_ROOT / "profiles" / f"{name}.yaml").read_text())
        merged = config._merge(default, overrides, "", [])
        within_named = tuple(f"{m}." for m in config.NAMED_MAPPINGS)  # replaced whole: the mapping's own row
        changed = [
            k
            for k, v in _keys(overrides).items()
            if (not isinstance(v, dict) or k in config.NAMED_MAPPINGS) and not k.startswith(within_named)
        ]
        assert changed, name
        for key in changed:
            if settings_page._get(merged, key) == settings_page._get(default, key):
                continue
            row, _ = _row_for(rows, key)
            assert f"*{name}:* `{settings_page.yaml_value(settings_page._get(merged, row.path))}`" in _line(
                page, row.path
            ), f"{name}: {key}"
    assert "*paper:* `224`" in _line(page, "simulator.height")
    assert "*camera:* `[128, 384]`" in _line(page, "simulator.render_sizes")
    assert "*paper:* `{balanced: {backbone: resnet50," in _line(page, "train.variants")


def test_the_committed_page_is_a_fresh_generation(generated, tmp_path: Path):
    _rows, _problems, _profiles, page = generated
    assert PAGE.read_text(encoding="utf-8") == page, "stale: run python scripts/settings_page.py"
    script = [sys.executable, str(PROJECT_ROOT / "scripts" / "settings_page.py"), "--check"]
    assert subprocess.run(script, capture_output=True, text=True).returncode == 0
    stale = tmp_path / "settings.md"
    stale.write_text(page.replace("| `seed` |", "| `seed` (old) |"), encoding="utf-8")
    run = subprocess.run([*script, "--page", str(stale)], capture_output=True, text=True)
    assert run.returncode == 1 and "stale" in run.stderr
    assert stale.read_text(encoding="utf-8") != page  # --check writes nothing


def test_a_key_added_without_documentation_is_caught(tmp_path: Path):
    data = yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())
    data["train"]["flow"]["dropout"] = 0.1
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump(data, sort_keys=False))
    _rows, problems, _profiles = settings_page.settings(params)
    assert [p for p in problems if p.startswith("train.flow.dropout: ")], problems
    assert settings_page.main(["--check", "--params", str(params), "--page", str(tmp_path / "page.md")]) == 1

    # a field written into the config without a docstring: no meaning; with one, documented
    class Undocumented(config.FlowParams):
        dropout: float

    class Documented(config.FlowParams):
        dropout: float
        """the dropout rate of the conditioners"""

    section = data["train"]["flow"]
    assert settings_page.collect(Undocumented, section)[1] == [
        "dropout: no meaning (write it as the docstring under Undocumented.dropout in components/core/config.py)"
    ]
    rows, problems = settings_page.collect(Documented, section)
    assert problems == [] and rows[-1].meaning == "the dropout rate of the conditioners"


def test_types_and_allowed_values_in_words():
    describe = settings_page.describe
    assert describe(PositiveInt) == "integer > 0"
    assert describe(typing.Literal["cosine", "plateau", "constant"]) == "`cosine`, `plateau` or `constant`"
    field = config.EvaluateConfig.model_fields["images"]
    assert describe(field.annotation, field.metadata) == "integer > 0 or `all`"
    field = config.ExportConfig.model_fields["champion_max_calibration_error"]
    assert describe(field.annotation, field.metadata) == "number in (0, 1]"
    field = config.FlowParams.model_fields["passes"]
    assert describe(field.annotation, field.metadata) == "integer in [2, 6] or null"
    assert describe(tuple[PositiveInt, ...]) == "list of integer > 0"


@pytest.mark.parametrize("path", [p.relative_to(PROJECT_ROOT).as_posix() for p in PARAMS_FILES])
def test_params_files_say_unit_and_values_only(path: str):
    """params.yaml and the profiles: lines of at most 100 characters, no citations of other documents' sections
    (the meanings live in config.py, the measurements in docs/studies/)."""
    text = (PROJECT_ROOT / path).read_text(encoding="utf-8")
    long = [i for i, line in enumerate(text.splitlines(), 1) if len(line) > 100]
    assert long == [], f"{path}: lines over 100 characters: {long}"
    for word in ("BENCHMARKS", "README"):
        assert word not in text, f"{path} cites {word}"
