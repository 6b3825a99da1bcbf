"""The quadcopter on the MAVLink simulator behind the agent's control hub and its
WebSocket server, as the MAVLink tests fly it, and what they share: the simulator
started as its own process (``python -m agents sim mavlink``) and another ground station
on it, a controller's telemetry watched, a condition polled.

``tests/agents/conftest.py`` hands the rigs out as the ``make_quad_rig`` fixture.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from websockets.asyncio.client import ClientConnection, connect

from agents.control import ControlHub, ControlServer
from agents.protocol import (
    VehicleTask,
    generate_keypair,
    load_private_key,
    load_public_key,
)
from agents.simulation import simulator_running
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.mavlink.copter import CopterAdapter
from agents.vehicles.mavlink.dialect import MAV, mavutil
from agents.vehicles.registry import adapter_create
from tests.agents.documents import grant_for, task_for
from tests.control import recv

ROOT = Path(__file__).resolve().parents[2]
PRIVATE_PEM, PUBLIC_PEM = generate_keypair()
PRIVATE = load_private_key(PRIVATE_PEM)
VEHICLE = "quad-test-1"
HOME = (40.6306, -8.6588)
DRONE_COMMANDS = (
    "arm",
    "disarm",
    "take_off",
    "up",
    "down",
    "rotate_left",
    "rotate_right",
    "front",
    "back",
    "left",
    "right",
    "land",
    "return_to_home",
    "go_to_waypoint",
)
#: Fast flights: 4x flight time, RTL at 6 m with a short loiter above home.
#: The tasks' link-loss timeout (see make_task).
LINK_LOSS_TIMEOUT_MS = 2000
SIM = {"speedup": 4, "params": {"RTL_ALT": 600, "RTL_LOIT_TIME": 500}}


@dataclass
class Rig:
    hub: ControlHub
    server: ControlServer
    drone: MavlinkAdapter
    #: The simulator's process (``python -m agents sim mavlink``).
    sim_process: subprocess.Popen[bytes]
    reports: list[tuple[str, str | None, dict[str, Any]]] = field(default_factory=list)
    events: list[tuple[str, dict[str, Any]]] = field(default_factory=list)

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.server.port}/"

    def reported(self, name: str) -> list[dict[str, Any]]:
        return [data for event, _, data in self.reports if event == name]

    def event_names(self) -> list[str]:
        return [name for name, _ in self.events]


def make_task(**limits: Any) -> VehicleTask:
    return task_for(
        VEHICLE,
        DRONE_COMMANDS,
        **{
            # Not 500 ms: a test's loop stalled that long by a loaded machine would trip
            # the fail-safe in tests about something else (the link-loss tests wait).
            "link_loss_timeout_ms": LINK_LOSS_TIMEOUT_MS,
            "failsafe_action": "return_to_home",
            "max_altitude_m": 6,
            **limits,
        },
    )


def make_grant() -> str:
    return grant_for(VEHICLE, DRONE_COMMANDS, PRIVATE)


def drone_options(**overrides: Any) -> dict[str, Any]:
    return {
        "origin": list(HOME),
        "simulator": SIM,
        "heartbeat_timeout_s": 1.5,
        "command_timeout_s": 2.0,
        **overrides,
    }


RigFactory = Callable[..., Awaitable[Rig]]
Reports = list[tuple[str, str | None, dict[str, Any]]]
Events = list[tuple[str, dict[str, Any]]]
A = TypeVar("A", bound=MavlinkAdapter)
R = TypeVar("R")


@contextlib.asynccontextmanager
async def control_rigs(
    rig: Callable[[ControlHub, ControlServer, A, subprocess.Popen[bytes], Reports, Events], R],
    *,
    adapter: type[A],
    options: Callable[..., dict[str, Any]],
    default_task: Callable[[], VehicleTask],
    vehicle_id: str,
    vehicle_name: str,
    public_pem: str,
) -> AsyncIterator[Callable[..., Awaitable[R]]]:
    """Build rigs of a vehicle on the MAVLink simulator, the quadcopter's (:func:`rigs`)
    or the boat's (test_mavlink_boat): ``await build(task=None, **overrides)`` starts a
    simulator with ``options(**overrides)``, the vehicle's ``adapter`` on it (its events
    recorded), a ControlHub trusting ``public_pem`` (its reports recorded) with ``task``
    (``default_task()`` when None) accepted, and the hub's ControlServer; returns
    ``rig(hub, server, vehicle, simulator process, reports, events)``. Everything is
    closed at the end, the simulators last."""
    opened: list[tuple[ControlServer, ControlHub, MavlinkAdapter]] = []
    simulators = contextlib.AsyncExitStack()

    async def build(task: VehicleTask | None = None, **overrides: Any) -> R:
        simulation = await simulators.enter_async_context(
            simulator_running("mavlink", options(**overrides))
        )
        vehicle = adapter_create("mavlink", simulation.options)
        assert isinstance(vehicle, adapter)
        events: Events = []
        vehicle.on_event = lambda name, data: events.append((name, data))
        await vehicle.start()
        reports: Reports = []
        hub = ControlHub(
            vehicle_id=vehicle_id,
            vehicle_name=vehicle_name,
            public_key=load_public_key(public_pem),
            adapter=vehicle,
            report=lambda e, s, d: reports.append((e, s, d)),
        )
        await hub.start()
        server = ControlServer(hub)
        await server.start()
        opened.append((server, hub, vehicle))
        hub.task_accept(task or default_task())
        return rig(hub, server, vehicle, simulation.simulator, reports, events)

    try:
        yield build
    finally:
        for server, hub, vehicle in reversed(opened):
            await server.close()
            await hub.close()
            await vehicle.close()
        await simulators.aclose()


def rigs() -> contextlib.AbstractAsyncContextManager[RigFactory]:
    """Build quadcopter rigs (:func:`control_rigs` with :func:`drone_options` and
    :func:`make_task`)."""
    return control_rigs(
        Rig,
        adapter=CopterAdapter,
        options=drone_options,
        default_task=make_task,
        vehicle_id=VEHICLE,
        vehicle_name="quad-1",
        public_pem=PUBLIC_PEM,
    )


TOPICS = [
    "altitude",
    "location",
    "heading",
    "flight_mode",
    "is_armed",
    "autopilot_link",
    "battery_level",
    "number_of_gps_satellites",
    "speed",
]


async def join(rig: Rig) -> ClientConnection:
    """alice's controller socket on the rig, subscribed to :data:`TOPICS` at 10 Hz."""
    ws = await connect(rig.url, compression=None, proxy=None)
    await ws.send(json.dumps({"type": "auth", "grant": make_grant()}))
    welcome = await recv(ws, "welcome")
    assert welcome["role"] == "controller"
    await ws.send(json.dumps({"type": "subscribe", "topics": TOPICS, "rate_hz": 10}))
    return ws


