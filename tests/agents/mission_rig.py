"""The rescue drone of the mission tests: the MAVLink simulator and the pieces the Agent
wires together for missions (adapter, ControlHub, MissionControl, ThermalFeed), with its
task and options, and a small fake platform for whole-agent tests (tests/agents/missions/).

``tests/agents/conftest.py`` hands the rigs out as the ``make_mission_rig`` fixture.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jwt
import pytest
from websockets.asyncio.server import ServerConnection, serve

from agents.artifacts import ArtifactStore
from agents.config import AgentConfig, ControlConfig
from agents.control import ControlHub, ControlServer
from agents.geo import distance_m, offset
from agents.missions.control import MissionControl
from agents.missions.search.thermal import SyntheticSeaThermal, ThermalFeed
from agents.missions.spec import MissionSpec
from agents.protocol import (
    PROTOCOL_VERSION,
    TOKEN_TYPES,
    VehicleTask,
    generate_keypair,
    key_thumbprint,
    load_private_key,
    load_public_key,
)
from agents.runtime import Agent
from agents.simulation import simulator_running
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.mavlink.dialect import MAV, mavutil
from agents.vehicles.registry import adapter_create
from tests.agents import mavlink_rig
from tests.agents.documents import grant_for, task_for

PRIVATE_PEM, PUBLIC_PEM = generate_keypair()
PRIVATE = load_private_key(PRIVATE_PEM)
VEHICLE = "rescue-drone-1"
#: The rescue drone takes off where the MAVLink tests' quadcopter does.
HOME = mavlink_rig.HOME
#: 6x flight time: quick, yet the simulator's 50 Hz physics stays steady when the
#: machine is busy (a starved step covers up to 0.2 s x speedup of flight).
SIM = {"speedup": 6, "params": {"WPNAV_SPEED": 1000, "RTL_ALT": 1500}}


def make_task(
    mission: MissionSpec | dict[str, Any] | None, session: str = "s-1", **limits: Any
) -> VehicleTask:
    return task_for(
        VEHICLE,
        (),
        session=session,
        ttl=60,
        mission=mission,
        **{"failsafe_action": "return_to_home", "max_altitude_m": 60, **limits},
    )


def raw_task_token(mission: Any, session: str = "s-1") -> str:
    """A task token carrying ``mission`` as it is (not decoded into a spec), signed with
    the platform's key as :meth:`VehicleTask.sign` signs: for what the agent must refuse."""
    claims = make_task(None, session).to_payload()
    claims["mission"] = mission
    headers = {"kid": key_thumbprint(PRIVATE), "typ": TOKEN_TYPES["vehicle_task"]}
    return jwt.encode(claims, PRIVATE, algorithm="EdDSA", headers=headers)


def make_grant() -> str:
    """alice's controller grant for the missions' session (s-1): no commands."""
    return grant_for(VEHICLE, (), PRIVATE, session="s-1", ttl=60)


def drone_options(**overrides: Any) -> dict[str, Any]:
    return {
        "origin": list(HOME),
        "simulator": SIM,
        "payload": {"method": "gripper"},
        **overrides,
    }


def releases(drone: MavlinkAdapter) -> int:
    """Payload releases the autopilot performed: it says so in a STATUSTEXT each time
    (the adapter keeps the recent ones)."""
    return sum(1 for _, _, text in drone.texts if text == "Gripper load released")


