"""The CARLA backend without a server: weather mapping on real ``carla`` objects, the connection
timeout against an unreachable port and a silent fake server (the socket boundary), argument checks,
and the seeded scene plan."""

from __future__ import annotations

import importlib.metadata
import math
import socket
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator

import carla  # the optional `carla` extra is part of the development environment
import numpy as np
import pytest

from components.core import seeding
from components.core.config import CarlaConfig, SimulatorConfig
from components.core.weather import ALL_NAMES, FIXED, NUISANCE, PARAMETERS, PREDICTED
from components.simulate.base import Simulator
from components.simulate.carla import (
    TOWNS,
    CarlaConnectionError,
    CarlaSimulator,
    asynchronous_settings,
    bgra_to_rgb,
    choose_map,
    hood_camera_transform,
    plan_scene,
    synchronous_settings,
    weather_parameters,
)

TIMEOUT_S = 1.5
#: wall-clock slack allowed on top of the timeout (a loaded 2-core machine)
SLACK_S = 1.0


def _random_weather(rng: np.random.Generator) -> dict[str, float]:
    return {n: float(rng.uniform(PARAMETERS[n].low, PARAMETERS[n].high)) for n in PREDICTED + NUISANCE}


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --- weather ----------------------------------------------------------------------------------------


def test_weather_parameters_reads_back_every_field() -> None:
    rng = seeding.rng(0, "test_carla", "weather")
    for _ in range(20):
        weather = _random_weather(rng)
        params = weather_parameters(weather)
        assert isinstance(params, carla.WeatherParameters)
        for name in ALL_NAMES:
            expected = weather.get(name, FIXED.get(name))
            # CARLA stores float32
            assert getattr(params, name) == pytest.approx(expected, rel=1e-6, abs=1e-5), name
        assert params.dust_storm == 0.0


def test_weather_parameters_fills_the_fixed_values_in_the_right_fields() -> None:
    # fog_falloff and wetness swap places in the positional order of some CARLA versions
    params = weather_parameters({n: 50.0 for n in PREDICTED} | {"sun_azimuth_angle": 200.0})
    assert params.fog_distance == pytest.approx(0.75)
    assert params.fog_falloff == pytest.approx(0.1)
    assert params.wetness == 0.0
    assert params.scattering_intensity == pytest.approx(1.0)
    assert params.mie_scattering_scale == pytest.approx(0.03)
    assert params.rayleigh_scattering_scale == pytest.approx(0.0331)
    assert params.sun_altitude_angle == pytest.approx(50.0)
    assert params.sun_azimuth_angle == pytest.approx(200.0)


@pytest.mark.parametrize(
    ("change", "word"),
    [
        ({"fog_density": 101.0}, "fog_density"),
        ({"sun_altitude_angle": -91.0}, "sun_altitude_angle"),
        ({"precipitation": math.nan}, "precipitation"),
        ({"wetness": 30.0}, "wetness"),
        ({"fog": 3.0}, "fog"),
        ({"cloudiness": "cloudy"}, "cloudiness"),
    ],
)
def test_weather_parameters_rejects_bad_weather(change: dict, word: str) -> None:
    weather = {n: 10.0 for n in PREDICTED} | {"sun_azimuth_angle": 0.0} | change
    with pytest.raises(ValueError, match=word):
        weather_parameters(weather)


def test_weather_parameters_requires_every_predicted_parameter() -> None:
    weather = {n: 10.0 for n in PREDICTED if n != "wind_intensity"} | {"sun_azimuth_angle": 0.0}
    with pytest.raises(ValueError, match="wind_intensity"):
        weather_parameters(weather)


# --- connection: the socket boundary ------------------------------------------------------------------


def _stop(listener: socket.socket) -> None:
    """Close a listening socket and wake the thread blocked in its accept()."""
    try:
        listener.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    listener.close()


@pytest.fixture
def silent_server() -> Iterator[tuple[int, list[socket.socket]]]:
    """A local TCP listener that accepts connections and never answers (a hung CARLA server)."""
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(16)
    accepted: list[socket.socket] = []

    def accept() -> None:
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            accepted.append(conn)

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    yield listener.getsockname()[1], accepted
    _stop(listener)
    for conn in accepted:
        conn.close()
    thread.join(timeout=2.0)


