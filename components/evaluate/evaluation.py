"""Task I of one exported model on the test split: its draws, metrics, posterior predictive checks and plots.

What the ``evaluate`` stage runs once per model (:func:`evaluate_exported`), in a worker of its own: the model of
``registry/<model>/`` on the torch-free onnxruntime posterior (one thread: the stage runs models in parallel, not one
model on many threads), its posterior draws for the first ``evaluate.images`` test images
(:mod:`components.evaluate.task1`), the per-parameter scores (:mod:`components.evaluate.marginals`,
:mod:`components.evaluate.profile`), the posterior predictive checks and the model's plots. The stage keeps the result
under a key that covers this module's code (``flows/evaluate.py``, ``EVALUATION_MODULES``).
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import time
from pathlib import Path

import numpy as np

from components import plots
from components.core import seeding
from components.core.code import code_fingerprint
from components.core.config import Params
from components.core.files import atomic_write_bytes
from components.core.paths import ProjectPaths
from components.evaluate import marginals, named, profile, task1
from components.evaluate.local import posterior_summary
from components.export.runtime import OnnxPosterior
from components.features import cache as features
from components.features.backbones import get_backbone
from components.simulate import dataset
from components.simulate.base import make_simulator, new_scene_simulator

__all__ = ["evaluate_exported", "named_renders", "local_metrics"]


def evaluate_exported(
    params: Params, paths: ProjectPaths, model_id: str, band: float, plot_dir: Path, logger: logging.Logger
) -> dict:
    """Task I of the exported model ``model_id`` on the test split, its plots written into ``plot_dir``.

    Arguments:
        params: the project's settings (``evaluate``, ``seed``, ``prior``, ``simulator`` are read).
        paths: the project's folders (``registry/``, ``data/``, ``features/``).
        model_id: the model, a folder of ``registry/``.
        band: the calibration band of a perfectly calibrated model on the stage's number of images.
        plot_dir: where the model's PNG plots go (``ppc.png``, ``profile.png``, ``histograms-<i>.png``,
            ``corner-[zoom-]<i>.png``).
        logger: receives one line of timings (seconds of wall and CPU time per step).

    Returns:
        The JSON-serializable result: ``model``, ``metrics`` (headline metrics, with ``images``, ``samples`` and
        ``ppc_score`` and ``ppc_images``, the images checked: 0 with recorded data), ``coverage`` and ``pi`` (lists of floats), ``parameters`` and ``profiles`` (nested dicts), ``local`` (the
        named weathers and the local test, :func:`_named`).
    """
    import torch

    ev = params.evaluate
    # one thread for onnxruntime and torch (the named weathers' features and the local test): the stage runs models
    # in parallel, and torch's sums depend on its thread count (the same figures in any worker)
    torch.set_num_threads(1)
    start, cpu = time.perf_counter(), time.thread_time()  # one onnxruntime thread: the calling one
    folder = paths.registry / model_id
    posterior = OnnxPosterior.load(folder, intra_op_num_threads=1)  # parallel over models, not inside one
    task1.check_model_matches_data(posterior.box, params, folder / "card.json")
    card = posterior.card
    test = dataset.open_split(paths.data, "test")
    n = task1.images_evaluated(ev.images, len(test))
    backbone = get_backbone(card["backbone"], **card["backbone_options"])
    x = features.inputs_from_cached(backbone, features.open_features(paths.features, card["backbone"], test, stop=n))
    truth = test.theta[:n]
    loaded = time.perf_counter()
    samples, lp, lp_truth = task1.posterior_draws(
        posterior, x, truth, ev.samples, seeding.derive_seed(params.seed, model_id)
    )
    drawn = time.perf_counter()
    metrics, coverage, pi = task1.task1_metrics(lp, lp_truth, params.box.log_volume(), band)
    metrics |= {"images": n, "samples": ev.samples}
    scores = marginals.marginal_scores(samples, truth, params.box)
    parameters = marginals.summarize_subsets(scores, truth, params.box)
    profiles = profile.truth_profile(scores, truth, params.box, ev.profile_bins)
    scored = time.perf_counter()

    metrics["ppc_score"] = _posterior_predictive(params, test, n, samples, model_id, plot_dir)
    metrics["ppc_images"] = 0 if params.simulator.backend == "recorded" else min(ev.ppc_images, n)
    plots.save_figure(
        plots.truth_profile_plot(profiles, title=f"{model_id}: Task I across the true value ({n} test images)"),
        plot_dir / "profile.png",
    )
    _example_plots(params, samples, lp, truth, model_id, plot_dir)
    plotted = time.perf_counter()
    local = _named(params, paths, posterior, backbone, model_id, plot_dir)
    metrics |= local_metrics(local)
    end = time.perf_counter()
    logger.info(
        "%s: %d images × %d draws in %.1f s, CPU %.1f s (load %.1f s, draws %.1f s, metrics %.1f s, PPC and plots %.1f s, "
        "named weathers %.1f s)",
        model_id,
        n,
        ev.samples,
        end - start,
        time.thread_time() - cpu,
        loaded - start,
        drawn - loaded,
        scored - drawn,
        plotted - scored,
        end - plotted,
    )
    return {
        "model": model_id,
        "metrics": metrics,
        "coverage": coverage.tolist(),
        "pi": pi.tolist(),
        "parameters": parameters,
        "profiles": profiles,
        "local": local,
    }


def _posterior_predictive(
    params: Params, test: dataset.Split, n: int, samples: np.ndarray, model_id: str, plot_dir: Path
) -> float:
    """The posterior predictive checks of the first ``evaluate.ppc_images`` test images: each scene re-rendered under
    posterior and prior draws (``samples``: ``(n, draws, 6)``), the sheet of the first written to ``ppc.png``.

    Arguments:
        params: the project's settings (``evaluate``, ``seed``, ``prior``, ``simulator``).
        test: the test split.
        n: the number of test images evaluated.
        samples: the posterior draws, ``(n, draws, 6)`` in physical units.
        model_id: the model (its random stream and the sheet's title).
        plot_dir: the folder of ``ppc.png``.

    Returns:
        The median PPC score over the checked images, NaN when none is checked: always with recorded data
        (``simulator.backend: recorded``), whose scenes no simulator can render again (``ppc_images`` 0 in the
        metrics).
    """
    ev = params.evaluate
    if params.simulator.backend == "recorded":
        return float("nan")
    n_ppc = min(ev.ppc_images, n)
    ppc_images = test.images(stop=n_ppc)
    checks = task1.posterior_predictive_checks(
        make_simulator(params.simulator),
        ppc_images,
        test.scene_seed[:n_ppc],
        test.weather[:n_ppc, 6],
        samples,
        params.box,
        ev.ppc_renders,
        seeding.rng(params.seed, "ppc", model_id),
    )
    score = float(np.median([c.score for c in checks])) if checks else float("nan")
    if checks:
        c = checks[0]
        plots.save_figure(
            plots.ppc_sheet(
                ppc_images[0],
                c.posterior_renders,
                c.prior_renders,
                {"posterior": c.d_posterior, "prior": c.d_prior},
                title=f"{model_id}: posterior predictive check (score {c.score:.2f})",
            ),
            plot_dir / "ppc.png",
        )
    return score


def _example_plots(
    params: Params, samples: np.ndarray, lp: np.ndarray, truth: np.ndarray, model_id: str, plot_dir: Path
) -> None:
    """The marginal histograms and the corner plots (whole prior box and zoomed) of the first
    ``evaluate.example_images`` test images.

    Arguments:
        params: the project's settings (``evaluate.example_images``, ``prior``).
        samples: the posterior draws, ``(n, draws, 6)`` in physical units.
        lp: their log-densities, ``(n, draws)`` (nats).
        truth: the true weather of the images, ``(n, 6)``.
        model_id: the model (the plots' titles).
        plot_dir: the folder of ``histograms-<i>.png``, ``corner-<i>.png`` and ``corner-zoom-<i>.png``.
    """
    for i in range(min(params.evaluate.example_images, len(truth))):
        plots.save_figure(
            plots.marginal_histograms(samples[i], lp[i], truth[i], box=params.box), plot_dir / f"histograms-{i}.png"
        )
        for zoom in (False, True):
            plots.save_figure(
                plots.corner_plot(
                    samples[i],
                    lp[i],
                    truth[i],
                    box=params.box,
                    zoom=zoom,
                    title=f"{model_id}, test image {i}" + (" (zoomed)" if zoom else ""),
                ),
                plot_dir / f"corner-{'zoom-' if zoom else ''}{i}.png",
            )


#: what the named weathers' entry says when no simulator can render them and no recorded folder is named
NO_RENDERER = (
    "simulator.recorded.renderer is null and evaluate.named.folders is empty: no named weather can be rendered; set "
    "the renderer (procedural or carla) or name recorded folders"
)


def named_renders(params: Params, paths: ProjectPaths) -> tuple[list[named.NamedSet], str | None]:
    """The rendered named weathers (``evaluate.named``: the presets and one's own weathers on new scenes) and the
    reason, when any, why there are none (recorded data without a renderer).

    Every model of a run reads the same images: they are rendered once and kept in ``.cache/named/<key>.npz``, the
    key a digest of the weathers, the scenes, the seed, the simulator's settings and its code
    (:func:`components.core.code.code_fingerprint`), so that a change of any renders them again. The ``evaluate``
    flow calls this before it fans out over the models.
    """
    nc = params.evaluate.named
    weathers = named.named_weathers(nc.presets, nc.weathers)
    if not weathers:
        return [], None
    simulator = new_scene_simulator(params.simulator)
    if simulator is None:
        return [], NO_RENDERER
    if params.simulator.backend != "recorded":  # a recorded dataset's scenes are not renderer seeds
        used = {int(s) for name in dataset.SPLITS for s in dataset.open_split(paths.data, name).scene_seed}
        named.check_new_scenes(used, params.seed, list(weathers), nc.scenes)
    parts = {
        "weathers": weathers,
        "scenes": nc.scenes,
        "seed": params.seed,
        "simulator": params.simulator.model_dump(mode="json"),
        "code": code_fingerprint(["components.simulate.procedural", type(simulator).__module__]),
    }
    key = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]
    path = paths.kept("named", f"{key}.npz")
    if path.is_file():
        with np.load(path) as z:
            return [
                named.NamedSet(str(n), str(k), t, im)
                for n, k, t, im in zip(z["names"], z["kinds"], z["truth"], z["images"], strict=True)
            ], None
    sets = named.render_sets(simulator.render, weathers, params.seed, nc.scenes)
    buffer = io.BytesIO()
    np.savez(
        buffer,
        names=np.array([s.name for s in sets]),
        kinds=np.array([s.kind for s in sets]),
        truth=np.stack([s.truth for s in sets]),
        images=np.stack([s.images for s in sets]),
    )
    atomic_write_bytes(path, buffer.getvalue())
    return sets, None


def _named_sets(params: Params, paths: ProjectPaths) -> tuple[list[named.NamedSet], str | None]:
    """The named weathers' images (``evaluate.named``): the rendered ones on new scenes (:func:`named_renders`), then
    the recorded folders; and the reason, when any, why the rendered ones were left out (recorded data without a
    renderer)."""
    from components.monitor.recorded import read_recorded
    from components.simulate.recorded import fit_image

    nc = params.evaluate.named
    sets, note = named_renders(params, paths)
    size = (params.simulator.height, params.simulator.width)
    for name, folder in nc.folders.items():
        rec = read_recorded(paths.root / folder, params.box)
        images = np.stack(
            [
                fit_image(im, size, str(rec.folder / f), f"evaluate.named.folders.{name}")
                for im, f in zip(rec.images, rec.names, strict=True)
            ]
        )
        sets.append(named.NamedSet(name, "recorded", rec.theta, images))
    return sets, note


def _named(
    params: Params, paths: ProjectPaths, posterior: OnnxPosterior, backbone, model_id: str, plot_dir: Path
) -> dict:
    """The model at the named weathers (:mod:`components.evaluate.named`): per weather the coverage of its HDIs
    beside the exact toy's and the L-C2ST, fitted on the first ``local_test.calibration_images`` validation images;
    the same test on all named images together and on the first ``local_test.test_images`` test images; the
    heatmap ``named.png``. ``{"skipped": reason}`` when there is no named weather to evaluate."""
    nc, box, card = params.evaluate.named, params.box, posterior.card
    lt = nc.local_test
    sets, note = _named_sets(params, paths)
    if not sets:
        return {"skipped": note or "evaluate.named names no weather (presets: none, no weathers, no folders)"}
    root = seeding.derive_seed(params.seed, "named", model_id)

    def cached(split_name: str, n: int | str) -> tuple[np.ndarray, np.ndarray]:
        split = dataset.open_split(paths.data, split_name)
        n = len(split) if n == "all" else n
        x = features.inputs_from_cached(
            backbone, features.open_features(paths.features, card["backbone"], split, stop=n)
        )
        return x, split.theta[: len(x)].astype(np.float64)

    def summary(x: np.ndarray, key: str) -> np.ndarray:
        return posterior_summary(posterior.sample(x, lt.summary_draws, seeding.derive_seed(root, key, "summary")), box)

    x_cal, theta_cal = cached("val", lt.calibration_images)
    one = posterior.sample(x_cal, 1, seeding.derive_seed(root, "calibration"))[:, 0]
    tests = named.fit_local_tests(
        theta_cal, summary(x_cal, "calibration"), one, box, steps=lt.steps, null_trials=lt.null_trials, seed=root
    )
    rows, summaries, draws_all = [], [], []
    for s in sets:
        x = features.posterior_inputs(backbone, s.images)
        draws = posterior.sample(x, nc.draws, seeding.derive_seed(root, s.name, "draws"))
        sx = summary(x, s.name)
        row = named.weather_row(s, draws, box, nc.tolerance, nc.toy_images, seeding.rng(root, s.name, "toy"))
        row["lc2st"] = named.local_rejections(tests, sx, draws[:, : lt.test_draws], lt.level)
        rows.append(row)
        summaries.append(sx)
        draws_all.append(draws[:, : lt.test_draws])
    x_test, _ = cached("test", lt.test_images)
    control = named.local_rejections(
        tests,
        summary(x_test, "test"),
        posterior.sample(x_test, lt.test_draws, seeding.derive_seed(root, "test")),
        lt.level,
    )
    together = named.local_rejections(tests, np.concatenate(summaries), np.concatenate(draws_all), lt.level)
    plots.save_figure(
        plots.named_heatmap(rows, lt.level, f"{model_id}: named weathers ({sum(r['images'] for r in rows)} images)"),
        plot_dir / "named.png",
    )
    pooled = {kind: named.pooled(rows, box, kind=kind) for kind in ("preset", "own", "recorded", None)}
    out = {
        "weathers": rows,
        "pooled": {("all" if kind is None else kind): v for kind, v in pooled.items() if v is not None},
        "lc2st": {"level": lt.level, "named": together, "test": control, "test_images": len(x_test)},
    }
    if note:
        out["note"] = note
    return out


LOCAL_METRICS = (
    "named_weathers",
    "named_cells_below",
    "named_cells_above",
    "named_coverage68",
    "lc2st_named_rate",
    "lc2st_named_p",
    "lc2st_test_rate",
    "lc2st_test_p",
)
"""The keys of :func:`local_metrics`, in order."""


def local_metrics(local: dict) -> dict:
    """The headline figures of :func:`_named` (keys :data:`LOCAL_METRICS`): the named weathers and images, the cells
    whose 68 % coverage lies below or above a correct model's range, the pooled 68 % coverage (mean over parameters),
    and the joint L-C2ST's rejection rate and p-value on the named images together and on the test images (NaN when
    skipped)."""
    if "skipped" in local:
        return dict.fromkeys(LOCAL_METRICS, float("nan"))
    rows = local["weathers"]
    cells = [c for r in rows for c in r["parameters"].values()]
    pooled = local["pooled"]["all"]["parameters"].values()
    lc2st = local["lc2st"]
    values = (
        len(rows),
        sum(c["below"] for c in cells),
        sum(c["above"] for c in cells),
        float(np.mean([p["coverage68"] for p in pooled])),
        lc2st["named"]["joint"]["rate"],
        lc2st["named"]["joint"]["p_value"],
        lc2st["test"]["joint"]["rate"],
        lc2st["test"]["joint"]["p_value"],
    )
    return dict(zip(LOCAL_METRICS, values, strict=True))
