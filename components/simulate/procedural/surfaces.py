"""Surface attributes of the first camera hits: materials, albedo (with textures), normals, windows.

Given the closest-hit buffers of :func:`.geometry.cast_objects` and the ground distances, assigns
every pixel a material id (:mod:`.layout`), a linear RGB albedo, a normal and a world position;
ground points get their material from the road cross-section (lanes, markings, sidewalks, grass),
building faces get a window grid whose lit windows (at night) are drawn from the "windows" stream.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .calibration import Calibration
from .geometry import Hits
from .layout import BUILDING, FOLIAGE, GRASS, MARKING, ROAD, SIDEWALK, SKY, WINDOW, Layout
from .noise import sample_texture

__all__ = ["Surfaces", "surfaces"]


@dataclass(frozen=True)
class Surfaces:
    """Per-pixel (N = H·W) first-hit attributes: ``t`` distance (inf: sky), ``material`` (N,) int8,
    ``albedo`` (N, 3), ``normal`` (N, 3), ``pos`` (N, 3) world points (camera origin for sky),
    ``window_lit`` (N,) bool, ``ground`` (N,) bool."""

    t: np.ndarray
    material: np.ndarray
    albedo: np.ndarray
    normal: np.ndarray
    pos: np.ndarray
    window_lit: np.ndarray
    ground: np.ndarray


_GRASS = (0.07, 0.12, 0.035)
_F32 = np.float32


def _ground_albedo(
    lay: Layout, x: np.ndarray, z: np.ndarray, tex: np.ndarray, cal: Calibration
) -> tuple[np.ndarray, np.ndarray]:
    """Material id and albedo (n, 3) of ground points at world (x, z)."""
    n = x.shape[0]
    mat = np.full(n, GRASS, np.int8)
    alb = np.tile(np.asarray(lay.outer_albedo, _F32), (n, 1))
    if lay.outer_albedo != _GRASS:
        mat[:] = SIDEWALK
    side = (x > lay.road_right) & (x <= lay.road_right + lay.sidewalk) | (x < lay.road_left) & (
        x >= lay.road_left - lay.sidewalk
    )
    mat[side] = SIDEWALK
    alb[side] = lay.sidewalk_albedo
    road = (x >= lay.road_left) & (x <= lay.road_right) & ~((x > lay.median[0]) & (x < lay.median[1]))
    mat[road] = ROAD
    alb[road] = lay.road_albedo
    med = (x > lay.median[0]) & (x < lay.median[1])
    mat[med] = GRASS
    alb[med] = _GRASS
    for xc, hw, dashed in lay.markings:
        on = road & (np.abs(x - xc) < hw)
        if dashed:
            on &= np.mod(z, 12.0) < 4.0
        mat[on] = MARKING
        alb[on] = (0.55, 0.55, 0.52) if xc >= 0.05 or dashed or lay.median[1] > 0 else (0.50, 0.40, 0.12)
    tu, tv = x * (tex.shape[1] / 20.0), z * (tex.shape[0] / 20.0)
    t = sample_texture(tex, tu, tv)
    alb *= (1.0 + cal.texture_strength * np.clip(t, -2.5, 2.5) * 0.5)[:, None]
    return mat, alb


def surfaces(
    lay: Layout,
    origin: np.ndarray,
    dirs: np.ndarray,
    hits: Hits,
    t_ground: np.ndarray,
    tex: np.ndarray,
    r_window: np.random.Generator,
    cal: Calibration,
) -> Surfaces:
    """First-hit surface attributes; ``dirs`` (N, 3), ``t_ground`` (N,), ``tex`` a standardized
    texture (texels), ``r_window`` the scene's window stream."""
    H, W = hits.t.shape
    N = H * W
    t = np.where(hits.kind > 0, hits.t, t_ground.reshape(H, W)).ravel()
    kind = hits.kind.ravel()
    index = hits.index.ravel()
    pos = origin + np.where(np.isfinite(t), t, 0.0)[:, None] * dirs
    material = np.full(N, SKY, np.int8)
    albedo = np.zeros((N, 3))
    normal = hits.normal.reshape(N, 3).copy()
    # ground
    g = (kind == 0) & np.isfinite(t)
    gm, ga = _ground_albedo(lay, pos[g, 0], pos[g, 2], tex, cal)
    material[g] = gm
    albedo[g] = ga
    normal[g] = (0.0, 1.0, 0.0)
    # boxes, with a screen-space texture (the texture tiled over the image, period 64 px at 128 px)
    b = kind == 1
    bi = index[b]
    material[b] = lay.box_material[bi]
    albedo[b] = lay.box_albedo[bi]
    ti = (np.arange(H) * (128.0 / H)).astype(np.int64) % tex.shape[0]
    tj = (np.arange(W) * (128.0 / W)).astype(np.int64) % tex.shape[1]
    screen = tex[ti[:, None], tj[None, :]].ravel()
    albedo[b] *= (1.0 + 0.5 * cal.texture_strength * np.clip(screen[b], -2, 2))[:, None]
    # windows on building faces: a 3 m × 3.3 m grid above the ground floor
    window_lit = np.zeros(N, bool)
    bld = np.zeros(N, bool)
    bld[b] = lay.box_material[bi] == BUILDING
    if bld.any():
        n_b = normal[bld]
        p_b = pos[bld]
        along = np.where(np.abs(n_b[:, 0]) > 0.5, p_b[:, 2], p_b[:, 0])
        y = p_b[:, 1]
        top = lay.box_hi[index[bld], 1]
        fa, fy = np.mod(along / 3.0, 1.0), np.mod(y / 3.3, 1.0)
        win = (
            (fa > 0.22)
            & (fa < 0.78)
            & (fy > 0.35)
            & (fy < 0.85)
            & (y > 3.0)
            & (y < top - 0.8)
            & (np.abs(n_b[:, 1]) < 0.5)
        )
        lit_table = r_window.random(4096) < cal.window_lit_fraction
        key = np.mod(
            lay.box_block[index[bld]] * 7919
            + np.floor(along / 3.0).astype(np.int64) * 131
            + np.floor(y / 3.3).astype(np.int64) * 17,
            4096,
        )
        wi = np.flatnonzero(bld)[win]
        material[wi] = WINDOW
        albedo[wi] = (0.035, 0.04, 0.05)
        window_lit[wi] = lit_table[key[win]]
    # tree crowns
    s = kind == 2
    material[s] = FOLIAGE
    albedo[s] = lay.sphere_albedo[index[s]] * (1.0 + 0.8 * cal.texture_strength * np.clip(screen[s], -2, 2))[:, None]
    return Surfaces(t, material, albedo, normal, pos, window_lit, g)
