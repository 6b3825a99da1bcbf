"""The simulated autopilot's mission, driven by a plain ground station (pymavlink, over
UDP): the upload protocol as ArduPilot answers it, its refusals, and AUTO flying it;
then the agent's adapter uploading one (agents/vehicles/mavlink/mission.py).

Each test runs its own simulator process (agents/vehicles/mavlink/sim/); the ground
station is system 200, which ArduPilot does not take for its GCS (no fail-safe here).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

import pytest

from agents.geo import distance_m, offset
from agents.simulation import simulator_running
from agents.vehicles.base import AdapterError
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.mavlink.dialect import MAV
from agents.vehicles.mavlink.mission import MissionItem, plan_items
from agents.vehicles.plan import Hold, Release, ReturnHome, Speed, TakeOff, Waypoint
from agents.vehicles.registry import adapter_create
from tests.agents.mavlink_rig import HOME, ground_station, poll, simulator_listening

AUTO, GUIDED, RTL = 3, 4, 6
RELATIVE = MAV.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
MISSION = MAV.MAV_MISSION_TYPE_MISSION


async def wait_for(
    gcs: Any, kinds: str | list[str], within: float, where: Callable[[Any], bool] = bool
) -> Any:
    """The first message of ``kinds`` from the autopilot for which ``where`` holds (the
    ground station heartbeats meanwhile, as one does)."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        gcs.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        msg = await asyncio.to_thread(gcs.recv_match, type=kinds, blocking=True, timeout=0.3)
        if msg is not None and msg.get_srcSystem() == 1 and where(msg):
            return msg
    raise AssertionError(f"no {kinds} within {within:g} s")


Item = tuple[int, int, tuple[float, float], float, float, float]


def item(
    seq: int,
    command: int,
    *,
    point: tuple[float, float] = (0.0, 0.0),
    alt: float = 0.0,
    p1: float = 0.0,
    p2: float = 0.0,
) -> Item:
    """A mission item as :func:`send_item` sends it (relative altitude)."""
    return (seq, command, point, alt, p1, p2)


def send_item(
    gcs: Any,
    seq: int,
    command: int,
    point: tuple[float, float],
    alt: float,
    p1: float,
    p2: float,
) -> None:
    gcs.mav.mission_item_int_send(
        1, 1, seq, RELATIVE, command, 0, 1, p1, p2, 0, 0,
        round(point[0] * 1e7), round(point[1] * 1e7), alt, MISSION,
    )  # fmt: skip


async def upload(gcs: Any, items: list[Item]) -> Any:
    """MISSION_COUNT, each item as it is asked for; returns the MISSION_ACK."""
    gcs.mav.mission_count_send(1, 1, len(items), MISSION)
    while True:
        msg = await wait_for(gcs, ["MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"], 5)
        if msg.get_type() == "MISSION_ACK":
            return msg
        send_item(gcs, *items[msg.seq])


def command(gcs: Any, cmd: int, *params: float) -> None:
    p = list(params) + [0.0] * (7 - len(params))
    gcs.mav.command_long_send(1, 1, cmd, 0, *p)


async def ack(gcs: Any, cmd: int) -> int:
    msg = await wait_for(gcs, "COMMAND_ACK", 5, lambda m: m.command == cmd)
    return int(msg.result)


async def mode(gcs: Any, number: int) -> int:
    command(gcs, MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, number)
    return await ack(gcs, MAV.MAV_CMD_DO_SET_MODE)


async def mission_count(gcs: Any) -> int:
    gcs.mav.mission_request_list_send(1, 1, MISSION)
    return int((await wait_for(gcs, "MISSION_COUNT", 5, lambda m: m.mission_type == 0)).count)