@dataclass
class Rig:
    drone: MavlinkAdapter
    hub: ControlHub
    missions: MissionControl
    #: The synthetic thermal camera (None when the test gave the rig other sensors).
    feed: ThermalFeed | None
    reports: list[tuple[str, str | None, dict[str, Any]]] = field(default_factory=list)
    server: ControlServer | None = None
    #: Where the missions' files are kept (a rig built with ``artifacts``).
    store: ArtifactStore | None = None

    def kept(self, pattern: str = "*/*") -> list[Path]:
        """The files the missions keep waiting on disk (nobody uploads them), sorted."""
        assert self.store is not None, "a rig built without artifacts keeps no files"
        return sorted(p for p in self.store.directory.glob(pattern) if p.suffix != ".json")

    def accept(self, task: VehicleTask) -> None:
        """What Agent._task does with a verified task."""
        self.hub.task_accept(task)
        self.missions.task_accepted(task)

    def events(self, name: str | None = None) -> list[tuple[str, dict[str, Any]]]:
        return [(e, d) for e, _, d in self.reports if name is None or e == name]

    def progress(self) -> list[tuple[str, int | None]]:
        return [(d["phase"], d["waypoint"]) for _, d in self.events("mission_progress")]

    async def event(self, name: str, within: float, count: int = 1) -> dict[str, Any]:
        """The ``count``-th ``name`` event, waiting for it."""
        deadline = time.monotonic() + within
        while time.monotonic() < deadline:
            found = self.events(name)
            if len(found) >= count:
                return found[count - 1][1]
            await asyncio.sleep(0.05)
        raise AssertionError(f"no {name} within {within} s; reports: {self.reports}")


RigFactory = Callable[..., Awaitable[Rig]]


@contextlib.asynccontextmanager
async def rigs() -> AsyncIterator[RigFactory]:
    """Build rigs: ``await build(persons=None, *, control=False, sensors=None,
    artifacts=None, autopilot=None, **options)`` starts a simulator
    (:func:`drone_options`; given ``autopilot``, the options of a drone on a simulator
    running already, none is started: a restarted agent's), the drone on it, a hub,
    missions and a synthetic thermal feed seeing ``persons`` (or, with ``sensors``, the
    agent's sensors that ``sensors(drone)`` returns instead), a control server with
    ``control``, the missions' files kept in the folder ``artifacts`` (an ArtifactStore
    with nobody to upload to); everything is closed at the end, the simulators last."""
    opened: list[Rig] = []
    simulators = contextlib.AsyncExitStack()

    async def build(
        persons: list[Any] | None = None,
        *,
        control: bool = False,
        sensors: Callable[[MavlinkAdapter], dict[str, Any]] | None = None,
        artifacts: Path | None = None,
        autopilot: dict[str, Any] | None = None,
        **options: Any,
    ) -> Rig:
        if autopilot is None:
            simulation = await simulators.enter_async_context(
                simulator_running("mavlink", drone_options(**options))
            )
            autopilot = simulation.options
        drone = adapter_create("mavlink", autopilot)
        assert isinstance(drone, MavlinkAdapter)
        await drone.start()
        feed: ThermalFeed | None = None
        if sensors is None:
            feed = ThermalFeed(SyntheticSeaThermal(drone.state, persons=persons or [], seed=3))
        store = None
        if artifacts is not None:
            store = await simulators.enter_async_context(ArtifactStore(directory=artifacts))
        reports: list[tuple[str, str | None, dict[str, Any]]] = []
        holder: list[MissionControl] = []
        hub = ControlHub(
            vehicle_id=VEHICLE,
            vehicle_name="rescue-1",
            public_key=load_public_key(PUBLIC_PEM),
            adapter=drone,
            report=lambda e, s, d: reports.append((e, s, d)),
            on_task_end=lambda task: holder[0].task_ended(task),
        )
        await hub.start()
        missions = MissionControl(
            hub=hub,
            adapter=drone,
            report=lambda e, s, d: reports.append((e, s, d)),
            sensors={"thermal": feed} if sensors is None else sensors(drone),
            artifacts=store,
        )
        holder.append(missions)
        rig = Rig(drone, hub, missions, feed, reports, store=store)
        if control:
            rig.server = ControlServer(hub)
            await rig.server.start()
        opened.append(rig)
        return rig

    try:
        yield build
    finally:
        for rig in reversed(opened):
            await rig.missions.close()
            if rig.server is not None:
                await rig.server.close()
            await rig.hub.close()
            if rig.feed is not None:
                await rig.feed.close()
            await rig.drone.close()
        await simulators.aclose()


# --- the missions flown in the tests ----------------------------------------------------

