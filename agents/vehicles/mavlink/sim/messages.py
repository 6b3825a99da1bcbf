"""What the simulated autopilot says about its vehicle: HEARTBEAT and the telemetry
messages, built from a :class:`~.vehicle.SimVehicle` as ArduPilot fills them in.

Before the EKF has an origin (no GPS fix yet) ArduPilot reports the location it starts
with, 0/0 at 0 m AMSL, no LOCAL_POSITION_NED and no HOME_POSITION; so does this.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

from agents.vehicles.mavlink.dialect import MAV
from agents.vehicles.mavlink.sim.params import FIRMWARES
from agents.vehicles.mavlink.sim.vehicle import SimVehicle, wrap180

#: Message names this simulator can stream; everything else is "unsupported".
STREAMABLE = frozenset(
    {
        "SYS_STATUS",
        "GPS_RAW_INT",
        "GLOBAL_POSITION_INT",
        "LOCAL_POSITION_NED",
        "ATTITUDE",
        "VFR_HUD",
        "BATTERY_STATUS",
        "HOME_POSITION",
        "EXTENDED_SYS_STATE",
        "EKF_STATUS_REPORT",
        "AUTOPILOT_VERSION",
        "SYSTEM_TIME",
        "MISSION_CURRENT",
    }
)


@dataclass(frozen=True)
class Clocks:
    """The times a message carries: since boot in simulated time (``time_boot_ms``),
    and wall-clock microseconds since the autopilot started (GPS_RAW_INT's)."""

    boot_ms: int
    uptime_us: int


def heartbeat(v: SimVehicle, *, critical: bool) -> Any:
    """HEARTBEAT: the vehicle's MAV_TYPE, ArduPilot's base mode flags, the custom mode,
    and the system status (``critical``: a fail-safe under way)."""
    base = MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MAV.MAV_MODE_FLAG_STABILIZE_ENABLED
    base |= MAV.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    if v.mode in v.POSITION_MODES:
        base |= MAV.MAV_MODE_FLAG_GUIDED_ENABLED
    if v.armed:
        base |= MAV.MAV_MODE_FLAG_SAFETY_ARMED
    if critical or v.battery_pct < 5:
        status = MAV.MAV_STATE_CRITICAL
    else:
        status = MAV.MAV_STATE_ACTIVE if v.armed else MAV.MAV_STATE_STANDBY
    return MAV.MAVLink_heartbeat_message(
        v.MAV_TYPE, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA, base, v.mode, status, 3
    )


def message(name: str, v: SimVehicle, clocks: Clocks, *, sysid: int, firmware: str) -> Any:
    """The message ``name`` as of now; None when ArduPilot would send nothing."""
    lat, lon = v.latlon
    lat_i, lon_i = round(lat * 1e7), round(lon * 1e7)
    amsl_mm = int((v.home_alt_amsl + v.up) * 1000)
    ground_speed = math.hypot(v.vn, v.ve)
    if name == "GLOBAL_POSITION_INT":
        # Before the EKF has an origin ArduPilot sends the location it starts with,
        # 0/0 at 0 m AMSL; the height above home comes from the barometer.
        known = v.origin_set
        return MAV.MAVLink_global_position_int_message(
            clocks.boot_ms,
            lat_i if known else 0,
            lon_i if known else 0,
            amsl_mm if known else 0,
            int(v.up * 1000),
            int(v.vn * 100),
            int(v.ve * 100),
            int(-v.vu * 100),
            int(v.yaw * 100) % 36000,
        )
    if name == "LOCAL_POSITION_NED":
        if not v.origin_set:
            return None  # no origin to be local to
        return MAV.MAVLink_local_position_ned_message(
            clocks.boot_ms, v.north, v.east, -v.up, v.vn, v.ve, -v.vu
        )
    if name == "GPS_RAW_INT":
        fixed = v.gps_fix >= 2
        return MAV.MAVLink_gps_raw_int_message(
            clocks.uptime_us,
            v.gps_fix,
            lat_i if fixed else 0,
            lon_i if fixed else 0,
            amsl_mm if fixed else 0,
            80 if fixed else 9999,
            120 if fixed else 9999,
            int(ground_speed * 100),
            int(math.degrees(math.atan2(v.ve, v.vn)) % 360 * 100) if ground_speed > 0.1 else 0,
            v.satellites,
        )
    if name == "ATTITUDE":
        # No roll or pitch: a multicopter's lean and a boat's roll are cosmetic here.
        return MAV.MAVLink_attitude_message(
            clocks.boot_ms,
            0.0,
            0.0,
            math.radians(wrap180(v.yaw)),
            0.0,
            0.0,
            math.radians(v.yaw_rate),
        )
    if name == "VFR_HUD":
        return MAV.MAVLink_vfr_hud_message(
            ground_speed,
            ground_speed,
            round(v.yaw) % 360,
            v.throttle_pct(),
            v.home_alt_amsl + v.up,
            v.vu,
        )
    if name == "SYS_STATUS":
        sensors = (
            MAV.MAV_SYS_STATUS_SENSOR_3D_GYRO
            | MAV.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | MAV.MAV_SYS_STATUS_SENSOR_3D_MAG
            | MAV.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | MAV.MAV_SYS_STATUS_SENSOR_GPS
            | MAV.MAV_SYS_STATUS_SENSOR_BATTERY
        )
        health = sensors if v.position_ok else sensors & ~MAV.MAV_SYS_STATUS_SENSOR_GPS
        return MAV.MAVLink_sys_status_message(
            sensors, sensors, health, 250, millivolts(v), v.current_ca(), int(v.battery_pct),
            0, 0, 0, 0, 0, 0,
        )  # fmt: skip
    if name == "BATTERY_STATUS":
        cells = [int(millivolts(v) / 4)] * 4 + [65535] * 6
        used = v.p("BATT_CAPACITY") * (100.0 - v.battery_pct) / 100.0
        return MAV.MAVLink_battery_status_message(
            0,
            MAV.MAV_BATTERY_FUNCTION_ALL,
            MAV.MAV_BATTERY_TYPE_LIPO,
            2500,
            cells,
            v.current_ca(),
            int(used),
            -1,
            int(v.battery_pct),
        )
    if name == "HOME_POSITION":
        if not v.origin_set:
            return None  # ArduPilot sets home with the EKF origin
        home_lat, home_lon = v.home
        return MAV.MAVLink_home_position_message(
            int(home_lat * 1e7), int(home_lon * 1e7), int(v.home_alt_amsl * 1000),
            0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
        )  # fmt: skip
    if name == "EXTENDED_SYS_STATE":
        return MAV.MAVLink_extended_sys_state_message(
            MAV.MAV_VTOL_STATE_UNDEFINED, v.landed_state()
        )
    if name == "EKF_STATUS_REPORT":
        flags = 0x1 | 0x2 | 0x4 | 0x8 | 0x20  # attitude, velocity, position, alt
        if v.position_ok:
            flags |= 0x10 | 0x100  # absolute horizontal position, pred pos abs
        return MAV.MAVLink_ekf_status_report_message(flags, 0.1, 0.1, 0.1, 0.05, 0.0)
    if name == "SYSTEM_TIME":
        return MAV.MAVLink_system_time_message(int(time.time() * 1e6), clocks.boot_ms)
    if name == "AUTOPILOT_VERSION":
        return autopilot_version(v, sysid=sysid, firmware=firmware)
    if name == "MISSION_CURRENT":
        return mission_current(v)
    return None


def mission_current(v: SimVehicle) -> Any:
    """MISSION_CURRENT: the navigation item AUTO flies (or will resume at), how many
    items follow home, and the mission's state, as ArduPilot fills them in."""
    m = v.mission
    if not m.flyable():
        state = MAV.MISSION_STATE_NO_MISSION
    elif m.state == "complete":
        state = MAV.MISSION_STATE_COMPLETE
    elif m.state == "running":
        state = MAV.MISSION_STATE_ACTIVE
    elif m.current is None:
        state = MAV.MISSION_STATE_NOT_STARTED
    else:
        state = MAV.MISSION_STATE_PAUSED
    in_auto = v.modes.get(v.mode) == "AUTO"
    return MAV.MAVLink_mission_current_message(
        m.current or 0, max(0, m.count - 1), state, 1 if in_auto else 2
    )


def autopilot_version(v: SimVehicle, *, sysid: int, firmware: str) -> Any:
    """AUTOPILOT_VERSION: the capabilities the simulator has and the release it plays."""
    capabilities = (
        MAV.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        | MAV.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
        | MAV.MAV_PROTOCOL_CAPABILITY_MISSION_INT
        | MAV.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
        | MAV.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
        | MAV.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
        | MAV.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
        | MAV.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION
    )
    uid = abs(hash((v.home, sysid))) & 0xFFFFFFFFFFFF
    major, minor, patch, kind = FIRMWARES[firmware]
    return MAV.MAVLink_autopilot_version_message(
        capabilities,
        (major << 24) | (minor << 16) | (patch << 8) | kind,
        0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0x1209, 0x5740, uid,
    )  # fmt: skip


def millivolts(v: SimVehicle) -> int:
    """A 4S LiPo: 16.8 V full, 14.0 V empty, linear enough for a display."""
    return int((14.0 + 2.8 * v.battery_pct / 100.0) * 1000)
