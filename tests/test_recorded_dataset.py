"""Recorded datasets (``simulator.backend: recorded``): `pidc record` writes a folder of images and labels from a
simulator, the generate stage imports it into the same shards as rendered data, and every bad input is one line naming
the file and the row.

The known answers: a folder recorded from the procedural renderer's own plan must import to the very bytes (images and
weather) the generate stage renders for that plan, so the same model gives the same Task I figures on it; an import is
a pure function of the folder's files and the params, so importing twice gives the same content hash.
"""

from __future__ import annotations

import csv
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from components.core.config import ConfigError, load_params, parse_params
from components.simulate import dataset, recorded
from components.simulate.contact_sheet import save_png
from components.simulate.labels import LABELS, RecordedError
from components.simulate.resized import area_resize
from tests.conftest import FAST_TRAINING, build_project, copy_project, micro_params, run_in, write_params

#: a small plan: 8 + 4 + 4 images, 4 to a scene (so 2, 1 and 1 scenes)
SMALL = {
    "data.splits": {"train": 8, "val": 4, "test": 4},
    "train.sizes": [4, 8],
    "train.variants": {},
    "evaluate.images": 4,
}


def _record(folder: Path, out: Path, **overrides) -> Path:
    """``pidc record OUT`` of a micro params file written into ``folder`` (every split of the generate stage's plan)."""
    from components.cli.main import main

    params = write_params(folder, **overrides)
    assert main(["record", str(out), "--params", str(params)]) == 0
    return out


def _recorded_params(folder: Path | str, *, labels: str = LABELS, renderer=None, **overrides):
    """Micro params (``overrides`` as for :func:`micro_params`) importing the recorded ``folder``."""
    p = micro_params(**overrides)
    p["simulator"].update(backend="recorded")
    p["simulator"]["recorded"] = {"folders": [str(folder)], "labels": labels, "renderer": renderer}
    return parse_params(p)


def _import(params, root: Path, project: Path = Path("/")) -> dict:
    """What the generate stage does with recorded data, without Prefect: plan, import the unfinished shards, write the
    manifest. Returns the manifest."""
    imported = recorded.plan_import(params, project)
    for p in imported.plans:
        for spec in p.plan.shards():
            if not dataset.shard_is_done(spec, root):
                recorded.import_shard(p.rows(spec), (params.simulator.height, params.simulator.width), root)
    return dataset.write_manifest(
        root,
        [p.plan for p in imported.plans],
        renderer_version=recorded.SOURCE_KIND,
        resolution=(params.simulator.height, params.simulator.width),
        seed=params.seed,
        box=params.box,
        images_per_scene=None,
        source=recorded.source_entry(imported, root),
    )


