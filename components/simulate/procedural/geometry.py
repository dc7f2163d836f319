"""Pinhole camera and analytic ray casting of a layout (ground plane, boxes, spheres).

Rays are cast once per scene (the geometry pass); everything here is weather-independent.
Pixel ``(i, j)`` (row, column) of an ``H × W`` image looks along the unit direction ``d[i, j]``
(world frame of :mod:`components.simulate.procedural.layout`). Boxes and spheres are only tested inside their
projected screen rectangle, so the cost scales with their screen area, not with their number.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Camera", "make_camera", "Hits", "cast_objects", "rect_pixels", "nearest_per_pixel"]


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: ``origin`` (3,) m, ``rot`` (3, 3) with columns = right, up, forward (world),
    ``focal`` in pixels, image ``height`` × ``width``."""

    origin: np.ndarray
    rot: np.ndarray
    focal: float
    height: int
    width: int

    def rays(self) -> np.ndarray:
        """Unit ray directions, shape (H, W, 3), float64."""
        j = (np.arange(self.width) + 0.5 - self.width / 2) / self.focal
        i = -(np.arange(self.height) + 0.5 - self.height / 2) / self.focal
        k = np.stack(np.broadcast_arrays(j[None, :], i[:, None], np.ones((1, 1))), axis=-1)
        k = k / np.linalg.norm(k, axis=-1, keepdims=True)
        return k @ self.rot.T

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points (..., 3) → (column, row, camera depth) with pixel centres at integers."""
        k = (np.asarray(points) - self.origin) @ self.rot
        z = k[..., 2]
        zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
        col = self.focal * k[..., 0] / zs + self.width / 2 - 0.5
        row = -self.focal * k[..., 1] / zs + self.height / 2 - 0.5
        return col, row, z


def make_camera(
    origin: np.ndarray, fov_deg: float, pitch_deg: float, yaw_deg: float, height: int, width: int
) -> Camera:
    """Camera looking along +z, rotated by ``pitch`` (up positive) then ``yaw`` (right positive)."""
    p, y = math.radians(pitch_deg), math.radians(yaw_deg)
    rp = np.array([[1, 0, 0], [0, math.cos(p), math.sin(p)], [0, -math.sin(p), math.cos(p)]]).T
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    rot = ry @ rp
    focal = (width / 2) / math.tan(math.radians(fov_deg) / 2)
    return Camera(np.asarray(origin, dtype=np.float64), rot, focal, height, width)


@dataclass
class Hits:
    """Closest object hits per pixel: ``t`` (H, W) distance (inf: none), ``kind`` (H, W) int8
    (0 none, 1 box, 2 sphere), ``index`` (H, W) int32 object index, ``normal`` (H, W, 3)."""

    t: np.ndarray
    kind: np.ndarray
    index: np.ndarray
    normal: np.ndarray


def _rects(
    cam: Camera, lo: np.ndarray, hi: np.ndarray, o: np.ndarray, rows: tuple[int, int]
) -> list[tuple[int, int, int, int] | None]:
    """Screen rectangles (r0, r1, c0, c1) of boxes lo/hi (n, 3), None when not visible.

    Boxes reaching behind the camera are clipped to z ≥ camera z + 0.1 (nothing behind is visible)."""
    n = len(lo)
    if n == 0:
        return []
    clo = lo.copy()
    clo[:, 2] = np.maximum(lo[:, 2], o[2] + 0.1)
    pts = clo[:, None, :] + _CORNERS[None] * (hi - clo)[:, None, :]
    col, row, z = cam.project(pts)
    out: list[tuple[int, int, int, int] | None] = []
    behind = hi[:, 2] <= o[2] + 0.1
    some = (z <= 0.05).any(axis=1)
    every = (z <= 0.05).all(axis=1)
    c0 = np.floor(col.min(1) - 1.0).astype(np.int64).clip(0, cam.width)
    c1 = (np.ceil(col.max(1) + 1.0).astype(np.int64) + 1).clip(0, cam.width)
    r0 = np.floor(row.min(1) - 1.0).astype(np.int64).clip(rows[0], rows[1])
    r1 = (np.ceil(row.max(1) + 1.0).astype(np.int64) + 1).clip(rows[0], rows[1])
    for k in range(n):
        if behind[k] or every[k]:
            out.append(None)
        elif some[k]:
            out.append((rows[0], rows[1], 0, cam.width) if rows[0] < rows[1] else None)
        elif c0[k] >= c1[k] or r0[k] >= r1[k]:
            out.append(None)
        else:
            out.append((int(r0[k]), int(r1[k]), int(c0[k]), int(c1[k])))
    return out


_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)


def rect_pixels(rects: list[tuple[int, int, int, int] | None], width: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices covered by each rectangle and the owning object index, concatenated."""
    keep = [k for k, r in enumerate(rects) if r is not None]
    if not keep:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    r = np.array([rects[k] for k in keep], dtype=np.int64)
    h, w = r[:, 1] - r[:, 0], r[:, 3] - r[:, 2]
    area = h * w
    obj = np.repeat(np.asarray(keep, np.int64), area)
    start = np.repeat(np.cumsum(area) - area, area)
    j = np.arange(int(area.sum()), dtype=np.int64) - start
    ww = np.repeat(w, area)
    rows = np.repeat(r[:, 0], area) + j // ww
    cols = np.repeat(r[:, 2], area) + j % ww
    return (rows * width + cols).astype(np.int32), obj.astype(np.int32)


