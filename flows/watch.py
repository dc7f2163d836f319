"""Scheduled watch of a folder of drives: ``pidc watch`` on every new drive, one MLflow run each. Not a DVC stage.

``python -m flows.watch --folder drives --sources SOURCE [SOURCE ...] [--out reports/watch] [--model URI] …``, and the
deployment ``watch/watch-drives`` of ``prefect.yaml`` (every 10 minutes).

A run lists the drives of ``folder`` (:func:`components.watch.folder.list_drives`: its sub-folders of frames and its
videos, in name order) and watches, one Prefect task each, those not watched yet: a drive is skipped when
``<out>/<drive>/summary.json`` records the same watch key (:func:`components.watch.folder.watch_key`: the drive's
fingerprint — its files' names, sizes and modification times — the registered model version, the sources and the
settings). Each watched drive (:func:`components.watch.run.watch`, against the sources read and calibrated once per
run by :func:`components.watch.run.prepare_sources`) gets

- ``<out>/<drive>/``: ``timeline.png``, ``frames.csv``, ``windows.csv`` and ``summary.json`` (as ``pidc watch --out``
  writes them; the summary with the key under ``watched``, written last);
- one MLflow run named after the drive in ``experiment`` (``pidc-watch``): params (the drive and its path, the sources,
  the model's URI, id and version, the fingerprint, ``settings.<name>``), metrics (``alarms``, ``first_alarm_s`` when
  the rule fired, ``frames``, ``seconds``, ``realtime_factor``, ``frames_per_second``, ``windows``, ``windows_flagged``,
  ``threshold``, ``false_alarms_per_hour``, and for a drive of known weather ``truth.exit_s``, ``truth.delay_s``,
  ``truth.false_alarms``, …), the artifacts ``timeline.png`` and ``summary.json``, and tags (``pidc.drive``,
  ``pidc.outside``, ``pidc.alarms``, ``pidc.model``, ``pidc.registered_version``, ``pidc.fingerprint``,
  ``pidc.prefect_flow_run``); status FAILED when the drive left the ODD, else FINISHED.

The model is a registered version loaded from MLflow (``models:/pidc@champion``: the champion by its alias, resolved
to its version once per run; or ``models:/pidc/<version>``). After every drive, the run ends FAILED
(:class:`components.watch.folder.DrivesLeftOdd`) when a drive watched in it left the sources' ODD (the rule raised an
alarm) — the message names each such drive, its first alarm's time and cause — or could not be watched (a bad file).
Nothing here is a DVC output or dependency.

The MLflow calls are here, not in :mod:`flows.tracking` as every other flow's are: ``flows/tracking.py`` is a
dependency of the train, export, evaluate, task2 and task3 stages, and a change to it re-runs them. They belong there
with the next change that re-runs those stages anyway.
"""

from __future__ import annotations

import re
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import mlflow
from mlflow.entities import Metric, Param
from prefect import flow, task
from prefect.cache_policies import NO_CACHE
from prefect.runtime import flow_run

from components.export.lookup import load_registered
from components.watch import folder as drives
from components.watch.errors import WatchError
from components.watch.frames import Frames, open_frames
from components.watch.run import PreparedSources, prepare_sources, watch
from components.watch.settings import WATCH_DEFAULTS, WatchOptions
from flows import tracking
from flows.stage import open_stage, parse_stage_args

#: ``models:/<name>@<alias>`` or ``models:/<name>/<version>``
_MODEL_URI = re.compile(r"^models:/(?P<name>[^/@]+)(?:@(?P<alias>[^/@]+)|/(?P<version>\d+))$")


def registered_version(base: Path, uri: str) -> dict[str, str]:
    """The registered model version ``uri`` names: ``{"uri", "name", "version", "id"}`` (``id`` its version tag
    ``pidc.model``). ``FileNotFoundError`` naming the URI and the store when it is not registered there."""
    found = _MODEL_URI.match(uri)
    if found is None:
        raise ValueError(
            f"model {uri!r}: expected models:/<name>@<alias> (models:/pidc@champion) or models:/<name>/<n>"
        )
    client = mlflow.MlflowClient(tracking_uri=tracking.tracking_uri(base))
    name = found["name"]
    try:
        if found["alias"]:
            version = client.get_model_version_by_alias(name, found["alias"])
        else:
            version = client.get_model_version(name, found["version"])
    except mlflow.exceptions.MlflowException as e:
        raise FileNotFoundError(
            f"{uri}: not in the MLflow Model Registry at {tracking.tracking_uri(base)} ({e.message}); export and "
            "evaluate the models first (`dvc repro`)"
        ) from None
    model_id = version.tags.get("pidc.model")
    if not model_id:
        raise ValueError(f"{uri}: version {version.version} of {name!r} has no tag pidc.model (re-export it)")
    return {"uri": uri, "name": name, "version": str(version.version), "id": model_id}


