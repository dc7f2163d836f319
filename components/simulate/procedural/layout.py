"""Scene layout: the weather-independent nuisance of one scene, drawn from its scene seed.

World frame (metres): x to the right of the road, y up, z along the road ahead; the ground is
``y = 0`` and the camera sits at ``z = 0``. A layout is a straight road of one archetype ("map":
urban canyon, suburban, highway, rural) with lanes, sidewalks, building blocks, trees, street
lamps, traffic, parked cars and pedestrians, plus the ego vehicle's camera (height
1.3·(0.5 + extent_z) as in CARLA's ``manual_control.py``, field of view, pitch, yaw) and the car's
heading in the world (so the sun azimuth relative to the camera is a nuisance), and the wind
azimuth relative to the camera.

Everything is drawn from one ``numpy.random.Generator`` (the scene's "layout" stream); weather
never enters here.

Part of the embedded renderer: used by the ``generate``, ``evaluate`` (PPCs) and ``task2`` (rendered bag) stages and the
``pidc`` CLI (``render``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .calibration import CALIBRATION, Calibration

__all__ = [
    "Layout",
    "sample_layout",
    "MATERIALS",
    "SKY",
    "ROAD",
    "MARKING",
    "SIDEWALK",
    "GRASS",
    "BUILDING",
    "WINDOW",
    "VEHICLE",
    "PEDESTRIAN",
    "FOLIAGE",
    "POLE",
]

# material ids of the per-pixel material map
SKY, ROAD, MARKING, SIDEWALK, GRASS, BUILDING, WINDOW, VEHICLE, PEDESTRIAN, FOLIAGE, POLE = range(11)
MATERIALS = (
    "sky",
    "road",
    "marking",
    "sidewalk",
    "grass",
    "building",
    "window",
    "vehicle",
    "pedestrian",
    "foliage",
    "pole",
)

# linear albedos of the scene palette (RGB)
_ROAD_ALBEDO = (0.085, 0.085, 0.09)
_SIDEWALK_ALBEDO = (0.26, 0.25, 0.24)
_GRASS_ALBEDO = (0.07, 0.12, 0.035)
_PAVEMENT_ALBEDO = (0.18, 0.17, 0.16)
_FACADES = (
    (0.30, 0.27, 0.24),
    (0.45, 0.42, 0.38),
    (0.36, 0.18, 0.12),
    (0.22, 0.22, 0.24),
    (0.55, 0.50, 0.42),
    (0.40, 0.33, 0.25),
    (0.28, 0.30, 0.33),
)
_CARS = (
    (0.55, 0.55, 0.57),
    (0.04, 0.04, 0.045),
    (0.60, 0.04, 0.03),
    (0.05, 0.12, 0.40),
    (0.75, 0.75, 0.74),
    (0.20, 0.22, 0.24),
    (0.45, 0.35, 0.10),
    (0.06, 0.25, 0.10),
)
_CLOTHES = ((0.05, 0.05, 0.06), (0.20, 0.10, 0.08), (0.10, 0.15, 0.35), (0.40, 0.40, 0.38), (0.45, 0.10, 0.10))
_FOLIAGE = ((0.05, 0.10, 0.03), (0.07, 0.12, 0.03), (0.09, 0.11, 0.04))
_TRUNK = (0.10, 0.07, 0.05)
_POLE_ALBEDO = (0.20, 0.20, 0.21)


@dataclass(frozen=True)
class Layout:
    """One scene's geometry and camera, all in the world frame (metres, degrees).

    Boxes are axis-aligned: ``box_lo``/``box_hi`` (N, 3), ``box_albedo`` (N, 3) linear RGB,
    ``box_material`` (N,) material ids, ``box_block`` (N,) building block id or -1.
    Spheres (tree crowns): ``sphere_center`` (M, 3), ``sphere_radius`` (M,), ``sphere_albedo`` (M, 3).
    ``lamps`` (L, 3) lamp head positions; ``lights`` (V, 3) vehicle light positions with
    ``light_is_head`` (V,) (True: white head light facing the camera, False: red tail light).
    ``markings`` (K, 3): lane lines as (x centre, half width, dashed 0/1).
    """

    archetype: str
    camera: np.ndarray
    ego_extent_z: float
    fov_deg: float
    pitch_deg: float
    yaw_deg: float
    heading_deg: float
    wind_azimuth_deg: float
    road_left: float
    road_right: float
    median: tuple[float, float]
    sidewalk: float
    outer_albedo: tuple[float, float, float]
    markings: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    box_albedo: np.ndarray
    box_material: np.ndarray
    box_block: np.ndarray
    sphere_center: np.ndarray
    sphere_radius: np.ndarray
    sphere_albedo: np.ndarray
    lamps: np.ndarray
    lights: np.ndarray
    light_is_head: np.ndarray

    @property
    def road_albedo(self) -> tuple[float, float, float]:
        return _ROAD_ALBEDO

    @property
    def sidewalk_albedo(self) -> tuple[float, float, float]:
        return _SIDEWALK_ALBEDO


class _Builder:
    def __init__(self) -> None:
        self.lo: list[tuple[float, float, float]] = []
        self.hi: list[tuple[float, float, float]] = []
        self.albedo: list[tuple[float, float, float]] = []
        self.material: list[int] = []
        self.block: list[int] = []
        self.sc: list[tuple[float, float, float]] = []
        self.sr: list[float] = []
        self.sa: list[tuple[float, float, float]] = []
        self.lamps: list[tuple[float, float, float]] = []
        self.lights: list[tuple[float, float, float]] = []
        self.head: list[bool] = []

    def box(self, lo, hi, albedo, material, block=-1) -> None:  # noqa: ANN001 - internal
        self.lo.append(tuple(lo))
        self.hi.append(tuple(hi))
        self.albedo.append(tuple(albedo))
        self.material.append(material)
        self.block.append(block)


def _pick(rng: np.random.Generator, table: tuple) -> tuple:
    return table[int(rng.integers(len(table)))]


def _jitter(rng: np.random.Generator, albedo: tuple, amount: float = 0.15) -> tuple:
    return tuple(float(a) * float(rng.uniform(1 - amount, 1 + amount)) for a in albedo)


def _buildings(
    b: _Builder,
    rng: np.random.Generator,
    side: int,
    x_front: float,
    length: float,
    span: tuple[float, float],
    height: tuple[float, float],
    gap: tuple[float, float],
    gap_p: float,
    depth: float,
    block0: int,
) -> int:
    """Blocks along one side (side=+1 right, -1 left) from z=-20 to ``length``; returns next block id."""
    z = -20.0 + float(rng.uniform(0, 8))
    block = block0
    while z < length:
        if rng.random() < gap_p:
            z += float(rng.uniform(*gap))
            continue
        seg = float(rng.uniform(*span))
        h = float(rng.uniform(*height))
        x0, x1 = (x_front, x_front + depth) if side > 0 else (x_front - depth, x_front)
        b.box((x0, 0.0, z), (x1, h, z + seg), _jitter(rng, _pick(rng, _FACADES)), 5, block)
        block += 1
        z += seg
    return block


def _tree(b: _Builder, rng: np.random.Generator, x: float, z: float, scale: float = 1.0) -> None:
    trunk = float(rng.uniform(1.8, 3.2)) * scale
    r = float(rng.uniform(1.3, 2.8)) * scale
    b.box((x - 0.15, 0.0, z - 0.15), (x + 0.15, trunk, z + 0.15), _TRUNK, 10)
    b.sc.append((x, trunk + 0.7 * r, z))
    b.sr.append(r)
    b.sa.append(_jitter(rng, _pick(rng, _FOLIAGE), 0.25))


def _lamps(b: _Builder, rng: np.random.Generator, x_pole: float, arm: float, length: float, cal: Calibration) -> None:
    z = float(rng.uniform(0, cal.lamp_spacing[0]))
    spacing = float(rng.uniform(*cal.lamp_spacing))
    h = float(rng.uniform(*cal.lamp_height))
    while z < min(length, 180.0):
        b.box((x_pole - 0.1, 0.0, z - 0.1), (x_pole + 0.1, h, z + 0.1), _POLE_ALBEDO, 10)
        b.box(
            (min(x_pole, x_pole + arm) - 0.05, h - 0.12, z - 0.05),
            (max(x_pole, x_pole + arm) + 0.05, h, z + 0.05),
            _POLE_ALBEDO,
            10,
        )
        b.lamps.append((x_pole + arm, h - 0.2, z))
        z += spacing


def _vehicle(b: _Builder, rng: np.random.Generator, x: float, z: float, oncoming: bool, lights: bool = True) -> None:
    if rng.random() < 0.12:  # van/truck
        w, h, length = float(rng.uniform(2.2, 2.5)), float(rng.uniform(2.4, 3.4)), float(rng.uniform(6.0, 9.0))
    else:
        w, h, length = float(rng.uniform(1.75, 2.0)), float(rng.uniform(1.35, 1.8)), float(rng.uniform(4.0, 5.0))
    colour = _jitter(rng, _pick(rng, _CARS), 0.1)
    b.box((x - w / 2, 0.25, z), (x + w / 2, h, z + length), colour, 7)
    b.box((x - w / 2 + 0.15, 0.0, z + 0.5), (x + w / 2 - 0.15, 0.3, z + length - 0.5), (0.03, 0.03, 0.03), 7)
    if lights:
        y = 0.75
        face = z - 0.02  # the face towards the camera (vehicles are ahead)
        for dx in (-w / 2 + 0.3, w / 2 - 0.3):
            b.lights.append((x + dx, y, face))
            b.head.append(oncoming)


def _pedestrian(b: _Builder, rng: np.random.Generator, x: float, z: float) -> None:
    h = float(rng.uniform(1.55, 1.9))
    b.box((x - 0.25, 0.0, z - 0.17), (x + 0.25, h * 0.86, z + 0.17), _jitter(rng, _pick(rng, _CLOTHES)), 8)
    b.box((x - 0.11, h * 0.86, z - 0.11), (x + 0.11, h, z + 0.11), (0.35, 0.25, 0.20), 8)


def sample_layout(rng: np.random.Generator, cal: Calibration = CALIBRATION) -> Layout:
    """Draw one scene layout from the layout stream ``rng`` (weather-independent).

    One function on purpose (over 80 lines): its sequence of draws from ``rng`` *is* the dataset (every scene of
    every split descends from it), so it reads top to bottom in the order of the draws; a split that reordered one
    draw would change every image.
    """
    arch_idx = int(rng.choice(len(cal.archetypes), p=np.asarray(cal.archetype_weights) / sum(cal.archetype_weights)))
    arch = cal.archetypes[arch_idx]
    lw = cal.lane_width
    length = cal.scene_length
    b = _Builder()
    markings: list[tuple[float, float, float]] = []
    median = (0.0, 0.0)
    if arch == "highway":
        n_fwd, n_back = int(rng.integers(2, 4)), int(rng.integers(2, 4))
        m = float(rng.uniform(1.0, 2.0))
        median = (-m, m)
        shoulder = 2.5
        road_right = m + n_fwd * lw + shoulder
        road_left = -m - n_back * lw - shoulder
        lanes_fwd = [m + (i + 0.5) * lw for i in range(n_fwd)]
        lanes_back = [-m - (i + 0.5) * lw for i in range(n_back)]
        for i in range(1, n_fwd):
            markings.append((m + i * lw, 0.08, 1.0))
        for i in range(1, n_back):
            markings.append((-m - i * lw, 0.08, 1.0))
        for x in (m + 0.2, -m - 0.2, m + n_fwd * lw, -m - n_back * lw):
            markings.append((x, 0.1, 0.0))
        sidewalk = 0.0
        outer = _GRASS_ALBEDO
        b.box((-0.3, 0.0, -10.0), (0.3, 0.9, length), (0.35, 0.35, 0.34), 10)  # concrete barrier
        _lamps(b, rng, 0.0, 0.0, length, cal)
        if rng.random() < 0.5:
            _buildings(
                b, rng, +1, road_right + float(rng.uniform(25, 60)), length, (20, 60), (5, 14), (20, 80), 0.5, 30.0, 0
            )
        for _ in range(int(rng.poisson(8))):
            side = 1 if rng.random() < 0.5 else -1
            x = side * (road_right + float(rng.uniform(4, 25))) if side > 0 else road_left - float(rng.uniform(4, 25))
            _tree(b, rng, x, float(rng.uniform(5, 200)))
    else:
        n_fwd = int(rng.integers(1, 3)) if arch == "urban_canyon" else 1
        n_back = n_fwd
        parking = 2.3 if arch in ("urban_canyon", "suburban") else 0.0
        shoulder = 0.6 if arch == "rural" else 0.0
        road_right = n_fwd * lw + parking + shoulder
        road_left = -n_back * lw - parking - shoulder
        lanes_fwd = [(i + 0.5) * lw for i in range(n_fwd)]
        lanes_back = [-(i + 0.5) * lw for i in range(n_back)]
        markings.append((0.12, 0.06, 0.0))
        markings.append((-0.12, 0.06, 0.0))
        for i in range(1, n_fwd):
            markings.append((i * lw, 0.07, 1.0))
            markings.append((-i * lw, 0.07, 1.0))
        if arch == "rural":
            markings.append((n_fwd * lw, 0.08, 0.0))
            markings.append((-n_back * lw, 0.08, 0.0))
        if arch == "urban_canyon":
            sidewalk = float(rng.uniform(3.0, 4.5))
            outer = _PAVEMENT_ALBEDO
            xr, xl = road_right + sidewalk, road_left - sidewalk
            nb = _buildings(b, rng, +1, xr, length, (10, 30), (10, 32), (3, 8), 0.1, 20.0, 0)
            _buildings(b, rng, -1, xl, length, (10, 30), (10, 32), (3, 8), 0.1, 20.0, nb)
            for _ in range(int(rng.poisson(2))):
                _tree(b, rng, road_right + sidewalk * 0.6, float(rng.uniform(5, 120)), 0.8)
        elif arch == "suburban":
            sidewalk = float(rng.uniform(2.0, 3.0))
            outer = _GRASS_ALBEDO
            sb = float(rng.uniform(4.0, 10.0))
            xr, xl = road_right + sidewalk + sb, road_left - sidewalk - sb
            nb = _buildings(b, rng, +1, xr, length, (8, 14), (4, 9), (4, 12), 0.35, 10.0, 0)
            _buildings(b, rng, -1, xl, length, (8, 14), (4, 9), (4, 12), 0.35, 10.0, nb)
            for side_x in (road_right + sidewalk + 1.2, road_left - sidewalk - 1.2):
                z = float(rng.uniform(2, 12))
                while z < 200:
                    if rng.random() < 0.7:
                        _tree(b, rng, side_x, z)
                    z += float(rng.uniform(9, 18))
        else:  # rural
            sidewalk = 0.0
            outer = _GRASS_ALBEDO
            z = 0.0
            block = 0
            while z < length:
                z += float(rng.uniform(25, 70))
                if rng.random() < 0.3:
                    side = 1 if rng.random() < 0.5 else -1
                    sb = float(rng.uniform(10, 30))
                    x0 = road_right + sb if side > 0 else road_left - sb - 10
                    h = float(rng.uniform(4, 7))
                    b.box(
                        (x0, 0.0, z),
                        (x0 + 10, h, z + float(rng.uniform(8, 14))),
                        _jitter(rng, _pick(rng, _FACADES)),
                        5,
                        block,
                    )
                    block += 1
            for _ in range(int(rng.poisson(16))):
                side = 1 if rng.random() < 0.5 else -1
                d = float(rng.uniform(2.5, 14))
                x = road_right + d if side > 0 else road_left - d
                _tree(b, rng, x, float(rng.uniform(4, 220)), float(rng.uniform(0.9, 1.5)))
        if arch != "rural" or rng.random() < 0.5:
            _lamps(b, rng, road_right + min(sidewalk, 1.0) * 0.4 + 0.4, -1.6, length, cal)
            if arch == "urban_canyon" or rng.random() < 0.4:
                _lamps(b, rng, road_left - min(sidewalk, 1.0) * 0.4 - 0.4, 1.6, length, cal)
        if parking > 0:
            for side in (+1, -1):
                z = float(rng.uniform(3, 10))
                while z < 120:
                    if rng.random() < 0.45:
                        x = road_right - parking / 2 if side > 0 else road_left + parking / 2
                        _vehicle(b, rng, x, z, oncoming=side < 0, lights=False)
                    z += float(rng.uniform(6.0, 9.0))
        if sidewalk > 0:
            for _ in range(int(rng.poisson(cal.pedestrians_mean[arch_idx]))):
                side = 1 if rng.random() < 0.5 else -1
                x = (
                    road_right + float(rng.uniform(0.4, sidewalk - 0.4))
                    if side > 0
                    else road_left - float(rng.uniform(0.4, sidewalk - 0.4))
                )
                _pedestrian(b, rng, x, float(rng.uniform(4, 50)))
        elif arch == "rural":
            for _ in range(int(rng.poisson(cal.pedestrians_mean[arch_idx]))):
                _pedestrian(b, rng, road_right + float(rng.uniform(0.3, 1.5)), float(rng.uniform(6, 50)))
    # ego lane and camera
    ego_x = float(lanes_fwd[int(rng.integers(len(lanes_fwd)))]) + float(rng.uniform(-0.4, 0.4))
    extent_z = float(cal.ego_extent_z[int(rng.integers(len(cal.ego_extent_z)))])
    camera = np.array([ego_x, 1.3 * (0.5 + extent_z), 0.0])
    # traffic: moving vehicles in the lanes ahead (no overlaps within a lane)
    lanes = [(x, False) for x in lanes_fwd] + [(x, True) for x in lanes_back]
    occupied: dict[int, list[float]] = {}
    for _ in range(int(rng.poisson(cal.vehicles_mean[arch_idx]))):
        li = int(rng.integers(len(lanes)))
        x, oncoming = lanes[li]
        z = float(rng.uniform(*cal.vehicle_range))
        if abs(x - ego_x) < 1.5 and z < 10.0:
            z += 10.0
        if any(abs(z - z2) < 10.0 for z2 in occupied.get(li, [])):
            continue
        occupied.setdefault(li, []).append(z)
        _vehicle(b, rng, x + float(rng.uniform(-0.3, 0.3)), z, oncoming)
    fov = float(rng.uniform(*cal.fov_deg))
    pitch = float(rng.uniform(-cal.pitch_deg, cal.pitch_deg))
    yaw = float(rng.uniform(-cal.yaw_deg, cal.yaw_deg))
    heading = float(rng.uniform(0.0, 360.0))
    wind = float(rng.uniform(0.0, 360.0))

    def arr(x: list, n: int) -> np.ndarray:
        return np.asarray(x, dtype=np.float64).reshape(-1, n)

    return Layout(
        archetype=arch,
        camera=camera,
        ego_extent_z=extent_z,
        fov_deg=fov,
        pitch_deg=pitch,
        yaw_deg=yaw,
        heading_deg=heading,
        wind_azimuth_deg=wind,
        road_left=road_left,
        road_right=road_right,
        median=median,
        sidewalk=sidewalk,
        outer_albedo=outer,
        markings=arr(markings, 3),
        box_lo=arr(b.lo, 3),
        box_hi=arr(b.hi, 3),
        box_albedo=arr(b.albedo, 3),
        box_material=np.asarray(b.material, dtype=np.int64),
        box_block=np.asarray(b.block, dtype=np.int64),
        sphere_center=arr(b.sc, 3),
        sphere_radius=np.asarray(b.sr, dtype=np.float64),
        sphere_albedo=arr(b.sa, 3),
        lamps=arr(b.lamps, 3),
        lights=arr(b.lights, 3),
        light_is_head=np.asarray(b.head, dtype=bool),
    )