def nearest_per_pixel(
    pix: np.ndarray, t: np.ndarray, obj: np.ndarray, n_pixels: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel, the smallest t among candidate hits ``(pix, t, obj)``: returns (pixels, t, object),
    pixels ascending; exact ties go to the larger object index (deterministic)."""
    best = np.full(n_pixels, np.inf, dtype=np.result_type(t.dtype, np.float32))
    np.minimum.at(best, pix, t)
    win = t == best[pix]
    owner = np.full(n_pixels, -1, np.int64)
    np.maximum.at(owner, pix[win], obj[win])
    hit = np.flatnonzero(owner >= 0)
    return hit, best[hit], owner[hit]


def cast_objects(
    cam: Camera,
    dirs: np.ndarray,
    box_lo: np.ndarray,
    box_hi: np.ndarray,
    sphere_center: np.ndarray,
    sphere_radius: np.ndarray,
    t_min: np.ndarray,
    t_max: np.ndarray,
    rows: tuple[int, int] | None = None,
) -> Hits:
    """Closest box/sphere hit along each ray from ``cam.origin`` with ``t_min < t < t_max``.

    ``dirs`` (H, W, 3) unit directions; ``t_min``/``t_max`` (H, W). Boxes (N, 3) lo/hi corners,
    spheres (M, 3) centres and (M,) radii; only image ``rows`` (start, stop) are cast when given.
    Every object is tested only on the pixels of its screen rectangle, all objects in one
    vectorized pass (slab test for boxes, quadratic for spheres), then the nearest hit wins.
    """
    H, W = t_min.shape
    o = cam.origin
    rows = (0, H) if rows is None else rows
    d = dirs.reshape(-1, 3)
    tmin, tmax = t_min.ravel(), t_max.ravel()
    safe = np.where(np.abs(d) < 1e-9, 1e-9, d)
    inv = [np.ascontiguousarray(1.0 / safe[:, a], np.float32) for a in range(3)]  # float32: ample for < 10 km
    dc = [np.ascontiguousarray(d[:, a], np.float32) for a in range(3)]
    tmin, tmax = tmin.astype(np.float32), tmax.astype(np.float32)
    # boxes
    pix, obj = rect_pixels(_rects(cam, box_lo, box_hi, o, rows), W)
    tn = tf = None
    for a in range(3):
        iv = inv[a][pix]
        t1 = (box_lo[:, a] - o[a]).astype(np.float32)[obj] * iv
        t2 = (box_hi[:, a] - o[a]).astype(np.float32)[obj] * iv
        near, far = np.minimum(t1, t2), np.maximum(t1, t2)
        tn = near if tn is None else np.maximum(tn, near)
        tf = far if tf is None else np.minimum(tf, far)
    ok = (tn <= tf) & (tn > tmin[pix]) & (tn < tmax[pix]) if len(pix) else np.zeros(0, bool)
    bp, bt, bo = nearest_per_pixel(pix[ok], tn[ok], obj[ok], H * W)
    # spheres
    lo_s, hi_s = sphere_center - sphere_radius[:, None], sphere_center + sphere_radius[:, None]
    pix, obj = rect_pixels(_rects(cam, lo_s, hi_s, o, rows), W)
    oc = (sphere_center - o).astype(np.float32)
    bq = dc[0][pix] * oc[obj, 0] + dc[1][pix] * oc[obj, 1] + dc[2][pix] * oc[obj, 2]
    disc = bq * bq - ((oc * oc).sum(axis=1) - sphere_radius**2).astype(np.float32)[obj]
    tn = bq - np.sqrt(np.maximum(disc, 0.0))
    ok = (disc > 0) & (tn > tmin[pix]) & (tn < tmax[pix])
    sp, st, so = nearest_per_pixel(pix[ok], tn[ok], obj[ok], H * W)
    t_best = np.full(H * W, np.inf)
    kind = np.zeros(H * W, np.int8)
    index = np.full(H * W, -1, np.int32)
    t_best[bp] = bt
    kind[bp] = 1
    index[bp] = bo
    closer = st < t_best[sp]
    sp, st, so = sp[closer], st[closer], so[closer]
    t_best[sp] = st
    kind[sp] = 2
    index[sp] = so
    normal = np.zeros((H * W, 3))
    m = np.flatnonzero(kind == 1)
    if len(m):
        idx = index[m]
        p = o + t_best[m][:, None] * d[m]
        dist = np.concatenate([np.abs(p - box_lo[idx]), np.abs(p - box_hi[idx])], axis=1)
        table = np.concatenate([-np.eye(3), np.eye(3)])
        normal[m] = table[dist.argmin(axis=1)]
    m = np.flatnonzero(kind == 2)
    if len(m):
        idx = index[m]
        p = o + t_best[m][:, None] * d[m]
        normal[m] = (p - sphere_center[idx]) / sphere_radius[idx][:, None]
    return Hits(t_best.reshape(H, W), kind.reshape(H, W), index.reshape(H, W), normal.reshape(H, W, 3))