def test_unreachable_port_gives_a_clear_error_at_once() -> None:
    port = _free_port()
    sim = CarlaSimulator(port=port, timeout_s=TIMEOUT_S)
    start = time.monotonic()
    with pytest.raises(CarlaConnectionError) as info:
        sim.connect()
    elapsed = time.monotonic() - start
    assert isinstance(info.value, ConnectionError)
    message = str(info.value)
    assert f"127.0.0.1:{port}" in message and f"{TIMEOUT_S:g} s" in message
    assert elapsed < TIMEOUT_S + SLACK_S
    assert "not connected" in repr(sim)


def test_silent_server_times_out_within_the_timeout(silent_server: tuple[int, list[socket.socket]]) -> None:
    port, accepted = silent_server
    sim = CarlaSimulator(port=port, timeout_s=TIMEOUT_S)
    start = time.monotonic()
    with pytest.raises(CarlaConnectionError) as info:
        sim.connect()
    elapsed = time.monotonic() - start
    message = str(info.value)
    assert f"127.0.0.1:{port}" in message and f"{TIMEOUT_S:g} s" in message
    # the client really reached the listener and then waited for an answer, but no longer than the timeout
    assert accepted
    assert 0.5 * TIMEOUT_S < elapsed < TIMEOUT_S + SLACK_S


def test_render_against_a_silent_server_raises_the_connection_error(
    silent_server: tuple[int, list[socket.socket]],
) -> None:
    port, _ = silent_server
    weather = {n: 20.0 for n in PREDICTED} | {"sun_azimuth_angle": 90.0}
    start = time.monotonic()
    with CarlaSimulator(port=port, timeout_s=TIMEOUT_S) as sim:
        with pytest.raises(ConnectionError, match=f"127.0.0.1:{port}"):
            sim.render(weather, scene_seed=3)
        assert sim.scene is None
    assert time.monotonic() - start < TIMEOUT_S + SLACK_S


def test_render_validates_before_touching_the_server() -> None:
    # nothing listens on the port: any server call would raise ConnectionError instead
    sim = CarlaSimulator(port=_free_port(), timeout_s=TIMEOUT_S)
    good = {n: 20.0 for n in PREDICTED} | {"sun_azimuth_angle": 90.0}
    with pytest.raises(ValueError, match="fog_density"):
        sim.render(good | {"fog_density": 150.0}, scene_seed=0)
    with pytest.raises(ValueError, match="scene_seed"):
        sim.render(good, scene_seed=-1)
    with pytest.raises(TypeError, match="scene_seed"):
        sim.render(good, scene_seed=1.5)  # type: ignore[arg-type]


def test_context_manager_does_not_mask_errors_and_close_is_idempotent() -> None:
    with pytest.raises(KeyError, match="inside"):
        with CarlaSimulator(port=_free_port(), timeout_s=TIMEOUT_S):
            raise KeyError("inside")
    sim = CarlaSimulator(port=_free_port(), timeout_s=TIMEOUT_S)
    sim.close()
    sim.close()
    assert sim.scene is None


# --- a fake CARLA server at the socket boundary: msgpack-rpc over TCP ---------------------------------


def _pack(v: object) -> bytes:
    """msgpack encoding of None, bool, non-negative int, str and list (enough for the fake server)."""
    if v is None:
        return b"\xc0"
    if isinstance(v, bool):
        return b"\xc3" if v else b"\xc2"
    if isinstance(v, int):
        return bytes([v]) if v < 128 else b"\xce" + v.to_bytes(4, "big")
    if isinstance(v, str):
        b = v.encode()
        return (bytes([0xA0 | len(b)]) if len(b) < 32 else b"\xd9" + bytes([len(b)])) + b
    if isinstance(v, list):
        head = bytes([0x90 | len(v)]) if len(v) < 16 else b"\xdc" + len(v).to_bytes(2, "big")
        return head + b"".join(_pack(x) for x in v)
    raise TypeError(v)