async def watch(
    ws: ClientConnection, until: Callable[[dict[str, Any]], bool], within: float, what: str
) -> dict[str, Any]:
    """Read the telemetry stream (staying a live controller: keepalives, pongs) until
    ``until(data)`` holds; returns that telemetry."""
    deadline = time.monotonic() + within
    last_keepalive = 0.0
    data: dict[str, Any] = {}
    while time.monotonic() < deadline:
        if time.monotonic() - last_keepalive > 0.1:
            await ws.send(json.dumps({"type": "keepalive"}))
            last_keepalive = time.monotonic()
        try:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 0.2))
        except TimeoutError:
            continue
        if msg["type"] == "ping":
            await ws.send(json.dumps({"type": "pong", "t": msg["t"]}))
        elif msg["type"] == "telemetry":
            data = msg["data"]
            if until(data):
                return data
    raise AssertionError(f"timed out waiting for {what}; last telemetry {data}")


async def poll(predicate: Callable[[], bool], within: float, what: str) -> None:
    """Check ``predicate`` every 50 ms until it holds."""
    for _ in range(int(within / 0.05)):
        if predicate():
            return
        await asyncio.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


@contextlib.contextmanager
def simulator_listening(*args: str) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """``python -m agents sim mavlink --listen udpin:127.0.0.1:0 ARGS``: the simulator in
    its own process on a free UDP port, as an autopilot the agent did not start. Yields
    the process and the address to reach it at (``udpout:127.0.0.1:PORT``, from its
    READY line). At the end it is sent SIGTERM; one still running 5 s later is killed
    and fails the test."""
    sim = subprocess.Popen(
        [sys.executable, "-m", "agents", "sim", "mavlink", "--listen", "udpin:127.0.0.1:0", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert sim.stdout is not None
        ready = sim.stdout.readline().split()
        assert ready and ready[0] == "READY", ready
        yield sim, ready[1].replace("udpin:", "udpout:")
    finally:
        sim.terminate()
        try:
            sim.wait(5)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.wait()
            raise AssertionError("the simulator was still running 5 s after SIGTERM") from None


@contextlib.contextmanager
def ground_station(address: str) -> Iterator[Any]:
    """Another ground station (system 200) on the autopilot at ``address``, as a second
    operator's laptop would be; closed at the end."""
    gcs = mavutil.mavlink_connection(address, source_system=200)
    try:
        yield gcs
    finally:
        gcs.close()


def sent_off(
    gcs: Any,
    point: tuple[float, float],
    alt_m: float,
    *,
    target: tuple[int, int] = (1, 1),
    change_mode: bool = False,
) -> None:
    """Another ground station (``gcs``) sends the vehicle to ``point`` at ``alt_m``
    (DO_REPOSITION, at the autopilot's own speed; ``change_mode``: to GUIDED first):
    a move no command of the agent's asked for."""
    flags = MAV.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE if change_mode else 0
    gcs.mav.command_int_send(
        target[0], target[1], MAV.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        MAV.MAV_CMD_DO_REPOSITION, 0, 0, -1, flags, 0, 0,
        round(point[0] * 1e7), round(point[1] * 1e7), alt_m,
    )  # fmt: skip


async def modes_until(
    gcs: Any, *, until: int, within: float, vehicle_type: int | None = None
) -> list[int]:
    """The autopilot's modes (``custom_mode``) in the heartbeats ``gcs`` sees (of
    ``vehicle_type`` only, when given), heartbeating itself, until mode ``until`` shows
    or ``within`` seconds passed."""
    modes: list[int] = []
    deadline = time.monotonic() + within
    while time.monotonic() < deadline and until not in modes:
        gcs.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        beat = await asyncio.to_thread(gcs.recv_match, type="HEARTBEAT", blocking=True, timeout=0.5)
        if beat is not None and (vehicle_type is None or beat.type == vehicle_type):
            modes.append(int(beat.custom_mode))
    return modes
