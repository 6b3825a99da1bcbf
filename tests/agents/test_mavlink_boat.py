"""The MAVLink boat over real UDP: the agent's RoverAdapter drives the simulated
ArduRover boat (``python -m agents sim mavlink --vehicle-class boat``, a separate
process) through a ControlHub and its WebSocket server, as a browser would.

The boat starts at sea off Barra beach, west of the demo's Costa Nova station; the
packaged land mask has land about 330 m to its north. Every rig runs the simulator with
``speedup`` so that trips take seconds; assertions are about where the boat goes and
what the user is told, with loose time bounds only.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import re
import subprocess
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection, connect

from agents.control import ControlHub, ControlServer
from agents.geo import distance_m, local_offset_m, offset
from agents.geography import is_land, land_at
from agents.protocol import (
    VehicleTask,
    generate_keypair,
    load_private_key,
)
from agents.simulation import simulator_running
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.mavlink.config import MavlinkConfig
from agents.vehicles.mavlink.copter import CopterAdapter
from agents.vehicles.mavlink.dialect import MAV, mavutil, wrap180
from agents.vehicles.mavlink.rover import HOLD, RoverAdapter
from agents.vehicles.mavlink.sim import simulator_command
from agents.vehicles.mavlink.sim.cli import parse_args
from agents.vehicles.registry import adapter_create
from tests.agents.documents import grant_for, task_for
from tests.agents.mavlink_rig import (
    LINK_LOSS_TIMEOUT_MS,
    control_rigs,
    ground_station,
    modes_until,
    poll,
    sent_off,
    simulator_listening,
    watch,
)
from tests.agents.waiting import Sampler
from tests.control import command, recv

PRIVATE_PEM, PUBLIC_PEM = generate_keypair()
PRIVATE = load_private_key(PRIVATE_PEM)
VEHICLE = "boat-test-1"
#: At sea off Barra beach, 720 m west of the demo's Costa Nova station (40.6443, -8.7455).
ORIGIN = (40.6443, -8.7540)
#: Due north across the land the mask has from 40.6472: water again in the lagoon.
ACROSS_LAND = (40.6560, -8.7540)
BOAT_COMMANDS = (
    "arm",
    "disarm",
    "forward",
    "backward",
    "left",
    "right",
    "stop",
    "return_to_home",
    "go_to_waypoint",
    "release_payload",
)
TOPICS = ["location", "speed", "heading", "mode", "is_armed", "autopilot_link", "battery_level"]
#: Quick trips: 4x driving time.
SIM: dict[str, Any] = {"speedup": 4}
#: ArduRover's defaults: the boat slows at 1 m/s/s, holds within 2 m.
DECEL_MPS2 = 1.0
LOIT_RADIUS_M = 2.0


@dataclass
class Rig:
    hub: ControlHub
    server: ControlServer
    boat: RoverAdapter
    sim_process: subprocess.Popen[bytes]
    reports: list[tuple[str, str | None, dict[str, Any]]] = field(default_factory=list)
    events: list[tuple[str, dict[str, Any]]] = field(default_factory=list)

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.server.port}/"

    def reported(self, name: str) -> list[dict[str, Any]]:
        return [data for event, _, data in self.reports if event == name]

    def warnings(self) -> list[str]:
        return [data["text"] for name, data in self.events if name == "autopilot_warning"]

    def texts(self, text: str) -> int:
        """How many times the autopilot said ``text`` (its recent STATUSTEXTs)."""
        return sum(1 for _, _, said in self.boat.texts if said == text)

    def here(self) -> tuple[float, float]:
        position = self.boat.state().position
        assert position is not None, "no position"
        return position


def make_task(**limits: Any) -> VehicleTask:
    return task_for(
        VEHICLE,
        BOAT_COMMANDS,
        **{"link_loss_timeout_ms": LINK_LOSS_TIMEOUT_MS, "failsafe_action": "stop", **limits},
    )


def make_grant() -> str:
    return grant_for(VEHICLE, BOAT_COMMANDS, PRIVATE)


def boat_options(**overrides: Any) -> dict[str, Any]:
    return {
        "vehicle_class": "boat",
        "origin": list(ORIGIN),
        "max_speed_mps": 5,
        "simulator": SIM,
        "heartbeat_timeout_s": 1.5,
        "command_timeout_s": 2.0,
        **overrides,
    }


RigFactory = Callable[..., Awaitable[Rig]]


@pytest.fixture
async def make_rig() -> AsyncIterator[RigFactory]:
    """Build rigs (simulator + boat + hub + server + task; see
    :func:`tests.agents.mavlink_rig.control_rigs`); everything is closed at the end, the
    simulators last."""
    async with control_rigs(
        Rig,
        adapter=RoverAdapter,
        options=boat_options,
        default_task=make_task,
        vehicle_id=VEHICLE,
        vehicle_name="boat-1",
        public_pem=PUBLIC_PEM,
    ) as build:
        yield build


@pytest.fixture
async def rig(make_rig: RigFactory) -> Rig:
    """In this module, one boat rig with the default task (conftest's ``rig`` is the
    control tests' car)."""
    return await make_rig()


async def join(rig: Rig) -> ClientConnection:
    """A controller's WebSocket, subscribed to the boat's telemetry at 10 Hz, once the
    boat reports a position."""
    ws = await connect(rig.url, compression=None, proxy=None)
    await ws.send(json.dumps({"type": "auth", "grant": make_grant()}))
    welcome = await recv(ws, "welcome")
    assert welcome["role"] == "controller"
    await ws.send(json.dumps({"type": "subscribe", "topics": TOPICS, "rate_hz": 10}))
    await watch(
        ws,
        lambda d: d["location"] is not None and d["heading"] is not None,
        10,
        "a position",
    )
    return ws


async def arm(ws: ClientConnection, seq: int = 1) -> None:
    assert (await command(ws, seq, "arm"))["ok"]
    await watch(ws, lambda d: d["is_armed"] is True and d["mode"] == "GUIDED", 5, "armed")


async def hold_until(
    ws: ClientConnection,
    keys: list[tuple[str, dict[str, Any]]],
    until: Callable[[dict[str, Any]], bool],
    within: float,
    seq: int,
    what: str,
) -> tuple[int, dict[str, Any]]:
    """Hold ``keys`` (repeat each every 100 ms, as the browser does while they are
    pressed; every repeat must be acknowledged ok) until the telemetry satisfies
    ``until``. Returns (the next free seq, that telemetry)."""
    deadline = time.monotonic() + within
    data: dict[str, Any] = {}
    while time.monotonic() < deadline:
        for name, args in keys:
            ack = await command(ws, seq, name, **args)
            assert ack["ok"], ack
            seq += 1
        with contextlib.suppress(AssertionError):
            data = await watch(ws, until, 0.1, what)
            return seq, data
    raise AssertionError(f"timed out holding {keys} for {what}; last telemetry {data}")


def point(location: dict[str, float]) -> tuple[float, float]:
    """A telemetry ``location`` as (lat, lon)."""
    return (location["lat"], location["lon"])


def metres(location: dict[str, float], origin: tuple[float, float] = ORIGIN) -> tuple[float, float]:
    """(north, east) metres of a telemetry ``location`` from ``origin``."""
    return local_offset_m(origin, point(location))


def bearing(a: dict[str, float], b: dict[str, float]) -> float:
    north, east = local_offset_m((a["lat"], a["lon"]), (b["lat"], b["lon"]))
    return math.degrees(math.atan2(east, north)) % 360.0


def near(location: dict[str, float] | None, point: tuple[float, float], metres: float) -> bool:
    return location is not None and distance_m((location["lat"], location["lon"]), point) < metres


class Track(Sampler):
    """Every position the adapter reports, sampled every 20 ms."""

    def __init__(self, boat: MavlinkAdapter) -> None:
        self.boat = boat
        self.positions: list[tuple[float, float]] = []

    def sample(self) -> None:
        position = self.boat.state().position
        if position is not None:
            self.positions.append(position)


# --- a boat, not a copter -----------------------------------------------------------------


async def test_the_boat_arms_in_guided_and_has_no_altitude(rig: Rig):
    boat = rig.boat
    ws = await join(rig)
    assert boat.t.mav_type == MAV.MAV_TYPE_SURFACE_BOAT  # ArduRover, FRAME_CLASS 2
    assert "altitude" not in boat.telemetry_topics() and boat.state().alt is None
    assert rig.warnings() == []  # the autopilot is the class the options say
    await arm(ws)
    assert boat.state().mode == "GUIDED" and boat.state().armed is True
    names = {c.name for c in boat.commands()}
    assert names == set(BOAT_COMMANDS) - {"release_payload"}  # no payload option
    assert rig.texts("Arming motors") == 1
    await ws.close()


# --- driving ------------------------------------------------------------------------------


async def test_forward_goes_along_the_heading_at_the_asked_speed_and_stop_stops_it(
    make_rig: RigFactory,
):
    rig = await make_rig(simulator={**SIM, "heading_deg": 90})  # bow to the east
    ws = await join(rig)
    await arm(ws)
    forward = [("forward", {"speed_mps": 2.0})]
    seq, data = await hold_until(
        ws, forward, lambda d: abs(d["speed"] - 2.0) < 0.05, 10, 2, "2 m/s"
    )
    start = data["location"]
    seq, data = await hold_until(
        ws, forward, lambda d: metres(d["location"], point(start))[1] > 10, 10, seq, "10 m"
    )
    assert abs(data["speed"] - 2.0) < 0.05  # the asked speed, held
    north, east = metres(data["location"], point(start))
    assert abs(north) < 0.5, (north, east)  # along the heading: east
    assert abs(wrap180(data["heading"] - 90)) < 1
    assert (await command(ws, seq, "stop"))["ok"]
    # Braking starts where the stop reached the agent, which is where it is measured
    # from: the telemetry the test last read can be a good way behind that on a busy
    # machine (0.13 m too far once, under stress-ng on both cores).
    stopped_at = rig.boat.state().position
    assert stopped_at is not None
    data = await watch(ws, lambda d: d["speed"] < 0.05, 5, "the boat to stop")
    # Its braking distance at ArduRover's 1 m/s/s, plus a telemetry period's worth.
    coasted = distance_m(stopped_at, point(data["location"]))
    assert coasted < 2.0**2 / (2 * DECEL_MPS2) + 1.5, coasted
    assert data["mode"] == "GUIDED" and data["is_armed"] is True
    await ws.close()


async def test_right_turns_on_the_spot_and_forward_with_left_is_a_curve(rig: Rig):
    ws = await join(rig)
    await arm(ws)
    start = await watch(ws, lambda d: True, 1, "telemetry")
    right = [("right", {"rate_deg_s": 30})]
    seq, data = await hold_until(
        ws, right, lambda d: 60 < d["heading"] < 180, 10, 2, "a turn to the right"
    )
    assert (await command(ws, seq, "stop"))["ok"]
    data = await watch(ws, lambda d: d["speed"] < 0.05, 5, "settled")
    assert distance_m(point(start["location"]), point(data["location"])) < 1.0
    turned = await watch(ws, lambda d: True, 1, "telemetry")
    h0, p0 = turned["heading"], turned["location"]

    curve = [("forward", {"speed_mps": 2.0}), ("left", {"rate_deg_s": 20})]
    seq, data = await hold_until(
        ws,
        curve,
        lambda d: wrap180(d["heading"] - h0) < -45,
        15,
        seq + 1,
        "45 degrees to the left",
    )
    assert (await command(ws, seq, "stop"))["ok"]
    # The chord of a left curve points left of where it started, right of where it ends.
    chord = wrap180(bearing(p0, data["location"]) - h0)
    assert wrap180(data["heading"] - h0) - 5 < chord < -5, (h0, data["heading"], chord)
    # Under way, not turning on the spot (which moves it less than a metre, above): from
    # rest at ArduRover's 1 m/s/s, 45 degrees at 20 deg/s covers about 3 m, less when
    # a loaded machine spaces the held keys' repeats.
    assert distance_m(point(p0), point(data["location"])) > 1.5
    await ws.close()


async def test_a_released_key_stops_the_boat_at_once(make_rig: RigFactory):
    """No ``stop`` from the browser: the agent stops the boat when the key's repeats
    end (``setpoint_hold_s``), long before ArduRover's own 3 s setpoint timeout."""
    rig = await make_rig(setpoint_hold_s=0.3)
    ws = await join(rig)
    await arm(ws)
    forward = [("forward", {"speed_mps": 3.0})]
    await hold_until(ws, forward, lambda d: d["speed"] > 2.9, 10, 2, "3 m/s")
    released = time.monotonic()
    await watch(ws, lambda d: d["speed"] < 0.05, 3, "the boat to stop")
    # Hold time, then 3 m/s at 1 m/s/s and 4x: 0.3 + 0.75 s and a telemetry period;
    # ArduRover's own timeout could not have stopped it before 3 s.
    assert time.monotonic() - released < 3.0
    assert rig.texts("target not received last 3secs, stopping") == 0
    await ws.close()


async def test_ardurovers_timeout_after_a_stop_is_not_a_warning_for_the_platform(rig: Rig):
    """A stop is a zero setpoint; 3 s later ArduRover says "target not received last
    3.0 secs, stopping", as it should once the agent sends no more: no
    autopilot_warning for that."""
    ws = await join(rig)
    await arm(ws)
    seq, _ = await hold_until(
        ws, [("forward", {"speed_mps": 1.0})], lambda d: d["speed"] > 0.5, 10, 2, "moving"
    )
    assert (await command(ws, seq, "stop"))["ok"]
    timeout = "target not received last 3secs, stopping"
    await watch(ws, lambda d: rig.texts(timeout) > 0, 10, "ArduRover's setpoint timeout")
    assert timeout not in rig.warnings()
    await ws.close()


# --- waypoints, land, home ------------------------------------------------------------------


async def test_go_to_waypoint_on_water_arrives_and_holds_there(rig: Rig):
    ws = await join(rig)
    await arm(ws)
    target = offset(ORIGIN, 60, 40)
    ack = await command(ws, 2, "go_to_waypoint", lat=target[0], lon=target[1], speed_mps=4)
    assert ack["ok"], ack
    await watch(ws, lambda d: d["speed"] > 3.5, 10, "cruising at 4 m/s")
    data = await watch(
        ws,
        lambda d: near(d["location"], target, 3) and d["speed"] < 0.1,
        30,
        "arrived and stopped",
    )
    assert data["mode"] == "GUIDED" and data["is_armed"] is True
    assert rig.texts("Reached destination") == 1
    await ws.close()


async def test_the_boat_sails_100_m_to_a_waypoint_at_the_speed_asked(rig: Rig):
    """ArduRover answers a speed FAILED unless it already drives to a position (a boat
    just armed loiters): the adapter sends the position first, then the speed. So a
    mission's first leg, from a boat holding where it armed, goes at its speed."""
    ws = await join(rig)
    await arm(ws)
    target = offset(ORIGIN, -100, 0)  # south: open water
    ack = await command(ws, 2, "go_to_waypoint", lat=target[0], lon=target[1], speed_mps=3)
    assert ack["ok"], ack
    data = await watch(ws, lambda d: d["speed"] > 2.9, 10, "cruising at 3 m/s")
    fastest = data["speed"]
    data = await watch(
        ws,
        lambda d: near(d["location"], target, 3) and d["speed"] < 0.1,
        60,
        "100 m out, holding",
    )
    assert fastest < 3.1 and data["mode"] == "GUIDED"
    assert rig.boat.stats["refusals"] == 0 and rig.texts("Reached destination") == 1
    await ws.close()


async def test_a_waypoint_across_land_stops_at_the_shore_and_never_on_land(
    make_rig: RigFactory,
):
    rig = await make_rig(max_speed_mps=8, simulator={"speedup": 8})
    ws = await join(rig)
    await arm(ws)
    async with Track(rig.boat) as track:
        lat, lon = ACROSS_LAND
        assert (await command(ws, 2, "go_to_waypoint", lat=lat, lon=lon, speed_mps=8))["ok"]
        aground = "Ran aground: stopped at the shore"
        await watch(ws, lambda d: aground in rig.warnings(), 30, "aground")
        data = await watch(ws, lambda d: d["speed"] < 0.05, 5, "stopped at the shore")
    shore = point(data["location"])
    assert land_at(*offset(shore, 5, 0)) is True  # the land is right ahead
    assert distance_m(ORIGIN, shore) > 300 and distance_m(shore, ACROSS_LAND) > 500
    assert track.positions and not any(is_land(*p) for p in track.positions)
    # It may leave the way it came.
    assert (await command(ws, 3, "go_to_waypoint", lat=ORIGIN[0], lon=ORIGIN[1]))["ok"]
    await watch(ws, lambda d: distance_m(shore, point(d["location"])) > 20, 10, "leaving the shore")
    await ws.close()


async def test_return_to_home_drives_back_and_holds_there_armed(rig: Rig):
    ws = await join(rig)
    await arm(ws)
    away = offset(ORIGIN, -50, 50)
    assert (await command(ws, 2, "go_to_waypoint", lat=away[0], lon=away[1], speed_mps=4))["ok"]
    await watch(ws, lambda d: not near(d["location"], ORIGIN, 30), 20, "30 m from home")
    assert (await command(ws, 3, "return_to_home"))["ok"]
    await watch(ws, lambda d: d["mode"] == "RTL", 3, "RTL")
    data = await watch(
        ws,
        lambda d: near(d["location"], ORIGIN, 4) and d["speed"] < 0.1,
        30,
        "home, holding",
    )
    assert data["mode"] == "RTL" and data["is_armed"] is True  # a boat does not land
    # Driving again takes it out of RTL (the user started the return).
    assert (await command(ws, 4, "forward", speed_mps=1))["ok"]
    await watch(ws, lambda d: d["mode"] == "GUIDED", 3, "GUIDED again")
    await ws.close()


async def test_the_payload_is_released_once(make_rig: RigFactory):
    rig = await make_rig(payload={"method": "gripper"})
    assert "release_payload" in {c.name for c in rig.boat.commands()}
    ws = await join(rig)
    await arm(ws)
    assert (await command(ws, 2, "release_payload"))["ok"]
    await poll(lambda: rig.texts("Gripper load released") == 1, 3, "the release")
    assert rig.boat.stats["refusals"] == 0
    await ws.close()


# --- holding still -----------------------------------------------------------------------------


async def test_loiter_holds_against_the_current_and_hold_drifts(make_rig: RigFactory):
    """The boat holds with LOITER-like control: pushed out of LOIT_RADIUS by the
    current it drives back, staying within a few metres; HOLD stops the motors and the
    current takes it away."""
    rig = await make_rig(simulator={**SIM, "current_mps": 0.5, "current_towards_deg": 90})
    boat = rig.boat
    ws = await join(rig)
    await arm(ws)  # GUIDED, holding where it armed
    held = rig.here()
    farthest, since = 0.0, boat.t.boot_ms
    # 30 s of the boat's own time (its boot clock) with the current pushing it east.
    while boat.t.boot_ms - since < 30_000:
        data = await watch(ws, lambda d: True, 1, "telemetry")
        farthest = max(farthest, distance_m(held, point(data["location"])))
    assert LOIT_RADIUS_M < farthest < LOIT_RADIUS_M + 3.0, farthest
    await boat._set_mode(HOLD, owner="user")
    data = await watch(
        ws, lambda d: metres(d["location"], held)[1] > 10, 30, "drifting east in HOLD"
    )
    assert data["mode"] == "HOLD"
    await ws.close()


# --- fail-safes --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("action", "mode"),
    [("stop", "LOITER"), ("land", "LOITER"), ("return_to_home", "RTL")],
)
async def test_a_lost_controller_holds_the_boat_or_brings_it_home(
    make_rig: RigFactory, action: str, mode: str
):
    """The agent's link-loss fail-safe: ``stop`` (and ``land``, which a boat cannot)
    hold it where it is with LOITER; ``return_to_home`` brings it home (RTL)."""
    rig = await make_rig(make_task(failsafe_action=action))
    ws = await join(rig)
    await arm(ws)
    forward = [("forward", {"speed_mps": 3.0})]
    await hold_until(ws, forward, lambda d: not near(d["location"], ORIGIN, 10), 10, 2, "10 m out")
    ws.transport.abort()
    await poll(lambda: bool(rig.reported("failsafe")), 3, "the fail-safe")
    assert rig.reported("failsafe") == [{"cause": "link_lost", "action": action}]
    await poll(lambda: rig.boat.state().mode == mode, 3, mode)
    boat = rig.boat
    if mode == "RTL":
        await poll(lambda: near_state(boat, ORIGIN, 3), 30, "home")
    await poll(lambda: (boat.state().speed_mps or 0) < 0.05, 10, "holding")
    assert boat.state().armed is True


