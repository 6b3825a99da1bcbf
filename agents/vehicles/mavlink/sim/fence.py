"""The simulated autopilot's fence: ArduPilot's AC_Fence, as ArduCopter and ArduRover
act on it (``libraries/AC_Fence/AC_Fence.cpp``, ``ArduCopter/fence.cpp``,
``Rover/fence.cpp``), no I/O.

Parameters (the firmware's): ``FENCE_ENABLE``; ``FENCE_TYPE``, a bitmask: 1 the maximum
altitude ``FENCE_ALT_MAX`` (ArduCopter), 2 the circle of ``FENCE_RADIUS`` around home,
4 the uploaded inclusion circles (``MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION``, sent with the
mission protocol for ``MAV_MISSION_TYPE_FENCE``: the autopilot, :mod:`.autopilot`, keeps
them here); ``FENCE_ACTION``; ``FENCE_MARGIN`` (ArduCopter's RTL stays that far under
``FENCE_ALT_MAX``).

Checked while armed (ArduCopter: 25 Hz). A new breach says "<Max Alt|Circle|Polygon>
fence breached" (NOTICE) and acts as FENCE_ACTION says, once: ArduCopter 0 report
only, 1 RTL (else LAND), 2 LAND, 3 SmartRTL (else RTL, else LAND), 4 BRAKE (else LAND),
5 SmartRTL (else LAND), and LAND whatever the action more than 100 m out (landed: it
disarms); ArduRover 0 report only, 1 RTL (else HOLD), 2 HOLD, 3 SmartRTL (else RTL,
else HOLD), 4 SmartRTL (else HOLD), 5 disarm, and HOLD more than 100 m out. Back
inside, "Fence breach cleared". Not modelled: polygons and exclusion
zones, the minimum altitude, the backup fences 20 m further out, pre-arm checks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from agents.geo import local_offset_m, offset
from agents.vehicles.mavlink.dialect import MAV

#: FENCE_TYPE bits, in the order ArduPilot names them.
ALT_MAX, CIRCLE, POLYGON = 1, 2, 4
FENCE_NAMES = {ALT_MAX: "Max Alt", CIRCLE: "Circle", POLYGON: "Polygon"}
#: ArduCopter lands rather than returns when this far (m) past a fence.
GIVE_UP_DISTANCE_M = 100.0


@dataclass
class SimFence:
    """The fence's uploaded circles and breach state (see the module docstring)."""

    #: Inclusion circles: (north, east, radius), metres from home.
    circles: list[tuple[float, float, float]] = field(default_factory=list)
    #: FENCE_TYPE bits breached now, how many breaches so far, and when the last began
    #: (ms of the vehicle's clock): FENCE_STATUS's fields.
    breached: int = 0
    breach_count: int = 0
    breach_time_ms: int = 0

    def check(
        self, params: dict[str, float], north: float, east: float, up: float, *, flies: bool
    ) -> tuple[int, float]:
        """The fences breached now that were not (FENCE_TYPE bits) and how far out the
        vehicle is (m); updates the state. Nothing while FENCE_ENABLE is 0."""
        if not params.get("FENCE_ENABLE"):
            self.breached = 0
            return 0, 0.0
        types = int(params.get("FENCE_TYPE", 0))
        now: int = 0
        distance = 0.0
        if flies and types & ALT_MAX and up >= params["FENCE_ALT_MAX"]:
            now |= ALT_MAX
            distance = max(distance, up - params["FENCE_ALT_MAX"])
        from_home = math.hypot(north, east)
        if types & CIRCLE and from_home >= params["FENCE_RADIUS"]:
            now |= CIRCLE
            distance = max(distance, from_home - params["FENCE_RADIUS"])
        if types & POLYGON and self.circles:
            out = min(math.hypot(north - n, east - e) - r for n, e, r in self.circles)
            if out >= 0:
                now |= POLYGON
                distance = max(distance, out)
        new = now & ~self.breached
        if new:
            self.breach_count += 1
        self.breached = now
        return new, distance


def fence_breach_type(types: int) -> int:
    """FENCE_STATUS's breach_type for FENCE_TYPE bits (as ArduCopter fills it in)."""
    if types & (CIRCLE | POLYGON):
        return int(MAV.FENCE_BREACH_BOUNDARY)
    if types & ALT_MAX:
        return int(MAV.FENCE_BREACH_MAXALT)
    return int(MAV.FENCE_BREACH_NONE)


