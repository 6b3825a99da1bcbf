"""The ``delivery`` mission (agents/missions/delivery/) flown on the MAVLink simulator:
the life ring dropped once over the person, however often the task comes."""

from __future__ import annotations

import asyncio

from agents.geo import distance_m, offset
from agents.missions.delivery.spec import DeliverySpec
from agents.missions.registry import mission_decode
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from tests.agents.mission_rig import (
    HOLD_M,
    HOME,
    RigFactory,
    agent_with_platform,
    delivery,
    make_task,
    releases,
)


def test_delivery_defaults_and_wire_shape() -> None:
    drop = mission_decode({"kind": "delivery", "id": "y", "altitude_m": 30, "target": HOME})
    assert isinstance(drop, DeliverySpec)
    assert (drop.drop_altitude_m, drop.speed_mps) == (5.0, 10.0)
    assert mission_decode(delivery()).to_payload() == delivery()


async def test_agent_delivery_releases_once_however_often_the_task_comes() -> None:
    async with agent_with_platform(None) as (agent, platform):
        assert isinstance(agent.adapter, MavlinkAdapter)
        await platform.task(delivery())
        await platform.wait(
            lambda: [d for d in platform.events("mission_progress") if d["phase"] == "transit"],
            10,
            "transit",
        )
        await platform.task(delivery())  # re-sent while flying: no restart
        released = await platform.wait(lambda: platform.events("payload_released"), 30, "drop")
        await platform.task(delivery())  # re-sent after the drop: reported, not repeated
        await platform.wait(lambda: len(platform.events("payload_released")) == 2, 5, "again")
        await platform.wait(
            lambda: [d for d in platform.events("mission_progress") if d["phase"] == "hold"],
            20,
            "hold",
        )
        await platform.task(delivery())  # and once more after it finished
        await platform.wait(lambda: len(platform.events("payload_released")) == 3, 5, "third")
        first = released[0]
        assert platform.events("payload_released") == [first, first, first]
        assert distance_m((first["lat"], first["lon"]), tuple(delivery()["target"])) < HOLD_M
        assert releases(agent.adapter) == 1
        phases = [d["phase"] for d in platform.events("mission_progress")]
        assert phases == ["takeoff", "transit", "delivery", "hold"]
        assert len(platform.of_type("task_accepted")) == 4
        state = agent.adapter.state()
        assert state.alt is not None and abs(state.alt - 30) < 2  # climbed back
        assert not platform.events("mission_failed")


async def test_an_unconfirmed_release_is_never_flown_for_again(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    # As left by a runner stopped while its release_payload was in flight.
    rig.missions.release_attempted.add("m-drop")
    rig.accept(make_task(delivery()))
    failed = await rig.event("mission_failed", 2)
    assert failed == {
        "mission": "m-drop",
        "reason": "the payload release was attempted already and not confirmed",
    }
    await asyncio.sleep(0.5)
    assert rig.missions.runner is None and rig.drone.state().armed is False


async def test_adapter_error_fails_the_mission_and_the_drone_holds(
    make_mission_rig: RigFactory,
) -> None:
    rig = await make_mission_rig()
    # 60 km away: the autopilot refuses to reposition that far, in its own words.
    rig.accept(make_task(delivery(target=list(offset(HOME, 60_000, 0)))))
    failed = await rig.event("mission_failed", 20)
    assert "autopilot refused" in failed["reason"] and "too far" in failed["reason"]
    assert [d["phase"] for _, d in rig.events("mission_progress")] == ["takeoff", "transit"]
    here = rig.drone.state()
    await asyncio.sleep(1.5)
    there = rig.drone.state()
    assert here.position is not None and there.position is not None
    assert distance_m(here.position, there.position) < 1.0  # hovering where it was
    assert there.mode == "GUIDED" and there.alt is not None and abs(there.alt - 30) < 2
    assert releases(rig.drone) == 0 and not rig.events("payload_released")
