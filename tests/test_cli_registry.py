"""`pidc characterize`, `pidc domain`, `pidc relate` on a tiny registry built here.

The registry holds one small NPE on the 377 cues (`cues`), trained for a few epochs with input noise, as the pipeline
trains its frozen-feature models (without it, 256 images of the version-6 cues' 375 features gave posteriors so sharp
that `relate`'s verdict on the in-ODD mix turned on the float order of one thread or two), on images of the procedural
simulator, and exported with the fast torchscript exporter; the champion pointer names it. Folders of images are
rendered at known weathers: two source domains (clear noon, overcast rain), an in-ODD target mixing fresh images of
both, and an out-of-ODD target (foggy night). Commands run in-process through `components.cli.main.main`, and once
through the installed `pidc` console script.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from components.cli.main import main
from components.core import weather
from components.evaluate.summary import hdi
from tests import tiny_registry

BOX = weather.Box.full()
NAMES = BOX.names
ROW = re.compile(
    r"^(?P<name>\w+) \[(?P<unit>[^\]]*)\]\s+(?P<median>-?\d+\.\d+)\s+\[(?P<low>-?\d+\.\d+), (?P<high>-?\d+\.\d+)\]"
    r"(?:\s+(?P<mean>-?\d+\.\d+)\s+(?P<std>\d+\.\d+))?$"
)
# weather boxes (cloud, fog, rain, sun, wind, deposits) of the domains
CLEAR = ([0, 0, 0, 50, 0, 0], [20, 10, 10, 90, 30, 10])
OVERCAST = ([80, 0, 60, 50, 50, 60], [100, 30, 100, 90, 100, 100])
NIGHT = ([0, 80, 0, -90, 0, 0], [20, 100, 10, -40, 30, 10])


def render_folder(folder: Path, box: tuple[list[float], list[float]], n: int, seed: int, prefix: str = "") -> Path:
    """n PNGs of 32×32 at weathers uniform in ``box`` (distinct scenes)."""
    return tiny_registry.render_folder(folder, box, n, seed, prefix, stream="cli-folder")


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict[str, Path]:
    """A registry with model ``cues-tiny`` (the champion) and folders of images."""
    from components.simulate.procedural import ProceduralSimulator

    root = tmp_path_factory.mktemp("cli-registry")
    registry = tiny_registry.build_registry(root, "cli-registry", {"model": "cues-tiny", "metric": "calibration_error"})

    mixed = root / "mixed"
    render_folder(mixed, CLEAR, 2, 10)
    wide = ProceduralSimulator(32, 48).render(weather.weather_from_theta(np.array(CLEAR[1]), 100.0), 7)
    Image.fromarray(wide).save(mixed / "002.jpg", quality=95)
    (mixed / "empty.png").write_bytes(b"")
    (mixed / "notimage.png").write_text("not an image\n")
    (mixed / "readme.txt").write_text("ignored: not an image extension\n")

    mix = render_folder(root / "mix", CLEAR, 8, 13, "c")
    render_folder(mix, OVERCAST, 8, 14, "o")
    return {
        "root": root,
        "registry": registry,
        "mixed": mixed,
        "clear": render_folder(root / "clear", CLEAR, 32, 11),
        "overcast": render_folder(root / "overcast", OVERCAST, 32, 12),
        "mix": mix,
        "night": render_folder(root / "night", NIGHT, 16, 15),
    }


def run(capsys, *args: str) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def parse_rows(text: str) -> dict[str, dict[str, float]]:
    rows = {}
    for line in text.splitlines():
        m = ROW.match(line)
        if m:
            rows[m["name"]] = {k: float(v) for k, v in m.groupdict().items() if k not in ("name", "unit") and v}
    return rows


def parse_blocks(out: str) -> dict[str, tuple[str, dict[str, dict[str, float]]]]:
    """``== path (note: …)`` blocks → {path: (header line, rows)}."""
    blocks = {}
    for chunk in out.strip().split("\n\n"):
        head, _, rest = chunk.strip().partition("\n")
        assert head.startswith("== "), chunk
        path = head[3:].split("  (note:")[0]
        blocks[path] = (head, parse_rows(rest))
    return blocks


def check_rows(rows: dict[str, dict[str, float]]) -> None:
    """Six parameters in order, each with low ≤ median ≤ high inside the prior box."""
    assert list(rows) == list(NAMES)
    for j, name in enumerate(NAMES):
        r = rows[name]
        assert BOX.low[j] <= r["low"] <= r["median"] <= r["high"] <= BOX.high[j], (name, r)


def test_characterize_a_folder_with_bad_images(world, capsys, tmp_path):
    csv_path = tmp_path / "draws.csv"
    code, out, err = run(
        capsys,
        "characterize",
        world["mixed"],
        "--registry",
        world["registry"],
        "--model",
        "cues-tiny",
        "--samples",
        300,
        "--seed",
        5,
        "--samples-out",
        csv_path,
        "--json",
        tmp_path / "summaries.json",
    )
    assert code == 0
    blocks = parse_blocks(out)
    good = [str(world["mixed"] / n) for n in ("000.png", "001.png", "002.jpg")]
    assert list(blocks) == good
    assert "note: not square (48×32 pixels)" in blocks[good[2]][0]
    # the one image not of the model's training size (32×32) is named once, with what its posterior is worth
    caveats = [line for line in err.splitlines() if "learned from" in line]
    assert caveats == [
        "pidc characterize: note: cues-tiny learned from 32×32 renders; images of 48×32 are area-resized, and the "
        "calibration measured in the pipeline does not cover them: the simulator's own renders made larger and "
        "resized gave overconfident posteriors (docs/studies/other-resolutions.md)"
    ]
    errors = [line for line in err.splitlines() if line.startswith("pidc characterize: skipped")]
    assert errors == [
        f"pidc characterize: skipped {world['mixed'] / 'empty.png'}: empty file (0 bytes)",
        f"pidc characterize: skipped {world['mixed'] / 'notimage.png'}: not an image file, or a format "
        "Pillow cannot read (cannot identify image file)",
    ]
    assert "characterized 3 images with cues-tiny (300 draws each, seed 5); skipped 2" in err
    # --json holds the printed summaries, image by image, with the notes
    report = json.loads((tmp_path / "summaries.json").read_text())
    assert report["model"] == "cues-tiny" and report["samples"] == 300 and report["skipped"] == 2
    assert [i["image"] for i in report["images"]] == good and report["images"][2]["note"].startswith("not square")
    for item in report["images"]:
        assert item["hdi_mass"] == 0.6827 and item["draws"] == 300 and list(item["parameters"]) == list(NAMES)
        for name, row in blocks[item["image"]][1].items():
            p = item["parameters"][name]
            assert (p["median"], p["hdi_low"], p["hdi_high"]) == pytest.approx(
                (row["median"], row["low"], row["high"]), abs=0.006
            )
    # the draws file holds exactly the draws the table summarizes
    import pandas as pd

    table = pd.read_csv(csv_path)
    assert list(table.columns) == ["image", "draw", *NAMES] and len(table) == 900
    for path in good:
        draws = table[table.image == path]
        assert draws["draw"].tolist() == list(range(300))
        rows = blocks[path][1]
        check_rows(rows)
        low, high = hdi(draws[list(NAMES)].to_numpy())
        for j, name in enumerate(NAMES):
            assert rows[name]["median"] == pytest.approx(np.median(draws[name]), abs=0.006)
            assert (rows[name]["low"], rows[name]["high"]) == pytest.approx((low[j], high[j]), abs=0.006)

    # same seed, same numbers (to the printed digit: an image's cues alone and in a batch differ by ~1e-7, the wet-road
    # block's convolutions, which can flip a last printed digit); another seed, other draws
    def alone(seed: int) -> str:
        args = ("--registry", world["registry"], "--model", "cues-tiny", "--samples", 300, "--seed", seed)
        return run(capsys, "characterize", world["mixed"] / "000.png", *args)[1]

    first, number = out.split("\n\n")[0] + "\n\n", r"-?\d+\.\d+"
    same = alone(5)
    assert re.sub(number, "#", same) == re.sub(number, "#", first)
    assert np.allclose(
        [float(v) for v in re.findall(number, same)], [float(v) for v in re.findall(number, first)], atol=0.011
    )
    other = alone(6)
    assert other != out.split("\n\n")[0] + "\n\n"


def test_characterize_writes_parquet_and_one_corner_plot_per_image(world, capsys, tmp_path):
    import pyarrow.parquet as pq

    images = [world["clear"] / "000.png", world["night"] / "000.png"]
    out_file = tmp_path / "out" / "draws.parquet"
    code, out, _ = run(
        capsys,
        "characterize",
        *images,
        "--registry",
        world["registry"],
        "--model",
        "cues-tiny",
        "--samples",
        200,
        "--samples-out",
        out_file,
        "--corner",
        tmp_path / "corner.png",
    )
    assert code == 0 and len(parse_blocks(out)) == 2
    table = pq.read_table(out_file)
    assert table.column_names == ["image", "draw", *NAMES] and table.num_rows == 400
    assert sorted(set(table.column("image").to_pylist())) == sorted(map(str, images))
    # two images both named 000.png: the second corner file gets a suffix
    corners = [tmp_path / "corner-000.png", tmp_path / "corner-000-2.png"]
    assert sorted(p.name for p in tmp_path.glob("corner*")) == sorted(p.name for p in corners)
    for path in corners:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        with Image.open(path) as im:
            im.verify()
            assert im.size[0] > 500


def test_characterize_with_the_champion_on_one_image_writes_the_named_corner(world, capsys, tmp_path):
    code, out, _ = run(
        capsys,
        "characterize",
        world["night"] / "001.png",
        "--registry",
        world["registry"],
        "--samples",
        100,
        "--corner",
        tmp_path / "one.png",
    )
    assert code == 0 and len(parse_blocks(out)) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["one.png"]


def test_characterize_when_no_image_is_readable(world, capsys, tmp_path):
    code, out, err = run(
        capsys,
        "characterize",
        world["mixed"] / "empty.png",
        world["mixed"] / "notimage.png",
        "--registry",
        world["registry"],
        "--samples-out",
        tmp_path / "d.csv",
    )
    assert code == 2 and out == ""
    assert err.count("skipped") == 2
    assert err.strip().splitlines()[-1] == "pidc characterize: error: none of the 2 images could be read"
    assert list(tmp_path.iterdir()) == []  # no partial draws file


def test_resize_caveat_once_per_command_and_for_cards_that_do_not_name_their_images(world, capsys, tmp_path):
    """A card exported before `training_renders` existed: the caveat when the backbone converts the images, once for
    all of relate's folders; a card naming the images' own size: none."""
    folder = tmp_path / "registry" / "old-card"
    shutil.copytree(world["registry"] / "cues-tiny", folder)
    card = json.loads((folder / "card.json").read_text())
    del card["training_renders"]
    card["model_id"] = "old-card"
    (folder / "card.json").write_text(json.dumps(card))
    common = ["--registry", tmp_path / "registry", "--model", "old-card", "--calibration-targets", 20]
    code, _, err = run(capsys, "relate", world["mix"], world["clear"], world["overcast"], *common)
    caveats = [line for line in err.splitlines() if "learned from" in line]
    assert code == 0 and caveats == [
        "pidc relate: note: old-card learned from renders of a size its card does not name (re-export it); images of "
        "32×32 are area-resized, and the calibration measured in the pipeline does not cover them: the simulator's own "
        "renders made larger and resized gave overconfident posteriors (docs/studies/other-resolutions.md)"
    ]
    code, _, err = run(capsys, "characterize", world["clear"], "--registry", world["registry"], "--samples", 100)
    assert code == 0 and "learned from" not in err


def test_the_command_line_notes_images_outside_a_camera_models_sizes(world, tmp_path, capsys):
    """`pidc characterize` with a model whose card names resized renders: no note for images of those sizes; one note
    naming the sizes outside them and saying how images of the model's own input size are taken."""
    from components.simulate.procedural import ProceduralSimulator
    from components.simulate.resized import ResizedRenders

    registry = tmp_path / "registry"
    folder = registry / "camera"
    shutil.copytree(world["registry"] / "cues-tiny", folder)
    card = json.loads((folder / "card.json").read_text())
    card["model_id"] = "camera"
    card["training_renders"] |= {"render_sizes": [40, 64]}
    (folder / "card.json").write_text(json.dumps(card))
    images = tmp_path / "images"
    images.mkdir()
    sim = ResizedRenders(32, 32, (40, 64))
    h = sim.render_height(1)
    Image.fromarray(
        ProceduralSimulator(h, h).render(
            weather.weather_from_theta(np.array([40.0, 20.0, 70.0, 35.0, 60.0, 50.0]), 120.0), 1
        )
    ).save(images / "large.png")
    Image.fromarray(
        ProceduralSimulator(32, 32).render(
            weather.weather_from_theta(np.array([40.0, 20.0, 70.0, 35.0, 60.0, 50.0]), 120.0), 1
        )
    ).save(images / "own.png")
    Image.fromarray(ProceduralSimulator(80, 80).render(weather.weather_from_theta(np.full(6, 30.0), 120.0), 2)).save(
        images / "huge.png"
    )
    common = ["--registry", registry, "--model", "camera", "--samples", 100]
    code, _, err = run(capsys, "characterize", images / "large.png", *common)
    assert code == 0 and "learned from" not in err
    code, _, err = run(capsys, "characterize", images / "own.png", images / "large.png", images / "huge.png", *common)
    caveats = [line for line in err.splitlines() if "learned from" in line]
    assert code == 0 and caveats == [
        "pidc characterize: note: camera learned from renders 40–64 pixels high, area-resized to 32×32; images of "
        "80×80 are outside them; images of 32×32 are taken as frames already shrunk to it, not as the renderer's own "
        "renders of that size: the calibration measured in the pipeline covers only what it learned "
        "(docs/studies/camera-renders.md)"
    ]


