"""Sun shadows (§2.6): a ground raster of projected occluders plus facade height profiles.

With s the unit vector to the sun (s_y > 0), an occluder point p casts its shadow on the ground at
p − (p_y / s_y)·(s_x, s_z), so every box (crowns: their inscribed box) becomes a convex hexagon, its
footprint swept from the base's to the top's shadow, on a ground raster (``cv2.fillConvexPoly``). Ground pixels
look their cell up; objects standing on the ground look up the raster of tall occluders (buildings, poles, trees)
at their own ground position; facades facing the road test the opposite side's building height profile along the
ray to the sun. The result is the fraction of direct sun reaching each pixel (0 or 1); its visibility fades with
clouds and fog because those dim the direct sun, not the shadow mask.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .calibration import CALIBRATION, Calibration
from .layout import BUILDING, FOLIAGE, PEDESTRIAN, POLE, VEHICLE, WINDOW, Layout

__all__ = ["ShadowGeometry", "shadow_geometry", "sun_visibility"]


@dataclass(frozen=True)
class ShadowGeometry:
    """Weather-independent shadow inputs of a scene.

    Receivers: ``ground_pixels`` (G,) with ``ground_cell`` (G,) flat cells of the ground raster
    (-1 outside); ``foot_pixels``/``foot_cell`` for objects standing on the ground; ``facade_pixels``
    (F,), ``facade_pos`` (F, 3), ``facade_side`` (F,) (+1 right facade facing left, -1 left).
    Occluders (tall ones first: buildings, poles, tree crowns): ``rect`` (K, 4) footprints
    (x0, z0, x1, z1), ``base``/``top`` (K,) heights (m), ``tall_count``.
    Profiles: ``profile_x`` (2,) left/right facade planes, ``profile_h`` (2, Z) building heights on a
    z grid from ``profile_z0`` with step ``profile_dz`` (m).
    """

    ground_pixels: np.ndarray
    ground_cell: np.ndarray
    foot_pixels: np.ndarray
    foot_cell: np.ndarray
    facade_pixels: np.ndarray
    facade_pos: np.ndarray
    facade_side: np.ndarray
    rect: np.ndarray
    base: np.ndarray
    top: np.ndarray
    tall_count: int
    profile_x: np.ndarray
    profile_h: np.ndarray
    profile_z0: float
    profile_dz: float


def shadow_geometry(
    lay: Layout,
    material: np.ndarray,
    normal: np.ndarray,
    pos: np.ndarray,
    ground: np.ndarray,
    cal: Calibration = CALIBRATION,
) -> ShadowGeometry:
    """Receivers and occluders of a scene; ``material`` (N,), ``normal``/``pos`` (N, 3), ``ground`` (N,) bool."""
    x0, x1, z0, z1 = cal.shadow_map_extent
    cell = cal.shadow_map_cell
    nx, nz = int(round((x1 - x0) / cell)), int(round((z1 - z0) / cell))

    def cells(p: np.ndarray) -> np.ndarray:
        ci = np.floor((p[:, 0] - x0) / cell).astype(np.int64)
        ri = np.floor((p[:, 2] - z0) / cell).astype(np.int64)
        ok = (ci >= 0) & (ci < nx) & (ri >= 0) & (ri < nz)
        return np.where(ok, ri * nx + ci, -1)

    ground_pixels = np.flatnonzero(ground)
    foot_pixels = np.flatnonzero(np.isin(material, (VEHICLE, PEDESTRIAN, POLE, FOLIAGE)))
    keep = ~((lay.box_material == VEHICLE) & (lay.box_hi[:, 1] < 0.35)) & (
        lay.box_lo[:, 1] < 1.0
    )  # no wheels, lamp arms
    crown = 0.8 * lay.sphere_radius  # crowns shadow like their inscribed boxes
    rect = np.concatenate(
        [
            np.stack([lay.box_lo[keep, 0], lay.box_lo[keep, 2], lay.box_hi[keep, 0], lay.box_hi[keep, 2]], 1),
            np.stack(
                [
                    lay.sphere_center[:, 0] - crown,
                    lay.sphere_center[:, 2] - crown,
                    lay.sphere_center[:, 0] + crown,
                    lay.sphere_center[:, 2] + crown,
                ],
                1,
            ),
        ]
    )
    base = np.concatenate([np.zeros(int(keep.sum())), lay.sphere_center[:, 1] - crown])
    top = np.concatenate([lay.box_hi[keep, 1], lay.sphere_center[:, 1] + crown])
    tall = np.concatenate([np.isin(lay.box_material[keep], (BUILDING, POLE)), np.ones(len(crown), bool)])
    # occluders starting beyond the raster cannot shade it unless the sun is behind the camera and
    # very low (then the direct sun is weak): they are left out
    near = rect[:, 1] < z1
    rect, base, top, tall = rect[near], base[near], top[near], tall[near]
    order = np.argsort(~tall, kind="stable")
    # facade planes (left, right) and building height profiles along z
    is_b = lay.box_material == BUILDING
    prof_z0, prof_dz = -30.0, 0.5
    prof = np.zeros((2, int((cal.scene_length + 60.0) / prof_dz)))
    planes = np.array([-1e6, 1e6])
    for side, sel in ((0, is_b & (lay.box_hi[:, 0] < 0)), (1, is_b & (lay.box_lo[:, 0] > 0))):
        if sel.any():
            planes[side] = lay.box_hi[sel, 0].max() if side == 0 else lay.box_lo[sel, 0].min()
            for lo, hi in zip(lay.box_lo[sel], lay.box_hi[sel], strict=False):
                a, b = max(int((lo[2] - prof_z0) / prof_dz), 0), max(int((hi[2] - prof_z0) / prof_dz), 0)
                prof[side, a:b] = np.maximum(prof[side, a:b], hi[1])
    fac = np.flatnonzero(np.isin(material, (BUILDING, WINDOW)) & (np.abs(normal[:, 0]) > 0.5))
    return ShadowGeometry(
        ground_pixels=ground_pixels,
        ground_cell=cells(pos[ground_pixels]),
        foot_pixels=foot_pixels,
        foot_cell=cells(pos[foot_pixels]),
        facade_pixels=fac,
        facade_pos=pos[fac].astype(np.float32),
        facade_side=np.where(normal[fac, 0] < 0, 1, -1).astype(np.int8),
        rect=rect[order],
        base=base[order],
        top=top[order],
        tall_count=int(tall.sum()),
        profile_x=planes,
        profile_h=prof.astype(np.float32),
        profile_z0=prof_z0,
        profile_dz=prof_dz,
    )


def sun_visibility(
    sh: ShadowGeometry, n_pixels: int, sun_dir: np.ndarray, cal: Calibration = CALIBRATION
) -> np.ndarray:
    """Direct-sun visibility ``(n_pixels,)`` float32 in {0, 1} for the pixels of a scene with shadow geometry ``sh``;
    all zeros when the sun is below 2° (its direct light is negligible then)."""
    N = n_pixels
    vis = np.ones(N, np.float32)
    sx, sy, sz = (float(v) for v in sun_dir)
    if sy <= np.sin(np.radians(2.0)):
        vis[:] = 0.0
        return vis
    x0, x1, z0, z1 = cal.shadow_map_extent
    cell = cal.shadow_map_cell
    nx, nz = int(round((x1 - x0) / cell)), int(round((z1 - z0) / cell))
    # each occluder: its footprint rectangle swept from the base's shadow to the top's shadow (a hexagon)
    rect = sh.rect
    kb = sh.base / sy
    kt = sh.top / sy
    bx, bz = -kb * sx, -kb * sz
    vx, vz = (kb - kt) * sx, (kb - kt) * sz
    corners = np.stack(
        [
            np.stack([rect[:, 0], rect[:, 1]], 1),
            np.stack([rect[:, 2], rect[:, 1]], 1),
            np.stack([rect[:, 2], rect[:, 3]], 1),
            np.stack([rect[:, 0], rect[:, 3]], 1),
        ],
        1,
    )
    corners = corners + np.stack([bx, bz], 1)[:, None, :]
    a = np.where(vx >= 0, np.where(vz >= 0, 0, 3), np.where(vz >= 0, 1, 2))
    ar = np.arange(len(rect))[:, None]
    idx = (a[:, None] + np.arange(4)[None, :]) % 4
    c = corners[ar, idx]  # corners starting at the one opposite to the sweep
    v = np.stack([vx, vz], 1)[:, None, :]
    hexa = np.concatenate([c[:, :2], c[:, 1:] + v, c[:, 3:]], axis=1)  # (K, 6, 2)
    lim = 4.0 * max(nx, nz)
    poly = np.round(np.clip((hexa - (x0, z0)) / cell, -lim, lim) * 16).astype(np.int32)
    tall_map = np.zeros((nz, nx), np.uint8)
    n_tall = sh.tall_count
    for i in range(n_tall):
        cv2.fillConvexPoly(tall_map, poly[i], 1, lineType=cv2.LINE_8, shift=4)
    all_map = tall_map.copy() if n_tall < len(poly) else tall_map
    for i in range(n_tall, len(poly)):
        cv2.fillConvexPoly(all_map, poly[i], 1, lineType=cv2.LINE_8, shift=4)
    flat_all, flat_tall = all_map.ravel(), tall_map.ravel()
    gc = sh.ground_cell
    shadow = np.where(gc >= 0, flat_all[np.maximum(gc, 0)], 0)
    vis[sh.ground_pixels] = 1.0 - shadow
    fc = sh.foot_cell
    shadow = np.where(fc >= 0, flat_tall[np.maximum(fc, 0)], 0)
    vis[sh.foot_pixels] = 1.0 - shadow
    # facades: the opposite side's building profile along the ray to the sun
    if len(sh.facade_pixels):
        p = sh.facade_pos
        side = sh.facade_side  # +1: right facade (facing -x) ⇒ occluded by the left side (index 0)
        plane = np.where(side > 0, sh.profile_x[0], sh.profile_x[1]).astype(np.float32)
        toward = (side > 0) & (sx < 0) | (side < 0) & (sx > 0)
        t = (plane - p[:, 0]) / (sx if abs(sx) > 1e-6 else 1e-6)
        y = p[:, 1] + t * sy
        zi = np.clip(
            ((p[:, 2] + t * sz - sh.profile_z0) / sh.profile_dz).astype(np.int64), 0, sh.profile_h.shape[1] - 1
        )
        h = np.where(side > 0, sh.profile_h[0, zi], sh.profile_h[1, zi])
        occluded = toward & (t > 0) & (y < h) & (np.abs(plane) < 1e5)
        vis[sh.facade_pixels] = np.where(occluded, 0.0, 1.0)
    return vis