def _unpack(buf: bytes, i: int = 0) -> tuple[object, int]:
    """One msgpack value of ``buf`` at ``i`` and the index after it; IndexError when incomplete."""
    t = buf[i]
    if t < 0x80:
        return t, i + 1
    if 0x90 <= t <= 0x9F or t == 0xDC:
        n, i = (t & 0x0F, i + 1) if t != 0xDC else (int.from_bytes(buf[i + 1 : i + 3], "big"), i + 3)
        out = []
        for _ in range(n):
            x, i = _unpack(buf, i)
            out.append(x)
        return out, i
    if 0xA0 <= t <= 0xBF or t == 0xD9:
        n, i = (t & 0x1F, i + 1) if t != 0xD9 else (buf[i + 1], i + 2)
        if i + n > len(buf):
            raise IndexError
        return buf[i : i + n].decode(), i + n
    if t in (0xC0, 0xC2, 0xC3):
        return {0xC0: None, 0xC2: False, 0xC3: True}[t], i + 1
    size = {0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8}[t]
    if i + 1 + size > len(buf):
        raise IndexError
    return int.from_bytes(buf[i + 1 : i + 1 + size], "big"), i + 1 + size


class FakeCarlaServer:
    """Answers libcarla's ``version`` and ``get_available_maps`` calls like a CARLA server would:
    msgpack-rpc responses ``[1, msgid, nil, [[1, value]]]`` (``carla::rpc::Response<T>``)."""

    def __init__(self, version: str, maps: list[str]) -> None:
        self.results = {"version": version, "get_available_maps": maps}
        self.calls: list[str] = []
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(16)
        self.port = self.listener.getsockname()[1]
        self.connections: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.listener.accept()
            except OSError:
                return
            self.connections.append(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        buf = b""
        while True:
            try:
                chunk = conn.recv(4096)
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            while buf:
                try:
                    (kind, msgid, method, _params), end = _unpack(buf)
                except IndexError:
                    break
                buf = buf[end:]
                assert kind == 0, "a msgpack-rpc request"
                self.calls.append(method)
                conn.sendall(_pack([1, msgid, None, [[1, self.results[method]]]]))

    def close(self) -> None:
        _stop(self.listener)
        for conn in self.connections:
            conn.close()


#: what a CARLA 0.9.16 server lists without its AdditionalMaps package: the towns, their layered variants, and a
#: non-town map where no vehicle spawns (CARLA issue #9253)
BASE_MAPS = [
    f"/Game/Carla/Maps/{town}{variant}"
    for town in ("Town01", "Town02", "Town03", "Town04", "Town05", "Town10HD")
    for variant in ("", "_Opt")
] + ["/Game/Carla/Maps/AnnotationColorLandscape"]
#: ... and with it: Town06, Town07 and the large maps, one folder each
FULL_MAPS = BASE_MAPS + [
    "/Game/Carla/Maps/Town06",
    "/Game/Carla/Maps/Town06_Opt",
    "/Game/Carla/Maps/Town07",
    "/Game/Carla/Maps/Town07_Opt",
    "/Game/Carla/Maps/Town12/Town12",
    "/Game/Carla/Maps/Town13/Town13",
    "/Game/Carla/Maps/Town15/Town15",
]


@pytest.fixture
def fake_carla() -> Iterator[FakeCarlaServer]:
    server = FakeCarlaServer(importlib.metadata.version("carla"), FULL_MAPS)
    yield server
    server.close()


def test_connects_to_a_carla_server(fake_carla: FakeCarlaServer) -> None:
    with CarlaSimulator(port=fake_carla.port, timeout_s=TIMEOUT_S, maps=("Town03",)) as sim:
        start = time.monotonic()
        sim.connect()
        assert time.monotonic() - start < TIMEOUT_S
        assert sim.version == f"carla-{importlib.metadata.version('carla')}"
        assert "connected" in repr(sim) and "not connected" not in repr(sim)
        sim.connect()  # idempotent
    # the probe, then libcarla's own handshake
    assert fake_carla.calls == ["version", "version", "get_available_maps"]


def test_version_mismatch_warns(fake_carla: FakeCarlaServer) -> None:
    fake_carla.results["version"] = "0.9.15"
    sim = CarlaSimulator(port=fake_carla.port, timeout_s=TIMEOUT_S)
    with pytest.warns(UserWarning, match="0.9.15"):
        sim.connect()
    assert sim.version == "carla-0.9.15"
    sim.close()


def test_the_default_towns_are_on_a_full_server_among_maps_that_are_no_towns(fake_carla: FakeCarlaServer) -> None:
    with CarlaSimulator(port=fake_carla.port, timeout_s=TIMEOUT_S) as sim:
        sim.connect()  # the server also lists AnnotationColorLandscape and the large maps: they are not drawn
        assert sim.maps == TOWNS
        assert {choose_map(seed, sim.maps) for seed in range(200)} == set(TOWNS)


def test_configured_maps_must_exist_on_the_server(fake_carla: FakeCarlaServer) -> None:
    fake_carla.results["get_available_maps"] = BASE_MAPS  # no AdditionalMaps package: no Town06, Town07
    sim = CarlaSimulator(port=fake_carla.port, timeout_s=TIMEOUT_S)
    with pytest.raises(ValueError) as info:
        sim.connect()
    message = str(info.value)
    assert message.startswith("simulator.carla.maps: Town06, Town07 not on the server")
    assert "whose towns are Town01, Town01_Opt, Town02" in message and "AdditionalMaps" in message
    assert "AnnotationColorLandscape" not in message
    sim = CarlaSimulator(port=fake_carla.port, timeout_s=TIMEOUT_S, maps=("Town01", "Town10HD_Opt"))
    sim.connect()
    sim.close()


@pytest.mark.parametrize(
    ("answer", "word"),
    [(b"HTTP/1.1 400 Bad Request\r\n\r\n", "not as a CARLA server"), (b"", "without answering")],
)
def test_a_service_that_is_not_carla_is_reported(answer: bytes, word: str) -> None:
    # libcarla itself would abort the whole process on such an answer
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(4)

    def serve() -> None:
        conn, _ = listener.accept()
        with conn:
            conn.recv(1024)
            conn.sendall(answer)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    port = listener.getsockname()[1]
    try:
        with pytest.raises(CarlaConnectionError, match=word) as info:
            CarlaSimulator(port=port, timeout_s=TIMEOUT_S).connect()
        assert f"127.0.0.1:{port}" in str(info.value)
    finally:
        thread.join(timeout=2.0)
        listener.close()


# --- arguments and configuration ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "error", "word"),
    [
        ({"height": 0}, ValueError, "height"),
        ({"width": 12.0}, TypeError, "width"),
        ({"height": True}, TypeError, "height"),
        ({"host": ""}, ValueError, "host"),
        ({"host": "my host"}, ValueError, "host"),
        ({"port": 0}, ValueError, "port"),
        ({"port": 65535}, ValueError, "port"),
        ({"timeout_s": 0.0}, ValueError, "timeout_s"),
        ({"timeout_s": math.inf}, ValueError, "timeout_s"),
        ({"timeout_s": "10"}, TypeError, "timeout_s"),
        ({"maps": "Town01"}, TypeError, "maps"),
        ({"maps": ("Town01", "Town01")}, ValueError, "duplicates"),
        ({"maps": ("Town01", "")}, ValueError, "maps"),
        ({"maps": ()}, ValueError, "maps is empty"),
        (
            {"maps": ("Town01", "AnnotationColorLandscape")},
            ValueError,
            "'AnnotationColorLandscape' is not a CARLA town",
        ),
        ({"maps": ("Town12",)}, ValueError, "'Town12' is one of CARLA's large maps"),
        ({"maps": ("/Game/Carla/Maps/Town01",)}, ValueError, r"is a path: give the map's name \('Town01'\)"),
        ({"fixed_delta_seconds": 0.2}, ValueError, "fixed_delta_seconds"),
        ({"fixed_delta_seconds": 0.0}, ValueError, "fixed_delta_seconds"),
        ({"settle_ticks": 0}, ValueError, "settle_ticks"),
        ({"traffic_manager_port": 2001}, ValueError, "traffic_manager_port"),
        ({"traffic_manager_port": 70000}, ValueError, "traffic_manager_port"),
        ({"max_vehicles": -1}, ValueError, "max_vehicles"),
        ({"max_pedestrians": 2.5}, TypeError, "max_pedestrians"),
        ({"fov": 180.0}, ValueError, "fov"),
        ({"fov": -10.0}, ValueError, "fov"),
    ],
)
def test_arguments_are_validated_eagerly(kwargs: dict, error: type[Exception], word: str) -> None:
    with pytest.raises(error, match=word):
        CarlaSimulator(**kwargs)