def near_state(boat: MavlinkAdapter, point: tuple[float, float], metres: float) -> bool:
    here = boat.state().position
    return here is not None and distance_m(here, point) < metres


async def test_low_battery_brings_the_boat_home(make_rig: RigFactory):
    # 27 % and 240 %/min at full effort (a fifth of it idle) and 4x: below 25 % within
    # a second of arming. Armed, the boat counts as out: it is brought home.
    rig = await make_rig(
        simulator={**SIM, "battery_pct": 27, "drain_pct_per_min": 240}, low_battery_pct=25
    )
    ws = await join(rig)
    await arm(ws)
    await watch(ws, lambda d: d["mode"] == "RTL", 10, "the low-battery return")
    [data] = [d for n, d in rig.events if n == "low_battery"]
    assert data["action"] == "return_to_home" and data["battery"] < 25
    ack = await command(ws, 2, "forward", speed_mps=3)
    assert ack["code"] == "low_battery" and "returning home" in ack["error"]
    await ws.close()


async def test_a_dead_agent_leaves_the_boat_to_ardurovers_own_failsafe():
    """A real deployment's path: the adapter reaches an autopilot it did not start.
    When the agent dies its heartbeats stop, and ArduRover's GCS fail-safe
    (FS_GCS_ENABLE=1: 2 s of silence, then FS_TIMEOUT) does FS_ACTION=1: RTL."""
    with simulator_listening(
        "--vehicle-class", "boat",
        "--home", f"{ORIGIN[0]},{ORIGIN[1]}", "--speedup", "4",
        "--param", "FS_GCS_ENABLE=1", "--param", "FS_ACTION=1", "--param", "WP_SPEED=4",
    ) as (_, address):  # fmt: skip
        boat = adapter_create(
            "mavlink", {"vehicle_class": "boat", "connection": address, "close_action": "none"}
        )
        assert isinstance(boat, RoverAdapter)
        async with boat:
            assert await boat.check_failsafe_params("return_to_home") == []
            [problem] = await boat.check_failsafe_params("stop")
            assert "does RTL (FS_ACTION=1) but the task expects stop" in problem
            assert boat.gcs_sysid_param == "SYSID_MYGCS"
            await boat.execute("arm", {})
            away = offset(ORIGIN, 80, 0)
            await boat.execute("go_to_waypoint", {"lat": away[0], "lon": away[1]})
            await poll(lambda: not near_state(boat, ORIGIN, 10), 10, "10 m out")
        gone = time.monotonic()
        # The agent is gone (close_action "none": like a crash). Listen as another GCS.
        with ground_station(address) as observer:
            modes = await modes_until(
                observer, until=11, within=10, vehicle_type=MAV.MAV_TYPE_SURFACE_BOAT
            )
        assert 11 in modes, f"no RTL after the agent died; modes seen {modes}"
        # 2 s of silence, then FS_TIMEOUT's 1.5 s, counted from the agent's last heartbeat.
        assert time.monotonic() - gone > 2.0


