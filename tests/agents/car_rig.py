"""The simulated car behind the agent's control hub and its WebSocket server, and the
task and grants that let a user drive it: the rig of the control tests (test_control,
test_rtc, test_protocol_schema) and of the data-channel benchmarks' tests.

``tests/agents/conftest.py`` hands it to tests as the ``rig`` fixture.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Any

from agents.control import ControlHub, ControlServer
from agents.protocol import (
    VehicleTask,
    generate_keypair,
    load_private_key,
    load_public_key,
)
from agents.simulation import adapter_simulated
from agents.vehicles.car.adapter import CarAdapter
from agents.vehicles.car.sim.world import CarWorld
from tests.agents.documents import grant_for, task_for

PRIVATE_PEM, PUBLIC_PEM = generate_keypair()
PRIVATE = load_private_key(PRIVATE_PEM)
VEHICLE = "car-test-1"
SESSION = "session-1"
CAR_COMMANDS = (
    "forward",
    "backward",
    "left",
    "right",
    "stop",
    "camera_up",
    "camera_down",
    "camera_left",
    "camera_right",
)
#: The car of the ``rig`` fixture: with the camera arm and the distance sensor.
CAR_OPTIONS = {"camera_arm": True, "distance_sensor": True, "origin": [40.63, -8.65]}


@dataclass
class Rig:
    hub: ControlHub
    server: ControlServer
    car: CarAdapter
    world: CarWorld
    reports: list[tuple[str, str | None, dict[str, Any]]] = field(default_factory=list)
    #: When each report was made (monotonic), in the same order.
    stamps: list[float] = field(default_factory=list)

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.server.port}/"

    def events(self, name: str) -> list[dict[str, Any]]:
        return [data for event, _, data in self.reports if event == name]

    def report(self, event: str, session: str | None, data: dict[str, Any]) -> None:
        self.reports.append((event, session, data))
        self.stamps.append(time.monotonic())


def make_task(*, session: str = SESSION, user: str = "alice", **limits: Any) -> VehicleTask:
    return task_for(
        VEHICLE,
        CAR_COMMANDS,
        session=session,
        user=user,
        ttl=60,
        **{"link_loss_timeout_ms": 500, "failsafe_action": "stop", **limits},
    )


def make_grant(
    *,
    session: str = SESSION,
    user: str = "alice",
    role: str = "controller",
    vehicle: str = VEHICLE,
    ttl: float = 60,
    key: Any = PRIVATE,
) -> str:
    return grant_for(vehicle, CAR_COMMANDS, key, session=session, user=user, role=role, ttl=ttl)


@contextlib.asynccontextmanager
async def car_rig(options: dict[str, Any] | None = None, **limits: Any) -> AsyncIterator[Rig]:
    """The simulated car (``options``, :data:`CAR_OPTIONS` by default) behind a
    ControlHub and its ControlServer on a free port, with ``make_task(**limits)``
    accepted; everything is closed at the end."""
    rigs: list[Rig] = []
    async with adapter_simulated("car", CAR_OPTIONS if options is None else options) as (
        car,
        simulation,
    ):
        assert isinstance(car, CarAdapter)
        hub = ControlHub(
            vehicle_id=VEHICLE,
            vehicle_name="car-1",
            public_key=load_public_key(PUBLIC_PEM),
            adapter=car,
            report=lambda e, s, d: rigs[0].report(e, s, d),
        )
        async with hub, ControlServer(hub) as server:
            rigs.append(Rig(hub, server, car, simulation.simulator))
            hub.task_accept(make_task(**limits))
            yield rigs[0]