async def take_off(gcs: Any, alt: float) -> None:
    assert await mode(gcs, GUIDED) == MAV.MAV_RESULT_ACCEPTED
    command(gcs, MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert await ack(gcs, MAV.MAV_CMD_COMPONENT_ARM_DISARM) == MAV.MAV_RESULT_ACCEPTED
    command(gcs, MAV.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt)
    assert await ack(gcs, MAV.MAV_CMD_NAV_TAKEOFF) == MAV.MAV_RESULT_ACCEPTED
    await wait_for(gcs, "GLOBAL_POSITION_INT", 20, lambda m: m.relative_alt > (alt - 0.5) * 1000)


def streaming(gcs: Any) -> None:
    """The position at 10 Hz, where the mission is at 2 Hz (nothing else: the others
    would crowd what the tests wait for)."""
    command(gcs, MAV.MAV_CMD_SET_MESSAGE_INTERVAL, MAV.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 1e5)
    command(gcs, MAV.MAV_CMD_SET_MESSAGE_INTERVAL, MAV.MAVLINK_MSG_ID_MISSION_CURRENT, 5e5)


TARGET = offset(HOME, 40.0, 0.0)
FLIGHT = [
    item(0, MAV.MAV_CMD_NAV_WAYPOINT, point=HOME),
    item(1, MAV.MAV_CMD_NAV_TAKEOFF, alt=10),
    item(2, MAV.MAV_CMD_DO_CHANGE_SPEED, p1=1, p2=8),
    item(3, MAV.MAV_CMD_NAV_WAYPOINT, point=TARGET, alt=10, p1=1),
    item(4, MAV.MAV_CMD_DO_GRIPPER, p1=1, p2=MAV.GRIPPER_ACTION_RELEASE),
    item(5, MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH),
]


async def test_auto_flies_an_uploaded_mission_and_lands_at_home_by_itself() -> None:
    args = ("--home", f"{HOME[0]},{HOME[1]}", "--speedup", "6", "--stream-rate", "0")
    with simulator_listening(*args) as (_, address), ground_station(address) as gcs:
        streaming(gcs)
        # Without a mission AUTO is refused, as ArduCopter refuses it.
        assert await mode(gcs, AUTO) == MAV.MAV_RESULT_FAILED
        assert (await upload(gcs, FLIGHT)).type == MAV.MAV_MISSION_ACCEPTED
        assert await mission_count(gcs) == len(FLIGHT)
        # Armed on the ground, a mission must start with a take-off; AUTO is not armable.
        await take_off(gcs, 5)
        assert await mode(gcs, AUTO) == MAV.MAV_RESULT_ACCEPTED
        reached = await wait_for(gcs, "MISSION_ITEM_REACHED", 40)
        assert reached.seq == 3
        where = await wait_for(gcs, "GLOBAL_POSITION_INT", 5)
        assert distance_m((where.lat / 1e7, where.lon / 1e7), TARGET) < 3
        await wait_for(gcs, "STATUSTEXT", 10, lambda m: m.text == "Gripper load released")
        current = await wait_for(gcs, "MISSION_CURRENT", 5, lambda m: m.seq == 5)
        assert current.total == len(FLIGHT) - 1
        # The return is AUTO's own (the mode stays AUTO), down to a landing at home.
        landed = await wait_for(
            gcs, "HEARTBEAT", 60, lambda m: not m.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED
        )
        assert landed.custom_mode == AUTO
        where = await wait_for(gcs, "GLOBAL_POSITION_INT", 5)
        assert distance_m((where.lat / 1e7, where.lon / 1e7), HOME) < 3
        assert where.relative_alt < 300
        done = await wait_for(gcs, "MISSION_CURRENT", 5)
        assert done.mission_state == MAV.MISSION_STATE_COMPLETE


EAST = offset(HOME, 0.0, 60.0)
TURNS = [
    item(0, MAV.MAV_CMD_NAV_WAYPOINT, point=HOME),
    item(1, MAV.MAV_CMD_NAV_TAKEOFF, alt=10),
    item(2, MAV.MAV_CMD_NAV_WAYPOINT, point=EAST, alt=10),
    item(3, MAV.MAV_CMD_NAV_WAYPOINT, point=HOME, alt=10),
    item(4, MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH),
]


async def test_in_auto_the_nose_turns_towards_the_next_waypoint() -> None:
    """ArduCopter's WP_YAW_BEHAVIOR (the simulator's default, 1): a camera fixed to the
    frame looks where the copter flies, east then back west."""
    args = ("--home", f"{HOME[0]},{HOME[1]}", "--speedup", "6", "--stream-rate", "0")
    with simulator_listening(*args) as (_, address), ground_station(address) as gcs:
        streaming(gcs)
        command(gcs, MAV.MAV_CMD_SET_MESSAGE_INTERVAL, MAV.MAVLINK_MSG_ID_VFR_HUD, 2e5)
        assert (await upload(gcs, TURNS)).type == MAV.MAV_MISSION_ACCEPTED
        await take_off(gcs, 5)
        assert await mode(gcs, AUTO) == MAV.MAV_RESULT_ACCEPTED
        await wait_for(gcs, "MISSION_CURRENT", 20, lambda m: m.seq == 2)
        east = await wait_for(gcs, "VFR_HUD", 20, lambda m: m.groundspeed > 3)
        assert abs(east.heading - 90) <= 5, east.heading
        await wait_for(gcs, "MISSION_CURRENT", 40, lambda m: m.seq == 3)
        # It turns about (at its yaw rate) and flies home facing west.
        await wait_for(gcs, "VFR_HUD", 20, lambda m: abs(m.heading - 270) <= 5)
        where = await wait_for(gcs, "GLOBAL_POSITION_INT", 5)
        assert distance_m((where.lat / 1e7, where.lon / 1e7), HOME) > 20  # still on the way


async def heard_for(gcs: Any, seconds: float) -> list[Any]:
    """What the autopilot sends while ``seconds`` pass on its own clock (the positions'
    ``time_boot_ms``: simulated time, whatever the machine's load)."""
    kinds = ["GLOBAL_POSITION_INT", "HEARTBEAT", "MISSION_CURRENT", "MISSION_ITEM_REACHED"]
    first = await wait_for(gcs, "GLOBAL_POSITION_INT", 5)
    heard = [first]
    deadline = time.monotonic() + seconds + 30
    while time.monotonic() < deadline:
        gcs.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        msg = await asyncio.to_thread(gcs.recv_match, type=kinds, blocking=True, timeout=0.3)
        if msg is None or msg.get_srcSystem() != 1:
            continue
        heard.append(msg)
        if (
            msg.get_type() == "GLOBAL_POSITION_INT"
            and msg.time_boot_ms - first.time_boot_ms >= seconds * 1000
        ):
            return heard
    raise AssertionError(f"the autopilot's clock did not pass {seconds:g} s")


HOLD_AT = offset(HOME, 30.0, 20.0)
#: A hold over HOLD_AT at 15 m, after a waypoint there at 10 m.
HOLD_THERE = [
    item(0, MAV.MAV_CMD_NAV_WAYPOINT, point=HOME),
    item(1, MAV.MAV_CMD_NAV_TAKEOFF, alt=10),
    item(2, MAV.MAV_CMD_NAV_WAYPOINT, point=HOLD_AT, alt=10),
    item(3, MAV.MAV_CMD_NAV_LOITER_UNLIM, point=HOLD_AT, alt=15),
]
#: A hold with no position and no altitude: where the copter is, as high as it is.
HOLD_HERE = [
    item(0, MAV.MAV_CMD_NAV_WAYPOINT, point=HOME),
    item(1, MAV.MAV_CMD_NAV_TAKEOFF, alt=10),
    item(2, MAV.MAV_CMD_NAV_LOITER_UNLIM),
]


@pytest.mark.parametrize(
    ("mission", "where", "alt"),
    [(HOLD_THERE, HOLD_AT, 15.0), (HOLD_HERE, HOME, 10.0)],
    ids=["at its point", "where it is"],
)
async def test_auto_holds_at_an_unlimited_loiter_until_the_mode_changes(
    mission: list[Item], where: tuple[float, float], alt: float
) -> None:
    """NAV_LOITER_UNLIM as ArduCopter flies it (ModeAuto::do_loiter_unlimited): to its
    point and altitude (latitude and longitude 0: the stopping point; altitude 0: the
    current one), then hovering there in AUTO; never verified, so the mission stays on
    it (no MISSION_ITEM_REACHED for it, never complete) until the mode changes."""
    args = ("--home", f"{HOME[0]},{HOME[1]}", "--speedup", "6", "--stream-rate", "0")
    with simulator_listening(*args) as (_, address), ground_station(address) as gcs:
        streaming(gcs)
        assert (await upload(gcs, mission)).type == MAV.MAV_MISSION_ACCEPTED
        await take_off(gcs, 5)
        assert await mode(gcs, AUTO) == MAV.MAV_RESULT_ACCEPTED
        hold = len(mission) - 1
        await wait_for(gcs, "MISSION_CURRENT", 30, lambda m: m.seq == hold)

        def there(m: Any) -> bool:
            off = distance_m((m.lat / 1e7, m.lon / 1e7), where)
            return off < 2 and abs(m.relative_alt / 1000 - alt) < 1

        await wait_for(gcs, "GLOBAL_POSITION_INT", 30, there)
        heard = await heard_for(gcs, 20.0)
        positions = [m for m in heard if m.get_type() == "GLOBAL_POSITION_INT"]
        assert all(there(m) for m in positions), positions[-1]
        beats = [m for m in heard if m.get_type() == "HEARTBEAT"]
        assert beats and all(m.custom_mode == AUTO for m in beats)
        currents = [m for m in heard if m.get_type() == "MISSION_CURRENT"]
        assert currents and all(
            m.seq == hold and m.mission_state == MAV.MISSION_STATE_ACTIVE for m in currents
        )
        assert not [m for m in heard if m.get_type() == "MISSION_ITEM_REACHED"]
        # Only a change of mode ends it.
        assert await mode(gcs, GUIDED) == MAV.MAV_RESULT_ACCEPTED


async def test_an_out_of_sequence_item_is_refused_and_the_upload_waits_for_the_right_one():
    args = (
        "--home",
        f"{HOME[0]},{HOME[1]}",
    )
    with simulator_listening(*args) as (_, address), ground_station(address) as gcs:
        gcs.mav.mission_count_send(1, 1, 3, MISSION)
        request = await wait_for(gcs, ["MISSION_REQUEST", "MISSION_REQUEST_INT"], 5)
        assert request.seq == 0
        send_item(gcs, *item(1, MAV.MAV_CMD_NAV_TAKEOFF, alt=10))
        refused = await wait_for(gcs, "MISSION_ACK", 5)
        assert refused.type == MAV.MAV_MISSION_INVALID_SEQUENCE
        send_item(gcs, 0, MAV.MAV_CMD_NAV_WAYPOINT, HOME, 0, 0, 0)
        request = await wait_for(gcs, ["MISSION_REQUEST", "MISSION_REQUEST_INT"], 5)
        assert request.seq == 1  # still waiting for its items, in order


async def test_a_stalled_upload_times_out_and_auto_flies_nothing_the_agent_did_not_finish():
    args = (
        "--home",
        f"{HOME[0]},{HOME[1]}",
        "--speedup",
        "6",
    )
    with simulator_listening(*args) as (_, address), ground_station(address) as gcs:
        gcs.mav.mission_count_send(1, 1, 3, MISSION)
        await wait_for(gcs, ["MISSION_REQUEST", "MISSION_REQUEST_INT"], 5)
        send_item(gcs, 0, MAV.MAV_CMD_NAV_WAYPOINT, HOME, 0, 0, 0)
        # Item 1 never comes: asked for again every second, then cancelled at 8 s.
        again = await wait_for(gcs, ["MISSION_REQUEST", "MISSION_REQUEST_INT"], 3)
        assert again.seq == 1
        cancelled = await wait_for(gcs, "MISSION_ACK", 15)
        assert cancelled.type == MAV.MAV_MISSION_OPERATION_CANCELLED
        # ArduPilot keeps what came (item 0, home): still nothing AUTO can fly.
        assert await mission_count(gcs) == 1
        await take_off(gcs, 5)
        assert await mode(gcs, AUTO) == MAV.MAV_RESULT_FAILED
        beat = await wait_for(gcs, "HEARTBEAT", 3)
        assert beat.custom_mode == GUIDED


async def test_items_the_autopilot_cannot_store_end_the_upload_with_its_reason():
    args = (
        "--home",
        f"{HOME[0]},{HOME[1]}",
    )
    with simulator_listening(*args) as (_, address), ground_station(address) as gcs:
        unknown = [item(0, MAV.MAV_CMD_NAV_WAYPOINT, point=HOME), item(1, 31000)]
        assert (await upload(gcs, unknown)).type == MAV.MAV_MISSION_UNSUPPORTED
        gcs.mav.mission_count_send(1, 1, 701, MISSION)
        full = await wait_for(gcs, "MISSION_ACK", 5)
        assert full.type == MAV.MAV_MISSION_NO_SPACE
        text = await wait_for(gcs, "STATUSTEXT", 5)
        assert text.text == "Only 700 items are supported"


async def test_a_fence_breach_in_auto_brings_the_copter_home():
    """FENCE_ACTION 1 (RTL) acts in AUTO as in any mode: the mission crosses the circle."""
    args = (
        "--home", f"{HOME[0]},{HOME[1]}", "--speedup", "6",
        "--param", "FENCE_ENABLE=1", "--param", "FENCE_TYPE=2", "--param", "FENCE_RADIUS=25",
    )  # fmt: skip
    with simulator_listening(*args) as (_, address), ground_station(address) as gcs:
        streaming(gcs)
        assert (await upload(gcs, FLIGHT)).type == MAV.MAV_MISSION_ACCEPTED
        await take_off(gcs, 5)
        assert await mode(gcs, AUTO) == MAV.MAV_RESULT_ACCEPTED
        text = await wait_for(gcs, "STATUSTEXT", 30, lambda m: "fence" in m.text)
        assert text.text == "Circle fence breached"
        await wait_for(gcs, "HEARTBEAT", 5, lambda m: m.custom_mode == RTL)


# --- the agent's side: agents/vehicles/mavlink/mission.py -------------------------------


def test_a_hold_is_an_unlimited_loiter_over_the_last_waypoint() -> None:
    """The plan's hold becomes NAV_LOITER_UNLIM where the last waypoint left the vehicle
    (a boat: no altitude, as its waypoints); with no waypoint before it, ArduPilot's 0,
    0 and 0 m: where the vehicle is, as high as it is."""
    plan = [
        TakeOff(30), Speed(8), Waypoint(TARGET, 30), Waypoint(TARGET, 5), Release(),
        Waypoint(TARGET, 30), Hold(),
    ]  # fmt: skip
    gripper = {"method": "gripper"}
    items, indices = plan_items(plan, home=HOME, payload=gripper)
    unlimited = MAV.MAV_CMD_NAV_LOITER_UNLIM
    assert items[-1] == MissionItem(unlimited, RELATIVE, lat=TARGET[0], lon=TARGET[1], z=30)
    assert len(items) == len(plan) + 1 and indices == list(range(len(plan)))
    items, indices = plan_items(plan, home=HOME, payload=gripper, flies=False)
    assert items[-1] == MissionItem(unlimited, RELATIVE, lat=TARGET[0], lon=TARGET[1], z=0)
    assert indices == list(range(1, len(plan)))  # no take-off
    items, indices = plan_items([Speed(8), Hold()], home=HOME, payload=None)
    assert items[-1] == MissionItem(unlimited, RELATIVE) and indices == [0, 1]


async def test_a_refused_upload_is_named_cleared_and_changes_nothing_the_copter_does():
    options = {"origin": list(HOME), "simulator": {"speedup": 6}}
    async with simulator_running("mavlink", options) as sim:
        drone = adapter_create("mavlink", sim.options)
        assert isinstance(drone, MavlinkAdapter)
        async with drone:
            await poll(lambda: drone.t.home is not None, 10, "home")
            short = [TakeOff(10), Waypoint(TARGET, 10), ReturnHome()]
            with pytest.raises(AdapterError, match="take off before starting a mission"):
                await drone.mission_upload(short)
                await drone.mission_start()  # on the ground: ArduCopter arms in no AUTO
            await drone.execute("take_off", {"altitude_m": 5})
            await poll(lambda: (drone.t.alt or 0) > 4.5, 20, "5 m")
            # More than the autopilot stores: refused whole, named, and what it had
            # before (the short plan) cleared too, so that nothing half-meant can fly.
            too_long = [Waypoint(offset(HOME, i / 10, 0), 10) for i in range(700)]
            refusal = r"refused the mission: MAV_MISSION_NO_SPACE \(more items than the autopilot"
            with pytest.raises(AdapterError, match=refusal):
                await drone.mission_upload(too_long)
            with pytest.raises(AdapterError, match="no mission has been uploaded"):
                await drone.mission_start()
            assert await stored_items(drone) == 0
            assert drone.state().mode == "GUIDED"
            here = drone.state().position
            assert here is not None and distance_m(here, HOME) < 2  # holding where it was


async def stored_items(drone: MavlinkAdapter) -> int:
    """How many mission items the autopilot holds (MISSION_REQUEST_LIST)."""
    answer = await drone.link.request(
        lambda: MAV.MAVLink_mission_request_list_message(1, 1, MISSION),
        "MISSION_COUNT",
        lambda m: m.mission_type == MISSION,
        what="the mission's count",
    )
    return int(answer.count)