# --- options ------------------------------------------------------------------------------


def test_bad_boat_options_are_refused_naming_the_option(capsys: pytest.CaptureFixture[str]):
    boat = {"vehicle_class": "boat"}
    for bad, named in (
        ({**boat, "takeoff_default_m": 5}, "unknown key takeoff_default_m"),
        ({**boat, "velocity_frame": "body_ned"}, "unknown key velocity_frame"),
        ({**boat, "close_action": "land"}, "close_action: a boat cannot land"),
        ({**boat, "turn_rate_deg_s": 120}, "turn_rate_deg_s: above max_turn_rate_deg_s"),
        ({**boat, "max_speed_mps": 60}, "max_speed_mps: must be <= 50"),
        ({"vehicle_class": "submarine"}, "vehicle_class: one of copter, rover, boat"),
    ):
        with pytest.raises(ValueError, match=re.escape(named)):
            MavlinkConfig.from_options(bad)
    for params, vehicle, named in (
        ({"params": {"WPNAV_SPEED": 500}}, "boat", "ArduRover 4.5 has no parameter WPNAV_SPEED"),
        ({"params": {"FS_ACTION": 1}}, "copter", "ArduCopter 4.5 has no parameter FS_ACTION"),
        ({"current_mps": 9}, "boat", "simulator.current_mps: must be <= 5"),
        ({"current_mps": 0.5}, "copter", "unknown key current_mps"),
        ({}, "rover", "plays a copter or a boat, not a rover"),
    ):
        with pytest.raises(ValueError, match=re.escape(named)):
            simulator_command(params, home=ORIGIN, vehicle_class=vehicle)
    # FS_GCS_TIMEOUT is ArduRover's from 4.7 only.
    assert "--param" in simulator_command(
        {"firmware": "4.7", "params": {"FS_GCS_TIMEOUT": 3}}, home=ORIGIN, vehicle_class="boat"
    )
    with pytest.raises(
        ValueError, match=re.escape("ArduRover 4.5 has no parameter FS_GCS_TIMEOUT")
    ):
        simulator_command({"params": {"FS_GCS_TIMEOUT": 3}}, home=ORIGIN, vehicle_class="boat")
    with pytest.raises(SystemExit):
        parse_args(["--current", "0.5,90"])
    assert "--current is a boat's" in capsys.readouterr().err


