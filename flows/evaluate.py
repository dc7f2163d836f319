"""The ``evaluate`` stage: Task I for every model of the grid on the test split.

``python -m flows.evaluate [--params params.yaml]``. The models are the exported ones of ``registry/``, run on the
torch-free onnxruntime posterior (what a vehicle would run), ``evaluate.runner.workers`` models at a time (one
onnxruntime thread each). Per model (:mod:`components.evaluate.evaluation`, :mod:`components.evaluate.task1`): posterior
samples and their log-densities for ``evaluate.images`` test images (``all``: the whole split), HPD credibility of the
ground truth, expected coverage, calibration error beside the band of a perfectly calibrated model on as many images,
signed coverage area, superiority π, test NLL, information gain, a quantitative posterior predictive check, and per
parameter (:mod:`components.evaluate.marginals`) interval widths and coverage, median errors and marginal information
gain, for all, day and night truths. Writes ``reports/task1/`` (:mod:`components.evaluate.publish`): ``metrics.json``
(model → headline metrics), ``models/<model>.json`` (one flat row per model: the DVC metrics), ``parameters.json``
(model → subset → parameter → figures), ``profiles.json`` (the same by bin of the true value,
:mod:`components.evaluate.profile`), ``local.json`` (model → the named weathers' coverage beside an exact toy's and the
local test L-C2ST, :mod:`components.evaluate.named`), ``coverage.json``, ``table.md`` (the results table) and PNG plots; logs
them to each model's MLflow run; names the champion (:mod:`components.evaluate.champion`): MLflow aliases ``champion``
and ``challenger`` (the runner-up) and the pointer ``reports/task1/champion.json`` (written before the aliases move: a
kill between the two leaves the aliases behind the pointer, never ahead of it).

Each model's finished evaluation (its result and its plots) is kept under ``.cache/task1/<model>/<key>/``
(:meth:`ProjectPaths.kept`, outside the stage's DVC outputs, which DVC removes when the stage starts), written
atomically, the key covering all it depends on (:func:`evaluation_key`: the model card, the test data and features,
the settings, the code and library versions). A later run with the same key reuses it (the plots copied into
``reports/task1/plots/<model>/``), so a killed evaluate redoes only the models it had not finished; ``reports/task1/``
is the same to the byte whether a model was evaluated or reused (the flow uses the kept result in both cases).
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import inspect
import json
import platform
from pathlib import Path

from prefect import flow, task

from components.core import kept
from components.core.code import code_fingerprint
from components.core.config import Params
from components.core.files import sha256_file
from components.core.paths import ProjectPaths
from components.evaluate import evaluation, named, publish, task1
from components.evaluate.champion import NoChampionError, champion_pointer, choose_champion
from components.export.lookup import CHAMPION_POINTER
from components.features import cache as features
from components.simulate import dataset
from flows import tracking
from flows.stage import Stage, at_most, open_stage, parse_stage_args, share_api_with_workers, task_runner

#: The project module a model's evaluation (:func:`_evaluate_into`) runs: its import closure is the code of its key.
EVALUATION_MODULES = ("components.evaluate.evaluation",)
#: The libraries whose versions can change a model's figures or plot files (distribution names; absent ones count too).
EVALUATION_LIBRARIES = (
    "numpy",
    "onnxruntime",
    "scipy",
    "matplotlib",
    "pillow",
    "opencv-python-headless",
    "opencv-python",
    "torch",
)
#: The keys of a model's result (what :func:`_evaluate_into` returns and the flow reads).
RESULT_KEYS = ("model", "metrics", "coverage", "pi", "parameters", "profiles", "local")


def _library(dist: str) -> str:
    try:
        return f"{dist}=={importlib.metadata.version(dist)}"
    except importlib.metadata.PackageNotFoundError:
        return f"{dist} absent"


def evaluation_code() -> str:
    """The fingerprint of the code a model's evaluation runs: the import closure of :data:`EVALUATION_MODULES`
    (:func:`components.core.code.code_fingerprint`), the source of :func:`_evaluate_into` (this file's part), the
    Python and :data:`EVALUATION_LIBRARIES` versions."""
    extra = [
        f"python {platform.python_version()}",
        *map(_library, EVALUATION_LIBRARIES),
        inspect.getsource(_evaluate_into),
    ]
    return code_fingerprint(EVALUATION_MODULES, extra=extra)


def _features_identity(paths: ProjectPaths, backbone: str, split: dataset.Split, n: int) -> dict | None:
    """What identifies the cached features of ``backbone`` for the first ``n`` images of ``split``: the cache's
    backbone fingerprint and dataset hash (its manifest) and the sha256 of every shard read (their receipts); None
    when the cache is missing or damaged (the evaluation then fails with the cache's own error, and keeps nothing)."""
    store = features.FeatureStore(paths.features, backbone)
    try:
        manifest = json.loads((store.folder / "manifest.json").read_text())
        shards, have = [], 0
        for k, info in enumerate(split.manifest["splits"][split.name]["shards"]):
            if have >= n:
                break
            shards.append(json.loads(store.receipt_path(split.name, k).read_text())["sha256"])
            have += int(info["count"])
        return {
            "fingerprint": manifest["fingerprint"],
            "dataset_content_hash": manifest["dataset_content_hash"],
            "shards": shards,
        }
    except (OSError, ValueError, KeyError, TypeError):
        return None


def evaluation_key(
    params: Params, paths: ProjectPaths, model_id: str, split: dataset.Split, n: int, band: float, code: str
) -> tuple[str, dict]:
    """The key of ``model_id``'s evaluation (sha256 hex of its parts) and its parts: everything the evaluation reads,
    so that a kept one is reused only when nothing it depends on has changed — the model (sha256 of its card, which
    records its graphs' sha256), the test data (content hash) and the features read, the ``evaluate`` settings but
    the runner, the number of images and the calibration band, the seed, the prior box, the simulator (the PPC
    re-renders), the contents of the recorded named weathers' folders and the code (:func:`evaluation_code`)."""
    card_file = paths.registry / model_id / "card.json"
    backbone = json.loads(card_file.read_text())["backbone"]
    parts = {
        "model": model_id,
        "card_sha256": sha256_file(card_file),
        "data_content_hash": split.content_hash,
        "features": _features_identity(paths, backbone, split, n),
        "images": n,
        "band": band,
        "evaluate": params.evaluate.model_dump(mode="json", exclude={"runner"}),
        "seed": params.seed,
        "prior": params.model_dump(mode="json", include={"prior"})["prior"],
        "simulator": params.simulator.model_dump(mode="json"),
        # a recorded named weather's images (DVC does not track the folders: their contents key the evaluation)
        "named_folders": {
            name: named.folder_fingerprint(paths.root / folder)
            for name, folder in params.evaluate.named.folders.items()
        },
        "code": code,
    }
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest(), parts


def reuse_kept(paths: ProjectPaths, model_id: str, key: str, logger) -> dict | None:
    """``model_id``'s evaluation kept under ``key`` (:mod:`components.core.kept`), its plots restored into
    ``reports/task1/plots/<model>/``, or None (logged) when there is none or it cannot be trusted."""
    folder = paths.kept("task1", model_id)
    try:
        entry = kept.read(folder, key)
        if entry is not None:
            result = entry["result"]
            if not isinstance(result, dict) or result.get("model") != model_id or not set(RESULT_KEYS) <= set(result):
                raise kept.KeptError(f"{folder / key}: no complete result of {model_id}")
    except kept.KeptError as e:
        logger.warning("%s: kept evaluation ignored, evaluating again: %s", model_id, e)
        return None
    if entry is None:
        logger.info("%s: no kept evaluation for key %s…: evaluating", model_id, key[:12])
        return None
    result = kept.restore(folder, key, entry, paths.reports("task1", "plots", model_id))
    logger.info("%s: kept evaluation reused (key %s…)", model_id, key[:12])
    return result


@task(name="evaluate-model")
def evaluate_model(model_id: str, params_path: str, band: float, key: str, parts: dict) -> dict:
    """Task I of one exported model (``band``: the calibration band of the stage's number of images), kept under
    ``key`` (:func:`components.core.kept.keep`); returns the kept result, its plots copied into the reports, as a
    later run reusing it would."""
    stage = open_stage(params_path)
    folder = stage.paths.kept("task1", model_id)
    kept.keep(folder, key, lambda plot_dir: _evaluate_into(stage, model_id, band, plot_dir), parts)
    result = kept.restore(folder, key, kept.read(folder, key), stage.paths.reports("task1", "plots", model_id))
    stage.logger.info("%s: evaluation kept (key %s…)", model_id, key[:12])
    return result


def _evaluate_into(stage: Stage, model_id: str, band: float, plot_dir: Path) -> dict:
    """Task I of one exported model, its plots written into ``plot_dir``; the result (JSON-serializable,
    :func:`components.evaluate.evaluation.evaluate_exported`)."""
    return evaluation.evaluate_exported(stage.params, stage.paths, model_id, band, plot_dir, stage.logger)


def _results(stage: Stage, test: dataset.Split, n: int, band: float) -> tuple[list[dict], dict[str, str]]:
    """Every model's result in grid order, kept ones reused and the others evaluated ``evaluate.runner.workers`` at a
    time, the costliest first; and model id → the key it is kept under."""
    params, paths = stage.params, stage.paths
    ids = params.model_ids()
    cards = {m: json.loads((paths.registry / m / "card.json").read_text()) for m in ids}
    code = evaluation_code()
    keyed = {m: evaluation_key(params, paths, m, test, n, band, code) for m in ids}
    reused = {m: r for m in ids if (r := reuse_kept(paths, m, keyed[m][0], stage.logger)) is not None}
    if len(reused) < len(ids):
        evaluation.named_renders(params, paths)  # rendered once here, read by every model's task
    share_api_with_workers()
    done = at_most(
        params.evaluate.runner.workers,
        [m for m in task1.evaluation_order(ids, cards) if m not in reused],
        lambda m: evaluate_model.submit(m, str(stage.params_file), band, *keyed[m]),
        "evaluate models",
    )
    return [reused[m] if m in reused else done[m] for m in ids], {m: k for m, (k, _) in keyed.items()}


def _log_models(logger, metrics: dict[str, dict]) -> None:
    """One log line of headline figures per model."""
    for m, v in metrics.items():
        logger.info(
            "%s: calibration error %.3f (band %.3f: %s), coverage gap %+.3f, π median %.2f, NLL %.2f (information "
            "gain %.2f nats), PPC %.2f",
            m,
            v["calibration_error"],
            v["calibration_band"],
            "within" if v["within_band"] else "outside",
            v["coverage_auc_gap"],
            v["pi_median"],
            v["test_nll"],
            v["info_gain_nats"],
            v["ppc_score"],
        )


def _name_champion(stage: Stage, out: Path, grid: publish.GridReports, data_hash: str) -> None:
    """Choose the champion and the runner-up; write the table and ``champion.json``, move the MLflow aliases and
    describe the grid's run. Without a champion: no pointer, no aliases, the table without one, then
    :class:`NoChampionError`."""
    params, paths, metrics = stage.params, stage.paths, grid.metrics
    band_level = params.evaluate.band_level
    try:
        champion, runner_up = choose_champion(metrics, params.export.champion_max_calibration_error)
    except NoChampionError:
        (paths.root / CHAMPION_POINTER).unlink(missing_ok=True)  # no stale pick for task2, task3 and the CLI
        tracking.clear_champion_aliases(paths.root, params)  # nor for models:/pidc@champion (the monitoring)
        table = publish.write_table(out, grid.rows, None, band_level)
        tracking.describe_grid(paths.root, params, data_hash, metrics, None, table, grid.files)
        raise
    table = publish.write_table(out, grid.rows, champion.model, band_level)
    files = [*grid.files, out / "table.md"]
    pointer = publish.registered_pointer(
        champion_pointer(metrics, champion, runner_up), tracking.registered_model(params)
    )
    # the pointer first, then the aliases: a kill in between leaves the aliases behind champion.json, never ahead
    publish.write_json(paths.root / CHAMPION_POINTER, pointer)
    aliases = tracking.set_champion_alias(
        paths.root, params, metrics, champion.model, runner_up.model if runner_up else None, paths.registry
    )
    if aliases:  # the versions the aliases now name
        pointer = publish.with_versions(pointer, aliases, tracking.CHAMPION_ALIAS, tracking.CHALLENGER_ALIAS)
        publish.write_json(paths.root / CHAMPION_POINTER, pointer)
    tracking.describe_grid(paths.root, params, data_hash, metrics, pointer, table, files)
    stage.logger.info(
        "champion: %s (%s: %s), %s",
        champion.model,
        champion.rule,
        champion.reason,
        pointer.get("uri", "not in the MLflow Model Registry"),
    )
    if runner_up:
        stage.logger.info("runner-up (challenger): %s (%s)", runner_up.model, runner_up.rule)


@flow(name="evaluate", log_prints=True)
def evaluate(params_path: str) -> dict:
    """Evaluate every model of the grid; write reports/task1/, log to MLflow and name the champion."""
    stage = open_stage(params_path)
    params, paths, ev = stage.params, stage.paths, stage.params.evaluate
    out = paths.reports("task1")
    missing = [m for m in params.model_ids() if not (paths.registry / m / "card.json").is_file()]
    if missing:
        raise FileNotFoundError(f"no exported model in registry/ for {', '.join(missing)}: run `dvc repro export`")
    test = dataset.open_split(paths.data, "test")  # a missing test split fails here, before any work
    n = task1.images_evaluated(ev.images, len(test))
    band = task1.calibration_band(n, ev.samples, ev.band_level, ev.band_replicates, params.seed)
    results, keys = _results(stage, test, n, band)
    grid = publish.write_grid_reports(out, results, params, n, band)
    tracking.log_task1(paths.root, params.train.experiment, results, out / "plots")
    _log_models(stage.logger, grid.metrics)
    _name_champion(stage, out, grid, test.content_hash)
    for stale in kept.prune(paths.kept("task1"), keys):
        stage.logger.info("removed the stale kept evaluation %s", stale)
    return grid.metrics


def main(argv: list[str] | None = None) -> None:
    args, params = parse_stage_args("Task I evaluation of the grid (the evaluate stage).", argv)
    evaluate.with_options(task_runner=task_runner(params.evaluate.runner))(str(args.params))


if __name__ == "__main__":
    main()
