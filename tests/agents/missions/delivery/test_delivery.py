"""The ``delivery`` mission (agents/missions/delivery/) flown on the MAVLink simulator:
the life ring dropped once over the person, however often the task comes; the autopilot
flies it (AUTO) and holds over the person, or the agent flies each step; with the agent
dead while it holds, the autopilot's GCS fail-safe decides what follows."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from agents.geo import distance_m, offset
from agents.geography import land_at
from agents.missions.delivery.runner import delivery_plan
from agents.missions.delivery.spec import DeliverySpec
from agents.missions.registry import mission_decode
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.plan import Hold, MissionProgress, Release, Waypoint
from tests.agents.mission_rig import (
    HOLD_M,
    HOME,
    SIM,
    RigFactory,
    agent_dies,
    agent_with_platform,
    delivery,
    landed_at_home,
    last_position,
    listen,
    make_task,
    releases,
    texts,
)
from tests.agents.waiting import until

TARGET = tuple(delivery()["target"])
PHASES = ["takeoff", "transit", "delivery", "hold"]


def test_delivery_defaults_and_wire_shape() -> None:
    drop = mission_decode({"kind": "delivery", "id": "y", "altitude_m": 30, "target": HOME})
    assert isinstance(drop, DeliverySpec)
    assert (drop.drop_altitude_m, drop.speed_mps) == (5.0, 10.0)
    assert mission_decode(delivery()).to_payload() == delivery()


def test_the_delivery_as_one_plan_ends_holding_over_the_target() -> None:
    """The steps the agent flies, as one plan for the autopilot: the same phases, the
    release once between the descent and the climb, and a hold at the end (nothing may
    follow it: the autopilot never goes past it)."""
    spec = mission_decode(delivery())
    assert isinstance(spec, DeliverySpec)
    plan = delivery_plan(spec, speed_mps=8)
    assert [s.phase for s in plan.steps if s.phase] == PHASES[1:]
    assert [type(s.item) for s in plan.steps[2:]] == [Waypoint, Waypoint, Release, Waypoint, Hold]
    assert [s.item.altitude_m for s in plan.steps if isinstance(s.item, Waypoint)] == [30, 5, 30]
    assert {s.item.point for s in plan.steps if isinstance(s.item, Waypoint)} == {TARGET}
    assert [s.event for s in plan.steps if s.event] == ["payload_released"]
    with pytest.raises(ValueError, match="nothing can follow a hold"):
        plan.return_home()


async def held(drone: MavlinkAdapter, point: tuple[float, ...], *, alt: float | None) -> None:
    """The vehicle stays within HOLD_M of ``point`` (and 2 m of ``alt``) in AUTO while
    20 s pass on the autopilot's clock (its positions' time since boot: simulated time,
    whatever the machine's load)."""
    start = drone.t.boot_ms
    away: list[Any] = []

    def over() -> bool:
        st = drone.state()
        off = distance_m(st.position or (0.0, 0.0), (point[0], point[1]))
        if off > HOLD_M or st.mode != "AUTO" or (alt is not None and abs((st.alt or 0) - alt) > 2):
            away.append((off, st.alt, st.mode))
        return drone.t.boot_ms - start >= 20_000

    await until(over, within=60, what="20 s on the autopilot's clock")
    assert not away, away[:5]


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
        assert phases == PHASES
        assert len(platform.of_type("task_accepted")) == 4
        state = agent.adapter.state()
        assert state.alt is not None and abs(state.alt - 30) < 2  # climbed back
        assert state.mode == "AUTO"  # holding in the autopilot's own mission
        assert not platform.events("mission_failed")


async def test_the_autopilot_flies_the_delivery_releases_once_and_holds_over_the_person(
    make_mission_rig: RigFactory,
) -> None:
    """A copter's autopilot flies the whole delivery (AUTO): the agent reports the same
    phases and events as when it flies each step, and its part ends once the autopilot
    holds over the target at the cruise altitude, where it stays in AUTO."""
    rig = await make_mission_rig()
    rig.accept(make_task(delivery()))
    released = await rig.event("payload_released", within=90)
    assert distance_m((released["lat"], released["lon"]), TARGET) < HOLD_M
    await until(lambda: rig.missions.runner and rig.missions.runner.done, within=60, what="end")
    assert [phase for phase, _ in rig.progress()] == PHASES
    assert rig.missions.runner is not None
    assert rig.missions.runner.result == ("payload_released", released)
    assert releases(rig.drone) == 1
    # On the autopilot's last item, the hold, which it never goes past.
    hold = len(delivery_plan(rig.missions.runner.mission, speed_mps=10).steps) - 1
    assert rig.drone.mission_progress().current == hold
    await held(rig.drone, TARGET, alt=30)
    assert rig.drone.mission_progress().current == hold
    assert not rig.drone.mission_progress().finished
    assert releases(rig.drone) == 1 and not rig.events("mission_failed")


