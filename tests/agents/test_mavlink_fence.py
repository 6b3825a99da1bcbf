"""The autopilot's own fence as the second line: set from a task's limits by the agent
(agents/vehicles/mavlink/fence.py), it holds the copter when the agent no longer does.

The simulated ArduCopter checks its fence as ArduCopter does (25 Hz, FENCE_ACTION);
another ground station (system 200) plays whatever moves the copter once the agent is
gone, and watches.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

from agents.geo import distance_m, local_offset_m, offset
from agents.simulation import simulator_running
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.mavlink.dialect import MAV, mavutil
from agents.vehicles.registry import adapter_create
from tests.agents.mavlink_rig import HOME, poll

SIM = {"speedup": 4, "params": {"RTL_ALT": 1500}}
LAND, RTL = 9, 6


async def wait_for(gcs: Any, kind: str, within: float, where: Callable[[Any], bool]) -> Any:
    """The first ``kind`` message from the autopilot for which ``where`` holds."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        gcs.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        msg = await asyncio.to_thread(gcs.recv_match, type=kind, blocking=True, timeout=0.5)
        if msg is not None and msg.get_srcSystem() == 1 and where(msg):
            return msg
    raise AssertionError(f"no {kind} within {within:g} s")


async def param(gcs: Any, name: str) -> float:
    gcs.mav.param_request_read_send(1, 1, name.encode(), -1)
    msg = await wait_for(gcs, "PARAM_VALUE", 5, lambda m: m.param_id == name)
    return float(msg.param_value)


def reposition(gcs: Any, point: tuple[float, float], alt: float) -> None:
    """Another ground station sends the copter somewhere (DO_REPOSITION, GUIDED)."""
    gcs.mav.command_int_send(
        1, 1, MAV.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, MAV.MAV_CMD_DO_REPOSITION, 0, 0,
        -1, MAV.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, 0,
        round(point[0] * 1e7), round(point[1] * 1e7), alt,
    )  # fmt: skip


async def test_with_the_agent_gone_the_autopilots_fence_holds_the_ceiling_and_the_circle():
    async with simulator_running("mavlink", {"origin": list(HOME), "simulator": SIM}) as sim:
        address = sim.options["connection"]
        drone = adapter_create("mavlink", sim.options)
        assert isinstance(drone, MavlinkAdapter)
        events: list[tuple[str, dict[str, Any]]] = []
        drone.on_event = lambda name, data: events.append((name, data))
        async with drone:
            await poll(lambda: drone.t.home is not None, 10, "home")
            problems = await drone.fence_set(
                "land", max_altitude_m=10, geofence_center=HOME, geofence_radius_m=20
            )
            assert problems == []
            [(_, fence)] = [e for e in events if e[0] == "autopilot_fence_set"]
            # 10 m + 2 m of margin, 20 m + 4 m; centred on home: ArduPilot's own circle.
            assert fence == {"alt_max": 12.0, "radius": 24.0, "type": 3, "action": 2, "enable": 1}
            await drone.execute("take_off", {"altitude_m": 5})
            await poll(lambda: (drone.t.alt or 0) > 4.5, 10, "5 m")
        # The agent is gone (close_action none, as a crash leaves it). Someone else
        # sends the copter up to 30 m.
        gcs = mavutil.mavlink_connection(address, source_system=200)
        try:
            assert await param(gcs, "FENCE_ENABLE") == 1  # still set
            reposition(gcs, HOME, 30)
            text = await wait_for(gcs, "STATUSTEXT", 20, lambda m: "fence" in m.text)
            assert text.text == "Max Alt fence breached"
            status = await wait_for(gcs, "FENCE_STATUS", 5, lambda m: m.breach_status == 1)
            assert status.breach_type == MAV.FENCE_BREACH_MAXALT
            await wait_for(gcs, "HEARTBEAT", 5, lambda m: m.custom_mode == LAND)
        finally:
            gcs.close()


async def test_a_fence_centred_away_from_home_is_uploaded_and_put_back_after():
    async with simulator_running("mavlink", {"origin": list(HOME), "simulator": SIM}) as sim:
        address = sim.options["connection"]
        drone = adapter_create("mavlink", sim.options)
        assert isinstance(drone, MavlinkAdapter)
        centre = offset(HOME, 30.0, 0.0)
        async with drone:
            await poll(lambda: drone.t.home is not None, 10, "home")
            problems = await drone.fence_set(
                "return_to_home", geofence_center=centre, geofence_radius_m=40
            )
            assert problems == []
            gcs = mavutil.mavlink_connection(address, source_system=200)
            try:
                assert await param(gcs, "FENCE_TYPE") == 4  # inclusion circles
                assert await param(gcs, "FENCE_ACTION") == 1  # RTL
                gcs.mav.mission_request_list_send(1, 1, MAV.MAV_MISSION_TYPE_FENCE)
                count = await wait_for(gcs, "MISSION_COUNT", 5, lambda m: m.mission_type == 1)
                assert count.count == 1
                gcs.mav.mission_request_int_send(1, 1, 0, MAV.MAV_MISSION_TYPE_FENCE)
                item = await wait_for(gcs, "MISSION_ITEM_INT", 5, lambda m: True)
                assert item.command == MAV.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION
                assert item.param1 == 45.0  # 40 m + 5 m of margin
                assert distance_m(centre, (item.x / 1e7, item.y / 1e7)) < 0.1
                # Out of it (south of home, 30 m from the circle's edge): back home.
                await drone.execute("take_off", {"altitude_m": 5})
                await poll(lambda: (drone.t.alt or 0) > 4.5, 10, "5 m")
                reposition(gcs, offset(HOME, -60.0, 0.0), 5)
                text = await wait_for(gcs, "STATUSTEXT", 20, lambda m: "fence" in m.text)
                assert text.text == "Polygon fence breached"
                await wait_for(gcs, "HEARTBEAT", 5, lambda m: m.custom_mode == RTL)
                here = drone.state().position
                assert here is not None
                north, _ = local_offset_m(centre, here)
                assert north < -40  # it did get out
                # The task ends: the autopilot's fence is as it was.
                assert await drone.fence_clear() == []
                assert await param(gcs, "FENCE_ENABLE") == 0
                assert await param(gcs, "FENCE_TYPE") == 7
                gcs.mav.mission_request_list_send(1, 1, MAV.MAV_MISSION_TYPE_FENCE)
                count = await wait_for(gcs, "MISSION_COUNT", 5, lambda m: m.mission_type == 1)
                assert count.count == 0
            finally:
                gcs.close()
