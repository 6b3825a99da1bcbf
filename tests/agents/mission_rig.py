"""The rescue drone of the mission tests: the MAVLink simulator and the pieces the Agent
wires together for missions (adapter, ControlHub, MissionControl, ThermalFeed), with its
task and options (test_mission, test_mission_parcel).

``tests/agents/conftest.py`` hands the rigs out as the ``make_mission_rig`` fixture.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from agents.control import ControlHub, ControlServer
from agents.mission import MissionControl
from agents.protocol import (
    VehicleTask,
    generate_keypair,
    load_private_key,
    load_public_key,
)
from agents.simulation import simulator_running
from agents.thermal import SyntheticSeaThermal, ThermalFeed
from agents.vehicles.mavlink.adapter import MavlinkAdapter
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


def make_task(mission: dict[str, Any] | None, session: str = "s-1", **limits: Any) -> VehicleTask:
    return task_for(
        VEHICLE,
        (),
        session=session,
        ttl=60,
        mission=mission,
        **{"failsafe_action": "return_to_home", "max_altitude_m": 60, **limits},
    )


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
    feed: ThermalFeed
    reports: list[tuple[str, str | None, dict[str, Any]]] = field(default_factory=list)
    server: ControlServer | None = None

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
    """Build rigs: ``await build(persons=None, *, control=False, **options)`` starts a
    simulator (:func:`drone_options`), the drone on it, a hub, missions and a synthetic
    thermal feed seeing ``persons`` (and a control server with ``control``); everything
    is closed at the end, the simulators last."""
    opened: list[Rig] = []
    simulators = contextlib.AsyncExitStack()

    async def build(
        persons: list[Any] | None = None, *, control: bool = False, **options: Any
    ) -> Rig:
        simulation = await simulators.enter_async_context(
            simulator_running("mavlink", drone_options(**options))
        )
        drone = adapter_create("mavlink", simulation.options)
        assert isinstance(drone, MavlinkAdapter)
        await drone.start()
        feed = ThermalFeed(SyntheticSeaThermal(drone.state, persons=persons or [], seed=3))
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
            hub=hub, adapter=drone, report=lambda e, s, d: reports.append((e, s, d)), thermal=feed
        )
        holder.append(missions)
        rig = Rig(drone, hub, missions, feed, reports)
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
            await rig.feed.close()
            await rig.drone.close()
        await simulators.aclose()