def _rows(folder: Path) -> tuple[list[str], list[dict]]:
    with open(folder / LABELS, newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def _write_rows(folder: Path, header: list[str], rows: list[dict]) -> None:
    with open(folder / LABELS, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=header, extrasaction="ignore", lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)


@pytest.fixture(scope="module")
def small_folder(tmp_path_factory) -> Path:
    """A recorded folder of the SMALL plan (16 images), recorded once; copy it before changing it."""
    base = tmp_path_factory.mktemp("small")
    return _record(base / "project", base / "recorded", **SMALL)


@pytest.fixture
def folder(small_folder, tmp_path) -> Path:
    return Path(shutil.copytree(small_folder, tmp_path / "recorded"))


# --- the round trip ----------------------------------------------------------------------------------------------


def test_a_recording_of_the_renderers_plan_imports_to_the_rendered_bytes(small_folder, tmp_path):
    """Recorded images are lossless PNGs and the labels hold each float's repr: the imported splits hold the very images
    and weather rows (azimuth and fixed values included) the generate stage renders for the same plan, in its order."""
    from components.simulate.base import make_simulator

    params = load_params(write_params(tmp_path / "rendered", **SMALL))
    simulator = make_simulator(params.simulator)
    plans = recorded.split_plans(params, list(dataset.SPLITS), None, simulator.version)
    for plan in plans:
        for spec in plan.shards():
            dataset.render_shard(plan.rows(spec), simulator, tmp_path / "rendered-data")
    dataset.write_manifest(
        tmp_path / "rendered-data",
        plans,
        renderer_version=simulator.version,
        resolution=(32, 32),
        seed=params.seed,
        box=params.box,
        images_per_scene=4,
    )
    manifest = _import(_recorded_params(small_folder, **SMALL), tmp_path / "data")
    for plan in plans:
        rendered = dataset.open_split(tmp_path / "rendered-data", plan.name)
        imported = dataset.open_split(tmp_path / "data", plan.name, verify=True)
        assert np.array_equal(imported.images(), rendered.images()), plan.name
        assert np.array_equal(imported.weather, rendered.weather), plan.name
        assert np.array_equal(imported.scene_id, rendered.scene_id)  # sequences = the renderer's scenes, in order
        assert (imported.scene_seed == recorded.NO_SCENE_SEED).all()
    assert manifest["source"]["kind"] == "recorded" and manifest["source"]["resized"] == 0
    assert manifest["source"]["splits_from"] == "the split column" and manifest["source"]["left_out"] == 0
    assert manifest["renderer"] == "recorded" and manifest["images_per_scene"] is None


def test_importing_twice_gives_the_same_bytes_and_content_hash(small_folder, tmp_path, prefect_harness):
    """Through the generate flow: two imports into two data folders give byte-identical shards, manifests and content
    hashes; a second run over the first skips every shard (resumable) and writes the contact sheet of recorded images."""
    from flows.generate import generate

    runs = []
    for k in (1, 2):
        project = tmp_path / f"project{k}"
        p = micro_params(**SMALL)
        p["simulator"].update(backend="recorded")
        p["simulator"]["recorded"] = {"folders": [str(small_folder)], "labels": LABELS, "renderer": None}
        project.mkdir()
        (project / "params.yaml").write_text(yaml.safe_dump(p, sort_keys=False))
        runs.append(generate(str(project / "params.yaml")))
        assert (project / "reports/data/contact_sheet.png").stat().st_size > 1000
    assert runs[0]["content_hash"] == runs[1]["content_hash"]
    files = sorted(p.relative_to(tmp_path / "project1/data") for p in (tmp_path / "project1/data").rglob("*.npz"))
    assert len(files) == 3
    for f in [*files, Path("manifest.json")]:
        assert (tmp_path / "project1/data" / f).read_bytes() == (tmp_path / "project2/data" / f).read_bytes(), f
    mtime = (tmp_path / "project1/data" / files[0]).stat().st_mtime_ns
    again = generate(str(tmp_path / "project1/params.yaml"))
    assert again == runs[0] and (tmp_path / "project1/data" / files[0]).stat().st_mtime_ns == mtime


def test_an_interrupted_import_resumes_and_a_changed_image_is_imported_again(folder, tmp_path):
    """A shard deleted and another truncated (a killed run) are imported again to the same bytes, the finished one left
    alone; an image whose file changes changes its split's plan, so that split is imported again (content hash moves)."""
    params = _recorded_params(folder, **SMALL)
    first = _import(params, tmp_path / "data")
    snapshot = {p: p.read_bytes() for p in (tmp_path / "data").rglob("shard-*.npz")}
    (tmp_path / "data/train/shard-00000.npz").unlink()
    val = tmp_path / "data/val/shard-00000.npz"
    val.write_bytes(val.read_bytes()[:500])
    untouched = tmp_path / "data/test/shard-00000.npz"
    mtime = untouched.stat().st_mtime_ns
    second = _import(params, tmp_path / "data")
    assert second["content_hash"] == first["content_hash"]
    assert all(p.read_bytes() == data for p, data in snapshot.items())
    assert untouched.stat().st_mtime_ns == mtime

    image = folder / "test/scene-000000/000001.png"
    save_png(image, 255 - dataset.open_split(tmp_path / "data", "test").images()[1])  # another valid image
    third = _import(_recorded_params(folder, **SMALL), tmp_path / "data")
    assert third["content_hash"] != first["content_hash"]
    assert third["splits"]["train"] == first["splits"]["train"] and third["splits"]["test"] != first["splits"]["test"]


def test_parquet_labels_import_as_the_csv_does(folder, tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    header, rows = _rows(folder)
    numeric = [c for c in header if c not in ("image", "sequence", "split")]
    table = {c: [float(r[c]) if c in numeric else r[c] for r in rows] for c in header}
    pq.write_table(pa.table(table), folder / "labels.parquet")
    from_csv = _import(_recorded_params(folder, **SMALL), tmp_path / "csv")
    (folder / LABELS).unlink()  # the folder holds the Parquet labels only
    from_parquet = _import(_recorded_params(folder, labels="labels.parquet", **SMALL), tmp_path / "parquet")
    assert from_parquet["content_hash"] == from_csv["content_hash"]

    table["sun_altitude_angle"][2] = 120.0
    pq.write_table(pa.table(table), folder / "labels.parquet")
    with pytest.raises(RecordedError, match=r"labels\.parquet, row 3, column sun_altitude_angle: 120 lies outside"):
        recorded.plan_import(_recorded_params(folder, labels="labels.parquet", **SMALL), Path("/"))


# --- splits by sequence ------------------------------------------------------------------------------------------


def _regroup(folder: Path, per_sequence: int, column: bool) -> None:
    """Rewrite the folder's labels without the split column: sequences of ``per_sequence`` images, named in a
    ``sequence`` column (interleaved rows: a sequence's frames are not consecutive), or as sub-folders."""
    header, rows = _rows(folder)
    header = [c for c in header if c not in ("split", "sequence")]
    for i, r in enumerate(rows):
        seq = f"drive{i % (len(rows) // per_sequence)}"
        if column:
            r["sequence"] = seq
        else:
            target = folder / seq / f"frame{i:03d}.png"
            target.parent.mkdir(exist_ok=True)
            (folder / r["image"]).rename(target)
            r["image"] = f"{seq}/frame{i:03d}.png"
    _write_rows(folder, header + (["sequence"] if column else []), rows)


@pytest.mark.parametrize("column", [True, False], ids=["sequence-column", "sub-folders"])
def test_splits_are_drawn_by_whole_sequence_and_never_share_one(folder, tmp_path, column):
    """16 images in 8 sequences of 2, dealt to test (4), val (4) and train (8): every split has its size and no sequence
    lies in two splits; the draw is the same on every run and follows the seed."""
    _regroup(folder, 2, column)
    params = _recorded_params(folder, **SMALL)
    imported = recorded.plan_import(params, Path("/"))
    header, rows = _rows(folder)
    by_file = {
        str((folder / r["image"]).resolve()): r.get("sequence") or Path(r["image"]).parent.as_posix() for r in rows
    }
    splits_of: dict[str, set[str]] = {}
    for plan in imported.plans:
        assert len(plan.plan) == params.data.splits[plan.plan.name]
        for file in plan.files:
            splits_of.setdefault(by_file[file], set()).add(plan.plan.name)
    assert all(len(s) == 1 for s in splits_of.values()), splits_of
    again = recorded.plan_import(params, Path("/"))
    assert [p.files for p in again.plans] == [p.files for p in imported.plans]
    other = recorded.plan_import(_recorded_params(folder, seed=7, **SMALL), Path("/"))
    assert [p.files for p in other.plans] != [p.files for p in imported.plans]
    source = _import(params, tmp_path / "data")["source"]
    assert source["splits_from"] == "whole sequences drawn from the seed" and source["sequences"] == 8


def test_a_sequence_cut_at_a_split_boundary_leaves_its_other_frames_out(folder, tmp_path):
    """Sequences of 3 frames cannot fill splits of 4 exactly: each split's last sequence is cut and its other frames
    are left out, never put into another split (counted in the manifest)."""
    header, rows = _rows(folder)
    rows = rows + [dict(r, image=f"extra{i}.png") for i, r in enumerate(rows[:5])]  # 21 images: 7 sequences of 3
    for i in range(5):
        save_png(folder / f"extra{i}.png", np.full((32, 32, 3), 17 + i, np.uint8))  # new, distinct images
    for i, r in enumerate(rows):
        r["sequence"] = f"drive{i // 3}"
    _write_rows(folder, [c for c in header if c != "split"], rows)
    params = _recorded_params(folder, **SMALL)
    manifest = _import(params, tmp_path / "data")
    assert {k: v["count"] for k, v in manifest["splits"].items()} == {"train": 8, "val": 4, "test": 4}
    assert manifest["source"]["images"] == 21 and manifest["source"]["left_out"] == 5  # 2 + 2 + 1 frames cut
    sequence = {str((folder / r["image"]).resolve()): r["sequence"] for r in rows}
    used = [{sequence[f] for f in p.files} for p in recorded.plan_import(params, Path("/")).plans]
    assert not (used[0] & used[1] or used[0] & used[2] or used[1] & used[2])


# --- images of another size ----------------------------------------------------------------------------------------


def test_larger_images_are_area_resized_and_the_card_records_it(folder, tmp_path):
    """Images recorded at 64×64 and 128×128 become the exact area average at 32×32 (as the camera-like renders); the
    receipts and the manifest count them, and the export stage copies that into the model card."""
    from flows.export import _recorded

    header, rows = _rows(folder)
    originals = {}
    for i, r in enumerate(rows[:3]):
        big = np.random.default_rng(i).integers(0, 256, (64 * (1 + i % 2), 64 * (1 + i % 2), 3), dtype=np.uint8)
        save_png(folder / r["image"], big)
        originals[r["image"]] = big
    params = _recorded_params(folder, **SMALL)
    manifest = _import(params, tmp_path / "data")
    assert manifest["source"]["resized"] == 3
    assert manifest["source"]["source_sizes"] == {"32x32": 13, "64x64": 2, "128x128": 1}
    train = dataset.open_split(tmp_path / "data", "train").images()
    for i, r in enumerate(rows[:3]):
        assert np.array_equal(train[i], area_resize(originals[r["image"]], (32, 32)))
    card = _recorded(tmp_path / "data")["recorded"]
    assert card["resized"] == 3 and card["source_sizes"]["64x64"] == 2 and card["used"] == 16


@pytest.mark.parametrize(
    "shape, message",
    [
        ((16, 16, 3), r"16×16 pixels is smaller than the dataset's 32×32"),
        ((64, 96, 3), r"96×64 pixels has another aspect"),
    ],
)
def test_images_smaller_or_of_another_aspect_are_refused(folder, tmp_path, shape, message):
    header, rows = _rows(folder)
    save_png(folder / rows[1]["image"], np.full(shape, 90, np.uint8))
    with pytest.raises(RecordedError, match=message + r".*named on .*labels\.csv, line 3") as e:
        _import(_recorded_params(folder, **SMALL), tmp_path / "data")
    assert "\n" not in str(e.value)


# --- every bad input: one line naming the file and the row --------------------------------------------------------


def _missing_image(folder, header, rows):
    (folder / rows[4]["image"]).unlink()
    return rf"{rows[4]['image']}: missing image \(named on line 6 of .*labels\.csv\)"


def _extra_image(folder, header, rows):
    save_png(folder / "train/stray.png", np.full((32, 32, 3), 3, np.uint8))
    return r"train/stray\.png: extra image: it lies in .* but no row of .*labels\.csv names it"


def _outside_box(folder, header, rows):
    rows[2]["precipitation"] = "101"
    _write_rows(folder, header, rows)
    return r"labels\.csv, line 4, column precipitation: 101 lies outside \[0, 100\] %"


def _missing_column(folder, header, rows):
    _write_rows(folder, [c for c in header if c != "fog_density"], rows)
    return r"labels\.csv: missing column\(s\) fog_density"


def _fixed_value(folder, header, rows):
    rows[0]["fog_distance"] = "75"
    _write_rows(folder, header, rows)
    return r"labels\.csv, line 2, column fog_distance: 75, but pidc fixes fog_distance to 0\.75"


def _truncated(folder, header, rows):
    path = folder / rows[5]["image"]
    path.write_bytes(path.read_bytes()[:200])
    return rf"{rows[5]['image']}: .*(truncated|damaged PNG).*\(named on .*labels\.csv, line 7\)"


def _unreadable(folder, header, rows):
    (folder / rows[6]["image"]).write_bytes(b"this is not an image at all")
    return rf"{rows[6]['image']}: not an image file.*\(named on .*labels\.csv, line 8\)"


def _duplicate_entry(folder, header, rows):
    rows[3]["image"] = rows[1]["image"]
    _write_rows(folder, header, rows)
    return rf"labels\.csv, line 5, column image: '{rows[1]['image']}' is listed twice \(lines 3 and 5\)"


def _duplicate_bytes(folder, header, rows):
    shutil.copy(folder / rows[0]["image"], folder / rows[9]["image"])
    return rf"{rows[9]['image']}: duplicate image: the same bytes as .*{rows[0]['image']}.*\(named on line 11 of"


def _split_too_small(folder, header, rows):
    return (
        r"labels\.csv: split train too small: data\.splits\.train is 12 images \(train\.sizes go up to 12: .*\), but "
        r"the split column gives it 8"
    )


def _drawn_too_small(folder, header, rows):
    _write_rows(folder, [c for c in header if c != "split"], rows)
    return r"split train too small: data\.splits\.train is 12 images .*only 8 images in whole sequences are left for it"


def _sequence_in_two_splits(folder, header, rows):
    rows[0]["split"] = "test"
    _write_rows(folder, header, rows)
    return r"labels\.csv, line 3, column split: sequence 'train/scene-000000' is in split train here and in split test"


BAD = {
    "missing image": (_missing_image, {}),
    "extra image": (_extra_image, {}),
    "label outside the prior box": (_outside_box, {}),
    "missing column": (_missing_column, {}),
    "fixed parameter of another value": (_fixed_value, {}),
    "truncated PNG": (_truncated, {}),
    "unreadable file": (_unreadable, {}),
    "duplicate file entries": (_duplicate_entry, {}),
    "duplicate image bytes": (_duplicate_bytes, {}),
    "split too small for train.sizes": (_split_too_small, {"data.splits": {"train": 12, "val": 4, "test": 4}}),
    "drawn split too small": (_drawn_too_small, {"data.splits": {"train": 12, "val": 4, "test": 4}}),
    "a sequence in two splits": (_sequence_in_two_splits, {}),
}


@pytest.mark.parametrize("case", list(BAD))
def test_every_bad_input_is_one_line_naming_the_file_and_row(folder, tmp_path, case):
    damage, overrides = BAD[case]
    header, rows = _rows(folder)
    message = damage(folder, header, rows)
    if overrides:  # a larger train split: train.sizes may go up to it
        overrides = {**overrides, "train.sizes": [4, 12]}
    params = _recorded_params(folder, **(SMALL | overrides))
    with pytest.raises(RecordedError, match=message) as e:
        _import(params, tmp_path / "data")
    assert "\n" not in str(e.value) and str(folder) in str(e.value)
    assert not (tmp_path / "data/manifest.json").exists()


def test_backend_recorded_needs_folders_named_in_the_config(tmp_path):
    p = micro_params()
    p["simulator"]["backend"] = "recorded"
    with pytest.raises(ConfigError, match=r"simulator: recorded\.folders is empty but backend is recorded"):
        parse_params(p)
    p["simulator"]["recorded"]["folders"] = ["a", "a"]
    with pytest.raises(ConfigError, match=r"simulator\.recorded\.folders: .*each value at most once"):
        parse_params(p)
    p["simulator"]["recorded"].update(folders=["a"], labels="labels.txt")
    with pytest.raises(ConfigError, match=r"simulator\.recorded\.labels"):
        parse_params(p)
    with pytest.raises(RecordedError, match=r"nowhere: no such folder"):
        recorded.plan_import(_recorded_params("nowhere"), tmp_path)


# --- pidc record -------------------------------------------------------------------------------------------------


def test_pidc_record_resumes_after_a_kill_and_refuses_another_plan(small_folder, tmp_path, capsys):
    """A recording killed after 5 images has no labels yet; the same command again renders the other 11 and gives the
    folder an uninterrupted recording gives (the same images, byte for byte, and labels); a third run renders nothing.
    Another plan into the same folder is refused rather than mixed."""
    from components.cli.main import main
    from components.simulate.base import make_simulator

    params = load_params(write_params(tmp_path / "project", **SMALL))
    simulator = make_simulator(params.simulator)
    plans = recorded.split_plans(params, list(dataset.SPLITS), None, simulator.version)
    seen = []

    def killed(n):
        seen.append(n)
        if len(seen) == 5:
            raise KeyboardInterrupt("killed")

    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        recorded.record(simulator, plans, out, progress=killed)
    assert not (out / LABELS).exists() and len(list(out.rglob("*.png"))) == 5
    capsys.readouterr()
    assert main(["record", str(out), "--params", str(tmp_path / "project/params.yaml")]) == 0
    assert "recorded 16 images of train, val, test" in capsys.readouterr().out.replace("\n", " ")
    assert recorded.record(simulator, plans, out) == {
        "images": 16,
        "rendered": 0,
        "kept": 16,
        "labels": str(out / LABELS),
    }
    for f in small_folder.rglob("*"):
        if f.is_file():
            assert (out / f.relative_to(small_folder)).read_bytes() == f.read_bytes(), f
    code = main(["record", str(out), "--params", str(tmp_path / "project/params.yaml"), "--count", "2"])
    assert code == 2 and "holds a recording of another plan" in capsys.readouterr().err


def test_pidc_record_needs_a_simulator_backend(tmp_path, capsys):
    from components.cli.main import main

    p = micro_params()
    p["simulator"].update(backend="recorded")
    p["simulator"]["recorded"]["folders"] = ["x"]
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(p))
    assert main(["record", str(tmp_path / "out"), "--params", str(tmp_path / "params.yaml")]) == 2
    assert "simulator.backend is recorded, which renders nothing" in capsys.readouterr().err
    command = ["record", str(tmp_path / "t"), "--params", str(tmp_path / "params.yaml"), "--backend", "procedural"]
    assert main([*command, "--split", "test", "--count", "3"]) == 0
    assert len(_rows(tmp_path / "t")[1]) == 3


def test_the_monitoring_reads_a_recorded_folder(small_folder):
    """One format: the scheduled monitoring's reader takes what `pidc record` writes (its first rows)."""
    from components.core import weather
    from components.monitor.recorded import read_recorded

    rec = read_recorded(small_folder, weather.Box.full(), limit=3)
    assert rec.names == [r["image"] for r in _rows(small_folder)[1][:3]]
    assert all(im.shape == (32, 32, 3) for im in rec.images)


# --- the whole pipeline on a recorded folder ------------------------------------------------------------------------


def _untimed(value):
    """``value`` without its run times (keys ending in ``_seconds``), which differ from run to run."""
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if not str(k).endswith("_seconds")}
    return [_untimed(v) for v in value] if isinstance(value, list) else value