async def test_without_native_missions_the_agent_flies_each_step_and_holds(
    make_mission_rig: RigFactory,
) -> None:
    """``native_missions: false``: the agent flies every leg itself (GUIDED) and ends
    with the copter holding over the target, as before the autopilot flew it."""
    rig = await make_mission_rig(native_missions=False)
    rig.accept(make_task(delivery()))
    released = await rig.event("payload_released", within=90)
    assert distance_m((released["lat"], released["lon"]), TARGET) < HOLD_M
    await until(lambda: rig.missions.runner and rig.missions.runner.done, within=60, what="end")
    assert [phase for phase, _ in rig.progress()] == PHASES
    st = rig.drone.state()
    assert st.mode == "GUIDED" and st.alt is not None and abs(st.alt - 30) < 2
    assert st.position is not None and distance_m(st.position, TARGET) < HOLD_M
    assert rig.drone.mission_progress() == MissionProgress()  # nothing uploaded
    assert releases(rig.drone) == 1 and not rig.events("mission_failed")


@pytest.mark.parametrize(
    ("fs_options", "expected"),
    [
        (0, "returns home"),  # ArduCopter's default: the GCS fail-safe's RTL, in AUTO too
        (2, "holds"),  # FS_OPTIONS bit 1: "continue if in auto", the hold included
    ],
)
async def test_when_the_agent_dies_while_the_drone_holds_the_gcs_failsafe_decides(
    make_mission_rig: RigFactory, fs_options: int, expected: str
) -> None:
    """The agent killed while its drone holds over the person in AUTO: ArduCopter's GCS
    fail-safe (FS_GCS_ENABLE 1) brings it home and lands it; with FS_OPTIONS bit 1 it
    continues the mission, which is the hold: it stays over the person."""
    params = {**SIM["params"], "FS_GCS_TIMEOUT": 2, "FS_OPTIONS": fs_options}
    rig = await make_mission_rig(simulator={**SIM, "params": params})
    rig.accept(make_task(delivery("m-dies")))
    await until(lambda: "hold" in [p for p, _ in rig.progress()], within=90, what="hold")
    assert rig.drone.state().mode == "AUTO" and releases(rig.drone) == 1
    address = await agent_dies(rig)
    if expected == "returns home":
        heard = await listen(address, landed_at_home, within=120)
        assert "GCS Failsafe" in texts(heard)
        assert heard[-1].custom_mode == 6  # RTL
        assert distance_m(last_position(heard), HOME) < 3
        return

    def continuing(msg: Any) -> bool:
        return msg.get_type() == "STATUSTEXT" and msg.text == "GCS Failsafe - Continuing Auto Mode"

    await listen(address, continuing, within=60)
    start: list[int] = []

    def twenty_seconds_on(msg: Any) -> bool:
        if msg.get_type() != "GLOBAL_POSITION_INT":
            return False
        start.append(msg.time_boot_ms)
        return msg.time_boot_ms - start[0] >= 20_000

    heard = await listen(address, twenty_seconds_on, within=60)
    positions = [m for m in heard if m.get_type() == "GLOBAL_POSITION_INT"]
    assert all(distance_m((m.lat / 1e7, m.lon / 1e7), TARGET) < HOLD_M for m in positions)
    assert all(abs(m.relative_alt / 1000 - 30) < 2 for m in positions)
    assert all(m.custom_mode == 3 for m in heard if m.get_type() == "HEARTBEAT")  # AUTO


#: A boat at sea off Barra beach, and a person 80 m out: the way there is water.
BOAT_HOME = (40.6443, -8.7540)
BOAT_TARGET = offset(BOAT_HOME, 60, 50)


async def test_a_boat_sails_the_delivery_in_auto_and_keeps_station_by_the_person(
    make_mission_rig: RigFactory,
) -> None:
    """No take-off, no descent or climb: the boat is armed, and ArduRover's AUTO sails
    to the person, releases the life ring once and keeps station there."""
    rig = await make_mission_rig(
        vehicle_class="boat", origin=list(BOAT_HOME), simulator={"speedup": 6}
    )
    assert land_at(*BOAT_HOME) is False and land_at(*BOAT_TARGET) is False
    rig.accept(make_task(delivery("m-boat", target=list(BOAT_TARGET))))
    released = await rig.event("payload_released", within=60)
    assert distance_m((released["lat"], released["lon"]), BOAT_TARGET) < HOLD_M
    await until(lambda: rig.missions.runner and rig.missions.runner.done, within=60, what="end")
    assert [phase for phase, _ in rig.progress()] == PHASES[1:]  # armed, not taken off
    await held(rig.drone, BOAT_TARGET, alt=None)
    assert releases(rig.drone) == 1 and not rig.events("mission_failed")


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
    """Flown step by step (natively, ArduPilot's AUTO flies a far waypoint without a
    word: only the task's geofence and the autopilot's fence bound it)."""
    rig = await make_mission_rig(native_missions=False)
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