#: Holding a position: the arrival radius (3 m) plus the simulator's wobble.
HOLD_M = 5.0
#: A 120 x 80 m search area starting 20 m north of home, lines 30 m apart at 40 m
#: (the camera sees a strip 43 m wide): (north, east) metres from home.
AREA_WAYPOINTS = [(35, 0), (35, 120), (65, 120), (65, 0), (95, 0), (95, 120)]
WAYPOINTS = [list(offset(HOME, n, e)) for n, e in AREA_WAYPOINTS]
PERSON = offset(HOME, 72, 40)  # under the second line, seen flying west


def search(mission_id: str = "m-search", **overrides: Any) -> dict[str, Any]:
    return {
        "kind": "search",
        "id": mission_id,
        "altitude_m": 40,
        "speed_mps": 10,
        "waypoints": WAYPOINTS,
        "start_index": 0,
        "min_confidence": 0.6,
        **overrides,
    }


def delivery(mission_id: str = "m-drop", **overrides: Any) -> dict[str, Any]:
    return {
        "kind": "delivery",
        "id": mission_id,
        "target": list(offset(HOME, 30, 20)),
        "altitude_m": 30,
        "drop_altitude_m": 5,
        "speed_mps": 10,
        **overrides,
    }


async def until_near(
    drone: MavlinkAdapter, point: tuple[float, ...], metres: float, within: float = 5.0
) -> None:
    """Wait for the drone to be within ``metres`` of ``point`` (it overshoots a little
    at corners and settles)."""
    deadline = time.monotonic() + within
    while True:
        here = drone.state().position
        if here is not None and distance_m(here, (point[0], point[1])) <= metres:
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"the drone is at {here}, not within {metres} m of {point}")
        await asyncio.sleep(0.05)


# --- an agent killed mid-mission -------------------------------------------------------


async def agent_dies(rig: Rig) -> str:
    """The agent is killed mid-mission: its runner stops where it is and its link to
    the autopilot goes silent, without a goodbye (a simulated vehicle's close_action is
    none: nothing more is sent). Returns the autopilot's address."""
    runner = rig.missions.runner
    assert runner is not None
    runner.cancel()
    await runner.wait()
    await rig.drone.close()
    return str(rig.drone.options["connection"])


async def listen(address: str, done: Callable[[Any], bool], *, within: float) -> list[Any]:
    """Another ground station (system 200, which the autopilot does not take for its
    GCS) listens to the autopilot until ``done(message)``; returns what it heard."""
    gcs = mavutil.mavlink_connection(address, source_system=200)
    heard: list[Any] = []
    deadline = time.monotonic() + within
    try:
        while time.monotonic() < deadline:
            gcs.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            msg = await asyncio.to_thread(gcs.recv_match, blocking=True, timeout=0.3)
            if msg is None or msg.get_srcSystem() != 1:
                continue
            heard.append(msg)
            if done(msg):
                return heard
    finally:
        gcs.close()
    raise AssertionError(f"not done within {within} s; heard {heard[-20:]}")


def landed_at_home(msg: Any) -> bool:
    return msg.get_type() == "HEARTBEAT" and not msg.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED


def texts(heard: list[Any]) -> list[str]:
    return [m.text for m in heard if m.get_type() == "STATUSTEXT"]


def last_position(heard: list[Any]) -> tuple[float, float]:
    where = [m for m in heard if m.get_type() == "GLOBAL_POSITION_INT"][-1]
    return where.lat / 1e7, where.lon / 1e7


# --- a fake platform for whole-agent tests ----------------------------------------------


