"""The quadcopter on the MAVLink simulator behind the agent's control hub and its
WebSocket server, as the MAVLink tests fly it, and what they share: the simulator
started as its own process (``python -m agents sim mavlink``), a controller's telemetry
watched, a condition polled.

``tests/agents/conftest.py`` hands the rigs out as the ``make_quad_rig`` fixture.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from websockets.asyncio.client import ClientConnection, connect

from agents.control import ControlHub, ControlServer
from agents.protocol import (
    Limits,
    UserGrant,
    VehicleTask,
    generate_keypair,
    load_private_key,
    load_public_key,
    new_nonce,
)
from agents.simulation import simulator_running
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.registry import adapter_create
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
    now = time.time()
    return VehicleTask(
        session_id="session-1",
        vehicle_id=VEHICLE,
        user="alice",
        allowed_commands=DRONE_COMMANDS,
        limits=Limits(
            **{
                "link_loss_timeout_ms": 500,
                "failsafe_action": "return_to_home",
                "max_altitude_m": 6,
                **limits,
            }
        ),
        issued_at=now,
        expires_at=now + 120,
        nonce=new_nonce(),
    )


def make_grant() -> str:
    now = time.time()
    return UserGrant(
        session_id="session-1",
        vehicle_id=VEHICLE,
        user="alice",
        role="controller",
        allowed_commands=DRONE_COMMANDS,
        issued_at=now - 1,
        expires_at=now + 120,
        nonce=new_nonce(),
    ).sign(PRIVATE)


def drone_options(**overrides: Any) -> dict[str, Any]:
    return {
        "origin": list(HOME),
        "simulator": SIM,
        "heartbeat_timeout_s": 1.5,
        "command_timeout_s": 2.0,
        **overrides,
    }


RigFactory = Callable[..., Awaitable[Rig]]


@contextlib.asynccontextmanager
async def rigs() -> AsyncIterator[RigFactory]:
    """Build rigs (simulator + drone + hub + server + task); everything is closed at
    the end, the simulators last."""
    opened: list[tuple[ControlServer, ControlHub, MavlinkAdapter]] = []
    simulators = contextlib.AsyncExitStack()

    async def build(task: VehicleTask | None = None, **options: Any) -> Rig:
        simulation = await simulators.enter_async_context(
            simulator_running("mavlink", drone_options(**options))
        )
        drone = adapter_create("mavlink", simulation.options)
        assert isinstance(drone, MavlinkAdapter)
        events: list[tuple[str, dict[str, Any]]] = []
        drone.on_event = lambda name, data: events.append((name, data))
        await drone.start()
        reports: list[tuple[str, str | None, dict[str, Any]]] = []
        hub = ControlHub(
            vehicle_id=VEHICLE,
            vehicle_name="quad-1",
            public_key=load_public_key(PUBLIC_PEM),
            adapter=drone,
            report=lambda e, s, d: reports.append((e, s, d)),
        )
        await hub.start()
        server = ControlServer(hub)
        await server.start()
        opened.append((server, hub, drone))
        hub.task_accept(task or make_task())
        return Rig(hub, server, drone, simulation.simulator, reports, events)

    try:
        yield build
    finally:
        for server, hub, drone in reversed(opened):
            await server.close()
            await hub.close()
            await drone.close()
        await simulators.aclose()


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


def start_simulator(*args: str) -> subprocess.Popen[str]:
    """``python -m agents sim mavlink ARGS`` with its stdout (the READY line) piped."""
    return subprocess.Popen(
        [sys.executable, "-m", "agents", "sim", "mavlink", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