async def test_the_copter_is_still_the_default_and_flies():
    async with simulator_running(
        "mavlink", {"origin": [40.6306, -8.6588], "simulator": SIM}
    ) as simulation:
        drone = adapter_create("mavlink", simulation.options)
        assert isinstance(drone, CopterAdapter)
        async with drone:
            await drone.execute("take_off", {"altitude_m": 2})
            await poll(lambda: (drone.t.alt or 0) > 1.8, 10, "2 m")
            assert drone.t.mav_type == MAV.MAV_TYPE_QUADROTOR and drone.state().alt is not None


# --- limits, measured at real speed ------------------------------------------------------

#: Stated in docs/vehicles/boat.md: a boat at 4 m/s with ``forward`` held ends at most
#: this far outside its geofence (it stops the fence's margin inside it) ...
BOAT_FENCE_MARGIN_M = 1.0
#: ... and one sent out at 4 m/s by another ground station at most this far.
BOAT_UNCOMMANDED_FENCE_MARGIN_M = 2.5


class Farthest(Sampler):
    """The boat's greatest distance from ``centre``, sampled every 20 ms."""

    def __init__(self, boat: MavlinkAdapter, centre: tuple[float, float]) -> None:
        self.boat, self.centre, self.value = boat, centre, 0.0

    def sample(self) -> None:
        here = self.boat.state().position
        if here is not None:
            self.value = max(self.value, distance_m(self.centre, here))