class FakePlatform:
    """The platform's side of the uplink, enough for one agent: answers ``hello`` with
    ``welcome`` and records everything the agent sends; ``send`` pushes a message."""

    def __init__(self) -> None:
        self.received: list[dict[str, Any]] = []
        self.ws: ServerConnection | None = None
        self.registered = asyncio.Event()
        self.port = 0

    async def handle(self, ws: ServerConnection) -> None:
        hello = json.loads(await ws.recv())
        assert hello["type"] == "hello" and hello["vehicle_id"] == VEHICLE
        await ws.send(
            json.dumps({"type": "welcome", "v": PROTOCOL_VERSION, "heartbeat_interval_s": 1})
        )
        self.ws = ws
        with contextlib.suppress(Exception):
            async for raw in ws:
                msg = json.loads(raw)
                self.received.append(msg)
                if msg["type"] == "profile":
                    self.registered.set()

    async def send(self, msg: dict[str, Any]) -> None:
        assert self.ws is not None
        await self.ws.send(json.dumps(msg))

    async def task(self, mission: dict[str, Any] | None, session: str = "s-1") -> None:
        """A freshly signed task (new nonce), as the platform re-sends one."""
        await self.send({"type": "task", "token": make_task(mission, session).sign(PRIVATE)})

    async def task_unchecked(self, mission: dict[str, Any], session: str = "s-1") -> None:
        """A task signed with ``mission`` as given, unchecked: what a platform that
        knows other missions (or a faulty one) could sign."""
        await self.send({"type": "task", "token": raw_task_token(mission, session)})

    def events(self, name: str) -> list[dict[str, Any]]:
        return [m["data"] for m in self.received if m["type"] == "event" and m["event"] == name]

    def of_type(self, kind: str) -> list[dict[str, Any]]:
        return [m for m in self.received if m["type"] == kind]

    async def wait(self, predicate: Callable[[], Any], within: float, what: str) -> Any:
        deadline = time.monotonic() + within
        while time.monotonic() < deadline:
            value = predicate()
            if value:
                return value
            await asyncio.sleep(0.05)
        raise AssertionError(f"timed out waiting for {what}; received {self.received}")


@contextlib.asynccontextmanager
async def agent_with_platform(
    thermal: dict[str, Any] | None, video: dict[str, Any] | None = None
) -> AsyncIterator[tuple[Agent, FakePlatform]]:
    """The whole Agent of the rescue drone (its ``thermal`` section and ``video``, if
    any) on its own simulator, registered with a :class:`FakePlatform`; cancelled at
    the end."""
    platform = FakePlatform()
    async with (
        contextlib.AsyncExitStack() as stack,
        serve(platform.handle, "127.0.0.1", 0) as server,
    ):
        port = next(iter(server.sockets)).getsockname()[1]
        simulation = await stack.enter_async_context(simulator_running("mavlink", drone_options()))
        config = AgentConfig(
            platform_url=f"ws://127.0.0.1:{port}",
            vehicle_id=VEHICLE,
            credential="secret",
            platform_public_key=PUBLIC_PEM,
            adapter="mavlink",
            adapter_options=simulation.options,
            control=ControlConfig(host="127.0.0.1", port=0),
            video=video,
            sensors={"thermal": thermal} if thermal is not None else {},
            name="rescue-1",
        )
        agent = Agent(config)
        run = asyncio.create_task(agent.run())
        try:
            await asyncio.wait_for(platform.registered.wait(), 30)
            yield agent, platform
        finally:
            run.cancel()
            with pytest.raises(asyncio.CancelledError):
                await run


#: Missions the agent cannot fly, and what its refusal of the task says (``field
#: 'mission.<path>': <problem>``): an unknown or missing kind, a wrong type, a value out
#: of range, a rule across fields, an unknown field.
MALFORMED: list[tuple[Any, str]] = [
    ({"kind": "rescue", "id": "m"}, "mission.kind"),
    ({"id": "m", "altitude_m": 40}, "mission.kind': is missing"),
    ("search", "got `str`"),
    (search(altitude_m=-5), "mission.altitude_m"),
    (search(altitude_m="high"), "mission.altitude_m"),
    (search(waypoints=[]), "mission.waypoints"),
    (search(waypoints=[[100, 0]]), "mission.waypoints[0]"),
    (search(waypoints=[[40.6, -8.7, 3]]), "mission.waypoints[0]"),
    (search(start_index=6), "mission.start_index"),
    (search(start_index=True), "mission.start_index"),
    (search(min_confidence=2), "mission.min_confidence"),
    (search(pattern="spiral"), "mission.pattern': is not known"),
    ({**search(), "altitude_m": None}, "mission.altitude_m"),
    (delivery(drop_altitude_m=40), "mission.drop_altitude_m"),
    (delivery(target="here"), "mission.target"),
    (delivery(speed_mps=0), "mission.speed_mps"),
    ({**delivery(), "id": ""}, "mission.id"),
    ({"kind": "return", "id": "h", "target": [0, 0]}, "mission.target': is not known"),
]
