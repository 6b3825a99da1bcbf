"""The simulated autopilot's mission: ArduPilot's AP_Mission store and the MAVLink
mission protocol for ``MAV_MISSION_TYPE_MISSION`` as ArduPilot answers it
(``libraries/GCS_MAVLink/MissionItemProtocol.cpp``, ``MissionItemProtocol_Waypoints.cpp``,
``libraries/AP_Mission/AP_Mission.cpp``), no I/O.

The store (:class:`SimMission`): item 0 is home (written by the upload like any item,
never flown), the mission proper starts at 1. What AUTO does with it is each vehicle's
(:mod:`.copter`); the store keeps where a mission is (the current navigation item, its
state) and what it has to say (MISSION_ITEM_REACHED).

The upload (:class:`MissionTransfer`), as ArduPilot does it, and with its sharp edges:

* MISSION_COUNT truncates the stored mission to that count at once and asks for item 0
  (MISSION_REQUEST); more than :data:`MAX_ITEMS` is MAV_MISSION_NO_SPACE and changes
  nothing; another system's upload while one is under way is MAV_MISSION_DENIED;
* each MISSION_ITEM_INT must be the one asked for, else MAV_MISSION_INVALID_SEQUENCE
  (the upload goes on waiting for the right one); an item ArduPilot cannot store (an
  unknown command, a frame it does not take, a position off the globe) ends the upload
  with its MAV_MISSION result. Items are written as they come: a broken upload leaves
  the mission truncated and partly replaced (a ground station clears or re-sends it);
* the last item is answered with MAV_MISSION_ACCEPTED and "Flight plan received";
* a request unanswered is repeated every second; nothing for
  :data:`UPLOAD_TIMEOUT_S` ends the upload with MAV_MISSION_OPERATION_CANCELLED and
  "Mission upload timeout";
* MISSION_CLEAR_ALL is refused (MAV_MISSION_ERROR) while an upload is under way or the
  mission runs (AP_Mission::clear); downloads (MISSION_REQUEST_LIST, then
  MISSION_REQUEST_INT per item) are DENIED during an upload.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from agents.vehicles.mavlink.dialect import MAV

#: How many items the simulated autopilot stores (ArduPilot: what its storage holds,
#: some 700 on a board with 16 KiB for the mission).
MAX_ITEMS = 700
#: ArduPilot's MissionItemProtocol: an upload silent this long is cancelled ...
UPLOAD_TIMEOUT_S = 8.0
#: ... and the item it waits for is asked for again after this long.
REQUEST_RESEND_S = 1.0

NAV_WAYPOINT = int(MAV.MAV_CMD_NAV_WAYPOINT)
NAV_LOITER_TIME = int(MAV.MAV_CMD_NAV_LOITER_TIME)
NAV_LOITER_UNLIM = int(MAV.MAV_CMD_NAV_LOITER_UNLIM)
NAV_RETURN_TO_LAUNCH = int(MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH)
NAV_LAND = int(MAV.MAV_CMD_NAV_LAND)
NAV_TAKEOFF = int(MAV.MAV_CMD_NAV_TAKEOFF)
DO_CHANGE_SPEED = int(MAV.MAV_CMD_DO_CHANGE_SPEED)
DO_SET_SERVO = int(MAV.MAV_CMD_DO_SET_SERVO)
DO_GRIPPER = int(MAV.MAV_CMD_DO_GRIPPER)
DO_DIGICAM_CONTROL = int(MAV.MAV_CMD_DO_DIGICAM_CONTROL)
DO_SET_CAM_TRIGG_DIST = int(MAV.MAV_CMD_DO_SET_CAM_TRIGG_DIST)
#: The navigation commands this simulator flies, and the "do" commands it performs.
NAV_COMMANDS = frozenset(
    {NAV_WAYPOINT, NAV_LOITER_TIME, NAV_LOITER_UNLIM, NAV_RETURN_TO_LAUNCH, NAV_LAND, NAV_TAKEOFF}
)
DO_COMMANDS = frozenset(
    {DO_CHANGE_SPEED, DO_SET_SERVO, DO_GRIPPER, DO_DIGICAM_CONTROL, DO_SET_CAM_TRIGG_DIST}
)
#: Frames AP_Mission stores a position in (global: AMSL; relative: above home).
GLOBAL_FRAMES = frozenset({0, 5})
RELATIVE_FRAMES = frozenset({3, 6})
#: MAV_FRAME_MISSION: a "do" command's frame (no position).
FRAME_MISSION = 2


@dataclass(frozen=True)
class Item:
    """One stored mission item: its command, frame, params 1-4, and position (degrees;
    metres above home, or AMSL in a global frame)."""

    command: int
    frame: int
    params: tuple[float, float, float, float]
    lat: float
    lon: float
    alt: float

    @property
    def is_nav(self) -> bool:
        return self.command in NAV_COMMANDS

    @property
    def has_position(self) -> bool:
        """A position to fly to (0/0 means "where the vehicle is", as in ArduPilot)."""
        return (self.lat, self.lon) != (0.0, 0.0)


@dataclass
class SimMission:
    """The stored mission and where AUTO is in it (see the module docstring)."""

    items: list[Item] = field(default_factory=list)
    #: The navigation item AUTO flies now (its index), or None (not started).
    current: int | None = None
    #: "stopped" (never run, or left), "running" (in AUTO), "complete".
    state: str = "stopped"
    #: MISSION_ITEM_REACHED to send, oldest first; and whether MISSION_CURRENT changed.
    reached: deque[int] = field(default_factory=lambda: deque(maxlen=64))
    current_changed: bool = False

    @property
    def count(self) -> int:
        """Items including home (MISSION_COUNT's count)."""
        return len(self.items)

    def flyable(self) -> bool:
        """Whether there is a mission beyond home (AUTO needs one)."""
        return len(self.items) > 1

    def set_current(self, index: int | None) -> None:
        if index != self.current:
            self.current = index
            self.current_changed = True


class MissionTransfer:
    """The mission protocol for ``MAV_MISSION_TYPE_MISSION`` on a :class:`SimMission`
    (see the module docstring). Each method takes what a ground station sent (and the
    wall-clock time) and returns the messages to send back; :meth:`update` those due by
    themselves (a repeated request, a timeout)."""

    def __init__(self, mission: SimMission, home: tuple[float, float]) -> None:
        self.mission = mission
        self.home = home
        self.receiving = False
        self.peer = (0, 0)
        self.expected = 0  # request_i
        self.last = -1  # request_last
        self.received_at = 0.0
        self.requested_at = 0.0
        #: STATUSTEXTs to say (severity, text), for the autopilot to send first.
        self.texts: deque[tuple[int, str]] = deque(maxlen=8)

    def count(self, msg: Any, now: float) -> list[Any]:
        peer = _peer(msg)
        if self.receiving and peer != self.peer:
            return [_ack(peer, MAV.MAV_MISSION_DENIED)]
        count = int(msg.count)
        if count > MAX_ITEMS:
            self.texts.append((MAV.MAV_SEVERITY_WARNING, f"Only {MAX_ITEMS} items are supported"))
            return [_ack(peer, MAV.MAV_MISSION_NO_SPACE)]
        # AP_Mission::truncate: the stored mission is cut to the new count at once.
        del self.mission.items[count:]
        if count == 0:
            self.receiving = False
            self.texts.append((MAV.MAV_SEVERITY_INFO, "Flight plan received"))
            return [_ack(peer, MAV.MAV_MISSION_ACCEPTED)]
        self.receiving, self.peer = True, peer
        self.expected, self.last = 0, count - 1
        self.received_at = self.requested_at = now
        return [_request(peer, 0)]

    def item(self, msg: Any, now: float) -> list[Any]:
        peer = _peer(msg)
        if not self.receiving:
            return [_ack(peer, MAV.MAV_MISSION_ERROR)]
        if int(msg.seq) != self.expected:
            return [_ack(peer, MAV.MAV_MISSION_INVALID_SEQUENCE)]
        if peer != self.peer:
            return [_ack(peer, MAV.MAV_MISSION_DENIED)]
        item, result = _stored(msg)
        if item is None:
            self.receiving = False
            return [_ack(peer, result)]
        seq = int(msg.seq)
        if seq < len(self.mission.items):
            self.mission.items[seq] = item
        else:
            self.mission.items.append(item)
        self.received_at = now
        self.expected += 1
        if self.expected > self.last:
            self.receiving = False
            self.texts.append((MAV.MAV_SEVERITY_INFO, "Flight plan received"))
            return [_ack(peer, MAV.MAV_MISSION_ACCEPTED)]
        self.requested_at = now
        return [_request(peer, self.expected)]

    def update(self, now: float) -> list[Any]:
        """A stalled upload: the request again after a second, cancelled after
        :data:`UPLOAD_TIMEOUT_S`."""
        if not self.receiving:
            return []
        if now - self.received_at > UPLOAD_TIMEOUT_S:
            self.receiving = False
            self.texts.append((MAV.MAV_SEVERITY_WARNING, "Mission upload timeout"))
            return [_ack(self.peer, MAV.MAV_MISSION_OPERATION_CANCELLED)]
        if now - self.requested_at > REQUEST_RESEND_S:
            self.requested_at = now
            return [_request(self.peer, self.expected)]
        return []

    def clear(self, msg: Any) -> list[Any]:
        if self.receiving or self.mission.state == "running":
            return [_ack(_peer(msg), MAV.MAV_MISSION_ERROR)]
        self.mission.items.clear()
        self.mission.set_current(None)
        self.mission.state = "stopped"
        return [_ack(_peer(msg), MAV.MAV_MISSION_ACCEPTED)]

    def request_list(self, msg: Any) -> list[Any]:
        peer = _peer(msg)
        if self.receiving:
            return [_ack(peer, MAV.MAV_MISSION_DENIED)]
        return [
            MAV.MAVLink_mission_count_message(
                peer[0], peer[1], self.mission.count, MAV.MAV_MISSION_TYPE_MISSION
            )
        ]

    def request(self, msg: Any) -> list[Any]:
        peer = _peer(msg)
        if self.receiving:
            return [_ack(peer, MAV.MAV_MISSION_DENIED)]
        seq = int(msg.seq)
        if not 0 <= seq < self.mission.count:
            return [_ack(peer, MAV.MAV_MISSION_ERROR)]
        item = self.mission.items[seq]
        return [
            MAV.MAVLink_mission_item_int_message(
                peer[0], peer[1], seq, item.frame, item.command,
                int(seq == self.mission.current), 1, *item.params,
                round(item.lat * 1e7), round(item.lon * 1e7), item.alt,
                MAV.MAV_MISSION_TYPE_MISSION,
            )
        ]  # fmt: skip


def _stored(msg: Any) -> tuple[Item | None, int]:
    """The item as AP_Mission stores it, or None and the MAV_MISSION result refusing it
    (AP_Mission::mavlink_int_to_mission_cmd)."""
    command, frame = int(msg.command), int(msg.frame)
    if command not in NAV_COMMANDS | DO_COMMANDS:
        return None, int(MAV.MAV_MISSION_UNSUPPORTED)
    lat, lon = msg.x / 1e7, msg.y / 1e7
    if command in NAV_COMMANDS:
        if frame not in GLOBAL_FRAMES | RELATIVE_FRAMES:
            return None, int(MAV.MAV_MISSION_UNSUPPORTED_FRAME)
        if not -90 <= lat <= 90:
            return None, int(MAV.MAV_MISSION_INVALID_PARAM5_X)
        if not -180 <= lon <= 180:
            return None, int(MAV.MAV_MISSION_INVALID_PARAM6_Y)
    params = (float(msg.param1), float(msg.param2), float(msg.param3), float(msg.param4))
    if not all(math.isfinite(p) for p in params):
        return None, int(MAV.MAV_MISSION_INVALID_PARAM1)
    return Item(command, frame, params, lat, lon, float(msg.z)), int(MAV.MAV_MISSION_ACCEPTED)


def _peer(msg: Any) -> tuple[int, int]:
    return msg.get_srcSystem(), msg.get_srcComponent()


def _request(peer: tuple[int, int], seq: int) -> Any:
    # ArduPilot asks with MISSION_REQUEST (queued_request_send), which ground stations
    # answer with MISSION_ITEM_INT when they speak MAVLink 2.
    return MAV.MAVLink_mission_request_message(peer[0], peer[1], seq, MAV.MAV_MISSION_TYPE_MISSION)


def _ack(peer: tuple[int, int], result: int) -> Any:
    return MAV.MAVLink_mission_ack_message(peer[0], peer[1], result, MAV.MAV_MISSION_TYPE_MISSION)