def domain_table(out: str) -> tuple[float, dict[str, dict[str, float]]]:
    size = float(re.search(r"effective size (\d+\.\d)", out)[1])
    rows = parse_rows(out)
    check_rows(rows)
    assert all("mean" in r and "std" in r for r in rows.values())
    return size, rows


def test_domain_with_equal_weights_a_weights_file_and_a_decaying_stream(world, capsys, tmp_path):
    folder, reg = world["mix"], world["registry"]
    code, equal, _ = run(
        capsys, "domain", folder, "--registry", reg, "--samples", 400, "--corner", tmp_path / "d.png", "--json",
        tmp_path / "d.json",
    )  # fmt: skip
    assert code == 0 and "16 images, equal weights" in equal
    size, rows = domain_table(equal)
    assert size == 16.0
    report = json.loads((tmp_path / "d.json").read_text())
    assert report["images"] == 16 and report["effective_size"] == pytest.approx(16.0) and report["draws"] == 400
    assert report["weighting"] == "equal weights" and list(report["parameters"]) == list(NAMES)
    for name, row in rows.items():
        p = report["parameters"][name]
        assert (p["median"], p["mean"], p["std"]) == pytest.approx((row["median"], row["mean"], row["std"]), abs=0.006)
    assert (tmp_path / "d.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # decay 1 is the equally weighted bag (same draws); decay 0.9: weights ∝ 0.9^age over 16 images
    code, same, _ = run(capsys, "domain", folder, "--registry", reg, "--samples", 400, "--decay", 1)
    assert code == 0 and domain_table(same)[1] == rows
    code, stream, _ = run(capsys, "domain", folder, "--registry", reg, "--samples", 400, "--decay", 0.9)
    w = 0.9 ** np.arange(16)
    assert code == 0 and domain_table(stream)[0] == pytest.approx(w.sum() ** 2 / (w**2).sum(), abs=0.05)
    assert "weight × 0.9 per image of age (newest last)" in stream
    # a weights file: a header, weights 1 and 3, a zero weight; the other images are left out (with a note)
    weights = tmp_path / "w.csv"
    weights.write_text("image,weight\nc000.png,1\no004.png,3\nc001.png,0\n")
    code, out, err = run(capsys, "domain", folder, "--registry", reg, "--samples", 400, "--weights", weights)
    assert code == 0 and "2 images, weights from" in out
    assert domain_table(out)[0] == pytest.approx(16 / 10, abs=0.05)
    assert "pidc domain: note: 13 image(s) of" in err and "left out" in err


@pytest.mark.parametrize(
    "content, message",
    [
        ("c000.png,-1\n", r"w\.csv line 1: weight of 'c000.png' must be finite and non-negative, got -1"),
        ("c000.png,nan\n", r"w\.csv line 1: weight of 'c000.png' must be finite and non-negative, got nan"),
        ("image,weight\nc000.png,0\no000.png,0\n", r"w\.csv: all weights are zero"),
        ("c000.png,1\nc000.png,2\n", r"w\.csv line 2: 'c000.png' is listed twice"),
        ("c000.png,1\no000.png,heavy\n", r"w\.csv line 2: weight 'heavy' of 'o000.png' is not a number"),
        ("c000.png,1,2\n", r"w\.csv line 1: expected 2 cells \(image,weight\), got 3"),
        ("image,weight\n", r"w\.csv: no weights"),
        ("c000.png,1\nzzz.png,1\n", r"1 listed image\(s\) not found among the images of .*mix, e\.g\. 'zzz\.png'"),
    ],
)
def test_domain_weights_file_errors(world, capsys, tmp_path, content, message):
    (tmp_path / "w.csv").write_text(content)
    code, out, err = run(
        capsys, "domain", world["mix"], "--registry", world["registry"], "--weights", tmp_path / "w.csv"
    )
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and re.search(message, err), err


def relate_output(out: str) -> dict[str, object]:
    weights = dict(re.findall(r"^(\S+)\s+\d+\s+(\d\.\d{4})$", out, re.M))
    return {
        "weights": {k: float(v) for k, v in weights.items()},
        "relative_gap": float(re.search(r"relative gap δ/mean\(b²\): (\S+)", out)[1]),
        "threshold": float(re.search(r"threshold: (\S+) \(relative gap", out)[1]),
        "degenerate": re.search(r"degenerate: (yes|no)", out)[1] == "yes",
        "outside": re.search(r"verdict: (OUTSIDE the ODD|inside the ODD)", out)[1] == "OUTSIDE the ODD",
    }


def test_relate_gives_weights_gaps_and_a_calibrated_verdict(world, capsys):
    sources = [world["clear"], world["overcast"]]
    common = ["--registry", world["registry"], "--model", "cues-tiny", "--calibration-targets", 40]
    # fresh images of both sources' weathers: inside
    code, out, err = run(capsys, "relate", world["mix"], *sources, *common)
    assert "learned from" not in err  # every folder holds images of the model's training size
    inside = relate_output(out)
    assert code == 0 and not inside["outside"] and inside["relative_gap"] <= inside["threshold"], out
    assert set(inside["weights"]) == {"clear", "overcast"}
    assert sum(inside["weights"].values()) == pytest.approx(1, abs=2e-4)
    assert not inside["degenerate"] and inside["threshold"] > 0.01
    assert "target " + str(world["mix"]) + ": 16 images; model cues-tiny; 64 points (seed 0)" in out
    assert "40 in-ODD targets of 16 images held out of the sources; false-alarm rate 0.05" in out
    assert "each folder: a kernel density of 64 posterior draws per image, bandwidth 3 × the sources' Scott rule" in out
    # the paper's exact mixtures, on request: the same verdicts here
    code, out, _ = run(capsys, "relate", world["mix"], *sources, *common, "--smoothing", "none", "--points", 16)
    exact = relate_output(out)
    assert code == 0 and not exact["outside"] and "the exact mixture of its images' posteriors" in out, out
    code, out, _ = run(capsys, "relate", world["night"], *sources, *common, "--smoothing", "none", "--points", 16)
    assert code == 0 and relate_output(out)["outside"], out
    # foggy night, far from both sources' weathers: outside
    code, out, _ = run(capsys, "relate", world["night"], *sources, *common)
    outside = relate_output(out)
    assert code == 0 and outside["outside"] and outside["relative_gap"] > outside["threshold"], out
    # sources of identical images (two copies of one folder): λ̂ is not unique
    small = world["mixed"]  # 3 readable images
    copies = [world["root"] / "copies" / c / "mixed" for c in ("a", "b")]
    for c in copies:
        if not c.exists():
            shutil.copytree(small, c)
    code, out, _ = run(capsys, "relate", small, *copies, *common[:-1], 19)
    same = relate_output(out)
    assert code == 0 and same["degenerate"] and same["weights"] and not same["outside"]
    assert str(copies[0]) in out  # equal folder names are shown as paths
    assert "folders of the same images, or densities that do not reach the target's points" in out
    # one source: λ̂ = 1, the verdict tests likeness (with one source and small bags the relative gap is heavy-tailed,
    # far above 1 at times, so this tiny model's verdict is not asserted, only that it follows the threshold)
    code, out, _ = run(capsys, "relate", world["night"], world["clear"], *common)
    single = relate_output(out)
    assert code == 0 and single["weights"] == {"clear": 1.0}
    assert single["outside"] == (single["relative_gap"] > single["threshold"])
    assert "note: one source, so λ̂ = 1" in out


DIFFERENCE = re.compile(
    r"^(?P<name>\w+) \[[^\]]*\]\s+(?P<target>-?\d+\.\d+)\s+(?P<mixture>-?\d+\.\d+)\s+(?P<w1>\d+\.\d+)"
    r"\s+(?P<level>\d+\.\d+)(?P<beyond> \*)?$",
    re.M,
)


def verdict_outside(out: str) -> bool:
    return "verdict: OUTSIDE the ODD" in out


def test_relate_says_where_the_target_differs_and_writes_json_and_a_plot(world, capsys):
    """The per-parameter table: every parameter once, sorted by W₁ over its in-ODD level; with an OUTSIDE verdict a *
    exactly where W₁ exceeds it, with an inside one none; the foggy night differs from clear and overcast noons in the
    sun first of all. --json holds the printed figures; --plot writes a PNG."""
    sources = [world["clear"], world["overcast"]]
    out_json, out_png = world["root"] / "relate" / "night.json", world["root"] / "relate" / "night.png"
    common = ["--registry", world["registry"], "--model", "cues-tiny", "--calibration-targets", 40]
    code, out, err = run(capsys, "relate", world["night"], *sources, *common, "--json", out_json, "--plot", out_png)
    assert code == 0 and f"wrote {out_json}" in err and f"wrote {out_png}" in err, err
    rows = [m.groupdict() for m in DIFFERENCE.finditer(out)]
    assert sorted(r["name"] for r in rows) == sorted(NAMES), out
    assert verdict_outside(out) and all((r["beyond"] is not None) == (float(r["w1"]) > float(r["level"])) for r in rows)
    ratios = [float(r["w1"]) / float(r["level"]) for r in rows]
    assert ratios == sorted(ratios, reverse=True)
    sun = next(r for r in rows if r["name"] == "sun_altitude_angle")
    assert sun["beyond"] and float(sun["target"]) < 0 < float(sun["mixture"]), out
    report, verdict = json.loads(out_json.read_text()), relate_output(out)
    assert report["outside"] == verdict["outside"] and report["relative_gap"] == pytest.approx(
        verdict["relative_gap"], 1e-3
    )
    assert [s["name"] for s in report["sources"]] == ["clear", "overcast"] and report["target"]["images"] == 16
    assert sum(s["weight"] for s in report["sources"]) == pytest.approx(1, abs=2e-4)
    for r in rows:
        p = report["parameters"][r["name"]]
        assert p["wasserstein"] == pytest.approx(float(r["w1"]), abs=0.006)
        assert p["exceeds_in_odd_level"] == (r["beyond"] is not None) and p["in_odd_level"] == pytest.approx(
            float(r["level"]), abs=0.006
        )
    assert Image.open(out_png).size[0] > 800
    # an inside verdict marks nothing, whatever its W₁
    code, out, _ = run(capsys, "relate", world["mix"], *sources, *common)
    assert code == 0 and not relate_output(out)["outside"] and " *" not in out, out
    # the exact mixtures (--smoothing none) say where too, from the same fixed draws
    code, out, _ = run(capsys, "relate", world["night"], *sources, *common, "--smoothing", "none", "--points", 16)
    assert code == 0 and sorted(m["name"] for m in DIFFERENCE.finditer(out)) == sorted(NAMES), out


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["relate", "{mix}", "{clear}", "--registry", "{registry}", "--json", "{root}/r.txt"],
            r"--json .*r\.txt: expected a \.json file name",
        ),
        (
            ["characterize", "{mixed}", "--registry", "{registry}", "--json", "{root}/c"],
            r"--json .*c: expected a \.json",
        ),
        (
            ["domain", "{mix}", "--registry", "{registry}", "--json", "{root}/d.csv"],
            r"--json .*d\.csv: expected a \.json",
        ),
        (
            ["relate", "{mix}", "{clear}", "--registry", "{registry}", "--plot", "{root}/r.xyz"],
            r"--plot .*r\.xyz: unknown image type '\.xyz'",
        ),
        (
            ["characterize", "{mixed}", "--registry", "{root}/elsewhere/registry"],
            r"elsewhere/reports/task1/champion\.json: no champion yet",
        ),
        (
            ["characterize", "{mixed}", "--registry", "{root}/nowhere/registry"],
            r"--registry .*nowhere/registry: no such folder \(in /.*\); run pidc from the project folder or pass "
            r"--registry PATH",
        ),
        (
            ["characterize", "{mixed}", "--registry", "{mixed}/000.png", "--model", "cues-tiny"],
            r"--registry .*000\.png: not a folder",
        ),
        (
            ["characterize", "{mixed}", "--registry", "{registry}", "--model", "cues-9"],
            r"no exported model 'cues-9' in .*registry \(known: cues-tiny",
        ),
        (["characterize", "{root}/empty", "--registry", "{registry}"], r"empty: no image files in this folder"),
        (
            ["characterize", "{mixed}", "--registry", "{registry}", "--samples", "0"],
            r"--samples must be at least 100 for a 68\.27 % HDI .*, got 0",
        ),
        (
            ["characterize", "{mixed}", "--registry", "{registry}", "--samples", "99"],
            r"--samples must be at least 100 .*, got 99",
        ),
        (
            ["domain", "{mix}", "--registry", "{registry}", "--samples", "1"],
            r"--samples must be at least 100 .*, got 1",
        ),
        (
            ["characterize", "{mixed}", "--registry", "{registry}", "--samples-out", "{root}/d.txt"],
            r"--samples-out .*d\.txt: unknown draws file type '\.txt'; use \.csv or \.parquet",
        ),
        (
            ["characterize", "{mixed}", "--registry", "{registry}", "--corner", "{root}/c.xyz"],
            r"--corner .*c\.xyz: unknown image type '\.xyz'",
        ),
        (["domain", "{root}/empty", "--registry", "{registry}"], r"empty: no image files in this folder"),
        (["domain", "{mixed}/000.png", "--registry", "{registry}"], r"000\.png: not a folder"),
        (["domain", "{mix}", "--registry", "{registry}", "--decay", "1.5"], r"--decay must be in \(0, 1\]"),
        (["domain", "{mix}", "--registry", "{registry}", "--weights", "{root}/none.csv"], r"none\.csv: no such"),
        (
            ["relate", "{mix}", "{clear}", "{overcast}", "--registry", "{registry}", "--points", "1"],
            r"--points 1 cannot determine 2 mixture weights",
        ),
        (
            ["relate", "{mix}", "{clear}", "--registry", "{registry}", "--false-alarm-rate", "1.5"],
            r"--false-alarm-rate must be in \(0, 1\)",
        ),
        (
            ["relate", "{mix}", "{clear}", "--registry", "{registry}", "--calibration-targets", "10"],
            r"--calibration-targets must be ≥ 19 for --false-alarm-rate 0\.05, got 10",
        ),
        (["relate", "{mix}", "{root}/nope", "--registry", "{registry}"], r"nope: no such folder"),
        (["domain", "{root}/nope", "--registry", "{registry}"], r"nope: no such folder$"),
        (["relate", "{mix}", "{mixed}/000.png", "--registry", "{registry}"], r"000\.png: not a folder"),
        (
            ["relate", "{mix}", "{clear}", "--registry", "{registry}", "--draws-per-image", "1"],
            r"--draws-per-image must be at least 2",
        ),
        (
            ["relate", "{mix}", "{clear}", "--registry", "{registry}", "--bandwidth-scale", "0"],
            r"--bandwidth-scale must be a positive number, got 0",
        ),
        # a missing input is refused before the model is loaded, as domain and relate refuse a missing folder
        (["characterize", "{root}/nowhere/", "--registry", "{registry}"], r": .*/nowhere/: no such folder$"),
        (
            ["characterize", "{mixed}/000.png", "{root}/gone.png", "--registry", "{registry}"],
            r": .*/gone\.png: no such file or folder$",
        ),
        # PGF needs a LaTeX engine to typeset: refused before any work, naming the types taken
        (
            ["characterize", "{mixed}/000.png", "--registry", "{registry}", "--corner", "{root}/c.pgf"],
            r"--corner .*c\.pgf: \.pgf \(PGF, LaTeX source\) needs a LaTeX engine, which pidc does not use; use one "
            r"of .*\.pdf, \.png, .*\.svg",
        ),
        (
            ["domain", "{mix}", "--registry", "{registry}", "--corner", "{root}/d.PGF"],
            r"--corner .*d\.PGF: \.PGF \(PGF, LaTeX source\) needs a LaTeX engine",
        ),
        (
            ["relate", "{mix}", "{clear}", "--registry", "{registry}", "--plot", "{root}/r.pgf"],
            r"--plot .*r\.pgf: \.pgf \(PGF, LaTeX source\) needs a LaTeX engine",
        ),
    ],
)
def test_user_errors_are_one_clear_line(world, capsys, args, message):
    (world["root"] / "empty").mkdir(exist_ok=True)
    (world["root"] / "elsewhere" / "registry").mkdir(parents=True, exist_ok=True)  # a registry, but no champion
    code, out, err = run(capsys, *[a.format(**{k: str(v) for k, v in world.items()}) for a in args])
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"pidc {args[0]}: error: ") and re.search(message, lines[0]), err


