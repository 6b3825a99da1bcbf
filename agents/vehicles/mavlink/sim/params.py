"""The simulated autopilots' parameters: ArduCopter's and ArduRover's, as each release
names them.

A table maps a name to ``(default, is_integer)``, in the units and with the defaults the
firmware ships (ArduCopter: cm, cm/s, ms; ArduRover: m, m/s, s), in the order the
autopilot indexes them (PARAM_VALUE's ``param_index``). Only the parameters the
simulator acts on, and those the agent or a ground station reads, are here.
"""

from __future__ import annotations

from collections.abc import Mapping

#: ArduCopter 4.5. FS_OPTIONS ships 16, "continue if in pilot controlled modes on GCS
#: failsafe" (ArduCopter/Parameters.cpp since 4.1).
COPTER_PARAMS: Mapping[str, tuple[float, bool]] = {
    "SYSID_THISMAV": (1, True),
    "SYSID_MYGCS": (255, True),
    "FS_GCS_ENABLE": (0, True),
    "FS_GCS_TIMEOUT": (5.0, False),
    "FS_OPTIONS": (16, True),
    "RTL_ALT": (1500, True),
    "RTL_ALT_FINAL": (0, True),
    "RTL_CLIMB_MIN": (0, True),
    "RTL_LOIT_TIME": (5000, True),
    "RTL_SPEED": (0, True),
    "WPNAV_SPEED": (500.0, False),
    "WPNAV_SPEED_UP": (250.0, False),
    "WPNAV_SPEED_DN": (150.0, False),
    "WPNAV_RADIUS": (200.0, False),
    "WPNAV_ACCEL": (250.0, False),
    "WPNAV_ACCEL_Z": (100.0, False),
    "PSC_JERK_XY": (5.0, False),
    "PSC_JERK_Z": (5.0, False),
    "LAND_SPEED": (50, True),
    "LAND_SPEED_HIGH": (0, True),
    "LAND_ALT_LOW": (1000, True),
    "DISARM_DELAY": (10, True),
    "GUID_TIMEOUT": (3.0, False),
    "WP_YAW_BEHAVIOR": (1, True),
    "ARMING_CHECK": (1, True),
    "BATT_CAPACITY": (5200, True),
    "BATT_ARM_VOLT": (0.0, False),
    "PILOT_TKOFF_ALT": (0.0, False),
    "MIS_RESTART": (0, True),
    "FENCE_ENABLE": (0, True),
    "FENCE_TYPE": (7, True),
    "FENCE_ACTION": (1, True),
    "FENCE_ALT_MAX": (100.0, False),
    "FENCE_RADIUS": (300.0, False),
    "FENCE_MARGIN": (2.0, False),
}

#: ArduRover 4.5 with FRAME_CLASS 2, a boat (Rover/Parameters.cpp, AR_WPNav,
#: AR_AttitudeControl). FS_ACTION: 0 nothing, 1 RTL, 2 Hold, 3 SmartRTL or RTL,
#: 4 SmartRTL or Hold, 5 Terminate (disarm), 6 Loiter or Hold; FS_OPTIONS bit 0: the
#: fail-safe acts in HOLD too. WP_SPEED 0 means CRUISE_SPEED; ATC_DECEL_MAX 0 means
#: ATC_ACCEL_MAX.
BOAT_PARAMS: Mapping[str, tuple[float, bool]] = {
    "SYSID_THISMAV": (1, True),
    "SYSID_MYGCS": (255, True),
    "FRAME_CLASS": (2, True),
    "FS_GCS_ENABLE": (0, True),
    "FS_ACTION": (2, True),
    "FS_TIMEOUT": (1.5, False),
    "FS_OPTIONS": (0, True),
    "CRUISE_SPEED": (2.0, False),
    "WP_SPEED": (2.0, False),
    "WP_RADIUS": (2.0, False),
    "RTL_SPEED": (0.0, False),
    "LOIT_TYPE": (0, True),
    "LOIT_RADIUS": (2.0, False),
    "LOIT_SPEED_GAIN": (0.5, False),
    "ATC_ACCEL_MAX": (1.0, False),
    "ATC_DECEL_MAX": (0.0, False),
    "ATC_STR_RAT_MAX": (120.0, False),
    "ATC_STR_ACC_MAX": (120.0, False),
    "ARMING_CHECK": (1, True),
    "BATT_CAPACITY": (5200, True),
    "MIS_RESTART": (0, True),
    "FENCE_ENABLE": (0, True),
    "FENCE_TYPE": (6, True),
    "FENCE_ACTION": (1, True),
    "FENCE_RADIUS": (300.0, False),
    "FENCE_MARGIN": (2.0, False),
}

#: The simulated vehicles (a ``vehicle_class`` of :mod:`..classes`) -> their firmware's
#: parameters at 4.5.
VEHICLE_PARAMS: Mapping[str, Mapping[str, tuple[float, bool]]] = {
    "copter": COPTER_PARAMS,
    "boat": BOAT_PARAMS,
}

#: ArduPilot 4.7 moved the MAVLink ids into the MAV_ namespace (a parameter conversion
#: of March 2025), and named the position controller's axes NE and D: old name -> new
#: name. SYSID_MYGCS, PSC_JERK_XY and PSC_JERK_Z no longer exist there.
RENAMED_IN_4_7 = {
    "SYSID_THISMAV": "MAV_SYSID",
    "SYSID_MYGCS": "MAV_GCS_SYSID",
    "PSC_JERK_XY": "PSC_JERK_NE",
    "PSC_JERK_Z": "PSC_JERK_D",
}
#: ... and added an upper end: GCS ids MAV_GCS_SYSID..MAV_GCS_SYSID_HI when HI >= the id.
#: ArduRover also has FS_GCS_TIMEOUT by then (before it, the GCS counted as lost after
#: a fixed 2 s of silence).
ADDED_IN_4_7: Mapping[str, Mapping[str, tuple[float, bool]]] = {
    "copter": {"MAV_GCS_SYSID_HI": (0, True)},
    "boat": {"MAV_GCS_SYSID_HI": (0, True), "FS_GCS_TIMEOUT": (5.0, False)},
}
#: The simulated releases: ``--firmware`` -> AUTOPILOT_VERSION's flight_sw_version
#: (major, minor, patch, type: 255 official, 0 development).
FIRMWARES = {"4.5": (4, 5, 7, 255), "4.7": (4, 7, 0, 0)}
#: The simulated release by default: 4.5.7, official.
DEFAULT_FIRMWARE = "4.5"


def firmware_params(firmware: str, vehicle: str = "copter") -> dict[str, tuple[float, bool]]:
    """The parameter table of ``vehicle``'s firmware (``copter`` or ``boat``) at release
    ``firmware`` (a key of :data:`FIRMWARES`), in index order."""
    params = dict(VEHICLE_PARAMS[vehicle])
    if firmware == "4.5":
        return params
    table = {RENAMED_IN_4_7.get(name, name): spec for name, spec in params.items()}
    return {**table, **ADDED_IN_4_7[vehicle]}


#: Every parameter name some simulated firmware has (what ``--param`` accepts before the
#: vehicle and the release are known).
KNOWN_PARAMS = frozenset(
    name for f in FIRMWARES for v in VEHICLE_PARAMS for name in firmware_params(f, v)
)
