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
from fleet.models import Vehicle
from tests import factories as f
from tests.control import command, recv
from tests.servers import agent_running, db, platform_process
from tests.vehicles import (
    CAR_COMMANDS,
    agent_registered,
    car_served,
    session_active,
    session_deployed,
    unintentional_end_recorded,
)

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
]


@pytest.fixture
async def running() -> AsyncIterator[tuple[str, Agent, Vehicle, Any]]:
    car, credential, service = await db(
        car_served, "car-1", service="drive-car", features=["camera_arm", "obstacle_sensor"]
    )
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

    vehicle = await agent_registered(car)
    assert vehicle.control_url == agent.control_url
    assert {c["name"] for c in vehicle.profile["commands"]} >= set(CAR_COMMANDS)

    session, user_task = await session_deployed(agent, service)
    assert user_task.control_url == agent.control_url

    # The user connects straight to the vehicle with the grant.
    ws = await connect(user_task.control_url, proxy=None, compression=None)
    await ws.send(json.dumps({"type": "auth", "grant": user_task.grant}))
    assert (await recv(ws, "welcome"))["role"] == "controller"

    await session_active(session)

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

    kinds = [kind for kind, _ in await unintentional_end_recorded(session)]
    assert kinds.index("task_deployed") < kinds.index("unintentional_end")