def test_weights_and_decay_are_mutually_exclusive(world, capsys, tmp_path):
    with pytest.raises(SystemExit) as info:
        main(["domain", str(world["mix"]), "--weights", str(tmp_path / "w.csv"), "--decay", "0.5"])
    assert info.value.code == 2 and "not allowed with argument" in capsys.readouterr().err


def test_console_script(world, tmp_path):
    script = Path(sys.executable).with_name("pidc")
    if not script.exists():
        script = Path(shutil.which("pidc") or "pidc")
    r = subprocess.run(
        [str(script), "characterize", str(world["clear"] / "003.png"), "--samples", "100"],
        cwd=world["root"],
        capture_output=True,
        text=True,
        timeout=120,
    )  # default registry: ./registry
    assert r.returncode == 0, r.stderr
    check_rows(parse_blocks(r.stdout)[str(world["clear"] / "003.png")][1])
    assert "with cues-tiny" in r.stderr


def test_relate_defaults_are_the_task3_stage_defaults():
    """`pidc relate` relates folders as the task3 stage does by default (params.yaml), whose figures docs/results.md reports."""
    from components.cli.relate import RELATE_DEFAULTS
    from components.core.config import load_params

    t = load_params(Path(__file__).resolve().parents[1] / "params.yaml").task3
    assert RELATE_DEFAULTS == {
        "n_points": t.n_points,
        "smoothing": t.smoothing,
        "draws_per_image": t.draws_per_image,
        "bandwidth_scale": t.bandwidth_scale,
    }


