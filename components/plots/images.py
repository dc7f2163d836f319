"""Sheets of images: the posterior predictive check (Task I, 3rd analysis) and bags of images (Task II).

Used (through :mod:`components.plots`) by the ``train``, ``evaluate``, ``task2`` and ``task3`` stages and
the ``pidc`` CLI.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from components.core.checks import whole_number
from components.plots.canvas import new_figure
from components.plots.checks import as_image, as_images

__all__ = ["ppc_sheet", "image_grid"]

_CELL = 2.3  # inches per image column


def _distances(distances: object, k_post: int, k_prior: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    if distances is None:
        return None, None
    if isinstance(distances, Mapping):
        unknown = set(distances) - {"posterior", "prior"}
        if unknown:
            raise ValueError(f"distances: unknown key(s) {sorted(unknown)}; use 'posterior' and/or 'prior'")
        post, prior = distances.get("posterior"), distances.get("prior")
    else:
        post, prior = distances, None
    out = []
    for name, d, k in (("posterior", post, k_post), ("prior", prior, k_prior)):
        if d is None:
            out.append(None)
            continue
        a = np.asarray(d, dtype=np.float64)
        if a.shape != (k,):
            raise ValueError(f"distances['{name}'] must have shape ({k},), one per {name} render, got {a.shape}")
        out.append(a)
    return out[0], out[1]


def ppc_sheet(
    observed: object,
    posterior_renders: object,
    prior_renders: object | None = None,
    distances: object | None = None,
    distance_name: str = "d",
    title: str = "Posterior predictive check",
) -> Figure:
    """The observed image beside re-renders of its scene under weathers drawn from the posterior (and prior).

    Arguments:
        observed: ``(H, W, 3)`` uint8 RGB, the input image i.
        posterior_renders: ``(k, H', W', 3)`` uint8, the same scene rendered with θ_j ~ P̂(W | I = i).
        prior_renders: ``(k', H', W', 3)`` uint8 or None, the scene under θ_j drawn from the prior (contrast).
        distances: per-render distances to ``observed`` for the captions: a ``(k,)`` array (posterior renders)
            or a mapping with keys ``"posterior"`` ``(k,)`` and/or ``"prior"`` ``(k',)``.
        distance_name: the symbol of the distance in the captions.
    """
    obs = as_image(observed, "observed")
    post = as_images(posterior_renders, "posterior_renders")
    prior = None if prior_renders is None else as_images(prior_renders, "prior_renders")
    d_post, d_prior = _distances(distances, post.shape[0], 0 if prior is None else prior.shape[0])
    rows = [("posterior", post, d_post)] + ([("prior", prior, d_prior)] if prior is not None else [])
    ncols = 1 + max(r[1].shape[0] for r in rows)
    aspect = obs.shape[0] / obs.shape[1]
    fig = new_figure(_CELL * ncols, _CELL * aspect * len(rows) + 1.0)
    axes = np.atleast_2d(fig.subplots(len(rows), ncols, squeeze=False))
    for ax in axes.ravel():
        ax.set_axis_off()
    axes[0, 0].imshow(obs)
    axes[0, 0].set_title("observed", fontsize=10, fontweight="bold")
    for r, (kind, images, dist) in enumerate(rows):
        for j, image in enumerate(images):
            ax = axes[r, j + 1]
            ax.imshow(image)
            caption = f"{kind} #{j + 1}"
            if dist is not None:
                caption += f"\n{distance_name} = {dist[j]:.3g}"
            ax.set_title(caption, fontsize=9)
    if prior is not None:
        axes[1, 0].text(
            0.5,
            0.5,
            "renders under\nprior draws\n(contrast)",
            ha="center",
            va="center",
            fontsize=9,
            transform=axes[1, 0].transAxes,
            color="dimgray",
        )
    fig.suptitle(title)
    return fig


def image_grid(images: object, ncols: int, titles: Sequence[str] | None = None, title: str | None = None) -> Figure:
    """A bag of ``n`` RGB images (``(n, H, W, 3)`` uint8) on a grid of ``ncols`` columns, optional captions."""
    imgs = as_images(images, "images")
    whole_number("ncols", ncols, low=1)
    n = imgs.shape[0]
    if titles is not None and len(titles) != n:
        raise ValueError(f"titles must have one entry per image ({n}), got {len(titles)}")
    ncols = min(int(ncols), n)
    nrows = math.ceil(n / ncols)
    aspect = imgs.shape[1] / imgs.shape[2]
    extra = 0.3 if titles is not None else 0.0
    fig = new_figure(_CELL * ncols, (_CELL * aspect + extra) * nrows + (0.6 if title else 0.1))
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for k, ax in enumerate(axes.ravel()):
        ax.set_axis_off()
        if k < n:
            ax.imshow(imgs[k])
            if titles is not None:
                ax.set_title(str(titles[k]), fontsize=9)
    if title:
        fig.suptitle(title)
    return fig