def _task1(project: Path) -> dict:
    metrics = json.loads((project / "reports/task1/metrics.json").read_text())
    return {m: {k: v for k, v in row.items() if k not in ("ppc_score", "ppc_images")} for m, row in metrics.items()}


@pytest.mark.slow
def test_a_recorded_folder_runs_the_micro_pipeline_to_the_same_task1_figures(
    micro_project, tmp_path_factory, prefect_server
):
    """The micro project's plan recorded from the renderer (every split) and imported by `dvc repro` with
    ``backend: recorded``: the data are the rendered ones to the byte, the grid trains on them, a champion is named,
    Task II (bag rendered by ``simulator.recorded.renderer: procedural``) and Task III run; the same images give the same
    models (weights are identical on one machine), hence the same Task I figures as the rendered project (the posterior
    predictive check aside: skipped), and the same champion the same Task II and III figures. Without a renderer,
    Task II is skipped with its reason."""
    base = tmp_path_factory.mktemp("recorded-pipeline")
    folder = _record(base / "plan", base / "recorded", **FAST_TRAINING)
    overrides = {
        **FAST_TRAINING,
        "simulator.backend": "recorded",
        "simulator.recorded": {"folders": [str(folder)], "labels": LABELS, "renderer": "procedural"},
    }
    project = build_project(base / "repo", prefect_server, **overrides)

    manifest = json.loads((project / "data/manifest.json").read_text())
    assert manifest["source"]["kind"] == "recorded" and manifest["source"]["used"] == 88
    for name in dataset.SPLITS:
        mine, rendered = dataset.open_split(project / "data", name), dataset.open_split(micro_project / "data", name)
        assert np.array_equal(mine.images(), rendered.images()) and np.array_equal(mine.weather, rendered.weather)

    champion = json.loads((project / "reports/task1/champion.json").read_text())
    assert champion["model"] in load_params(project / "params.yaml").model_ids()
    metrics = json.loads((project / "reports/task1/metrics.json").read_text())
    assert all(np.isnan(m["ppc_score"]) and m["ppc_images"] == 0 for m in metrics.values())
    assert _task1(project) == _task1(micro_project)

    task2 = json.loads((project / "reports/task2/metrics.json").read_text())
    assert task2["bag_renderer"].startswith("procedural") and "recorded images" in task2.pop("bag_note")
    assert np.isfinite(task2["energy_distance_sq"]["all"]["ratio"])
    # the same champion on the same renders of the bag, the same test split for Task III: the same figures
    assert task2 == json.loads((micro_project / "reports/task2/metrics.json").read_text())
    task3 = json.loads((project / "reports/task3/metrics.json").read_text())
    assert _untimed(task3) == _untimed(json.loads((micro_project / "reports/task3/metrics.json").read_text()))
    card = json.loads((project / f"registry/{champion['model']}/card.json").read_text())
    assert card["training_renders"]["simulator"] == "recorded" and card["training_renders"]["recorded"]["resized"] == 0

    # without a renderer for its bag, Task II is skipped and says why (no simulator is substituted)
    copy = copy_project(project, base / "no-renderer")
    p = yaml.safe_load((copy / "params.yaml").read_text())
    p["simulator"]["recorded"]["renderer"] = None
    (copy / "params.yaml").write_text(yaml.safe_dump(p, sort_keys=False))
    r = run_in([sys.executable, "-m", "flows.task2"], copy, env={"PREFECT_API_URL": prefect_server})
    assert r.returncode == 0, r.stdout + r.stderr
    skipped = json.loads((copy / "reports/task2/metrics.json").read_text())
    assert list(skipped) == ["skipped"] and "simulator.recorded.renderer is null" in skipped["skipped"]