def test_relate_draws_are_fixed_per_image_across_folders():
    """An image in two folders gets the same kernel draws in both (equal inputs, one draw per distinct image)."""
    from components.cli.relate import _fixed_draws

    class Shifted:  # q(θ | x) = N(x, I), seeded per call
        def sample(self, x: np.ndarray, m: int, seed: int) -> np.ndarray:
            return x[:, None, :] + np.random.default_rng(seed).standard_normal((len(x), m, x.shape[1]))

    a = np.arange(12.0).reshape(4, 3)
    b = np.vstack([a[2:], a[:1]])
    da, db = _fixed_draws(Shifted(), [a, b], 5, seed=3)
    assert da.shape == (4, 5, 3) and db.shape == (3, 5, 3)
    assert np.array_equal(da[2], db[0]) and np.array_equal(da[3], db[1]) and np.array_equal(da[0], db[2])
    assert not np.array_equal(da[0], da[1])
    again = _fixed_draws(Shifted(), [a, b], 5, seed=3)
    assert all(np.array_equal(x, y) for x, y in zip((da, db), again, strict=True))


# --- bad user input (the CLI audit): one clear line, before any work where it can be -----------------------------


def small_images(folder: Path, sizes: list[tuple[int, int]]) -> list[Path]:
    """PNGs of ``(width, height)`` in ``folder`` (uniform grey)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for w, h in sizes:
        path = folder / f"s{w}x{h}.png"
        Image.fromarray(np.full((h, w, 3), 120, np.uint8)).save(path)
        paths.append(path)
    return paths


def test_an_output_that_is_an_input_image_is_refused_before_any_work(world, capsys, tmp_path):
    folder = tmp_path / "ow"
    shutil.copytree(world["mix"], folder)
    image = folder / "c000.png"
    before = image.read_bytes()
    reg = ["--registry", world["registry"]]
    same = folder / ".." / "ow" / "c000.png"  # the same file by another path
    cases = [
        (["characterize", image, *reg, "--corner", image], "--corner", image),
        (["characterize", folder, *reg, "--corner", folder / "c.png"], None, None),
        (["domain", folder, *reg, "--corner", same], "--corner", same),
        (["relate", folder, world["clear"], *reg, "--plot", image], "--plot", image),
        (["relate", world["clear"], folder, *reg, "--plot", same], "--plot", same),
    ]
    for args, option, path in cases:
        if option is None:  # one corner per image, c-<image stem>.png: c-c000.png, here one of the folder's images
            (folder / "c-c000.png").write_bytes(before)
            option, path = "--corner", folder / "c-c000.png"
        code, out, err = run(capsys, *args)
        assert code == 2 and out == "", err
        assert err.strip().splitlines() == [
            f"pidc {args[0]}: error: {option} {path} is one of the input images; choose another file name"
        ], err
        assert image.read_bytes() == before
        (folder / "c-c000.png").unlink(missing_ok=True)


@pytest.mark.parametrize(
    "where, message",
    [
        ("{tmp}/a.png/x.{ext}", r"{opt} .*a\.png/x\.{ext}: .*a\.png is a file, not a folder"),
        ("{tmp}/isdir.{ext}", r"{opt} .*isdir\.{ext}: is a folder; give a file name"),
        (
            "/proc/pidc-test/x.{ext}",
            r"{opt} /proc/pidc-test/x\.{ext}: cannot write there \(No such file or directory\)",
        ),
    ],
)
def test_unwritable_outputs_are_one_line_before_any_work(world, capsys, tmp_path, where, message):
    (tmp_path / "a.png").write_bytes(b"")
    reg = ["--registry", world["registry"]]
    cases = [
        (["characterize", world["clear"] / "000.png", *reg], "--json", "json"),
        (["characterize", world["clear"] / "000.png", *reg], "--samples-out", "csv"),
        (["characterize", world["clear"] / "000.png", *reg], "--corner", "png"),
        (["domain", world["mix"], *reg], "--corner", "png"),
        (["relate", world["mix"], world["clear"], *reg], "--plot", "png"),
        (["relate", world["mix"], world["clear"], *reg], "--json", "json"),
    ]
    for args, option, ext in cases:
        path = where.format(tmp=tmp_path, ext=ext)
        if "isdir" in path:
            Path(path).mkdir(exist_ok=True)
        code, out, err = run(capsys, *args, option, path)
        assert code == 2 and out == "", err  # before any image is read
        lines = err.strip().splitlines()
        assert len(lines) == 1 and re.search(message.format(opt=option, ext=ext), lines[0]), err
        assert ".tmp" not in err
    assert not list(tmp_path.rglob("*.tmp"))  # no probe file left behind


def test_images_below_the_backbones_minimum_are_skipped(world, capsys, tmp_path):
    """No backbone takes images under 8×8 pixels (``imageops.MIN_SIDE``, the bound every backbone checks): such a file
    is skipped with one line; the run goes on."""
    folder = tmp_path / "small"
    tiny = small_images(folder, [(1, 1), (4, 6)])
    shutil.copy(world["clear"] / "000.png", folder / "good.png")
    reg = ["--registry", world["registry"]]
    code, out, err = run(capsys, "characterize", folder, *reg, "--samples", 100)
    skipped = [line for line in err.splitlines() if line.startswith("pidc characterize: skipped")]
    assert code == 0 and list(parse_blocks(out)) == [str(folder / "good.png")], err
    assert skipped == [
        f"pidc characterize: skipped {tiny[0]}: 1×1 pixels; no backbone takes images under 8×8",
        f"pidc characterize: skipped {tiny[1]}: 4×6 pixels; no backbone takes images under 8×8",
    ]
    assert "characterized 1 image with cues-tiny (100 draws each, seed 0); skipped 2" in err
    code, out, err = run(capsys, "domain", folder, *reg, "--samples", 100)
    assert code == 0 and "1 image, equal weights" in out and err.count("no backbone takes images under 8×8") == 2, err
    code, out, err = run(capsys, "characterize", tiny[0], *reg)
    assert code == 2 and err.strip().splitlines()[-1] == "pidc characterize: error: the only image could not be read"


def test_relate_refuses_a_verdict_when_the_kernels_do_not_overlap(world, capsys):
    """A tiny --bandwidth-scale: kernel densities that no longer overlap make every in-ODD gap ≈ 1 (the threshold
    saturates), and any target would be "inside": refused, naming --bandwidth-scale. Out-of-range densities at the
    extremes: an error naming it, and no numpy warning on the terminal."""
    common = ["--registry", world["registry"], "--calibration-targets", 19]
    sources = [world["clear"], world["overcast"]]
    code, out, err = run(capsys, "relate", world["night"], *sources, *common, "--bandwidth-scale", 0.01)
    assert code == 2 and out == "", err
    assert re.fullmatch(
        r"pidc relate: error: --bandwidth-scale 0\.01 is too small: the kernel densities of the folders do not overlap, "
        r"so in-ODD targets .* relative gaps near 1 \(threshold (1|0\.9[89]\d*|1\.0[0-2]\d*)\), .* no verdict is "
        r"possible; use a value near the default 3",
        err.strip().splitlines()[-1],
    ), err
    for scale in ("1e-300", "1e300"):
        with warnings.catch_warnings(record=True) as leaked:
            warnings.simplefilter("always")
            code, out, err = run(capsys, "relate", world["mix"], *sources, *common, "--bandwidth-scale", scale)
        assert code == 2 and out == "", err
        lines = [line for line in err.strip().splitlines() if "note: backbone" not in line]
        assert len(lines) == 1 and lines[0].startswith(f"pidc relate: error: --bandwidth-scale {float(scale):g} "), err
        assert "use a value near the default 3" in lines[0]
        assert not [w for w in leaked if issubclass(w.category, RuntimeWarning)]


def test_relate_bandwidth_scale_is_checked_with_smoothing_none_too(world, capsys):
    common = ["--registry", world["registry"], "--calibration-targets", 19, "--smoothing", "none", "--points", 16]
    code, out, err = run(capsys, "relate", world["mix"], world["clear"], *common, "--bandwidth-scale", -1)
    assert code == 2 and out == "" and "--bandwidth-scale must be a positive number, got -1" in err
    code, out, err = run(capsys, "relate", world["mix"], world["clear"], *common, "--bandwidth-scale", 2)
    assert code == 0 and "verdict:" in out
    assert "pidc relate: note: --bandwidth-scale is ignored with --smoothing none (no kernel)" in err
    code, out, err = run(capsys, "relate", world["mix"], world["clear"], *common)
    assert code == 0 and "--bandwidth-scale" not in err


@pytest.mark.parametrize(
    "folders, message",
    [
        (["{mix}", "{mix}"], r"the target folder .*mix is also given as a source$"),
        (["{mix}", "{clear}", "{clear}/"], r"source folder .*clear is given twice$"),
        (
            ["{mix}", "{clear}", "{root}/clear/../overcast", "{overcast}"],
            r"source folder .*overcast is given twice \(as ",
        ),
        (
            ["{mix}", "{clear}", "{root}/mix/../mix"],
            r"the target folder .*mix is also given as a source \(.*\.\./mix\)",
        ),
    ],
)
def test_relate_refuses_a_folder_given_twice(world, capsys, folders, message):
    args = [f.format(**{k: str(v) for k, v in world.items()}) for f in folders]
    code, out, err = run(capsys, "relate", *args, "--registry", world["registry"])
    lines = err.strip().splitlines()
    assert code == 2 and out == "" and len(lines) == 1 and re.search(message, lines[0]), err


def test_relate_names_the_folder_of_no_readable_image_and_one_image_sources(world, capsys, tmp_path):
    bad = tmp_path / "allbad"
    bad.mkdir()
    (bad / "a.png").write_bytes(b"")
    (bad / "b.png").write_text("not an image")
    reg = ["--registry", world["registry"]]
    code, _, err = run(capsys, "relate", world["mix"], world["clear"], bad, *reg)
    assert (
        code == 2 and err.strip().splitlines()[-1] == f"pidc relate: error: {bad}: none of its 2 images could be read"
    )
    code, _, err = run(capsys, "domain", bad, *reg)
    assert (
        code == 2 and err.strip().splitlines()[-1] == f"pidc domain: error: {bad}: none of its 2 images could be read"
    )
    ones = []
    for name in ("one1", "one2"):
        (tmp_path / name).mkdir()
        shutil.copy(world["clear"] / f"00{len(ones)}.png", tmp_path / name / "a.png")
        ones.append(tmp_path / name)
    code, out, err = run(capsys, "relate", world["mix"], *ones, *reg)
    assert code == 2 and out == "", err
    assert err.strip().splitlines()[-1] == (
        "pidc relate: error: every source folder has only 1 readable image (one1: 1, one2: 1); at least one source "
        "folder needs 2 or more images to calibrate the threshold (its in-ODD targets are images held out of the "
        "sources)"
    )


@pytest.mark.parametrize(
    "content, message",
    [
        (b"c000.png,abc\no000.png,2\n", r"w\.csv line 1: weight 'abc' of 'c000\.png' is not a number"),
        (b"c000.png,0x10\n", r"w\.csv line 1: weight '0x10' of 'c000\.png' is not a number"),
        (b"c000,abc\n", r"w\.csv: no weights"),  # a header (no image name), then nothing
        (b"\xff\xfe\x00junk,1\n", r"w\.csv: not a UTF-8 text CSV file \(byte 0xff at position 0\)"),
    ],
)
def test_domain_weights_header_and_encoding(world, capsys, tmp_path, content, message):
    (tmp_path / "w.csv").write_bytes(content)
    code, out, err = run(
        capsys, "domain", world["mix"], "--registry", world["registry"], "--weights", tmp_path / "w.csv"
    )
    lines = err.strip().splitlines()
    assert code == 2 and out == "" and len(lines) == 1 and re.search(message, lines[0]), err


def test_domain_weights_after_comments_and_huge_weights(world, capsys, tmp_path):
    reg = ["--registry", world["registry"], "--samples", 100]
    weights = tmp_path / "w.csv"
    weights.write_text("# weights of the mix\n\nimage,weight\nc000.png,1\no004.png,3\n")
    code, out, err = run(capsys, "domain", world["mix"], *reg, "--weights", weights)
    assert code == 0 and "2 images, weights from" in out, err
    assert domain_table(out)[0] == pytest.approx(16 / 10, abs=0.05)
    # only the weights' ratios matter: 1e308 twice (a sum that overflows) is two equal weights
    weights.write_text("c000.png,1e308\no004.png,1e308\n")
    code, huge, err = run(capsys, "domain", world["mix"], *reg, "--weights", weights)
    assert code == 0 and domain_table(huge)[0] == 2.0, err
    weights.write_text("c000.png,1\no004.png,1\n")
    code, equal, _ = run(capsys, "domain", world["mix"], *reg, "--weights", weights)
    assert code == 0 and parse_rows(huge) == parse_rows(equal)
    # a folder is not a weights file
    code, _, err = run(capsys, "domain", world["mix"], *reg, "--weights", tmp_path)
    assert code == 2 and err.strip() == f"pidc domain: error: --weights {tmp_path}: is a folder, not a weights file"


def test_the_same_image_twice_is_characterized_once(world, capsys, tmp_path):
    image = world["clear"] / "000.png"
    reg = ["--registry", world["registry"], "--samples", 100]
    code, out, err = run(
        capsys, "characterize", image, image, *reg, "--corner", tmp_path / "c.png", "--samples-out", tmp_path / "d.csv"
    )
    assert code == 0 and list(parse_blocks(out)) == [str(image)], err
    assert f"pidc characterize: note: {image} is given twice: taken once" in err
    assert [p.name for p in sorted(tmp_path.iterdir())] == ["c.png", "d.csv"]  # one image: the named corner
    assert f"wrote 100 draws of 1 image to {tmp_path / 'd.csv'}" in err
    # a folder and one of its images
    code, out, err = run(capsys, "characterize", world["mixed"], world["mixed"] / ".." / "mixed" / "001.png", *reg)
    assert code == 0 and len(parse_blocks(out)) == 3
    assert f"is given twice (as {world['mixed'] / '001.png'}): taken once" in err


def test_what_is_not_a_regular_file_is_skipped(world, capsys, tmp_path):
    fifo = tmp_path / "fifo.png"
    os.mkfifo(fifo)
    code, out, err = run(
        capsys, "characterize", fifo, world["clear"] / "000.png", "--registry", world["registry"], "--samples", 100
    )
    assert code == 0 and len(parse_blocks(out)) == 1
    assert f"pidc characterize: skipped {fifo}: not a regular file (a named pipe (FIFO))" in err


def test_library_warnings_while_reading_become_notes(world, capsys, monkeypatch):
    """Pillow's DecompressionBombWarning (here for a 32×32 image under a lowered limit) is a note, not a warning."""
    from PIL import Image as PILImage

    monkeypatch.setattr(PILImage, "MAX_IMAGE_PIXELS", 600)  # 1024 pixels: over it, under twice it (no error)
    image = world["clear"] / "000.png"
    with warnings.catch_warnings(record=True) as leaked:
        warnings.simplefilter("always")
        code, _, err = run(capsys, "characterize", image, "--registry", world["registry"], "--samples", 100)
    assert code == 0 and f"pidc characterize: note: {image}: Image size (1024 pixels) exceeds limit of 600" in err
    assert not [w for w in leaked if "DecompressionBomb" in w.category.__name__]


