"""End to end over real sockets: platform (iouv.serve, Postgres, Redis) + agent + user.

The agent registers on its uplink, the platform assigns the car and deploys a signed
task, and a user holding the grant drives the simulated car point-to-point.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator
from typing import Any

import pytest
from websockets.asyncio.client import connect

from agents.runtime import Agent
from fleet.credentials import vehicle_issue_credential
from fleet.models import Vehicle
from services.assignment import session_request
from services.deployment import session_deploy
from services.models import Session
from tests import factories as f
from tests.agents.test_control import command, recv
from tests.servers import agent_running, db, platform_process, until

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
]
CAR_COMMANDS = ["forward", "backward", "left", "right", "stop", "camera_up", "camera_down"]


def _fleet() -> tuple[Vehicle, str, Any]:
    station = f.station()
    car_type = f.vehicle_type("ground", "car", name="Raspberry Pi car")
    car = f.vehicle(
        station=station,
        vtype=car_type,
        name="car-1",
        online=False,
        environments=["land"],
        features=["camera_arm", "obstacle_sensor"],
    )
    service = f.service(
        "drive-car",
        roles=[{"name": "vehicle", "kinds": ["ground"], "min_battery": 20}],
        allowed_commands=CAR_COMMANDS,
        failsafe_action="stop",
        link_loss_timeout_ms=500,
    )
    return car, vehicle_issue_credential(vehicle=car), service


@pytest.fixture
async def running() -> AsyncIterator[tuple[str, Agent, Vehicle, Any]]:
    car, credential, service = await db(_fleet)
    with platform_process() as base:
        async with agent_running(
            base=base,
            vehicle=car,
            credential=credential,
            adapter="car",
            options={
                "camera_arm": True,
                "distance_sensor": True,
                "origin": [f.HOME[0], f.HOME[1]],
            },
        ) as agent:
            yield base, agent, car, service


async def test_register_deploy_drive_and_unintentional_end(running):
    _base, agent, car, service = running

    async def registered() -> bool:
        v = await db(Vehicle.objects.get, pk=car.pk)
        return v.status == Vehicle.Status.IDLE and bool(v.control_url)

    await until(registered, what="the agent to register")
    vehicle = await db(Vehicle.objects.get, pk=car.pk)
    assert vehicle.control_url == agent.control_url
    assert {c["name"] for c in vehicle.profile["commands"]} >= set(CAR_COMMANDS)

    client_user = await db(f.user, "alice")
    session = await db(session_request, user=client_user, service=service, target=f.HOME)
    user_task = await db(session_deploy, session=session)
    assert user_task.control_url == agent.control_url

    async def task_arrived() -> bool:
        return agent.hub is not None and agent.hub.task is not None

    await until(task_arrived, what="the task to reach the agent")

    # The user connects straight to the vehicle with the grant.
    ws = await connect(user_task.control_url, proxy=None, compression=None)
    await ws.send(json.dumps({"type": "auth", "grant": user_task.grant}))
    assert (await recv(ws, "welcome"))["role"] == "controller"

    async def active() -> bool:
        s = await db(Session.objects.get, pk=session.pk)
        return s.state == Session.State.ACTIVE

    await until(active, what="the platform to see the user connected")

    world = agent.adapter.sensors  # the simulated world
    start = world.position
    assert (await command(ws, 41, "forward", speed=1.0)) == {
        "type": "ack",
        "seq": 41,
        "ok": True,
        "error": None,
    }
    for _ in range(8):
        await ws.send(json.dumps({"type": "keepalive"}))
        await asyncio.sleep(0.1)
    assert world.position != start
    assert (await command(ws, 42, "camera_up", step_deg=20))["seq"] == 42

    await ws.send(json.dumps({"type": "subscribe", "topics": ["location"], "rate_hz": 5}))
    stamps = [(await recv(ws, "telemetry"))["t"] for _ in range(6)]
    assert 0.12 < (stamps[-1] - stamps[0]) / 5 < 0.4  # about 5 Hz

    # The browser dies while the car moves: the car stops, the platform records it.
    assert (await command(ws, 43, "forward", speed=1.0))["ok"]
    killed = time.monotonic()
    ws.transport.abort()
    for _ in range(100):
        if agent.adapter.telemetry()["motors"] == {"left": 0.0, "right": 0.0}:
            break
        await asyncio.sleep(0.01)
    assert time.monotonic() - killed < 0.5

    async def recorded() -> list[str]:
        kinds = await db(
            lambda: list(Session.objects.get(pk=session.pk).events.values_list("kind", flat=True))
        )
        return kinds if "unintentional_end" in kinds else []

    kinds = await until(recorded, what="the platform to record the unintentional end")
    assert kinds.index("task_deployed") < kinds.index("unintentional_end")
