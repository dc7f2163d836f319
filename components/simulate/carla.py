"""The CARLA client backend: the :class:`~components.simulate.base.Simulator` protocol against a server.

``CarlaSimulator.render(weather, scene_seed)`` returns the ego vehicle's hood-camera RGB image
(``(height, width, 3)`` uint8) of the scene named by ``scene_seed`` under ``weather``. The scene is a
function of ``scene_seed`` only (:func:`plan_scene`: map, ego vehicle and spawn point — hence the heading
and the sun azimuth relative to the camera —, numbers, blueprints and spawn points of NPC vehicles and
pedestrians, the seeds of the traffic manager and of the pedestrian navigation). It is built once and
cached while the same seed is requested: after a warm-up, every actor is frozen (autopilot off, physics
off, walker controllers stopped, traffic lights frozen), so posterior predictive checks re-render the same
scene under other weathers. CARLA's clouds and rain particles keep animating, so re-renders are close but
never byte-identical (treat it as simulator noise).

The map of a scene is one of the configured towns (:data:`TOWNS` by default; a non-town map, where no vehicle can
spawn, is refused by name), loaded with ``client.load_world_if_different`` so that a scene on the town already loaded
costs no reload.

Each weather is applied with :func:`weather_parameters` (all 13 fields by keyword), then the world is
ticked ``settle_ticks`` times in synchronous mode (auto-exposure adapts over frames) and the camera image
whose frame id matches the last tick is returned.

The ``carla`` package is an optional extra (``pip install 'pidc[carla]'``); it is imported lazily, so
this module can be imported without it. Every spawned actor is destroyed and the server is returned to
asynchronous mode on :meth:`CarlaSimulator.close`, on context-manager exit, before a new scene is built
and when rendering fails.

Imported by :func:`~components.simulate.base.make_simulator`, so used by the ``generate``, ``evaluate`` and ``task2``
stages (with ``simulator.backend: carla``); the ``pidc`` CLI imports it too.
"""

from __future__ import annotations

import importlib
import math
import queue
import socket
import time
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from types import ModuleType, TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np

from components.core import seeding
from components.core.checks import whole_number
from components.core.weather import ALL_NAMES, complete_weather

if TYPE_CHECKING:
    from components.core.config import SimulatorConfig

__all__ = [
    "TOWNS",
    "CarlaConnectionError",
    "CarlaSimulator",
    "ScenePlan",
    "bgra_to_rgb",
    "choose_map",
    "hood_camera_transform",
    "import_carla",
    "plan_scene",
    "probe_carla_server",
    "synchronous_settings",
    "asynchronous_settings",
    "weather_parameters",
]

#: The towns a scene seed draws from by default: CARLA 0.9.16's standard towns (``params.yaml``'s
#: ``simulator.carla.maps`` holds the same list; Town06 and Town07 come with CARLA's AdditionalMaps package).
TOWNS: tuple[str, ...] = ("Town01", "Town02", "Town03", "Town04", "Town05", "Town06", "Town07", "Town10HD")
#: Simulated seconds the traffic runs (autopilot, walkers) before the scene is frozen.
WARMUP_SECONDS = 2.0
#: Client timeout (s) while the server loads a map; loading a town takes tens of seconds.
LOAD_WORLD_TIMEOUT_S = 120.0
#: CARLA's default walking speed (m/s), used when a walker blueprint recommends none.
DEFAULT_WALKING_SPEED = 1.4

_INSTALL_HINT = "pip install 'pidc[carla]' (the client must match the server's version, e.g. carla==0.9.16)"


class CarlaConnectionError(ConnectionError):
    """No CARLA server answered at ``host:port`` within the timeout."""


def import_carla() -> ModuleType:
    """The ``carla`` client module; ``ImportError`` saying how to install it when it is missing."""
    try:
        return importlib.import_module("carla")
    except ImportError as exc:
        raise ImportError(f"the CARLA backend needs the `carla` client package: {_INSTALL_HINT}") from exc


# --- weather ---------------------------------------------------------------------------------------


def weather_parameters(weather: Mapping[str, float]) -> Any:
    """``carla.WeatherParameters`` of a pidc weather (CARLA names → values, :mod:`components.core.weather`).

    The weather is validated and completed (:func:`components.core.weather.complete_weather`, so a bad
    weather raises ``ValueError`` before anything touches the server); all 13 fields are passed by
    keyword, never by position (the positional order differs between CARLA versions), and
    ``dust_storm`` is set to 0 where the installed class has that field.
    """
    values = complete_weather(weather, where="CARLA backend: ")
    carla = import_carla()
    kwargs = {name: values[name] for name in ALL_NAMES}
    if hasattr(carla.WeatherParameters, "dust_storm"):
        kwargs["dust_storm"] = 0.0
    return carla.WeatherParameters(**kwargs)