def test_size_notes_say_width_by_height_and_name_a_squash(world, capsys, tmp_path):
    reg = ["--registry", world["registry"], "--samples", 100]
    code, _, err = run(capsys, "characterize", world["mixed"] / "002.jpg", *reg)  # 48 wide, 32 high
    assert (
        code == 0
        and (
            "pidc characterize: note: backbone 'cues': converting 48×32 images (width×height) to its input size 128×128"
        )
        in err
    ), err
    (strip,) = small_images(tmp_path, [(200, 10)])
    code, out, _ = run(capsys, "characterize", strip, *reg)
    head = parse_blocks(out)[str(strip)][0]
    assert code == 0 and "squashed: the resize to the backbone's 128×128 input changes its aspect ratio 20-fold" in head


def test_model_names_that_are_empty_or_malformed_uris(world, capsys):
    for model, message in [
        ("", "--model is empty; give champion, a model id, an exported folder or a models:/ URI"),
        ("models:/", "--model models:/: malformed models:/ URI; expected models:/NAME/VERSION"),
        ("models:/pidc/1/2", "--model models:/pidc/1/2: malformed models:/ URI"),
        ("models:/pidc@", "--model models:/pidc@: malformed models:/ URI"),
    ]:
        code, out, err = run(capsys, "characterize", world["mixed"], "--registry", world["registry"], "--model", model)
        assert code == 2 and out == "" and err.strip().startswith(f"pidc characterize: error: {message}"), err