def _experiment(client: mlflow.MlflowClient, name: str) -> str:
    """The id of experiment ``name``, created tagged as model development (the MLflow UI opens it on its runs)."""
    experiment = client.get_experiment_by_name(name)
    if experiment is None:
        return client.create_experiment(name, tags={"mlflow.experimentKind": tracking.EXPERIMENT_KIND})
    return experiment.experiment_id


def _start_drive_run(
    base: Path, experiment: str, name: str, tags: Mapping[str, str]
) -> tuple[mlflow.MlflowClient, str]:
    """A new MLflow run ``name`` in ``experiment``, after marking KILLED the runs of the same drive left RUNNING (a
    watch cut off between its run's start and end: the new run replaces it)."""
    client = mlflow.MlflowClient(tracking_uri=tracking.tracking_uri(base))
    experiment_id = _experiment(client, experiment)
    query = "tags.`pidc.task` = 'watch' and attributes.status = 'RUNNING'"
    for run in client.search_runs([experiment_id], query):
        if run.data.tags.get("pidc.drive") == tags["pidc.drive"]:
            client.set_terminated(run.info.run_id, "KILLED")
    return client, client.create_run(experiment_id, tags=dict(tags), run_name=name).info.run_id


def _params(
    name: str,
    path: Path,
    sources: Sequence[Frames],
    names: Sequence[str],
    model: Mapping[str, str],
    fingerprint: str,
    options: WatchOptions,
) -> dict[str, str]:
    """The MLflow params of a drive's run (every value a string)."""
    params = {
        "drive": name,
        "drive_path": str(path),
        "sources": ", ".join(names),
        "source_paths": ", ".join(str(s.path) for s in sources),
        "model": model["uri"],
        "registered_model": model["name"],
        "model_version": model["version"],
        "model_id": model["id"],
        "fingerprint": fingerprint,
    }
    return params | {f"settings.{k}": str(v) for k, v in options.to_dict().items()}


def _metrics(summary: Mapping[str, Any]) -> dict[str, float]:
    timing, windows = summary["timing"], summary["windows"]
    values = {
        "alarms": len(summary["alarms"]),
        "frames": summary["drive"]["frames"],
        "seconds": summary["drive"]["seconds"],
        "realtime_factor": timing["realtime_factor"],
        "frames_per_second": timing["frames_per_second"],
        "windows": windows["count"],
        "windows_flagged": windows["flagged"],
        "threshold": summary["threshold"]["relative_gap"],
        "false_alarms_per_hour": summary["rule"]["false_alarms_per_hour"]["per_hour"],
    }
    if summary["first_alarm_s"] is not None:
        values["first_alarm_s"] = summary["first_alarm_s"]
    truth = summary.get("truth") or {}  # a drive of known weather: its exit, detection delay and false alarms
    values |= tracking.flatten_numbers({k: v for k, v in truth.items() if not isinstance(v, Mapping)}, "truth")
    return {k: float(v) for k, v in values.items()}


