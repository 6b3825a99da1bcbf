"""End to end with a MAVLink drone: platform (iouv.serve, Postgres, Redis) + agent with the
simulated ArduCopter (a separate process on UDP) + a user flying it point-to-point.

The service's fail-safe is return_to_home: when the user's browser dies mid-flight,
the agent sends the drone home (RTL), it lands and disarms, and the platform's session
log records the unintentional end with the action taken.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator
from typing import Any

import pytest
from websockets.asyncio.client import connect

from agents.geo import distance_m
from agents.runtime import Agent
from fleet.models import Vehicle
from tests import factories as f
from tests.control import command, recv
from tests.servers import agent_simulated, db, platform_process, until
from tests.vehicles import (
    QUADCOPTER,
    agent_registered,
    session_deployed,
    unintentional_end_recorded,
    vehicle_served,
)

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
]
DRONE_COMMANDS = [
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
]


@pytest.fixture
async def running() -> AsyncIterator[tuple[Agent, Vehicle, Any]]:
    quad, credential, service = await db(
        vehicle_served,
        "quad-1",
        QUADCOPTER,
        service="fly-drone",
        commands=DRONE_COMMANDS,
        failsafe_action="return_to_home",
        attributes={"features": ["gps"]},
        max_altitude_m=30,
    )
    with platform_process() as base:
        async with agent_simulated(
            base=base,
            vehicle=quad,
            credential=credential,
            adapter="mavlink",
            options={
                "origin": [f.HOME[0], f.HOME[1]],
                "simulator": {"speedup": 4, "params": {"RTL_ALT": 800, "RTL_LOIT_TIME": 500}},
            },
        ) as (agent, simulation):
            yield agent, quad, service
    assert simulation.simulator.poll() is not None  # the simulator stopped after the agent


async def test_fly_then_browser_dies_drone_returns_home_and_platform_records_it(running):
    agent, quad, service = running

    vehicle = await agent_registered(quad, within=20, positioned=True)
    assert {c["name"] for c in vehicle.profile["commands"]} >= set(DRONE_COMMANDS)
    assert "autopilot_link" in vehicle.profile["telemetry"]

    session, user_task = await session_deployed(agent, service)
    assert agent.hub is not None and agent.hub.task is not None
    assert agent.hub.task.limits.failsafe_action == "return_to_home"

    ws = await connect(user_task.control_url, proxy=None, compression=None)
    await ws.send(json.dumps({"type": "auth", "grant": user_task.grant}))
    assert (await recv(ws, "welcome"))["role"] == "controller"
    await ws.send(json.dumps({"type": "subscribe", "topics": ["altitude"], "rate_hz": 10}))

    assert (await command(ws, 1, "take_off", altitude_m=5))["ok"]
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline:
        data = (await recv(ws, "telemetry"))["data"]
        await ws.send(json.dumps({"type": "keepalive"}))
        if (data["altitude"] or 0) > 4.5:
            break
    else:
        raise AssertionError("the drone did not reach 5 m")
    for seq in range(2, 12):  # hold "front" for a second
        assert (await command(ws, seq, "front", speed_mps=3))["ok"]
        await asyncio.sleep(0.1)
    drone = agent.adapter
    assert drone.t.lat is not None and drone.t.lon is not None
    assert distance_m(f.HOME, (drone.t.lat, drone.t.lon)) > 3

    # The browser dies mid-flight.
    killed = time.monotonic()
    ws.transport.abort()

    async def returning() -> bool:
        return drone.t.mode == 6  # RTL

    async def landed() -> bool:
        return drone.t.armed is False

    await until(returning, within=2, what="the agent to send the drone home (RTL)")
    await until(landed, within=40, what="the drone to land and disarm")
    assert time.monotonic() - killed < 40
    assert drone.t.alt is not None and drone.t.alt < 0.3
    assert distance_m(f.HOME, (drone.t.lat, drone.t.lon)) < 2

    events = await unintentional_end_recorded(session)
    kinds = [kind for kind, _ in events]
    assert kinds.index("task_deployed") < kinds.index("unintentional_end")
    [end] = [data for kind, data in events if kind == "unintentional_end"]
    assert end["cause"] == "link_lost" and end["action"] == "return_to_home"
