"""The MAVLink wire format as the adapter uses it: the ArduPilot dialect (pymavlink),
COMMAND_ACK results in words, the position-target masks, the telemetry streams and a
few conversions.

pymavlink picks MAVLink 1 or 2, and the dialect it loads first, from the environment
when it is first imported: this module sets MAVLink 2 and the ArduPilot dialect before
importing it (else pymavlink first loads its "all" dialect, only to be told another: a
tenth of a second in every process), so import pymavlink through here.
"""

from __future__ import annotations

import math
import os
from typing import Any

os.environ.setdefault("MAVLINK20", "1")
os.environ.setdefault("MAVLINK_DIALECT", "ardupilotmega")

from pymavlink import mavutil  # type: ignore[import-untyped, unused-ignore]

mavutil.set_dialect("ardupilotmega")
#: The MAVLink module of the ArduPilot dialect (message classes and constants).
MAV: Any = mavutil.mavlink

__all__ = ["MAV", "mavutil"]

#: COMMAND_ACK results in words.
RESULT_WORDS = {
    1: "temporarily rejected",
    2: "denied",
    3: "unsupported",
    4: "failed",
    5: "in progress",
    6: "cancelled",
    7: "accepted only as COMMAND_LONG",
    8: "accepted only as COMMAND_INT",
    9: "refused: unsupported frame",
}
#: What a result means when the autopilot gave no STATUSTEXT with it.
RESULT_HINTS = {
    1: "the autopilot cannot do it right now, e.g. pre-arm checks failed",
    2: "the autopilot does not allow it in its current state",
    3: "the autopilot does not implement it",
    4: "the autopilot tried and could not",
}

#: SET_POSITION_TARGET_LOCAL_NED type_mask: ignore position and acceleration (bits
#: 0-2, 6-8) and yaw (bit 10); use velocity and yaw rate. 0b010111000111 = 1479.
MASK_VELOCITY_YAW_RATE = 0b0000_0101_1100_0111
#: Velocity and a (relative, in a body frame) yaw; ignore yaw rate. 0b100111000111.
MASK_VELOCITY_YAW = 0b0000_1001_1100_0111
#: SET_POSITION_TARGET_GLOBAL_INT: position only.
MASK_POSITION = 0b0000_1101_1111_1000
#: MAV_FRAME_BODY_NED: velocities along the vehicle's heading (a rover's forward speed).
FRAME_BODY_NED = 8

#: The REQUEST_DATA_STREAM fallback for autopilots without SET_MESSAGE_INTERVAL:
#: (stream id, the messages in it), rate = the fastest of those messages.
DATA_STREAMS = (
    (2, ("SYS_STATUS", "GPS_RAW_INT", "EXTENDED_SYS_STATE", "MISSION_CURRENT")),  # EXT_STATUS
    (6, ("GLOBAL_POSITION_INT",)),  # POSITION
    (10, ("ATTITUDE",)),  # EXTRA1
    (11, ("VFR_HUD",)),  # EXTRA2
    (12, ("BATTERY_STATUS", "EKF_STATUS_REPORT")),  # EXTRA3
)

#: GPS_RAW_INT fix_type from which the autopilot's position is a position (3D fix).
GPS_FIX_3D = 3
#: EKF_STATUS_REPORT flag: the EKF has an absolute horizontal position (a GPS fix, or
#: what stands in for one, e.g. an external navigation system).
EKF_POS_HORIZ_ABS = 0x10
#: GPS_RAW_INT fix types in words.
GPS_FIX_WORDS = {0: "none", 1: "none", 2: "2D", 3: "3D", 4: "DGPS", 5: "RTK float", 6: "RTK"}


def command_name(command: int) -> str:
    """``MAV_CMD_NAV_TAKEOFF`` for 22; the number if the dialect does not know it."""
    entry = MAV.enums["MAV_CMD"].get(command)
    return str(entry.name) if entry is not None else f"MAV_CMD {command}"


def param_name(raw: Any) -> str:
    """A PARAM_VALUE's name as text (pymavlink may hand bytes with NUL padding)."""
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0].strip()


def statustext(msg: Any) -> str:
    """A STATUSTEXT's text (pymavlink may hand bytes with NUL padding)."""
    text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("ascii", "replace")
    return str(text).split("\x00", 1)[0].strip()


def body_to_ned(forward: float, right: float, heading_deg: float) -> tuple[float, float]:
    """(north, east) of a body-frame (forward, right) vector at ``heading_deg``."""
    h = math.radians(heading_deg)
    return (
        forward * math.cos(h) - right * math.sin(h),
        forward * math.sin(h) + right * math.cos(h),
    )


def wrap180(deg: float) -> float:
    """``deg`` folded into [-180, 180)."""
    return (deg + 180.0) % 360.0 - 180.0