@task(name="watch-drive", cache_policy=NO_CACHE)  # holds the model's onnxruntime sessions and the sources
def watch_drive(
    model: Any,
    model_info: dict[str, str],
    path: Path,
    sources: list[Frames],
    names: list[str],
    options: WatchOptions,
    fps: float | None,
    out: Path,
    key: dict[str, Any],
    base: Path,
    experiment: str,
    prepared: PreparedSources,
) -> drives.DriveOutcome:
    """Watch the drive ``path``, write ``out`` and log its MLflow run (module docstring); ``WatchError`` (one line
    naming the file) when the drive cannot be watched."""
    name = drives.drive_name(path)
    result = watch(model, drives.open_drive(path, fps), sources, names, options, progress=True, prepared=prepared)
    outputs = drives.write_tables(out, result)
    outside = bool(result.alarms)
    first = result.alarms[0] if result.alarms else None
    description = f"Watch of drive {name} with {model_info['id']} (v{model_info['version']}): " + (
        f"**left the ODD** at {first.fired_s:.1f} s ({', '.join(first.cause) or 'no single parameter'}), "
        f"{len(result.alarms)} alarm segment(s)"
        if first
        else "no alarm."
    )
    tags = {
        "pidc.task": "watch",
        "pidc.drive": name,
        "pidc.outside": str(outside).lower(),
        "pidc.alarms": str(len(result.alarms)),
        "pidc.model": model_info["id"],
        "pidc.registered_version": model_info["version"],
        "pidc.fingerprint": key["fingerprint"],
        "pidc.prefect_flow_run": str(flow_run.id or ""),
        "git_commit": tracking.git_commit(base),
        tracking.DESCRIPTION: description,
    }
    client, run_id = _start_drive_run(base, experiment, name, tags)
    try:
        record = key | {"prefect_flow_run": tags["pidc.prefect_flow_run"], "mlflow_run": run_id}
        summary = drives.watched_summary(result, record)
        params = _params(name, path, sources, names, model_info, key["fingerprint"], options)
        metrics = _metrics(summary)
        client.log_batch(
            run_id,
            metrics=[Metric(k, v, int(time.time() * 1000), 0) for k, v in metrics.items()],
            params=[Param(k, v) for k, v in params.items()],
        )
        client.log_artifact(run_id, str(outputs["timeline"]))
        with tempfile.TemporaryDirectory(prefix="pidc-watch-") as tmp:  # the very bytes of summary.json
            client.log_artifact(run_id, str(drives.write_summary(Path(tmp) / outputs["summary"].name, summary)))
    except BaseException:
        client.set_terminated(run_id, "FAILED")
        raise
    client.set_terminated(run_id, "FAILED" if outside else "FINISHED")
    drives.write_summary(outputs["summary"], summary)  # last: the drive counts as watched once its run is logged
    return drives.DriveOutcome.of(name, out, result, run_id)


def _options(
    window: int | None,
    stride: int | None,
    false_alarm_rate: float | None,
    consecutive: int | None,
    block: int | None,
    seed: int,
) -> WatchOptions:
    """The watch's settings: the defaults, with the flow's overrides that are given."""
    given = {"window": window, "stride": stride, "false_alarm_rate": false_alarm_rate, "consecutive": consecutive}
    given |= {"block": block}
    return WatchOptions(**{k: v for k, v in given.items() if v is not None}, seed=seed)


def _log_outcome(logger, o: drives.DriveOutcome) -> None:
    if o.error is not None:
        logger.error("%s: not watched: %s", o.name, o.error)
    elif o.outside:
        cause = ", ".join(o.cause) or "no single parameter"
        logger.info(
            "%s: %d frames, %d alarm(s): LEFT THE ODD at %.1f s (%s)",
            o.name,
            o.frames,
            o.alarms,
            o.first_alarm_s,
            cause,
        )
    else:
        logger.info("%s: %d frames, 0 alarms", o.name, o.frames)


