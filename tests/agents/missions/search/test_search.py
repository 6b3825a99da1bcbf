"""The ``search`` mission (agents/missions/search/) flown on the MAVLink simulator.

The simulator runs in its own process at 6x flight time with ``WPNAV_SPEED`` at the
missions' 10 m/s; the thermal camera is the synthetic sea rendered from the drone's own
telemetry. One test runs the whole Agent against a small fake platform (a WebSocket
server speaking the uplink protocol); the others use the same pieces the Agent wires
together (adapter, ControlHub, MissionControl, ThermalFeed) so they can look inside.
"""

from __future__ import annotations

import asyncio
import logging

import pytest

from agents.geo import distance_m
from agents.missions.registry import mission_decode
from agents.missions.search.spec import SearchSpec
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from tests.agents.mission_rig import (
    HOLD_M,
    HOME,
    PERSON,
    WAYPOINTS,
    RigFactory,
    agent_with_platform,
    make_task,
    search,
    until_near,
)


def test_search_defaults_and_wire_shape() -> None:
    parsed = mission_decode({"kind": "search", "id": "x", "altitude_m": 40, "waypoints": [HOME]})
    assert isinstance(parsed, SearchSpec)
    assert (parsed.speed_mps, parsed.start_index, parsed.min_confidence) == (10.0, 0, 0.6)
    # What the platform signs is the object the agent decodes, field for field.
    assert mission_decode(search()).to_payload() == search()


async def test_agent_searches_finds_the_person_and_holds_over_them() -> None:
    thermal = {"source": "synthetic", "persons": [list(PERSON)], "seed": 2}
    video = {"source": "thermal", "ice_host_addresses": ["127.0.0.1"]}
    async with agent_with_platform(thermal, video) as (agent, platform):
        profile = platform.of_type("profile")[0]
        assert profile["video"] is True
        # What its fail-safes do, in the copter's words, for the platform's pages.
        assert profile["safe_actions"]["land"] == "land where it is"
        await platform.task(search())
        found = await platform.wait(lambda: platform.events("person_detected"), 35, "detection")
        hold = await platform.wait(
            lambda: [d for d in platform.events("mission_progress") if d["phase"] == "hold"],
            15,
            "hold",
        )
        assert platform.of_type("task_accepted")
        detected = found[0]
        error = distance_m((detected["lat"], detected["lon"]), PERSON)
        assert error < 5.0, detected
        assert detected["mission"] == "m-search" and detected["confidence"] >= 0.6
        assert detected["waypoint"] == 2  # seen on the second line, after its start
        assert 0.1 <= detected["area_m2"] <= 0.4 and 20 < detected["temperature_c"] < 35
        phases = [(d["phase"], d["waypoint"]) for d in platform.events("mission_progress")]
        assert phases == [
            ("takeoff", None),
            ("transit", None),
            ("search", 0),
            ("search", 1),
            ("search", 2),
            ("hold", 2),
        ]
        assert all(d["of"] == 6 and d["mission"] == "m-search" for d in hold)
        assert not platform.events("search_complete") and not platform.events("mission_failed")
        # It stays over the person (the user keeps watching), at the search altitude.
        assert isinstance(agent.adapter, MavlinkAdapter)
        await until_near(agent.adapter, PERSON, HOLD_M)
        for _ in range(3):
            await asyncio.sleep(0.5)
            await until_near(agent.adapter, PERSON, HOLD_M, within=0.1)
            alt = agent.adapter.state().alt
            assert alt is not None and abs(alt - 40) < 2
        # The same task again (fresh token, same mission): nothing restarts.
        await platform.task(search())
        await platform.wait(lambda: len(platform.of_type("task_accepted")) == 2, 5, "accepted")
        await platform.wait(lambda: len(platform.events("person_detected")) == 2, 5, "re-report")
        assert platform.events("person_detected")[1] == detected
        assert len(platform.events("mission_progress")) == len(phases)
        # The session ends: the mission stops and the drone returns home.
        await platform.send({"type": "end_task", "session_id": "s-1", "reason": "rescued"})
        await platform.wait(lambda: platform.events("task_ended"), 10, "task_ended")
        assert agent.adapter.state().mode == "RTL"
        assert agent.missions is not None and agent.missions.runner is not None
        assert agent.missions.runner.done


async def test_search_without_a_person_completes_and_holds_at_the_last_waypoint(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    rig.accept(make_task(search()))
    done = await rig.event("search_complete", 35)
    assert done == {"mission": "m-search", "waypoint": 5}
    await rig.event("mission_progress", 5, count=9)
    assert rig.progress() == [
        ("takeoff", None),
        ("transit", None),
        *[("search", i) for i in range(6)],
        ("hold", 5),
    ]
    assert not rig.events("person_detected")
    await until_near(rig.drone, tuple(WAYPOINTS[5]), HOLD_M)  # it settles there and stays
    await asyncio.sleep(1.0)
    await until_near(rig.drone, tuple(WAYPOINTS[5]), HOLD_M, within=0.1)


async def test_start_index_skips_waypoints_and_a_new_mission_replaces_the_old(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    rig.accept(make_task(search("m-first")))
    await rig.event("mission_progress", 15, count=2)  # on its way to the first waypoint
    rig.accept(make_task(search("m-second", start_index=4)))
    await rig.event("search_complete", 35)
    second = [
        (d["phase"], d["waypoint"])
        for _, d in rig.events("mission_progress")
        if d["mission"] == "m-second"
    ]
    # Already in the air: straight to waypoint 4, the ones before are skipped.
    assert second == [("transit", None), ("search", 4), ("search", 5), ("hold", 5)], second
    first = [(e, d.get("phase")) for e, d in rig.events() if d["mission"] == "m-first"]
    # It took off and set off, then stopped without a word when replaced.
    assert first == [("mission_progress", "takeoff"), ("mission_progress", "transit")]
    assert rig.events("search_complete")[0][1] == {"mission": "m-second", "waypoint": 5}


async def test_a_camera_too_slow_for_the_speed_slows_the_search_and_the_person_is_found(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # One thermal frame a second while the simulator flies 10 m/s at 6x: 60 m of sea
    # between two frames whose footprint is 33 m along the track. At full speed most of
    # the sea would go unseen; the search slows down until the frames overlap.
    thermal = {"source": "synthetic", "persons": [list(PERSON)], "seed": 2, "fps": 1}
    caplog.set_level(logging.INFO, logger="agents.missions.search.runner")
    async with agent_with_platform(thermal, None) as (_agent, platform):
        await platform.task(search())
        found = await platform.wait(lambda: platform.events("person_detected"), 120, "detection")
        assert distance_m((found[0]["lat"], found[0]["lon"]), PERSON) < 5.0, found
        assert not platform.events("search_complete") and not platform.events("mission_failed")
    slowed = [r.getMessage() for r in caplog.records if "slowing to" in r.getMessage()]
    assert slowed, "the search never slowed down"