def test_from_config_carries_every_setting() -> None:
    from components.core.config import PROJECT_ROOT, load_params

    # the other backends' sections as params.yaml has them
    others = dict(load_params(PROJECT_ROOT / "params.yaml").simulator)
    cfg = SimulatorConfig(
        **others
        | dict(
            backend="carla",
            height=96,
            width=160,
            render_sizes=None,
            carla=CarlaConfig(
                host="10.0.0.7",
                port=3000,
                timeout_s=4.0,
                maps=("Town03", "Town01"),
                fixed_delta_seconds=0.1,
                settle_ticks=7,
                traffic_manager_port=8123,
                max_vehicles=4,
                max_pedestrians=2,
                fov=75.0,
            ),
        )
    )
    sim = CarlaSimulator.from_config(cfg)
    assert (sim.height, sim.width, sim.host, sim.port) == (96, 160, "10.0.0.7", 3000)
    assert (sim.timeout_s, sim.fixed_delta_seconds, sim.settle_ticks) == (4.0, 0.1, 7)
    assert (sim.traffic_manager_port, sim.max_vehicles, sim.max_pedestrians) == (8123, 4, 2)
    assert sim.maps == ("Town01", "Town03")
    assert sim.fov == 75.0


def test_the_default_towns_are_params_yaml_default() -> None:
    from components.core.config import PROJECT_ROOT, load_params

    assert load_params(PROJECT_ROOT / "params.yaml").simulator.carla.maps == TOWNS
    assert CarlaSimulator(port=_free_port()).maps == TOWNS


