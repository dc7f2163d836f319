"""Scheduled monitoring: the registered models judged on new labelled images at every run. Not a DVC stage.

``python -m flows.monitor [--params params.yaml] [--date YYYY-MM-DD] [--models champion|all] [--source simulator|DIR]``,
and the deployments ``monitor/nightly`` (the champion) and ``monitor/weekly`` (every model) of ``prefect.yaml``.

A run is named by its date: the ``date`` parameter, else the UTC date of its scheduled start. It draws what it judges
from that date (:mod:`components.monitor.draws`), so each day brings new images and targets:

- Task I: ``monitor.images`` new images rendered by the simulator from the date's seed (or the first ones of a folder
  of recorded images with their labels, :mod:`components.monitor.recorded`), ``monitor.samples`` posterior draws each:
  the calibration error against the band of a perfectly calibrated model on as many images and draws (at the level
  1 − (1 − ``monitor.alarm_level``)/k for k models judged, :func:`components.monitor.checks.model_level`), test NLL,
  information gain, π, coverage;
- Task III: ``monitor.false_alarm_targets`` in-ODD targets of new seeds — their in-ODD part from new images of the
  sources' weather (simulated, or the recorded images whose labels lie in a source's bag) — related to the pipeline's
  source bags and decided with the threshold the ``task3`` stage calibrated (``reports/task3/metrics.json``), for the
  model it was calibrated for.

The models are registered versions of ``export.registered_model`` loaded from MLflow: the champion by its alias URI
``models:/pidc@champion``, or every model's newest version (``monitor.models`` or the ``models`` parameter). Writes
``reports/monitoring/<date>/<champion|all>/`` (``metrics.json``, ``coverage.png``) and one MLflow run ``monitor-<date>``
in ``monitor.experiment`` (:func:`flows.tracking.log_monitoring`); neither is a DVC output or dependency. Ends FAILED
(:class:`components.monitor.checks.MonitoringAlarm`, after writing both, the MLflow run marked FAILED) when a model's
calibration error leaves its band or the ODD false-alarm count leaves its interval (:mod:`components.monitor.checks`).
"""

from __future__ import annotations

import datetime
import json
import time

import numpy as np
from prefect import flow, task
from prefect.cache_policies import NO_CACHE
from prefect.runtime import flow_run

from components import plots
from components.core.config import Params
from components.core.files import atomic_write_bytes
from components.core.images import map_by_size
from components.core.paths import ProjectPaths
from components.domains.task3 import build_sweep
from components.evaluate import task1
from components.export.lookup import load_registered
from components.monitor import checks, draws
from components.monitor.recorded import read_recorded
from components.simulate.base import make_simulator
from flows import tracking
from flows.stage import open_stage, parse_stage_args

SIMULATOR = "simulator"


@task(name="monitor-model", cache_policy=NO_CACHE)  # holds images and onnxruntime sessions
def judge_model(
    entry: tracking.MonitoredModel,
    params: Params,
    paths: ProjectPaths,
    draw: draws.Draw,
    seed: int,
    band: float,
    level: float,
) -> dict:
    """Task I of one registered version on the run's images (``band``: the calibration band at their number, the
    ``level`` quantile of a perfectly calibrated model's error)."""
    folder = tracking.download_registered_model(entry.uri, paths.root)
    model = load_registered(folder)
    if model.name != entry.model:
        raise ValueError(
            f"{entry.uri}: its card names model {model.name!r}, its version tag pidc.model {entry.model!r}"
        )
    task1.check_model_matches_data(model.posterior.box, params, folder / "card.json")
    x = map_by_size(draw.images, model.inputs)
    samples = params.monitor.samples
    _, lp, lp_truth = task1.posterior_draws(model.posterior, x, draw.theta, samples, seed)
    metrics, coverage, _ = task1.task1_metrics(lp, lp_truth, params.box.log_volume(), band)
    metrics |= {"images": len(draw), "samples": samples, "calibration_level": level}
    # images of a size the model did not learn from: resized, outside what the calibration covers
    if model.training_renders is not None:
        metrics["resized_images"] = sum(not model.learned_size(im.shape[:2]) for im in draw.images)
    return {"model": entry.model, "folder": str(folder), "metrics": metrics, "coverage": coverage.tolist()}


@task(name="monitor-odd", cache_policy=NO_CACHE)
def check_odd(
    params: Params,
    paths: ProjectPaths,
    folder: str,
    calibrated: checks.CalibratedOdd,
    pools: dict[str, draws.Draw] | None,
    seed: int,
) -> checks.FalseAlarmTest:
    """The ODD decision of ``calibrated`` on ``monitor.false_alarm_targets`` in-ODD targets of the root ``seed``:
    fresh ones with the new images ``pools`` (source → images of its weather) when it was calibrated on fresh targets,
    else the paper's."""
    model = load_registered(folder)  # one onnxruntime thread: many small calls
    inputs = [map_by_size(pools[s].images, model.inputs) for s in params.task3.sources] if pools else None
    sweep, _, _ = build_sweep(params, paths, model, inputs)
    fresh = calibrated.calibrated_on == "fresh"
    check, _ = sweep.check_false_alarms(calibrated.detector, params.monitor.false_alarm_targets, seed, fresh=fresh)
    return checks.FalseAlarmTest.of(check, calibrated.detector, params.monitor.alarm_level)