# --- the scene plan (pure, seeded) -----------------------------------------------------------------


@dataclass(frozen=True)
class ScenePlan:
    """Every seeded choice of a CARLA scene; a pure function of ``scene_seed`` and the candidate lists.

    Attributes:
        scene_seed: the scene seed it was drawn from.
        map_name: the chosen map (one of the candidate names).
        ego_blueprint: the ego vehicle's blueprint.
        ego_spawn_index: the index of its spawn point in the map's spawn points (its transform fixes the heading).
        ego_colour: a draw in [0, 1) that picks the colour among the blueprint's recommended colours.
        vehicle_blueprints: the NPC vehicles' blueprints.
        vehicle_spawn_indices: their spawn points (as many), distinct and never the ego's.
        vehicle_colours: their colour draws in [0, 1) (as many).
        walker_blueprints: one blueprint per pedestrian.
        pedestrian_seed: seed of the server's pedestrian RNG (navigation spawn locations, destinations).
        traffic_seed: seed of the traffic manager's random device.
    """

    scene_seed: int
    map_name: str
    ego_blueprint: str
    ego_spawn_index: int
    ego_colour: float
    vehicle_blueprints: tuple[str, ...]
    vehicle_spawn_indices: tuple[int, ...]
    vehicle_colours: tuple[float, ...]
    walker_blueprints: tuple[str, ...]
    pedestrian_seed: int
    traffic_seed: int

    @property
    def n_vehicles(self) -> int:
        return len(self.vehicle_blueprints)

    @property
    def n_pedestrians(self) -> int:
        return len(self.walker_blueprints)


def _check_scene_seed(scene_seed: object) -> int:
    return whole_number("scene_seed", scene_seed, low=0, type_error=TypeError)


def _names(what: str, names: Iterable[str]) -> list[str]:
    """Sorted, de-duplicated candidate names (so the plan does not depend on the server's list order)."""
    if isinstance(names, str):
        raise TypeError(f"{what} must be a sequence of names, not the string {names!r}")
    out = set()
    for n in names:
        if not isinstance(n, str) or not n:
            raise ValueError(f"{what} must be non-empty strings, got {n!r}")
        out.add(n)
    return sorted(out)


def choose_map(scene_seed: int, maps: Iterable[str]) -> str:
    """The map of scene ``scene_seed``: uniform over the sorted, de-duplicated ``maps``."""
    seed = _check_scene_seed(scene_seed)
    candidates = _names("maps", maps)
    if not candidates:
        raise ValueError("no map to choose from: `maps` is empty (set simulator.carla.maps)")
    return candidates[int(seeding.rng(seed, "carla", "map").integers(len(candidates)))]


def plan_scene(
    scene_seed: int,
    maps: Iterable[str],
    vehicle_blueprints: Iterable[str],
    walker_blueprints: Iterable[str],
    n_spawn_points: int,
    *,
    ego_blueprints: Iterable[str] | None = None,
    max_vehicles: int = 15,
    max_pedestrians: int = 10,
) -> ScenePlan:
    """Draw the scene named by ``scene_seed`` (pure and deterministic; no server needed).

    Arguments:
        scene_seed: non-negative integer; every draw descends from it (:mod:`components.core.seeding`).
        maps: candidate maps; the choice is :func:`choose_map`.
        vehicle_blueprints: candidate NPC vehicle blueprint ids.
        walker_blueprints: candidate pedestrian blueprint ids (may be empty when ``max_pedestrians`` is 0).
        n_spawn_points: number of vehicle spawn points of the chosen map (≥ 1).
        ego_blueprints: candidate ego blueprint ids; default ``vehicle_blueprints``.
        max_vehicles: the number of NPC vehicles is uniform on ``{0, …, max_vehicles}``, capped by the spawn points
            left after the ego's.
        max_pedestrians: the number of pedestrians is uniform on ``{0, …, max_pedestrians}``.

    Candidate lists are sorted and de-duplicated first, so their order does not matter. Each choice
    uses its own named stream, so e.g. changing ``max_pedestrians`` leaves the map, ego and vehicles as
    they were.
    """
    seed = _check_scene_seed(scene_seed)
    map_name = choose_map(seed, maps)
    vehicles = _names("vehicle_blueprints", vehicle_blueprints)
    walkers = _names("walker_blueprints", walker_blueprints)
    egos = vehicles if ego_blueprints is None else _names("ego_blueprints", ego_blueprints)
    n_spawn = whole_number("n_spawn_points", n_spawn_points, low=1, type_error=TypeError)
    max_vehicles = whole_number("max_vehicles", max_vehicles, low=0, type_error=TypeError)
    max_pedestrians = whole_number("max_pedestrians", max_pedestrians, low=0, type_error=TypeError)
    if not egos:
        raise ValueError("no ego vehicle blueprint to choose from (ego_blueprints is empty)")
    if max_vehicles > 0 and not vehicles:
        raise ValueError("max_vehicles > 0 but vehicle_blueprints is empty")
    if max_pedestrians > 0 and not walkers:
        raise ValueError("max_pedestrians > 0 but walker_blueprints is empty")

    ego_rng = seeding.rng(seed, "carla", "ego")
    ego_blueprint = egos[int(ego_rng.integers(len(egos)))]
    ego_colour = float(ego_rng.random())

    order = seeding.rng(seed, "carla", "spawn_points").permutation(n_spawn)
    vehicle_rng = seeding.rng(seed, "carla", "vehicles")
    n_vehicles = min(int(vehicle_rng.integers(max_vehicles + 1)), n_spawn - 1)
    vehicle_choice = vehicle_rng.integers(len(vehicles), size=n_vehicles) if n_vehicles else np.zeros(0, int)
    vehicle_colours = vehicle_rng.random(n_vehicles)

    walker_rng = seeding.rng(seed, "carla", "pedestrians")
    n_pedestrians = int(walker_rng.integers(max_pedestrians + 1))
    walker_choice = walker_rng.integers(len(walkers), size=n_pedestrians) if n_pedestrians else np.zeros(0, int)

    return ScenePlan(
        scene_seed=seed,
        map_name=map_name,
        ego_blueprint=ego_blueprint,
        ego_spawn_index=int(order[0]),
        ego_colour=ego_colour,
        vehicle_blueprints=tuple(vehicles[int(i)] for i in vehicle_choice),
        vehicle_spawn_indices=tuple(int(i) for i in order[1 : 1 + n_vehicles]),
        vehicle_colours=tuple(float(c) for c in vehicle_colours),
        walker_blueprints=tuple(walkers[int(i)] for i in walker_choice),
        # the server takes unsigned 32-bit seeds
        pedestrian_seed=seeding.derive_seed(seed, "carla", "pedestrian_server") % 2**31,
        traffic_seed=seeding.derive_seed(seed, "carla", "traffic_manager") % 2**31,
    )