@pytest.mark.parametrize(
    ("name", "town"),
    [("Town01", True), ("Town10HD", True), ("Town10HD_Opt", True), ("Town07_Opt", True), ("Town10", True)]
    + [("Town12", False), ("Town13", False), ("Town15", False), ("Town11", False)]
    + [("AnnotationColorLandscape", False), ("town01", False), ("Town", False), ("Town01HD_x", False)],
)
def test_the_town_rule(name: str, town: bool) -> None:
    """CARLA's town names: Town + digits + optional HD and _Opt; its large maps and other maps are no towns."""
    assert (CarlaConfig.town_problem(name) is None) == town


@pytest.mark.parametrize(
    ("maps", "message"),
    [
        ([], r"simulator\.carla\.maps: empty: list the towns a scene seed draws from \(the default: Town01"),
        (["Town01", "AnnotationColorLandscape"], r"maps: 'AnnotationColorLandscape' is not a CARLA town"),
        (["Town13", "Town15"], r"maps: 'Town13' is one of CARLA's large maps.*; 'Town15' is one"),
        (["Town01", "Town01"], r"maps: each value at most once"),
    ],
)
def test_params_refuse_maps_that_are_no_towns_by_name(maps: list, message: str) -> None:
    import copy

    import yaml

    from components.core.config import PROJECT_ROOT, ConfigError, parse_params

    params = yaml.safe_load((PROJECT_ROOT / "params.yaml").read_text())
    edited = copy.deepcopy(params)
    edited["simulator"]["carla"]["maps"] = maps
    with pytest.raises(ConfigError, match=message):
        parse_params(edited, source="params.yaml")
    edited["simulator"]["carla"]["maps"] = ["Town10HD_Opt", "Town02"]
    assert parse_params(edited, source="params.yaml").simulator.carla.maps == ("Town10HD_Opt", "Town02")


def test_the_installed_client_loads_only_a_different_map_and_returns_nothing() -> None:
    # what _load_world relies on: the call exists in the pinned client, takes a name and returns None (not a world)
    doc = carla.Client.load_world_if_different.__doc__
    assert "load_world_if_different( (Client)arg1, (str)map_name" in doc and "-> None" in doc


def test_version_before_connecting_is_the_client_version() -> None:
    sim = CarlaSimulator(port=_free_port())
    assert sim.version == f"carla-{importlib.metadata.version('carla')}"


def test_implements_the_simulator_protocol() -> None:
    sim = CarlaSimulator(64, 96, port=_free_port())
    assert isinstance(sim, Simulator)
    assert (sim.height, sim.width) == (64, 96)