class Fastest(Sampler):
    """The boat's greatest ground speed, sampled every 20 ms."""

    def __init__(self, boat: MavlinkAdapter) -> None:
        self.boat, self.value = boat, 0.0

    def sample(self) -> None:
        self.value = max(self.value, self.boat.t.speed or 0.0)


async def test_a_held_forward_key_stops_the_boat_inside_its_fence(make_rig: RigFactory):
    radius = 40.0
    task = make_task(geofence_center=ORIGIN, geofence_radius_m=radius)
    rig = await make_rig(task, simulator={"speedup": 1, "heading_deg": 180})  # south: water
    ws = await join(rig)
    await arm(ws)
    seq, refused, accepted_after = 2, 0, 0
    async with Farthest(rig.boat, ORIGIN) as farthest:
        end = time.monotonic() + 25
        while time.monotonic() < end:
            ack = await command(ws, seq, "forward", speed_mps=4.0)
            seq += 1
            refused += not ack["ok"]
            accepted_after += bool(refused and ack["ok"])
            if not ack["ok"]:
                assert ack["code"] == "geofence", ack
            await asyncio.sleep(0.1)
        await watch(ws, lambda d: d["speed"] < 0.05, 15, "stopped")
    print(f"\nboat, forward at 4 m/s to a {radius:g} m fence: farthest {farthest.value:.2f} m")
    assert refused and accepted_after == 0
    assert farthest.value <= radius + BOAT_FENCE_MARGIN_M, farthest.value
    assert not rig.reported("envelope_breach")
    await ws.close()