# --- small conversions (pure, testable without a server) --------------------------------------------


def hood_camera_transform(extent: Any) -> Any:
    """The hood camera of ``manual_control.py`` for a vehicle whose bounding-box half-extent is ``extent``.

    ``extent`` is a ``carla.Vector3D`` in metres; the camera sits at x = 0.8·(0.5 + extent.x) ahead of
    the vehicle's origin and z = 1.3·(0.5 + extent.z) above it, looking forward (so its height varies
    with the vehicle model, ≈ 1.5–2.7 m).
    """
    carla = import_carla()
    return carla.Transform(carla.Location(x=0.8 * (0.5 + extent.x), y=0.0, z=1.3 * (0.5 + extent.z)))


def synchronous_settings(settings: Any, fixed_delta_seconds: float) -> Any:
    """``settings`` (a ``carla.WorldSettings``) switched to synchronous mode with a fixed step (s)."""
    settings.synchronous_mode = True
    settings.fixed_delta_seconds = fixed_delta_seconds
    return settings


def asynchronous_settings(settings: Any) -> Any:
    """``settings`` switched back to CARLA's default asynchronous mode with a variable step."""
    settings.synchronous_mode = False
    settings.fixed_delta_seconds = None
    return settings


def bgra_to_rgb(raw: bytes | bytearray | memoryview, height: int, width: int) -> np.ndarray:
    """A CARLA camera buffer (``image.raw_data``: height·width·4 bytes, BGRA) as ``(height, width, 3)`` uint8 RGB."""
    buf = np.frombuffer(raw, dtype=np.uint8)
    if buf.size != height * width * 4:
        raise ValueError(f"a {height}x{width} BGRA image needs {height * width * 4} bytes, got {buf.size}")
    return np.ascontiguousarray(buf.reshape(height, width, 4)[:, :, 2::-1])


# --- connection probe (at the socket boundary) -------------------------------------------------------

#: libcarla's first request, in msgpack-rpc: [0 (request), msgid 1, "version", [[asynchronous_call=false]]]
_VERSION_REQUEST = b"\x94\x00\x01\xa7version\x91\x91\xc2"
#: how every msgpack-rpc response starts: a 4-element array whose first element is 1 (response)
_RESPONSE_PREFIX = b"\x94\x01"
_SERVER_HINT = (
    "start the CARLA server (CarlaUE4.sh -carla-rpc-port=PORT) or set simulator.carla.host/port in params.yaml"
)