def test_missing_carla_package_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "carla", None)  # makes `import carla` fail as if not installed
    with pytest.raises(ImportError, match=r"pip install 'pidc\[carla\]'"):
        CarlaSimulator()
    # a bad weather is still reported as such, before the missing package
    with pytest.raises(ValueError, match="fog_density"):
        weather_parameters({"fog_density": -1.0})


# --- pure conversions on real carla objects -----------------------------------------------------------


def test_hood_camera_follows_the_vehicle_bounding_box() -> None:
    for ex, ez in [(2.45, 0.75), (1.8, 0.6), (3.1, 1.3)]:
        t = hood_camera_transform(carla.Vector3D(ex, 1.0, ez))
        assert t.location.x == pytest.approx(0.8 * (0.5 + ex), rel=1e-6)
        assert t.location.y == 0.0
        assert t.location.z == pytest.approx(1.3 * (0.5 + ez), rel=1e-6)
        assert (t.rotation.pitch, t.rotation.yaw, t.rotation.roll) == (0.0, 0.0, 0.0)
    # taller vehicles carry the camera higher
    low = hood_camera_transform(carla.Vector3D(2.0, 1.0, 0.6)).location.z
    high = hood_camera_transform(carla.Vector3D(2.0, 1.0, 1.3)).location.z
    assert high > low


def test_synchronous_settings_round_trip() -> None:
    s = synchronous_settings(carla.WorldSettings(), 0.05)
    assert s.synchronous_mode and s.fixed_delta_seconds == pytest.approx(0.05)
    s = asynchronous_settings(s)
    assert not s.synchronous_mode and s.fixed_delta_seconds is None


def test_bgra_to_rgb_swaps_channels_and_drops_alpha() -> None:
    rng = seeding.rng(0, "test_carla", "bgra")
    bgra = rng.integers(0, 256, size=(5, 7, 4), dtype=np.uint8)
    rgb = bgra_to_rgb(bgra.tobytes(), 5, 7)
    assert rgb.shape == (5, 7, 3) and rgb.dtype == np.uint8 and rgb.flags.c_contiguous
    np.testing.assert_array_equal(rgb[..., 0], bgra[..., 2])
    np.testing.assert_array_equal(rgb[..., 1], bgra[..., 1])
    np.testing.assert_array_equal(rgb[..., 2], bgra[..., 0])
    with pytest.raises(ValueError, match="5x8"):
        bgra_to_rgb(bgra.tobytes(), 5, 8)


# --- the scene plan -----------------------------------------------------------------------------------

MAPS = ["/Game/Carla/Maps/Town01", "/Game/Carla/Maps/Town03", "/Game/Carla/Maps/Town05", "/Game/Carla/Maps/Town10HD"]
VEHICLES = ["vehicle.audi.a2", "vehicle.tesla.model3", "vehicle.lincoln.mkz_2020", "vehicle.carlamotors.firetruck"]
EGOS = ["vehicle.audi.a2", "vehicle.tesla.model3", "vehicle.lincoln.mkz_2020"]
WALKERS = [f"walker.pedestrian.{i:04d}" for i in range(1, 15)]


def _plan(seed: int, **kw):  # noqa: ANN202
    args = dict(maps=MAPS, vehicle_blueprints=VEHICLES, walker_blueprints=WALKERS, n_spawn_points=120)
    args.update(kw)
    return plan_scene(
        seed,
        args.pop("maps"),
        args.pop("vehicle_blueprints"),
        args.pop("walker_blueprints"),
        args.pop("n_spawn_points"),
        ego_blueprints=args.pop("ego_blueprints", EGOS),
        **args,
    )


def test_plan_is_a_deterministic_function_of_the_scene_seed() -> None:
    plans = [_plan(s) for s in range(40)]
    assert plans == [_plan(s) for s in range(40)]
    # the order of the server's lists does not matter
    shuffled = _plan(
        7,
        maps=MAPS[::-1],
        vehicle_blueprints=VEHICLES[::-1],
        walker_blueprints=WALKERS[::-1],
        ego_blueprints=EGOS[::-1],
    )
    assert shuffled == plans[7]
    # different seeds give different scenes
    assert len({(p.map_name, p.ego_spawn_index, p.vehicle_spawn_indices, p.walker_blueprints) for p in plans}) == 40
    for seed, p in enumerate(plans):
        assert p.scene_seed == seed and p.map_name == choose_map(seed, MAPS)