def test_a_models_uri_download_is_removed_after_loading(world, capsys, tmp_path, monkeypatch):
    """`--model models:/…` downloads the model from a real MLflow store (registered as the export flow registers it,
    the champion alias set as the evaluate flow sets it) into a temporary folder: removed once loaded, and after a
    failure. The store is the ``mlflow.db`` beside ``--registry``, or ``MLFLOW_TRACKING_URI`` when set."""
    import tempfile

    import mlflow

    from components.core.config import load_params
    from flows import tracking

    params = load_params()
    base = tmp_path / "project"  # <project>/registry/cues-tiny and <project>/mlflow.db, as the pipeline leaves them
    shutil.copytree(world["registry"] / "cues-tiny", base / "registry" / "cues-tiny")
    store = f"sqlite:///{base / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", store)
    try:
        client = mlflow.MlflowClient(store)
        client.create_experiment(params.train.experiment, artifact_location=str(base / "mlartifacts"))  # not ./mlruns
        entry = tracking.register_model(base / "registry" / "cues-tiny", params, base, "cues-tiny")
        found = tracking.set_champion_alias(base, params, {"cues-tiny": {}}, "cues-tiny")
        # the stages' check of the alias against champion.json: the model id and the version it names
        pointer = {"model": "cues-tiny", "version": found["champion"]["version"]}
        assert (tracking.registered_folder(base, params, "champion", pointer) / "card.json").is_file()
        with pytest.raises(
            ValueError, match=r"is version \d+ of 'cues-tiny' but reports/task1/champion.json names ver"
        ):
            tracking.registered_folder(base, params, "champion", pointer | {"version": "999"})
        with pytest.raises(ValueError, match=r"is 'cues-tiny' but reports/task1/champion.json names 'cues-8'"):
            tracking.registered_folder(base, params, "champion", pointer | {"model": "cues-8"})
    finally:
        mlflow.set_tracking_uri(None)  # the process-wide URI that register_model set
    uri = tracking.champion_uri(params)
    assert uri == "models:/pidc@champion" and found["champion"] == {"version": entry["version"], "uri": uri}
    shutil.rmtree(base / "registry" / "cues-tiny")  # the model can only come from the MLflow store now

    temp = tmp_path / "temp"
    temp.mkdir()
    monkeypatch.setenv("TMPDIR", str(temp))
    monkeypatch.setattr(tempfile, "tempdir", None)  # tempfile reads TMPDIR again
    made = []
    mkdtemp = tempfile.mkdtemp
    monkeypatch.setattr(tempfile, "mkdtemp", lambda *a, **kw: made.append(mkdtemp(*a, **kw)) or made[-1])
    image = world["clear"] / "000.png"
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)  # the store beside --registry
    code, out, err = run(
        capsys, "characterize", image, "--registry", base / "registry", "--model", uri, "--samples", 100
    )
    assert code == 0, err
    local = run(
        capsys, "characterize", image, "--registry", world["registry"], "--model", "cues-tiny", "--samples", 100
    )
    assert local[0] == 0 and out == local[1], "the registered model is the exported one"
    ((_, rows),) = parse_blocks(out).values()
    check_rows(rows)
    assert [Path(d).parent for d in made] == [temp] and Path(made[0]).name.startswith("pidc-model-")
    assert list(temp.iterdir()) == [], "the download was removed"

    made.clear()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", store)  # over the (absent) mlflow.db beside world["registry"]
    missing = "models:/pidc@nobody"
    code, out, err = run(capsys, "characterize", image, "--registry", world["registry"], "--model", missing)
    assert code == 2 and out == "", err
    assert err.startswith(f"pidc characterize: error: {missing}: not found in the MLflow store {store}: "), err
    assert "alias nobody not found" in err, err  # the store reached holds `pidc`, only not that alias
    assert len(made) == 1 and list(temp.iterdir()) == [] and not (world["root"] / "mlflow.db").exists()

    made.clear()  # no MLFLOW_TRACKING_URI and no mlflow.db beside --registry: refused, no empty store created there
    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    code, out, err = run(capsys, "characterize", image, "--registry", world["registry"], "--model", missing)
    db = world["registry"].resolve().parent / "mlflow.db"
    assert (
        code == 2
        and out == ""
        and f"{missing}: no MLflow store: MLFLOW_TRACKING_URI is not set and there is no {db}" in err
    ), err
    assert not db.exists() and list(temp.iterdir()) == []


