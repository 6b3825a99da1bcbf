"""What every mission shares (agents.missions.control, agents.missions.kit) on the
MAVLink simulator: one mission at a time through the hub's lock and the task's limits,
and whoever else acts on the vehicle (a user, the autopilot, its battery) ends it; a
mission the agent does not know or cannot read is refused with its task, and changes
nothing."""

from __future__ import annotations

import asyncio
import json
import re

import pytest
from websockets.asyncio.client import connect

from agents.geo import distance_m
from agents.safety import Refusal
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from tests.agents.mission_rig import (
    HOLD_M,
    MALFORMED,
    SIM,
    RigFactory,
    agent_with_platform,
    delivery,
    make_grant,
    make_task,
    releases,
    search,
)
from tests.control import command, recv


async def test_mission_commands_are_checked_inside_the_lock(make_mission_rig: RigFactory) -> None:
    rig = await make_mission_rig()
    rig.hub.task_accept(make_task(None))
    with pytest.raises(Refusal) as exc:
        await rig.hub.mission_execute("s-other", "take_off", {"altitude_m": 10}, epoch=0)
    assert exc.value.code == "no_task"
    with pytest.raises(Refusal) as exc:  # started before a user or a fail-safe acted
        await rig.hub.mission_execute("s-1", "take_off", {"altitude_m": 10}, epoch=-1)
    assert exc.value.code == "overridden"
    with pytest.raises(Refusal) as exc:
        await rig.hub.mission_execute("s-1", "take_off", {"altitude_m": 80}, epoch=0)
    assert exc.value.code == "altitude_limit"
    with pytest.raises(Refusal) as exc:
        await rig.hub.mission_execute("s-1", "take_off", {"altitude": 10}, epoch=0)
    assert exc.value.code == "bad_args"
    assert rig.drone.state().armed is False


async def test_mission_outside_the_task_limits_fails_on_the_ground(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    rig.accept(make_task(search(), max_altitude_m=20))
    failed = await rig.event("mission_failed", 5)
    assert "above the 20 m limit" in failed["reason"]
    assert rig.drone.state().armed is False


async def wait_battery(drone: MavlinkAdapter) -> None:
    for _ in range(100):
        if drone.state().battery is not None:
            return
        await asyncio.sleep(0.05)
    raise AssertionError("no battery level from the autopilot")


async def test_adapter_refusal_on_the_ground_fails_the_mission(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig(simulator={**SIM, "battery_pct": 20})
    await wait_battery(rig.drone)
    rig.accept(make_task(search()))
    failed = await rig.event("mission_failed", 10)
    assert re.fullmatch(r"battery at 1\d% \(below 25%\): take-off is refused", failed["reason"])
    assert rig.drone.state().armed is False


async def test_the_vehicles_own_low_battery_return_ends_the_mission(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig(simulator={**SIM, "battery_pct": 30, "drain_pct_per_min": 15})
    await wait_battery(rig.drone)
    rig.accept(make_task(search()))
    failed = await rig.event("mission_failed", 20)
    assert failed["reason"] == "interrupted: the vehicle switched to RTL by itself"
    await asyncio.sleep(1.0)
    assert rig.drone.state().mode == "RTL"  # the mission did not fight the return


async def test_a_user_command_takes_over_from_the_mission(make_mission_rig: RigFactory) -> None:
    rig = await make_mission_rig(control=True)
    task = make_task(search())
    rig.accept(task)
    await rig.event("mission_progress", 15, count=3)  # at the first waypoint
    assert rig.server is not None
    ws = await connect(f"ws://127.0.0.1:{rig.server.port}/", compression=None, proxy=None)
    await ws.send(json.dumps({"type": "auth", "grant": make_grant()}))
    assert (await recv(ws, "welcome"))["role"] == "controller"
    # Joining as controller does not stop the drone: the pattern goes on.
    await rig.event("mission_progress", 15, count=4)
    ack = await command(ws, 1, "stop")
    assert ack["ok"], ack
    failed = await rig.event("mission_failed", 5)
    assert failed["reason"] == "interrupted: the user sent stop"
    count = len(rig.events("mission_progress"))
    await asyncio.sleep(1.5)
    assert len(rig.events("mission_progress")) == count
    assert rig.hub.autonomous is False
    await ws.close()


async def test_a_malformed_mission_is_refused_with_its_task_and_changes_nothing() -> None:
    async with agent_with_platform(None) as (agent, platform):
        assert agent.hub is not None and isinstance(agent.adapter, MavlinkAdapter)
        # Nothing running: each is refused, naming the field, and nothing is accepted.
        await platform.task_unchecked(MALFORMED[0][0])
        refused = await platform.wait(lambda: platform.of_type("task_refused"), 5, "refusal")
        assert refused[0]["session_id"] == "s-1" and refused[0]["code"] == "bad_field"
        assert "mission.kind" in refused[0]["reason"]
        assert agent.hub.task is None and agent.adapter.state().armed is False
        # A delivery under way: a malformed task for its session leaves it flying.
        await platform.task(delivery())
        await platform.wait(
            lambda: [d for d in platform.events("mission_progress") if d["phase"] == "transit"],
            15,
            "transit",
        )
        for i, (mission, reason) in enumerate(MALFORMED, start=1):
            await platform.task_unchecked(mission)
            refused = await platform.wait(
                lambda i=i: platform.of_type("task_refused")[i:], 5, f"refusal {i}"
            )
            assert refused[0]["code"] == "bad_field", refused
            assert reason in refused[0]["reason"], (reason, refused[0]["reason"])
        assert agent.hub.task is not None and agent.hub.task.mission is not None
        assert agent.hub.task.mission.id == "m-drop"
        released = await platform.wait(lambda: platform.events("payload_released"), 40, "drop")
        target = delivery()["target"]
        assert distance_m((released[0]["lat"], released[0]["lon"]), tuple(target)) < HOLD_M
        assert len(platform.of_type("task_accepted")) == 1
        assert not platform.events("mission_failed")
        assert releases(agent.adapter) == 1