def _odd(params: Params, paths: ProjectPaths, day, source: str, draw: draws.Draw, simulator, judged: dict, logger):
    """The Task III check: ``(test or None, the model it judged or None, what to report)``."""
    if params.monitor.false_alarm_targets == 0:
        return None, None, {"skipped": "monitor.false_alarm_targets is 0"}
    path = paths.reports("task3", "metrics.json")
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no Task III metrics, so no calibrated ODD threshold: run `dvc repro task3` (or set "
            "monitor.false_alarm_targets: 0)"
        )
    calibrated = checks.CalibratedOdd.from_metrics(json.loads(path.read_text()), path)
    if sorted(calibrated.bag_sizes) != sorted(params.task3.sources):
        raise ValueError(
            f"{path} has the source bags {sorted(calibrated.bag_sizes)}, task3.bags the sources "
            f"{params.task3.sources}: the Task III report is stale; run `dvc repro task3`"
        )
    setting = {
        "model": calibrated.model,
        "targets": calibrated.calibrated_on,
        "threshold": calibrated.detector.threshold,
    }
    setting |= {"calibration_targets": calibrated.detector.n_calibration, "rank": calibrated.detector.rank}
    if calibrated.model not in judged:
        reason = f"{path} calibrated the threshold for {calibrated.model}, which this run does not judge"
        logger.warning("ODD check skipped: %s", reason)
        return None, None, setting | {"skipped": reason}
    sources, pools = params.task3.sources, None
    if calibrated.calibrated_on == "fresh":
        if source == SIMULATOR:
            sizes = {s: calibrated.pool_sizes[s] or calibrated.bag_sizes[s] for s in sources}
            pools = draws.simulated_pools(simulator, params, draws.run_seed(params.seed, day, "odd-pools"), sizes)
        else:
            pools = draws.pools_of(draw, params.task3.bags, sources)
            short = [
                f"{s}: {len(pools[s])} < {calibrated.bag_sizes[s]}"
                for s in sources
                if len(pools[s]) < calibrated.bag_sizes[s]
            ]
            if short:
                reason = f"too few recorded images of the sources' weather for a fresh target ({', '.join(short)})"
                logger.warning("ODD check skipped: %s", reason)
                return None, None, setting | {"skipped": reason}
        setting["pools"] = {s: len(p) for s, p in pools.items()}
    test = check_odd(
        params, paths, judged[calibrated.model], calibrated, pools, draws.run_seed(params.seed, day, "odd-targets")
    )
    return test, calibrated.model, setting | test.to_dict()


def _draw(params: Params, paths: ProjectPaths, source: str, day: datetime.date) -> tuple[draws.Draw, object]:
    """The run's labelled images: ``monitor.images`` new renders of the date's seed (``source`` ``simulator``), else
    the first ones of the recorded folder ``source``; and the simulator (None for recorded images)."""
    if source == SIMULATOR:
        simulator = make_simulator(params.simulator)
        seed = draws.run_seed(params.seed, day, "images")
        return draws.simulated_draw(simulator, params, seed, params.monitor.images), simulator
    recorded = read_recorded(paths.resolve(source), params.box, params.monitor.images)
    return draws.Draw(recorded.images, recorded.theta, recorded.names), None


def _report(
    params: Params,
    day: datetime.date,
    which: str,
    source: str,
    n: int,
    entries: list[tracking.MonitoredModel],
    results: list[dict],
    odd: dict,
    alarms: list[str],
    band: float,
    level: float,
    start: float,
) -> dict:
    """The content of ``metrics.json``: the run's setting, each model's version, aliases and Task I figures with its
    calibration alarm, the ODD check and the alarms."""
    task1_metrics = {r["model"]: r["metrics"] for r in results}
    return {
        "date": day.isoformat(),
        "models_monitored": which,
        "source": source,
        "images": n,
        "samples": params.monitor.samples,
        "alarm_level": params.monitor.alarm_level,
        "calibration_level": level,
        "calibration_band": band,
        "models": {
            e.model: {"registered_version": e.version, "aliases": list(e.aliases), "uri": e.uri}
            | task1_metrics[e.model]
            | {"calibration_alarm": checks.calibration_alarm(e.model, task1_metrics[e.model]) is not None}
            for e in entries
        },
        "odd": odd,
        "alarms": alarms,
        "seconds": time.perf_counter() - start,
    }


def _mlflow_values(report: dict, entries: list[tracking.MonitoredModel]) -> dict[str, float]:
    """The run's MLflow metrics: each model's figures (also under each alias it holds, so that a series follows the
    alias whatever model holds it), the ODD check's and the run's counts."""
    values = tracking.flatten_numbers(report["models"], "task1")
    for e in entries:  # the series that follow an alias whatever model holds it
        values |= tracking.flatten_numbers({alias: report["models"][e.model] for alias in e.aliases}, "task1")
    values |= tracking.flatten_numbers({k: v for k, v in report["odd"].items() if k != "threshold"}, "odd")
    values |= {"alarms": len(report["alarms"]), "images": report["images"], "samples": report["samples"]}
    values |= {"calibration_band": report["calibration_band"], "calibration_level": report["calibration_level"]}
    return values