# --- the second CLI audit: notes and skips in every command and in --json, caveats, inputs, names ------------------


def gray_copies(source: Path, folder: Path, n: int) -> list[Path]:
    """Grayscale (mode L) copies of the first ``n`` images of ``source`` in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for path in sorted(source.glob("*.png"))[:n]:
        with Image.open(path) as im:
            im.convert("L").save(folder / f"g{path.name}")
        out.append(folder / f"g{path.name}")
    return out


COLOURLESS = re.compile(
    r"^pidc (?P<command>\w+): note: (?P<n>\d+) of (?P<total>\d+) images? (has|have) no colour \((?P<kinds>[^:]+): "
    r"red, green and blue equal in every pixel\): cues-tiny learned from colour renders, and the calibration measured "
    r"in the pipeline does not cover images without colour"
)


def test_domain_and_relate_say_the_read_notes_and_the_colourless_caveat(world, capsys, tmp_path):
    """domain and relate say each image's read notes on stderr as characterize does (one line per image for a few,
    a count per kind and the first files for many), once for all folders; images without colour get a caveat once per
    command naming how many; --json holds the notes per kind, the caveats and the skipped images with their reasons."""
    folder = tmp_path / "gray"
    grays = gray_copies(world["clear"], folder, 8)
    with Image.open(world["clear"] / "010.png") as im:
        im.convert("RGBA").save(folder / "rgba.png")
    (folder / "broken.png").write_bytes(b"")
    reg = ["--registry", world["registry"], "--samples", 100]
    code, out, err = run(capsys, "domain", folder, *reg, "--json", tmp_path / "d.json")
    assert code == 0 and "9 images, equal weights" in out, err
    notes = [line for line in err.splitlines() if line.startswith("pidc domain: note: ")]
    shown = ", ".join(map(str, grays[:3]))
    assert f"pidc domain: note: grayscale → RGB: 8 images ({shown} and 5 more)" in notes, err
    assert f"pidc domain: note: alpha channel dropped: 1 image ({folder / 'rgba.png'})" in notes, err
    caveats = [m for line in notes if (m := COLOURLESS.match(line))]
    assert [(m["n"], m["total"]) for m in caveats] == [("8", "9")], err
    assert not [line for line in notes if line.startswith(f"pidc domain: note: {grays[0]}: ")], "a count per kind"
    report = json.loads((tmp_path / "d.json").read_text())
    assert report["notes"]["grayscale → RGB"] == {"count": 8, "images": list(map(str, grays))}
    assert report["notes"]["alpha channel dropped"] == {"count": 1, "images": [str(folder / "rgba.png")]}
    assert report["skipped"] == 1 and report["skipped_images"] == [
        {"image": str(folder / "broken.png"), "reason": "empty file (0 bytes)"}
    ]
    (colourless,) = [c for c in report["caveats"] if c["kind"] == "colourless"]
    assert colourless["count"] == 8 and colourless["images"] == list(map(str, grays))
    assert COLOURLESS.match(f"pidc domain: note: {colourless['text']}")

    # a few images: one line each, as characterize's notes
    few = tmp_path / "few"
    (one,) = gray_copies(world["clear"], few, 1)
    shutil.copy(world["clear"] / "001.png", few / "plain.png")
    code, _, err = run(capsys, "domain", few, *reg)
    assert code == 0 and f"pidc domain: note: {one}: grayscale → RGB; no colour: outside the calibration" in err, err
    assert [(m["n"], m["total"]) for line in err.splitlines() if (m := COLOURLESS.match(line))] == [("1", "2")]

    # relate: once for the target and the sources together, counted over all their images
    code, out, err = run(
        capsys, "relate", folder, world["clear"], world["overcast"], "--registry", world["registry"],
        "--calibration-targets", 19, "--json", tmp_path / "r.json",
    )  # fmt: skip
    assert code == 0 and "verdict:" in out, err
    assert [(m["n"], m["total"]) for line in err.splitlines() if (m := COLOURLESS.match(line))] == [("8", "73")], err
    assert f"pidc relate: note: grayscale → RGB: 8 images ({shown} and 5 more)" in err
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["notes"]["grayscale → RGB"]["count"] == 8 and report["skipped_images"] == [
        {"image": str(folder / "broken.png"), "reason": "empty file (0 bytes)"}
    ]
    assert [c["kind"] for c in report["caveats"]] == ["colourless"]


def test_gray_pictures_stored_as_colour_get_the_colour_caveat(world, capsys, tmp_path):
    """A grayscale picture saved as RGB (PNG and JPEG: red = green = blue in every pixel) is noted and gets the colour
    caveat like a grayscale file; a colour render, or one whose pixels are gray but for one, does not."""
    folder = tmp_path / "g"
    folder.mkdir()
    with Image.open(world["clear"] / "003.png") as im:
        colour = np.asarray(im.convert("RGB"))
        gray = np.asarray(im.convert("L"))
    rgb = np.repeat(gray[:, :, None], 3, axis=2)
    Image.fromarray(rgb).save(folder / "a.png")
    Image.fromarray(rgb).save(folder / "b.jpg", quality=90)
    almost = rgb.copy()
    almost[5, 7, 2] ^= 1  # one pixel one level off gray: colour in the file, however little
    Image.fromarray(almost).save(folder / "c.png")
    Image.fromarray(colour).save(folder / "d.png")
    code, out, err = run(
        capsys, "characterize", folder, "--registry", world["registry"], "--samples", 100, "--json", tmp_path / "c.json"
    )
    assert code == 0 and len(parse_blocks(out)) == 4, err
    notes = {Path(item["image"]).name: item["note"] for item in json.loads((tmp_path / "c.json").read_text())["images"]}
    expected = (
        "gray in every pixel (red = green = blue: a grayscale picture stored as colour); no colour: outside the "
        "calibration (cues-tiny learned from colour renders)"
    )
    assert notes == {"a.png": expected, "b.jpg": expected, "c.png": None, "d.png": None}
    caveats = [m for line in err.splitlines() if (m := COLOURLESS.match(line))]
    assert [(m["n"], m["total"], m["kinds"]) for m in caveats] == [("2", "4", "gray in every pixel")], err

    # a grayscale file is said once, as grayscale, not also as gray in every pixel
    Image.fromarray(gray, mode="L").save(folder / "e.png")
    code, _, err = run(capsys, "domain", folder, "--registry", world["registry"], "--samples", 100)
    caveats = [m for line in err.splitlines() if (m := COLOURLESS.match(line))]
    assert code == 0 and [(m["n"], m["total"], m["kinds"]) for m in caveats] == [
        ("3", "5", "gray in every pixel, grayscale → RGB")
    ], err


def test_characterize_json_holds_each_images_notes_caveats_and_skips(world, capsys, tmp_path):
    """--json: a resized image's note carries the resize caveat (it was null), a grayscale one the colour caveat; the
    skipped images are listed with their reasons; the colour caveat is said once on stderr, naming how many."""
    folder = tmp_path / "c"
    (gray,) = gray_copies(world["clear"], folder, 1)
    big = folder / "big.png"
    with Image.open(world["clear"] / "002.png") as im:
        im.resize((64, 64)).save(big)
    (folder / "broken.png").write_text("not an image")
    code, out, err = run(
        capsys, "characterize", folder, "--registry", world["registry"], "--samples", 100, "--json", tmp_path / "c.json"
    )
    assert code == 0 and len(parse_blocks(out)) == 2, err
    report = json.loads((tmp_path / "c.json").read_text())
    notes = {item["image"]: item["note"] for item in report["images"]}
    assert notes[str(big)] == (
        "resized: 64×64 is not a size cues-tiny learned from (32×32 renders): outside the calibration measured in the "
        "pipeline"
    )
    assert (
        notes[str(gray)]
        == "grayscale → RGB; no colour: outside the calibration (cues-tiny learned from colour renders)"
    )
    assert report["skipped"] == 1 and report["skipped_images"] == [
        {
            "image": str(folder / "broken.png"),
            "reason": "not an image file, or a format Pillow cannot read (cannot identify image file)",
        }
    ]
    assert report["notes"]["resized"] == {"count": 1, "images": [str(big)]}
    assert sorted(c["kind"] for c in report["caveats"]) == ["colourless", "resized"]
    assert [(m["n"], m["total"]) for line in err.splitlines() if (m := COLOURLESS.match(line))] == [("1", "2")], err
    assert len([line for line in err.splitlines() if "learned from 32×32 renders; images of 64×64" in line]) == 1


def test_domain_says_what_the_skipped_images_weighed(world, capsys, tmp_path):
    folder = tmp_path / "w"
    shutil.copytree(world["mix"], folder)
    (folder / "c000.png").write_bytes(b"")  # weight 3 of 7, skipped
    (folder / "o001.png").write_text("not an image")  # weight 2 of 7, skipped
    weights = tmp_path / "w.csv"
    weights.write_text("c000.png,3\no001.png,2\nc001.png,1\no002.png,1\n")
    code, out, err = run(
        capsys, "domain", folder, "--registry", world["registry"], "--samples", 100, "--weights", weights,
        "--json", tmp_path / "d.json",
    )  # fmt: skip
    assert code == 0 and "2 images, weights from" in out, err
    assert (
        "pidc domain: note: weights of skipped images: 5 of 7 (71 %), left out of the domain with the 2 images " in err
    )
    report = json.loads((tmp_path / "d.json").read_text())
    assert report["skipped_weight"] == {"weight": 5.0, "total": 7.0, "share": pytest.approx(5 / 7), "images": 2}
    assert [s["image"] for s in report["skipped_images"]] == [str(folder / "c000.png"), str(folder / "o001.png")]
    # nothing skipped: no such line, no such key
    weights.write_text("c001.png,1\no002.png,1\n")
    code, _, err = run(
        capsys, "domain", folder, "--registry", world["registry"], "--samples", 100, "--weights", weights,
        "--json", tmp_path / "d.json",
    )  # fmt: skip
    assert (
        code == 0
        and "weights of skipped" not in err
        and "skipped_weight" not in json.loads((tmp_path / "d.json").read_text())
    )


def test_folders_given_as_dot_are_named_and_one_image_is_one_image(world, capsys, tmp_path, monkeypatch):
    """`.` and `..` name the folder they resolve to (relate's table, JSON and plot; domain's labels); a target of one
    image makes in-ODD targets "of 1 image"."""
    from components.cli.reading import folder_name

    target = tmp_path / "single"
    target.mkdir()
    shutil.copy(world["mix"] / "c000.png", target / "a.png")
    monkeypatch.chdir(world["clear"])
    code, out, err = run(
        capsys, "relate", target, ".", world["overcast"], "--registry", world["registry"], "--calibration-targets",
        19, "--json", tmp_path / "r.json",
    )  # fmt: skip
    assert code == 0, err
    assert re.search(r"^clear\s+32\s+\d\.\d{4}$", out, re.M), out
    assert "in-ODD targets of 1 image made from the sources" in out and "19 in-ODD targets of 1 image held" in out
    report = json.loads((tmp_path / "r.json").read_text())
    assert [s["name"] for s in report["sources"]] == ["clear", "overcast"] and report["target"]["name"] == "single"
    code, out, err = run(
        capsys, "domain", ".", "--registry", world["registry"], "--samples", 100, "--json", tmp_path / "d.json"
    )
    assert code == 0 and json.loads((tmp_path / "d.json").read_text())["name"] == "clear", err
    assert folder_name(Path(".")) == "clear" and folder_name(Path("..")) == world["root"].name
    assert folder_name(Path("/")) == "/" and folder_name(world["mix"]) == "mix"


@pytest.mark.parametrize(
    "store, message",
    [
        ("sqlite:///{tmp}/none.db", r"MLFLOW_TRACKING_URI=sqlite:///{tmp}/none\.db: {tmp}/none\.db: no such file"),
        ("sqlite:///{tmp}", r"MLFLOW_TRACKING_URI=sqlite:///{tmp}: {tmp}: a folder, not a database file"),
        ("file://{tmp}/mlruns", r"MLFLOW_TRACKING_URI=file://{tmp}/mlruns: {tmp}/mlruns: no such folder"),
        ("{tmp}/mlruns", r"MLFLOW_TRACKING_URI={tmp}/mlruns: {tmp}/mlruns: no such folder"),
        ("sqlite://", r"MLFLOW_TRACKING_URI=sqlite:// is an in-memory store, which holds no registered model"),
    ],
)
def test_a_tracking_uri_of_a_store_that_does_not_exist_is_refused(world, capsys, tmp_path, monkeypatch, store, message):
    """MLflow creates an empty store where MLFLOW_TRACKING_URI names a local one that does not exist, then fails: the
    CLI refuses it first, naming the URI, and creates nothing."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", store.format(tmp=tmp_path))
    uri = "models:/pidc@champion"
    code, out, err = run(
        capsys, "characterize", world["clear"] / "000.png", "--registry", world["registry"], "--model", uri
    )
    lines = err.strip().splitlines()
    assert code == 2 and out == "" and len(lines) == 1, err
    assert re.fullmatch(
        rf"pidc characterize: error: {uri}: " + message.format(tmp=re.escape(str(tmp_path))) + ".*", lines[0]
    ), err
    assert list(tmp_path.iterdir()) == []