async def test_sent_out_by_another_ground_station_the_boat_is_caught_on_its_way(
    make_rig: RigFactory,
):
    radius = 40.0
    task = make_task(geofence_center=ORIGIN, geofence_radius_m=radius)
    rig = await make_rig(task, max_speed_mps=4, simulator={"speedup": 1, "heading_deg": 180})
    ws = await join(rig)
    await arm(ws)
    gcs = mavutil.mavlink_connection(rig.boat.config.connection, source_system=200)
    try:
        async with Farthest(rig.boat, ORIGIN) as farthest:
            gcs.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            sent_off(gcs, offset(ORIGIN, -150.0, 0.0), 0, change_mode=True)
            await watch(ws, lambda d: bool(rig.reported("envelope_breach")), 60, "the envelope")
            await watch(
                ws,
                lambda d: distance_m(ORIGIN, point(d["location"])) < radius and d["speed"] < 0.1,
                60,
                "back inside, holding",
            )
    finally:
        gcs.close()
    [breach] = rig.reported("envelope_breach")
    print(
        f"\nboat sent out at 4 m/s by another ground station, {radius:g} m fence: caught at "
        f"{breach['value']:.2f} m, at most {farthest.value:.2f} m out"
    )
    assert farthest.value <= radius + BOAT_UNCOMMANDED_FENCE_MARGIN_M, farthest.value
    await ws.close()