@flow(name="watch", log_prints=True)
def watch_folder(
    folder: str,
    sources: list[str],
    out: str = "reports/watch",
    model: str = "models:/pidc@champion",
    experiment: str = "pidc-watch",
    params_path: str = "params.yaml",
    window: int | None = None,
    stride: int | None = None,
    false_alarm_rate: float | None = None,
    consecutive: int | None = None,
    block: int | None = None,
    fps: float | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Watch the drives of ``folder`` not watched yet against ``sources`` (module docstring); fail when one left the
    ODD. ``window``, ``stride``, ``false_alarm_rate``, ``consecutive`` and ``block`` override the watch's defaults
    (:data:`components.watch.settings.WATCH_DEFAULTS`); ``fps`` is the rate of folders of frames without
    ``times.csv``; paths are relative to the project root."""
    stage = open_stage(params_path)
    paths, logger = stage.paths, stage.logger
    where, out_dir = paths.resolve(folder), paths.resolve(out)
    source_paths = [paths.resolve(s) for s in sources]
    if not source_paths:
        raise WatchError("sources: give at least one source (a folder of frames or a video)")
    options = _options(window, stride, false_alarm_rate, consecutive, block, seed)
    drives.check_layout(where, out_dir, source_paths)
    found = drives.list_drives(where)
    source_frames = [open_frames(p, timed=False) for p in source_paths]  # checked once per run
    names = drives.source_names(source_paths)
    source_keys = {n: drives.fingerprint(p) for n, p in zip(names, source_paths, strict=True)}
    model_info = registered_version(paths.root, model)
    logger.info(
        "%d drive(s) in %s; model %s = %s v%s; sources %s",
        len(found),
        where,
        model,
        model_info["id"],
        model_info["version"],
        ", ".join(names),
    )
    loaded = prepared = None
    outcomes: list[drives.DriveOutcome] = []
    skipped: list[str] = []
    for path in found:
        name = drives.drive_name(path)
        key = drives.watch_key(drives.fingerprint(path), model_info, source_keys, options.to_dict())
        if drives.already_watched(out_dir / name, key):
            logger.info("%s: watched already (the same frames, model version, sources and settings): skipped", name)
            skipped.append(name)
            continue
        if loaded is None:  # downloaded once, when a drive needs it
            folder_of = tracking.download_registered_model(
                f"models:/{model_info['name']}/{model_info['version']}", paths.root
            )
            loaded = load_registered(folder_of)
            if loaded.name != model_info["id"]:
                raise ValueError(
                    f"{model}: its card names model {loaded.name!r}, its version tag pidc.model {model_info['id']!r}"
                )
            # the sources read and the decision calibrated once per run, for every drive (a WatchError fails the run)
            prepared = prepare_sources(loaded, source_frames, names, options, progress=True)
        try:
            outcome = watch_drive(
                loaded,
                model_info,
                path,
                source_frames,
                names,
                options,
                fps,
                out_dir / name,
                key,
                paths.root,
                experiment,
                prepared,
            )
        except WatchError as e:
            outcome = drives.DriveOutcome(name, out_dir / name, error=str(e))
        _log_outcome(logger, outcome)
        outcomes.append(outcome)
    logger.info(
        "%d drive(s) watched, %d skipped; reports in %s, MLflow experiment %s",
        len(outcomes),
        len(skipped),
        out_dir,
        experiment,
    )
    message = drives.exit_message(outcomes, out_dir)
    if message:
        raise drives.DrivesLeftOdd(message)
    return {
        "watched": {o.name: {"frames": o.frames, "alarms": o.alarms, "mlflow_run": o.mlflow_run} for o in outcomes},
        "skipped": skipped,
    }


def main(argv: list[str] | None = None) -> None:
    d = WATCH_DEFAULTS
    args, _ = parse_stage_args(
        "Watch the new drives of a folder against source domains (`pidc watch` on each, an MLflow run each; not a "
        "DVC stage).",
        argv,
        [
            (["--folder"], {"required": True, "help": "the folder of drives (sub-folders of frames, videos)"}),
            (["--sources"], {"nargs": "+", "required": True, "help": "the source domains (folders of frames, videos)"}),
            (["--out"], {"default": "reports/watch", "help": "outputs, one folder per drive (default: %(default)s)"}),
            (["--model"], {"default": "models:/pidc@champion", "help": "registered model URI (default: %(default)s)"}),
            (["--experiment"], {"default": "pidc-watch", "help": "MLflow experiment (default: %(default)s)"}),
            (["--window"], {"type": int, "help": f"frames per window (default {d['window']})"}),
            (["--stride"], {"type": int, "help": f"frames between windows (default {d['stride']})"}),
            (["--false-alarm-rate"], {"type": float, "help": f"per window (default {d['false_alarm_rate']})"}),
            (["--consecutive"], {"type": int, "help": f"flagged windows for an alarm (default {d['consecutive']})"}),
            (["--block"], {"type": int, "help": f"frames per block of the sources (default {d['block']})"}),
            (["--fps"], {"type": float, "help": "frames per second of folders without times.csv"}),
            (["--seed"], {"type": int, "default": 0, "help": "seed of every random draw (default 0)"}),
        ],
    )
    watch_folder(
        args.folder,
        args.sources,
        args.out,
        args.model,
        args.experiment,
        str(args.params),
        args.window,
        args.stride,
        args.false_alarm_rate,
        args.consecutive,
        args.block,
        args.fps,
        args.seed,
    )


if __name__ == "__main__":
    main()