def probe_carla_server(host: str, port: int, timeout_s: float) -> None:
    """Check within ``timeout_s`` seconds that ``host:port`` answers libcarla's version request.

    Sends the request libcarla sends first and reads the first bytes of the answer. Raises
    :class:`CarlaConnectionError` (naming ``host:port`` and the timeout) when the port refuses, nothing
    answers in time, the peer hangs up, or the answer is not a msgpack-rpc response. The last case
    matters: libcarla terminates the whole Python process (``std::terminate`` on a msgpack
    ``type_error``) when another kind of service answers on the port.
    """
    where = f"{host}:{port}"
    deadline = time.monotonic() + timeout_s
    try:
        conn = socket.create_connection((host, port), timeout=timeout_s)
    except OSError as exc:
        reason = exc.strerror or str(exc) or type(exc).__name__
        raise CarlaConnectionError(
            f"cannot reach a CARLA server at {where} within the {timeout_s:g} s timeout ({reason}); {_SERVER_HINT}"
        ) from exc
    answer = b""
    with conn:
        try:
            conn.sendall(_VERSION_REQUEST)
            while len(answer) < len(_RESPONSE_PREFIX):
                conn.settimeout(max(deadline - time.monotonic(), 1e-3))
                chunk = conn.recv(64)
                if not chunk:
                    break
                answer += chunk
        except TimeoutError as exc:
            raise CarlaConnectionError(
                f"the service at {where} accepted the connection but did not answer within the {timeout_s:g} s "
                f"timeout; is the CARLA server still loading or stuck? {_SERVER_HINT}"
            ) from exc
        except OSError as exc:
            raise CarlaConnectionError(f"the connection to {where} failed ({exc}); {_SERVER_HINT}") from exc
    if not answer:
        raise CarlaConnectionError(f"the service at {where} closed the connection without answering; {_SERVER_HINT}")
    if not answer.startswith(_RESPONSE_PREFIX):
        raise CarlaConnectionError(
            f"the service at {where} answered, but not as a CARLA server (first bytes {answer[:16]!r}); "
            f"is another program listening on that port? {_SERVER_HINT}"
        )


# --- argument checks -------------------------------------------------------------------------------