async def test_a_waypoint_at_the_autopilots_own_speed_keeps_the_boat_to_the_limit(
    make_rig: RigFactory,
):
    """Speed 0 asks for ArduRover's own WP_SPEED (5 m/s here), faster than the task's
    2 m/s: the gate sends the limit instead (after the position, as ArduRover takes
    it), and the boat never breaks it."""
    rig = await make_rig(make_task(max_speed_mps=2.0), simulator={"speedup": 1})
    ws = await join(rig)
    await arm(ws)
    # 25 m: at 1 m/s/s either way, far enough to reach 5 m/s were the limit not sent.
    target = offset(ORIGIN, -25, 0)
    async with Fastest(rig.boat) as fastest:
        ack = await command(ws, 2, "go_to_waypoint", lat=target[0], lon=target[1], speed_mps=0)
        assert ack["ok"], ack
        await watch(
            ws,
            lambda d: distance_m(target, point(d["location"])) < 3 and d["speed"] < 0.1,
            60,
            "arrived",
        )
    print(f"\nboat, 2 m/s limit, a waypoint at speed 0: fastest {fastest.value:.2f} m/s")
    assert fastest.value <= 2.0 + 0.2, fastest.value
    assert not rig.reported("envelope_breach")
    await ws.close()


async def test_too_fast_on_its_way_the_boat_slows_down_as_ardurover_allows(
    make_rig: RigFactory,
):
    """Another ground station sends the boat off at ArduRover's own WP_SPEED (5 m/s
    here) under a 2 m/s limit: on its way to a position ArduRover takes DO_CHANGE_SPEED,
    so the envelope slows it there."""
    rig = await make_rig(make_task(max_speed_mps=2.0), simulator={"speedup": 1})
    ws = await join(rig)
    await arm(ws)
    gcs = mavutil.mavlink_connection(rig.boat.config.connection, source_system=200)
    try:
        gcs.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        sent_off(gcs, offset(ORIGIN, -150, 0), 0, change_mode=True)
        await watch(ws, lambda d: bool(rig.reported("envelope_restored")), 30, "slowed down")
    finally:
        gcs.close()
    [breach] = rig.reported("envelope_breach")
    assert breach["limit"] == "speed" and breach["action"] == "1.6 m/s at most"
    data = await watch(ws, lambda d: True, 2, "telemetry")
    assert data["speed"] <= 2.0 and data["mode"] == "GUIDED"
    await ws.close()
