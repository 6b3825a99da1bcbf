"""End to end over real sockets: platform (iouv.serve, Postgres, Redis) + the simulated
Spektrum VTOL's agent + a user.

The agent registers on its uplink, the platform assigns the plane to a service whose
fail-safe is "land" and deploys the signed task; the user flies it up point-to-point
and their browser dies: the plane lands and disarms on its own, and the platform's
session log records the fail-safe as an unintentional end.
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
from agents.vehicles.spektrum.adapter import SpektrumAdapter
from fleet.models import Vehicle
from tests import factories as f
from tests.agents.vtol import FAST, VTOL_COMMANDS
from tests.control import command, recv
from tests.servers import agent_simulated, db, platform_process
from tests.vehicles import (
    VTOL,
    agent_registered,
    session_active,
    session_deployed,
    unintentional_end_recorded,
    vehicle_served,
)

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
]


@pytest.fixture
async def running() -> AsyncIterator[tuple[Agent, Vehicle, Any, Any]]:
    plane, credential, service = await db(
        vehicle_served,
        "vtol-1",
        VTOL,
        service="fly-vtol",
        commands=list(VTOL_COMMANDS),
        failsafe_action="land",
        attributes={"environments": ["air", "land"], "features": ["gps"]},
    )
    with platform_process() as base:
        async with agent_simulated(
            base=base,
            vehicle=plane,
            credential=credential,
            adapter="spektrum",
            options={
                "origin": [f.HOME[0], f.HOME[1]],
                "vehicle_type": "Spektrum VTOL plane",
                **FAST,
            },
        ) as (agent, simulation):
            yield agent, plane, service, simulation.simulator


async def test_register_deploy_fly_and_link_loss_lands(running: Any) -> None:
    agent, plane, service, sim = running

    vehicle = await agent_registered(plane)
    assert vehicle.control_url == agent.control_url
    assert {c["name"] for c in vehicle.profile["commands"]} >= set(VTOL_COMMANDS)
    assert vehicle.profile["adapter"] == "spektrum"

    session, user_task = await session_deployed(agent, service)
    ws = await connect(user_task.control_url, proxy=None, compression=None)
    await ws.send(json.dumps({"type": "auth", "grant": user_task.grant}))
    assert (await recv(ws, "welcome"))["role"] == "controller"

    await session_active(session)

    adapter = agent.adapter
    assert isinstance(adapter, SpektrumAdapter)
    assert (await command(ws, 1, "arm"))["ok"]
    # Hold "w" as the browser does (a repeat every 100 ms) until the plane is 3 m up:
    # the throttle only stays up while the key is held.
    seq = 1
    deadline = time.monotonic() + 30
    while sim.snapshot()["alt"] < 3.0:
        assert time.monotonic() < deadline, f"not climbing: {sim.snapshot()}"
        seq += 1
        assert (await command(ws, seq, "throttle_up", step=0.1))["ok"]
        await asyncio.sleep(0.1)
    assert sim.snapshot()["alt"] >= 3.0 and sim.snapshot()["armed"]

    # The browser dies in the air: the plane lands and disarms by itself.
    ws.transport.abort()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        state = sim.snapshot()
        if state["on_ground"] and not state["armed"] and not adapter.controls.armed:
            break
        await asyncio.sleep(0.1)
    state = sim.snapshot()
    assert state["alt"] == 0.0 and not state["armed"] and state["hard_landings"] == 0
    assert adapter.controls.landings == 1

    events = await unintentional_end_recorded(session)
    kinds = [kind for kind, _ in events]
    assert kinds.index("task_deployed") < kinds.index("unintentional_end")
    end = next(data for kind, data in events if kind == "unintentional_end")
    assert (end["cause"], end["action"]) == ("link_lost", "land")