def _float_arg(name: str, value: object, low: float, high: float, *, low_open: bool, high_open: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a number, got {value!r}")
    v = float(value)
    ok = math.isfinite(v) and (v > low if low_open else v >= low) and (v < high if high_open else v <= high)
    if not ok:
        interval = f"{'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
        raise ValueError(f"{name} must be a finite number in {interval}, got {value!r}")
    return v


# --- the backend ------------------------------------------------------------------------------------


@dataclass
class _Scene:
    """The live state of one built scene: what must be undone on teardown."""

    plan: ScenePlan | None
    world: Any
    traffic_manager: Any = None
    synchronous: bool = False
    traffic_manager_synchronous: bool = False
    lights_frozen: bool = False
    camera: Any = None
    ego_id: int | None = None
    vehicle_ids: list[int] = field(default_factory=list)
    walker_ids: list[int] = field(default_factory=list)
    controllers: list[Any] = field(default_factory=list)
    images: queue.Queue = field(default_factory=queue.Queue)

    def actor_ids(self) -> list[int]:
        """Every spawned actor, sensors and controllers first (they are attached to the others)."""
        ids = [self.camera.id] if self.camera is not None else []
        ids += [c.id for c in self.controllers] + self.walker_ids + self.vehicle_ids
        return ids + ([self.ego_id] if self.ego_id is not None else [])


class CarlaSimulator:
    """Renders pidc weathers on a CARLA server (the :class:`~components.simulate.base.Simulator` protocol).

    Arguments:
        height: image height in pixels (the RGB camera's ``image_size_y``).
        width: image width in pixels (the RGB camera's ``image_size_x``).
        host: the server's RPC host.
        port: the server's RPC port (the streaming port is ``port + 1``).
        timeout_s: client timeout (s): connecting, ticking and waiting for camera images.
        maps: the towns the scene seed draws from, by name (default :data:`TOWNS`); a name that is no town
            (:meth:`components.core.config.CarlaConfig.town_problem`: not ``Town`` + digits + optional ``HD`` and
            ``_Opt``, or one of CARLA's large maps), an empty list or a repeated name is a ``ValueError``.
        fixed_delta_seconds: simulated seconds per tick in synchronous mode, in (0, 0.1].
        settle_ticks: ticks between setting a weather and capturing (auto-exposure adapts over frames).
        traffic_manager_port: port of the traffic manager that drives the NPC vehicles.
        max_vehicles: the number of NPC vehicles is uniform on ``{0, …, max_vehicles}`` per scene.
        max_pedestrians: the number of pedestrians is uniform on ``{0, …, max_pedestrians}`` per scene.
        fov: horizontal field of view of the camera (degrees), in (0, 180).

    The connection is opened at the first :meth:`render` (or by :meth:`connect`). Use it as a context
    manager, or call :meth:`close`, so the server gets its actors removed and its asynchronous mode back.
    """

    def __init__(
        self,
        height: int = 128,
        width: int = 128,
        *,
        host: str = "127.0.0.1",
        port: int = 2000,
        timeout_s: float = 10.0,
        maps: Sequence[str] = TOWNS,
        fixed_delta_seconds: float = 0.05,
        settle_ticks: int = 10,
        traffic_manager_port: int = 8000,
        max_vehicles: int = 15,
        max_pedestrians: int = 10,
        fov: float = 90.0,
    ) -> None:
        self.height = whole_number("height", height, low=1, type_error=TypeError)
        self.width = whole_number("width", width, low=1, type_error=TypeError)
        if not isinstance(host, str) or not host.strip() or any(c.isspace() for c in host):
            raise ValueError(f"host must be a host name or IP address without spaces, got {host!r}")
        self.host = host
        # the server also listens on port + 1 (sensor streaming)
        self.port = whole_number("port", port, low=1, high=65534, type_error=TypeError)
        self.timeout_s = _float_arg("timeout_s", timeout_s, 0.0, math.inf, low_open=True, high_open=True)
        if isinstance(maps, str):
            raise TypeError(f"maps must be a sequence of map names, not the string {maps!r}")
        given = tuple(maps)
        self.maps: tuple[str, ...] = tuple(_names("maps", given))
        if len(self.maps) != len(given):
            raise ValueError(f"maps has duplicates: {list(given)}")
        if not self.maps:
            raise ValueError(f"maps is empty: name the towns a scene seed draws from, e.g. {', '.join(TOWNS)}")
        from components.core.config import CarlaConfig  # the town rule has one home, beside the setting

        bad = [f"{m!r} {problem}" for m in self.maps if (problem := CarlaConfig.town_problem(m))]
        if bad:
            raise ValueError(f"maps: {'; '.join(bad)}")
        # CARLA warns that steps above 0.1 s break physics substepping
        self.fixed_delta_seconds = _float_arg(
            "fixed_delta_seconds", fixed_delta_seconds, 0.0, 0.1, low_open=True, high_open=False
        )
        self.settle_ticks = whole_number("settle_ticks", settle_ticks, low=1, type_error=TypeError)
        self.traffic_manager_port = whole_number(
            "traffic_manager_port", traffic_manager_port, low=1, high=65535, type_error=TypeError
        )
        if self.traffic_manager_port in (self.port, self.port + 1):
            raise ValueError(
                f"traffic_manager_port {self.traffic_manager_port} collides with the server's ports "
                f"{self.port} (RPC) and {self.port + 1} (streaming)"
            )
        self.max_vehicles = whole_number("max_vehicles", max_vehicles, low=0, type_error=TypeError)
        self.max_pedestrians = whole_number("max_pedestrians", max_pedestrians, low=0, type_error=TypeError)
        self.fov = _float_arg("fov", fov, 0.0, 180.0, low_open=True, high_open=True)
        self._carla = import_carla()
        self._client: Any = None
        self._server_version: str | None = None
        self._client_version: str | None = None
        self._scene: _Scene | None = None

    @classmethod
    def from_config(cls, sim: SimulatorConfig) -> CarlaSimulator:
        """From a :class:`components.core.config.SimulatorConfig` (its ``height``, ``width`` and ``carla`` section)."""
        c = sim.carla
        return cls(
            sim.height,
            sim.width,
            host=c.host,
            port=c.port,
            timeout_s=c.timeout_s,
            maps=tuple(c.maps),
            fixed_delta_seconds=c.fixed_delta_seconds,
            settle_ticks=c.settle_ticks,
            traffic_manager_port=c.traffic_manager_port,
            max_vehicles=c.max_vehicles,
            max_pedestrians=c.max_pedestrians,
            fov=c.fov,
        )

    # -- protocol ------------------------------------------------------------------------------------

    @property
    def version(self) -> str:
        """``carla-<server version>`` once connected, ``carla-<client version>`` before."""
        if self._server_version is not None:
            return f"carla-{self._server_version}"
        if self._client_version is None:
            # building a client opens no connection
            self._client_version = self._carla.Client(self.host, self.port).get_client_version()
        return f"carla-{self._client_version}"

    @property
    def scene(self) -> ScenePlan | None:
        """The plan of the scene currently built on the server (``None`` before the first render)."""
        return None if self._scene is None else self._scene.plan

    def render(self, weather: Mapping[str, float], scene_seed: int) -> np.ndarray:
        """The hood-camera image of scene ``scene_seed`` under ``weather``: ``(height, width, 3)`` uint8 RGB.

        The weather and seed are validated before any server call. On any error the scene is torn
        down (actors destroyed, asynchronous mode restored) and the error re-raised.
        """
        parameters = weather_parameters(weather)
        seed = _check_scene_seed(scene_seed)
        self.connect()
        try:
            if self._scene is None or self._scene.plan is None or self._scene.plan.scene_seed != seed:
                self._raise_cleanup_errors(self._teardown_scene(), f"before building scene {seed}")
                self._build_scene(seed)
            return self._capture(parameters)
        except BaseException as exc:
            for err in self._teardown_scene():
                exc.add_note(f"while cleaning up the CARLA scene after this error: {err!r}")
            raise

    # -- connection ----------------------------------------------------------------------------------

    def connect(self) -> None:
        """Open the connection (idempotent); :class:`CarlaConnectionError` within about ``timeout_s``.

        :func:`probe_carla_server` runs first with the whole timeout: a refused, unroutable or silent
        port fails within it, and a service that is not CARLA is reported instead of letting libcarla
        abort the process; libcarla's own handshake then gets what is left of the timeout.
        """
        if self._client is not None:
            return
        where = f"{self.host}:{self.port}"
        deadline = time.monotonic() + self.timeout_s
        probe_carla_server(self.host, self.port, self.timeout_s)
        client = self._carla.Client(self.host, self.port)
        # the probe may have used most of the timeout; libcarla still gets a tenth of it
        client.set_timeout(max(deadline - time.monotonic(), 0.1 * self.timeout_s))
        try:
            server_version = client.get_server_version()
            client.set_timeout(self.timeout_s)
            available = client.get_available_maps()
        except RuntimeError as exc:
            raise CarlaConnectionError(
                f"the service at {where} did not answer as a CARLA server within the {self.timeout_s:g} s "
                f"timeout ({exc}); {_SERVER_HINT}"
            ) from exc
        client_version = client.get_client_version()
        if server_version != client_version:
            warnings.warn(
                f"CARLA client {client_version} and server {server_version} at {where} differ; {_INSTALL_HINT}",
                stacklevel=2,
            )
        self._check_maps(available)
        self._client, self._server_version, self._client_version = client, server_version, client_version

    def _check_maps(self, available: Iterable[str]) -> None:
        """Every configured town is on the server (``get_available_maps`` lists paths; a town is its last part)."""
        offered = {path.rstrip("/").rsplit("/", 1)[-1] for path in available}
        missing = [m for m in self.maps if m not in offered]
        if missing:
            from components.core.config import CarlaConfig

            towns = sorted(n for n in offered if CarlaConfig.town_problem(n) is None)
            extra = {"Town06", "Town07"} & set(missing)
            hint = f" ({' and '.join(sorted(extra))} come with CARLA's AdditionalMaps package)" if extra else ""
            raise ValueError(
                f"simulator.carla.maps: {', '.join(missing)} not on the server at {self.host}:{self.port}, whose "
                f"towns are {', '.join(towns) or 'none'}{hint}: list only the towns the server has"
            )

    # -- scene ---------------------------------------------------------------------------------------

    def _load_world(self, town: str) -> Any:
        """The world with map ``town``, loaded by the server only where another map is loaded.

        ``client.load_world_if_different(name)`` compares ``name`` and ``"Carla/Maps/" + name`` with the current map's
        name (``Carla/Maps/Town01``) and returns ``None`` either way, so it takes the town's name, never the server's
        path (``/Game/Carla/Maps/Town01`` would never match and reload every scene), and the world is read after it.
        """
        self._client.set_timeout(max(self.timeout_s, LOAD_WORLD_TIMEOUT_S))
        try:
            self._client.load_world_if_different(town)
            return self._client.get_world()
        finally:
            self._client.set_timeout(self.timeout_s)

    def _build_scene(self, seed: int) -> None:
        carla = self._carla
        map_name = choose_map(seed, self.maps)
        world = self._load_world(map_name)
        scene = _Scene(plan=None, world=world)
        self._scene = scene  # from here on, a failure tears down whatever was spawned

        world.apply_settings(synchronous_settings(world.get_settings(), self.fixed_delta_seconds))
        scene.synchronous = True
        scene.traffic_manager = self._client.get_trafficmanager(self.traffic_manager_port)
        scene.traffic_manager.set_synchronous_mode(True)
        scene.traffic_manager_synchronous = True

        library = world.get_blueprint_library()
        four_wheeled = [bp for bp in library.filter("vehicle.*") if _attribute(bp, "number_of_wheels", "4") == "4"]
        # the ego is a car (not a truck or bus) where the server tags blueprints with a base type
        cars = [bp.id for bp in four_wheeled if _attribute(bp, "base_type", "car").lower() == "car"]
        cars = cars or [bp.id for bp in four_wheeled]
        walkers = [bp.id for bp in library.filter("walker.pedestrian.*")]
        spawn_points = world.get_map().get_spawn_points()
        plan = plan_scene(
            seed,
            self.maps,
            [bp.id for bp in four_wheeled],
            walkers,
            len(spawn_points),
            ego_blueprints=cars,
            max_vehicles=self.max_vehicles,
            max_pedestrians=self.max_pedestrians,
        )
        scene.plan = plan
        scene.traffic_manager.set_random_device_seed(plan.traffic_seed)

        ego_bp = library.find(plan.ego_blueprint)
        ego_bp.set_attribute("role_name", "hero")
        _set_colour(ego_bp, plan.ego_colour)
        ego = world.try_spawn_actor(ego_bp, spawn_points[plan.ego_spawn_index])
        if ego is None:
            raise RuntimeError(
                f"could not spawn the ego vehicle {plan.ego_blueprint} at spawn point {plan.ego_spawn_index} "
                f"of {plan.map_name} (scene {seed}): the spot is occupied, by an actor of another client?"
            )
        scene.ego_id = ego.id

        camera_bp = library.find("sensor.camera.rgb")
        camera_bp.set_attribute("image_size_x", str(self.width))
        camera_bp.set_attribute("image_size_y", str(self.height))
        camera_bp.set_attribute("fov", f"{self.fov:g}")
        camera_bp.set_attribute("sensor_tick", "0.0")
        scene.camera = world.spawn_actor(
            camera_bp,
            hood_camera_transform(ego.bounding_box.extent),
            attach_to=ego,
            attachment_type=carla.AttachmentType.Rigid,
        )
        scene.camera.listen(scene.images.put)

        self._spawn_vehicles(scene, library, spawn_points)
        self._spawn_pedestrians(scene, library)
        for _ in range(math.ceil(WARMUP_SECONDS / self.fixed_delta_seconds)):
            world.tick(self.timeout_s)
        self._freeze(scene)

    def _spawn_vehicles(self, scene: _Scene, library: Any, spawn_points: Sequence[Any]) -> None:
        command = self._carla.command
        plan = scene.plan
        assert plan is not None
        batch = []
        for name, index, colour in zip(
            plan.vehicle_blueprints, plan.vehicle_spawn_indices, plan.vehicle_colours, strict=False
        ):
            bp = library.find(name)
            bp.set_attribute("role_name", "autopilot")
            _set_colour(bp, colour)
            batch.append(
                command.SpawnActor(bp, spawn_points[index]).then(
                    command.SetAutopilot(command.FutureActor, True, self.traffic_manager_port)
                )
            )
        if batch:
            scene.vehicle_ids = [r.actor_id for r in self._client.apply_batch_sync(batch, True) if not r.error]

    def _spawn_pedestrians(self, scene: _Scene, library: Any) -> None:
        """Walkers at navigation-mesh locations drawn by the server's seeded RNG, each with an AI controller."""
        carla, command, world, plan = self._carla, self._carla.command, scene.world, scene.plan
        assert plan is not None
        if not plan.n_pedestrians:
            return
        world.set_pedestrians_seed(plan.pedestrian_seed)
        batch, speeds = [], []
        for name in plan.walker_blueprints:
            location = world.get_random_location_from_navigation()
            if location is None:
                continue
            bp = library.find(name)
            if bp.has_attribute("is_invincible"):
                bp.set_attribute("is_invincible", "false")
            recommended = bp.get_attribute("speed").recommended_values if bp.has_attribute("speed") else []
            speeds.append(float(recommended[1]) if len(recommended) > 1 else DEFAULT_WALKING_SPEED)
            batch.append(command.SpawnActor(bp, carla.Transform(location, carla.Rotation())))
        if not batch:
            return
        results = self._client.apply_batch_sync(batch, True)
        spawned = [(r.actor_id, s) for r, s in zip(results, speeds, strict=False) if not r.error]
        scene.walker_ids = [walker_id for walker_id, _ in spawned]
        controller_bp = library.find("controller.ai.walker")
        results = self._client.apply_batch_sync(
            [command.SpawnActor(controller_bp, carla.Transform(), walker_id) for walker_id, _ in spawned], True
        )
        controller_ids, controller_speeds = [], []
        for r, (_, speed) in zip(results, spawned, strict=False):
            if not r.error:
                controller_ids.append(r.actor_id)
                controller_speeds.append(speed)
        # (get_actors with no ids would list every actor of the world)
        scene.controllers = list(world.get_actors(controller_ids)) if controller_ids else []
        world.tick(self.timeout_s)  # the client needs the walkers' transforms before the controllers start
        world.set_pedestrians_cross_factor(0.0)
        by_id = {c.id: c for c in scene.controllers}
        for controller_id, speed in zip(controller_ids, controller_speeds, strict=False):
            controller = by_id[controller_id]
            controller.start()
            destination = world.get_random_location_from_navigation()
            if destination is not None:
                controller.go_to_location(destination)
            controller.set_max_speed(speed)

    def _freeze(self, scene: _Scene) -> None:
        """Stop all motion so that every later weather sees the same scene."""
        carla, command = self._carla, self._carla.command
        for controller in scene.controllers:
            controller.stop()
        batch = [command.SetAutopilot(i, False, self.traffic_manager_port) for i in scene.vehicle_ids]
        moving = scene.vehicle_ids + ([scene.ego_id] if scene.ego_id is not None else [])
        batch += [command.ApplyTargetVelocity(i, carla.Vector3D(0.0, 0.0, 0.0)) for i in moving]
        batch += [command.SetSimulatePhysics(i, False) for i in moving + scene.walker_ids]
        _check_batch(self._client.apply_batch_sync(batch, False), "freezing the scene")
        scene.world.freeze_all_traffic_lights(True)
        scene.lights_frozen = True
        scene.world.tick(self.timeout_s)

    def _capture(self, parameters: Any) -> np.ndarray:
        scene = self._scene
        assert scene is not None
        _drain(scene.images)
        scene.world.set_weather(parameters)
        frames = [scene.world.tick(self.timeout_s) for _ in range(self.settle_ticks)]
        frame = frames[-1]
        image = _image_of_frame(scene.images, frame, self.timeout_s)
        if (image.height, image.width) != (self.height, self.width):
            raise RuntimeError(
                f"the camera delivered {image.height}x{image.width} images, expected {self.height}x{self.width}"
            )
        return bgra_to_rgb(image.raw_data, image.height, image.width)

    # -- cleanup -------------------------------------------------------------------------------------

    def _teardown_scene(self) -> list[Exception]:
        """Undo the scene; every step is tried even if an earlier one fails. Returns the failures."""
        scene, self._scene = self._scene, None
        if scene is None:
            return []
        errors: list[Exception] = []

        def attempt(step: Callable[[], object]) -> None:
            try:
                step()
            except Exception as exc:  # noqa: BLE001 - collected and reported by the caller
                errors.append(exc)

        if scene.camera is not None:
            attempt(scene.camera.stop)
        for controller in scene.controllers:
            attempt(controller.stop)
        if scene.lights_frozen:
            attempt(lambda: scene.world.freeze_all_traffic_lights(False))
        if scene.synchronous:
            attempt(lambda: scene.world.apply_settings(asynchronous_settings(scene.world.get_settings())))
        if scene.traffic_manager_synchronous:
            attempt(lambda: scene.traffic_manager.set_synchronous_mode(False))
        ids = scene.actor_ids()
        if ids and self._client is not None:
            destroy = [self._carla.command.DestroyActor(i) for i in ids]
            client = self._client
            attempt(lambda: _check_batch(client.apply_batch_sync(destroy, False), "destroying the scene's actors"))
        return errors

    @staticmethod
    def _raise_cleanup_errors(errors: list[Exception], when: str) -> None:
        if errors:
            details = "; ".join(repr(e) for e in errors)
            raise RuntimeError(f"cleaning up the CARLA scene {when} failed: {details}") from errors[0]

    def close(self) -> None:
        """Destroy the scene's actors, restore asynchronous mode and drop the connection (idempotent)."""
        errors = self._teardown_scene()
        self._client = None
        self._raise_cleanup_errors(errors, "on close")

    def __enter__(self) -> CarlaSimulator:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc is None:
            self.close()
            return
        for err in self._teardown_scene():
            exc.add_note(f"while cleaning up the CARLA scene: {err!r}")
        self._client = None

    def __repr__(self) -> str:
        return (
            f"CarlaSimulator({self.height}x{self.width}, {self.host}:{self.port}, "
            f"{'connected' if self._client is not None else 'not connected'})"
        )


# --- helpers over live carla objects ----------------------------------------------------------------


def _attribute(bp: Any, name: str, default: str) -> str:
    return bp.get_attribute(name).as_str() if bp.has_attribute(name) else default


def _set_colour(bp: Any, draw: float) -> None:
    """Pick the blueprint's recommended colour at ``draw`` ∈ [0, 1) (colours are a seeded scene choice)."""
    if bp.has_attribute("color"):
        colours = list(bp.get_attribute("color").recommended_values)
        if colours:
            bp.set_attribute("color", colours[min(int(draw * len(colours)), len(colours) - 1)])


def _check_batch(responses: Iterable[Any], what: str) -> None:
    errors = [r.error for r in responses if r.error]
    if errors:
        raise RuntimeError(f"{what}: {len(errors)} command(s) failed, e.g. {errors[0]}")


def _drain(images: queue.Queue) -> None:
    while True:
        try:
            images.get_nowait()
        except queue.Empty:
            return


def _image_of_frame(images: queue.Queue, frame: int, timeout_s: float) -> Any:
    """The camera image of simulation frame ``frame``; older images are discarded."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            image = images.get(timeout=max(deadline - time.monotonic(), 0.0))
        except queue.Empty:
            raise TimeoutError(f"no camera image of frame {frame} arrived within {timeout_s:g} s") from None
        if image.frame == frame:
            return image
        if image.frame > frame:
            raise RuntimeError(f"the camera skipped frame {frame} (got frame {image.frame})")