def _log_summary(logger, report: dict, odd_test, odd_model) -> None:
    """One log line per model judged, then the ODD decision's count."""
    band, level, n = report["calibration_band"], report["calibration_level"], report["images"]
    for m, v in report["models"].items():
        logger.info(
            "%s: calibration error %.3f (band %.3f at %.4g %% on %d images: %s), NLL %.2f, information gain %.2f nats",
            m,
            v["calibration_error"],
            band,
            100 * level,
            n,
            "within" if v["within_band"] else "OUTSIDE",
            v["test_nll"],
            v["info_gain_nats"],
        )
    if odd_test is not None:
        c = odd_test.check
        logger.info(
            "ODD decision of %s: %d of %d new in-ODD targets flagged (interval [%d, %d])",
            odd_model,
            c.flagged,
            c.n,
            odd_test.low,
            odd_test.high,
        )


@flow(name="monitor", log_prints=True)
def monitor(
    params_path: str = "params.yaml", date: str | None = None, models: str | None = None, source: str | None = None
) -> dict:
    """Judge the registered models on the new draws of the run's date; write reports/monitoring/<date>/ and an MLflow
    run; fail on an alarm. ``models`` and ``source`` override ``monitor.models`` and ``monitor.source``."""
    start = time.perf_counter()
    stage = open_stage(params_path)
    params, paths, logger, mon = stage.params, stage.paths, stage.logger, stage.params.monitor
    day = draws.run_date(date, None if date is not None else flow_run.scheduled_start_time)
    which = models or mon.models
    if which not in (tracking.CHAMPION_ALIAS, "all"):
        raise ValueError(f"models: expected 'champion' or 'all', got {which!r}")
    source = source or mon.source
    entries = tracking.monitored_models(paths.root, params, which)
    logger.info("monitoring %s on %s (%s)", ", ".join(f"{e.model}@{e.version}" for e in entries), day, source)
    draw, simulator = _draw(params, paths, source, day)
    n = len(draw)
    # each model's band at the level that keeps the run's chance alarm ≤ 1 − alarm_level over all its models
    level = checks.model_level(mon.alarm_level, len(entries))
    replicates = checks.band_replicates(params.evaluate.band_replicates, params.evaluate.band_level, level)
    band = task1.calibration_band(n, mon.samples, level, replicates, params.seed)
    results = [
        judge_model(e, params, paths, draw, draws.run_seed(params.seed, day, e.model), band, level) for e in entries
    ]
    judged = {r["model"]: r["folder"] for r in results}
    odd_test, odd_model, odd = _odd(params, paths, day, source, draw, simulator, judged, logger)
    alarms = checks.alarms({r["model"]: r["metrics"] for r in results}, odd_test, odd_model)
    out = paths.reports("monitoring", day.isoformat(), which)
    report = _report(params, day, which, source, n, entries, results, odd, alarms, band, level, start)
    atomic_write_bytes(out / "metrics.json", json.dumps(report, indent=1).encode())
    curves = {
        f"{r['model']} (v{e.version})": (task1.LEVELS, np.array(r["coverage"]))
        for r, e in zip(results, entries, strict=True)
    }
    figure = plots.save_figure(
        plots.coverage_plot(
            curves,
            title=f"Monitoring {day}: expected coverage on {n} {'new simulated' if simulator else 'recorded'} images",
            band=band,
            band_label=f"{100 * level:.4g} % band of a calibrated\nmodel on {n} images",
        ),
        out / "coverage.png",
    )
    run_name = f"monitor-{day.isoformat()}" + ("" if which == tracking.CHAMPION_ALIAS else f"-{which}")
    tags = {"pidc.models_monitored": which, "pidc.source": source, "pidc.prefect_flow_run": str(flow_run.id or "")}
    run_id = tracking.log_monitoring(
        paths.root,
        mon.experiment,
        run_name,
        day,
        entries,
        _mlflow_values(report, entries),
        [out / "metrics.json", figure],
        alarms,
        tags,
    )
    _log_summary(logger, report, odd_test, odd_model)
    logger.info("report %s, MLflow run %s (%s)", out, run_id, mon.experiment)
    if alarms:
        raise checks.MonitoringAlarm(f"{len(alarms)} alarm(s) on {day}: " + "; ".join(alarms) + f" (report: {out})")
    return report


def main(argv: list[str] | None = None) -> None:
    args, _ = parse_stage_args(
        "Scheduled monitoring: the registered models on new draws of a date (not a DVC stage).",
        argv,
        [
            (["--date"], {"help": "the run's date, YYYY-MM-DD (default: today, UTC)"}),
            (["--models"], {"choices": ["champion", "all"], "help": "default: monitor.models"}),
            (["--source"], {"help": "'simulator' or a recorded folder (default: monitor.source)"}),
        ],
    )
    monitor(str(args.params), args.date, args.models, args.source)


if __name__ == "__main__":
    main()