def fence_names(types: int) -> str:
    """ArduPilot's words for FENCE_TYPE bits: "Max Alt and Circle fences"."""
    names = [name for bit, name in FENCE_NAMES.items() if types & bit]
    words = names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]
    return f"{words} fence" + ("s" if len(names) > 1 else "")


class FenceTransfer:
    """The mission protocol for ``MAV_MISSION_TYPE_FENCE``, as ArduPilot answers it,
    on a :class:`SimFence`: each method takes what a ground station sent and returns the
    messages to send back. Uploads (MISSION_COUNT, then a MISSION_REQUEST_INT for each
    MISSION_ITEM_INT, then MISSION_ACK), downloads (MISSION_REQUEST_LIST,
    MISSION_REQUEST_INT) and MISSION_CLEAR_ALL. Items other than inclusion circles are
    refused (MAV_MISSION_UNSUPPORTED): this simulator has no polygons."""

    def __init__(self, fence: SimFence, home: tuple[float, float]) -> None:
        self.fence = fence
        self.home = home
        self._expected = 0
        self._items: list[tuple[float, float, float]] = []

    def count(self, msg: Any) -> list[Any]:
        """MISSION_COUNT: a new upload (none: the fence is cleared)."""
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        self._expected, self._items = int(msg.count), []
        if self._expected == 0:
            self.fence.circles = []
            return [_ack(peer, MAV.MAV_MISSION_ACCEPTED)]
        return [_request(peer, 0)]

    def item(self, msg: Any) -> list[Any]:
        """MISSION_ITEM_INT of the upload under way: the next is asked for, or, after
        the last, the fence is replaced and acknowledged."""
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        seq = int(msg.seq)
        if not self._expected or seq > len(self._items):
            return [_ack(peer, MAV.MAV_MISSION_OPERATION_CANCELLED)]
        if seq < len(self._items):  # a resend: ask again for the one after it
            return [_request(peer, len(self._items))]
        if msg.command != MAV.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION or msg.param1 <= 0:
            self._expected = 0
            return [_ack(peer, MAV.MAV_MISSION_UNSUPPORTED)]
        north, east = local_offset_m(self.home, (msg.x / 1e7, msg.y / 1e7))
        self._items.append((north, east, float(msg.param1)))
        if len(self._items) < self._expected:
            return [_request(peer, len(self._items))]
        self.fence.circles, self._expected = list(self._items), 0
        return [_ack(peer, MAV.MAV_MISSION_ACCEPTED)]

    def clear(self, msg: Any) -> list[Any]:
        """MISSION_CLEAR_ALL: no uploaded fence any more."""
        self.fence.circles, self._expected = [], 0
        return [_ack((msg.get_srcSystem(), msg.get_srcComponent()), MAV.MAV_MISSION_ACCEPTED)]

    def request_list(self, msg: Any) -> list[Any]:
        """MISSION_REQUEST_LIST: how many items the fence has."""
        count = len(self.fence.circles)
        fence = MAV.MAV_MISSION_TYPE_FENCE
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        return [MAV.MAVLink_mission_count_message(peer[0], peer[1], count, fence)]

    def request(self, msg: Any) -> list[Any]:
        """MISSION_REQUEST_INT (or MISSION_REQUEST) of a download: that item."""
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        seq = int(msg.seq)
        if not 0 <= seq < len(self.fence.circles):
            return [_ack(peer, MAV.MAV_MISSION_INVALID_SEQUENCE)]
        north, east, radius = self.fence.circles[seq]
        lat, lon = offset(self.home, north, east)
        return [
            MAV.MAVLink_mission_item_int_message(
                peer[0], peer[1], seq, MAV.MAV_FRAME_GLOBAL,
                MAV.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, 0, 1, radius, 0, 0, 0,
                round(lat * 1e7), round(lon * 1e7), 0, MAV.MAV_MISSION_TYPE_FENCE,
            )
        ]  # fmt: skip


def _request(peer: tuple[int, int], seq: int) -> Any:
    return MAV.MAVLink_mission_request_int_message(
        peer[0], peer[1], seq, MAV.MAV_MISSION_TYPE_FENCE
    )


def _ack(peer: tuple[int, int], result: int) -> Any:
    return MAV.MAVLink_mission_ack_message(peer[0], peer[1], result, MAV.MAV_MISSION_TYPE_FENCE)