def test_plan_respects_the_candidates_and_the_spawn_points() -> None:
    for seed in range(200):
        p = _plan(seed, n_spawn_points=9, max_vehicles=15, max_pedestrians=10)
        assert p.map_name in MAPS and p.ego_blueprint in EGOS
        assert 0 <= p.n_vehicles <= 8 and 0 <= p.n_pedestrians <= 10
        spawn = (p.ego_spawn_index,) + p.vehicle_spawn_indices
        assert len(set(spawn)) == len(spawn) and all(0 <= i < 9 for i in spawn)
        assert set(p.vehicle_blueprints) <= set(VEHICLES) and set(p.walker_blueprints) <= set(WALKERS)
        assert len(p.vehicle_colours) == p.n_vehicles
        assert all(0.0 <= c < 1.0 for c in p.vehicle_colours + (p.ego_colour,))
        assert 0 <= p.pedestrian_seed < 2**31 and 0 <= p.traffic_seed < 2**31
    only_ego = _plan(3, n_spawn_points=1)
    assert only_ego.ego_spawn_index == 0 and only_ego.n_vehicles == 0


def test_plan_choices_are_uniform_over_the_seeds() -> None:
    n = 800
    plans = [_plan(s, max_vehicles=4, max_pedestrians=3) for s in range(n)]
    # Pearson χ² against the uniform law; the 0.1 % critical values are 16.3 (3 dof), 18.5 (4 dof), 16.3 (3 dof)
    for values, k, critical in [
        ([p.map_name for p in plans], len(MAPS), 16.3),
        ([p.n_vehicles for p in plans], 5, 18.5),
        ([p.n_pedestrians for p in plans], 4, 16.3),
    ]:
        counts = Counter(values)
        assert len(counts) == k
        chi2 = sum((c - n / k) ** 2 / (n / k) for c in counts.values())
        assert chi2 < critical, (counts, chi2)
    # the heading (ego spawn point) covers the map's spawn points
    assert len({p.ego_spawn_index for p in plans}) > 100


def test_plan_streams_are_independent() -> None:
    for seed in range(30):
        a, b = _plan(seed, max_pedestrians=10), _plan(seed, max_pedestrians=0)
        assert b.n_pedestrians == 0
        assert (a.map_name, a.ego_blueprint, a.ego_spawn_index, a.vehicle_blueprints, a.vehicle_spawn_indices) == (
            b.map_name,
            b.ego_blueprint,
            b.ego_spawn_index,
            b.vehicle_blueprints,
            b.vehicle_spawn_indices,
        )


def test_plan_without_traffic() -> None:
    p = _plan(5, vehicle_blueprints=[], walker_blueprints=[], max_vehicles=0, max_pedestrians=0)
    assert p.n_vehicles == 0 and p.n_pedestrians == 0 and p.ego_blueprint in EGOS


@pytest.mark.parametrize(
    ("kw", "error", "word"),
    [
        ({"maps": []}, ValueError, "maps"),
        ({"maps": "Town01"}, TypeError, "maps"),
        ({"n_spawn_points": 0}, ValueError, "n_spawn_points"),
        ({"walker_blueprints": []}, ValueError, "walker_blueprints"),
        ({"vehicle_blueprints": []}, ValueError, "vehicle_blueprints"),
        ({"ego_blueprints": []}, ValueError, "ego"),
        ({"max_vehicles": -2}, ValueError, "max_vehicles"),
    ],
)
def test_plan_rejects_bad_input(kw: dict, error: type[Exception], word: str) -> None:
    with pytest.raises(error, match=word):
        _plan(1, **kw)


@pytest.mark.parametrize(("seed", "error"), [(-1, ValueError), (True, TypeError), (2.0, TypeError), ("7", TypeError)])
def test_plan_rejects_bad_scene_seeds(seed: object, error: type[Exception]) -> None:
    with pytest.raises(error, match="scene_seed"):
        _plan(seed)  # type: ignore[arg-type]
