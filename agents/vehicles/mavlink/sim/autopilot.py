"""An ArduCopter-like MAVLink autopilot, for tests, demos and third-party ground stations.

``python -m agents sim mavlink --listen udpin:127.0.0.1:14550 --home LAT,LON`` runs a
simulated quadcopter that speaks MAVLink 2 through pymavlink the way ArduCopter does
for the command set the IoUV agent uses (see ``docs/vehicles/quadcopter.md``):

* HEARTBEAT at 1 Hz: ``MAV_TYPE_QUADROTOR``, ``MAV_AUTOPILOT_ARDUPILOTMEGA``, base_mode
  flags (custom mode enabled, guided, armed), ``custom_mode`` = ArduCopter's mode
  numbers (STABILIZE 0, GUIDED 4, LOITER 5, RTL 6, LAND 9, BRAKE 17, ...), system_status;
* a COMMAND_ACK for every COMMAND_LONG/COMMAND_INT addressed to it (unknown commands:
  ``MAV_RESULT_UNSUPPORTED``), with a STATUSTEXT explaining each refusal first, as
  ArduPilot does: arming checks (position/GPS fix, battery, mode), GUIDED takeoff,
  CONDITION_YAW (relative or absolute), DO_SET_MODE / SET_MODE, NAV_LAND,
  NAV_RETURN_TO_LAUNCH, DO_REPOSITION, SET_MESSAGE_INTERVAL, REQUEST_MESSAGE,
  REQUEST_AUTOPILOT_CAPABILITIES (AUTOPILOT_VERSION), GET_HOME_POSITION;
* SET_POSITION_TARGET_LOCAL_NED in the local frames and in the body frames
  (``MAV_FRAME_BODY_NED``/``BODY_OFFSET_NED``/``BODY_FRD``: velocities rotated by the
  heading) and SET_POSITION_TARGET_GLOBAL_INT, in GUIDED only. As in ArduCopter a
  velocity setpoint lapses after ``GUID_TIMEOUT`` s, and one that ignores both yaw and
  yaw rate hands yaw to ``WP_YAW_BEHAVIOR`` (by default the nose turns into the
  direction of travel);
* telemetry streams from the start, every stream group at ``--stream-rate`` (1 Hz, the
  default of ArduPilot's stream-rate parameters on ArduPlane and ArduRover; ArduCopter
  ships 0, which ``--stream-rate 0`` reproduces), changed per group by
  REQUEST_DATA_STREAM and per message by SET_MESSAGE_INTERVAL: SYS_STATUS,
  GLOBAL_POSITION_INT, GPS_RAW_INT, ATTITUDE, VFR_HUD, BATTERY_STATUS, HOME_POSITION,
  EXTENDED_SYS_STATE, EKF_STATUS_REPORT, LOCAL_POSITION_NED, SYSTEM_TIME;
* a GPS that may take ``--gps-fix-after`` seconds to get its fix: until then, as
  ArduCopter before its EKF has an origin, GPS_RAW_INT reports no fix and 0 satellites,
  GLOBAL_POSITION_INT 0/0, and there is no home;
* parameters (PARAM_REQUEST_READ / PARAM_REQUEST_LIST / PARAM_SET) for a small set:
  FS_GCS_ENABLE, FS_GCS_TIMEOUT, SYSID_MYGCS, RTL_ALT, RTL_LOIT_TIME, WPNAV_SPEED, ...,
  under the names of its ``--firmware``: ArduPilot 4.7 renamed SYSID_MYGCS to
  MAV_GCS_SYSID (with MAV_GCS_SYSID_HI for a range) and SYSID_THISMAV to MAV_SYSID;
* its own GCS fail-safe: armed, having heard a GCS (sysid ``SYSID_MYGCS``, or within
  ``MAV_GCS_SYSID``..``MAV_GCS_SYSID_HI``) and then nothing from it for
  ``FS_GCS_TIMEOUT`` s, it acts as ``FS_GCS_ENABLE`` says;
* kinematics at 50 Hz: velocity and acceleration limits (``WPNAV_*``), ground contact,
  LAND (fast then slow descent, disarm on touchdown), RTL (climb to ``RTL_ALT``, fly
  home, loiter ``RTL_LOIT_TIME``, land, disarm), BRAKE/LOITER (hold), auto-disarm after
  ``DISARM_DELAY`` s armed on the ground, battery drain (faster when flying).

Time: ``--speedup`` runs the flight physics (and the delays measured in flight time:
RTL loiter, disarm delay, battery drain) that many times faster than the wall clock.
Everything about the link stays on the wall clock: heartbeats, stream rates, the
``GUID_TIMEOUT`` of setpoints and the GCS fail-safe timeout, because the peer sends at
wall-clock rates; so does the time to the first GPS fix, which is not flight.

Not modelled: missions (MISSION_COUNT is always 0), RC input, wind, terrain, EKF
variances, signing.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import signal
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

# pymavlink picks its wire protocol from the environment when first imported.
os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil

from agents.geo import local_offset_m, offset

mavutil.set_dialect("ardupilotmega")
#: The MAVLink module of the ArduPilot dialect (message classes and constants).
MAV: Any = mavutil.mavlink

log = logging.getLogger(__name__)

#: ArduCopter's flight modes (custom_mode numbers), as in pymavlink's table.
COPTER_MODES: dict[int, str] = dict(mavutil.mode_mapping_acm)
MODE_NUMBERS: dict[str, int] = {name: number for number, name in COPTER_MODES.items()}
STABILIZE, ALT_HOLD, AUTO, GUIDED, LOITER, RTL, LAND = 0, 2, 3, 4, 5, 6, 9
POSHOLD, BRAKE, SMART_RTL = 16, 17, 21
#: Modes that need a position estimate (refused while armed without one).
POSITION_MODES = frozenset({AUTO, GUIDED, LOITER, RTL, 7, POSHOLD, BRAKE, SMART_RTL, 23})
#: Modes ArduCopter will not arm in.
NOT_ARMABLE = frozenset({AUTO, RTL, 7, LAND, SMART_RTL, 27})

#: ArduCopter's FS_GCS_ENABLE values (Copter 4.x).
FS_GCS_ACTIONS = {
    0: "disabled",
    1: "RTL",
    2: "RTL (or continue the mission in AUTO)",
    3: "SmartRTL or RTL",
    4: "SmartRTL or LAND",
    5: "LAND",
    6: "DO_LAND_START or RTL",
    7: "BRAKE or LAND",
}

#: The parameter set of ArduCopter 4.5: name -> (default, is_integer). Units as in
#: ArduCopter 4.x (cm, cm/s, ms); defaults as ArduCopter ships them.
PARAMS: dict[str, tuple[float, bool]] = {
    "SYSID_THISMAV": (1, True),
    "SYSID_MYGCS": (255, True),
    "FS_GCS_ENABLE": (0, True),
    "FS_GCS_TIMEOUT": (5.0, False),
    "FS_OPTIONS": (0, True),
    "RTL_ALT": (1500, True),
    "RTL_ALT_FINAL": (0, True),
    "RTL_CLIMB_MIN": (0, True),
    "RTL_LOIT_TIME": (5000, True),
    "RTL_SPEED": (0, True),
    "WPNAV_SPEED": (500.0, False),
    "WPNAV_SPEED_UP": (250.0, False),
    "WPNAV_SPEED_DN": (150.0, False),
    "WPNAV_ACCEL": (250.0, False),
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
}
#: ArduPilot 4.7 moved the MAVLink ids into the MAV_ namespace (a parameter conversion
#: of March 2025): old name -> new name. SYSID_MYGCS no longer exists there.
RENAMED_IN_4_7 = {"SYSID_THISMAV": "MAV_SYSID", "SYSID_MYGCS": "MAV_GCS_SYSID"}
#: ... and added an upper end: GCS ids MAV_GCS_SYSID..MAV_GCS_SYSID_HI when HI >= the id.
ADDED_IN_4_7: dict[str, tuple[float, bool]] = {"MAV_GCS_SYSID_HI": (0, True)}
#: The simulated ArduCopter releases: ``--firmware`` -> AUTOPILOT_VERSION's
#: flight_sw_version (major, minor, patch, type: 255 official, 0 development).
FIRMWARES = {"4.5": (4, 5, 7, 255), "4.7": (4, 7, 0, 0)}


def firmware_params(firmware: str) -> dict[str, tuple[float, bool]]:
    """The parameter table of the simulated ``firmware`` (a key of :data:`FIRMWARES`)."""
    if firmware == "4.5":
        return dict(PARAMS)
    table = {RENAMED_IN_4_7.get(name, name): spec for name, spec in PARAMS.items()}
    return {**table, **ADDED_IN_4_7}


#: Every parameter name some simulated firmware has (what ``--param`` accepts).
KNOWN_PARAMS = frozenset(name for f in FIRMWARES for name in firmware_params(f))

#: REQUEST_DATA_STREAM stream ids -> the messages ArduPilot sends in them (those of
#: them this simulator has), as GCS_MAVLink_Parameters.cpp groups them.
DATA_STREAMS: dict[int, tuple[str, ...]] = {
    2: ("SYS_STATUS", "GPS_RAW_INT", "EXTENDED_SYS_STATE"),  # EXTENDED_STATUS
    6: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),  # POSITION
    10: ("ATTITUDE",),  # EXTRA1
    11: ("VFR_HUD",),  # EXTRA2
    12: ("BATTERY_STATUS", "EKF_STATUS_REPORT", "SYSTEM_TIME"),  # EXTRA3
}
DATA_STREAMS[0] = tuple(m for ms in DATA_STREAMS.values() for m in ms)  # ALL

#: What every stream group sends before a ground station asks for anything, in Hz:
#: ArduPilot's stream-rate parameters (SRn_EXT_STAT, SRn_POSITION, SRn_EXTRA1..3;
#: MAVn_* from 4.7) default to 1 Hz on ArduPlane, ArduRover and AntennaTracker, and to 0
#: on ArduCopter (libraries/GCS_MAVLink/GCS_MAVLink_Parameters.cpp). The simulator
#: streams by default so that any ground station shows telemetry at once;
#: ``--stream-rate 0`` is ArduCopter's own behaviour (nothing until asked).
DEFAULT_STREAM_RATE_HZ = 1.0

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
    }
)

MAX_STREAM_HZ = 50.0
PHYSICS_HZ = 50.0
DEFAULT_YAW_RATE_DEG_S = 60.0
#: The simulated firmware by default: ArduCopter 4.5.7, official release.
DEFAULT_FIRMWARE = "4.5"

TYPE_MASK_POS = 0b111
TYPE_MASK_VEL = 0b111000
TYPE_MASK_ACC = 0b111000000
TYPE_MASK_YAW = 1024
TYPE_MASK_YAW_RATE = 2048
BODY_FRAMES = frozenset({8, 9, 12})  # BODY_NED, BODY_OFFSET_NED, BODY_FRD
OFFSET_FRAMES = frozenset({7, 8, 9, 12})


def _wrap360(deg: float) -> float:
    return deg % 360.0


def _wrap180(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def _approach(value: float, target: float, step: float) -> float:
    """Move ``value`` towards ``target`` by at most ``step``."""
    if abs(target - value) <= step:
        return target
    return value + math.copysign(step, target - value)


def _clamp_norm(x: float, y: float, limit: float) -> tuple[float, float]:
    norm = math.hypot(x, y)
    if norm <= limit or norm == 0:
        return x, y
    return x * limit / norm, y * limit / norm


# --------------------------------------------------------------------------------------
# The vehicle: flight modes and kinematics, no I/O
# --------------------------------------------------------------------------------------


@dataclass
class Copter:
    """State and flight logic of the simulated copter; :meth:`step` advances it.

    Positions are metres north/east/up of home; velocities m/s in the same axes; yaw in
    degrees clockwise from north. ``params`` is the live parameter table (ArduCopter
    units). Methods return None on success or the refusal text ArduCopter would show.
    """

    params: dict[str, float]
    home: tuple[float, float]
    home_alt_amsl: float = 50.0
    north: float = 0.0
    east: float = 0.0
    up: float = 0.0
    vn: float = 0.0
    ve: float = 0.0
    vu: float = 0.0
    yaw: float = 0.0
    yaw_rate: float = 0.0  # deg/s, for ATTITUDE
    armed: bool = False
    mode: int = STABILIZE
    landed: bool = True
    battery_pct: float = 100.0
    drain_pct_per_min: float = 5.0  # flying; a 20-minute battery
    gps_fix: int = 3  # GPS_FIX_TYPE: 0 no GPS, 1 no fix, 2 2D, 3 3D
    satellites: int = 12
    # The EKF's origin (and home) is set at the first good fix; before it ArduCopter
    # knows no position and sends 0/0.
    origin_set: bool = False
    sim_time: float = 0.0
    # GUIDED sub-mode: "idle" (hold), "takeoff", "velocity", "position"
    guided: str = "idle"
    hold: tuple[float, float, float] = (0.0, 0.0, 0.0)
    target_vel: tuple[float, float, float] = (0.0, 0.0, 0.0)
    target_vel_wall: float = 0.0
    target_pos: tuple[float, float, float] | None = None
    target_speed: float | None = None
    takeoff_alt: float = 0.0
    target_yaw: float | None = None
    yaw_dir: int = 0  # 1 clockwise, -1 counter-clockwise, 0 shortest
    yaw_speed: float = DEFAULT_YAW_RATE_DEG_S
    rate_cmd: float | None = None  # deg/s from a setpoint's yaw_rate
    look_ahead: bool = False  # WP_YAW_BEHAVIOR: face the direction of travel
    rtl_stage: str = ""
    rtl_loiter_until: float = 0.0
    landed_since: float = 0.0
    payload_released: bool = False
    texts: deque[tuple[int, str]] = field(default_factory=lambda: deque(maxlen=32))

    # --- helpers ----------------------------------------------------------------------
    def p(self, name: str) -> float:
        return float(self.params[name])

    def say(self, severity: int, text: str) -> None:
        """Queue a STATUSTEXT for the ground stations."""
        self.texts.append((severity, text[:50]))

    @property
    def position_ok(self) -> bool:
        return self.gps_fix >= 3 and self.satellites >= 6

    @property
    def latlon(self) -> tuple[float, float]:
        return offset(self.home, self.north, self.east)

    @property
    def flying(self) -> bool:
        return self.armed and not self.landed

    def _hold_here(self) -> None:
        self.hold = (self.north, self.east, self.up)

    # --- commands ---------------------------------------------------------------------
    def set_mode(self, mode: int) -> str | None:
        """Change flight mode; ArduCopter checks a mode's needs only while armed."""
        name = COPTER_MODES.get(mode)
        if name is None:
            return f"Mode change failed: unknown mode {mode}"
        if self.armed and mode in POSITION_MODES and not self.position_ok:
            return f"Mode change failed: {name} requires position"
        if mode == AUTO:
            return "Mode change failed: AUTO: no mission"
        if mode == self.mode:
            return None
        self.mode = mode
        self._hold_here()
        self.guided = "idle"
        self.target_yaw = None
        self.rate_cmd = None
        self.look_ahead = False
        if mode in (RTL, SMART_RTL):
            self.rtl_stage = "climb"
        return None

    def arm(self) -> tuple[int, str | None]:
        """Arm; returns (MAV_RESULT, refusal text)."""
        if self.armed:
            return MAV.MAV_RESULT_ACCEPTED, None
        if self.mode in NOT_ARMABLE:
            return MAV.MAV_RESULT_DENIED, f"Arm: Mode not armable ({COPTER_MODES[self.mode]})"
        if self.p("ARMING_CHECK") != 0:
            if self.mode in POSITION_MODES and not self.position_ok:
                reason = "no 3D fix" if self.gps_fix < 3 else f"{self.satellites} satellites"
                return MAV.MAV_RESULT_TEMPORARILY_REJECTED, f"PreArm: GPS: {reason}"
            if self.battery_pct < 10:
                return (
                    MAV.MAV_RESULT_TEMPORARILY_REJECTED,
                    f"PreArm: Battery 1 low capacity ({self.battery_pct:.0f}%)",
                )
        self.armed = True
        self.landed = True
        self.landed_since = self.sim_time
        self._hold_here()
        self.say(MAV.MAV_SEVERITY_INFO, "Arming motors")
        return MAV.MAV_RESULT_ACCEPTED, None

    def disarm(self, *, force: bool = False) -> tuple[int, str | None]:
        if not self.armed:
            return MAV.MAV_RESULT_ACCEPTED, None
        if self.flying and not force:
            return MAV.MAV_RESULT_DENIED, "Disarm: vehicle is flying"
        self._disarm("Disarming motors")
        return MAV.MAV_RESULT_ACCEPTED, None

    def _disarm(self, why: str) -> None:
        self.armed = False
        self.guided = "idle"
        self.vn = self.ve = self.vu = 0.0
        self.say(MAV.MAV_SEVERITY_INFO, why)

    def takeoff(self, altitude: float) -> str | None:
        if self.mode != GUIDED:
            return f"Takeoff: not in GUIDED ({COPTER_MODES.get(self.mode, self.mode)})"
        if not self.armed:
            return "Takeoff: motors not armed"
        if not self.landed:
            return "Takeoff: already flying"
        if not 0 < altitude <= 1000:
            return f"Takeoff: bad altitude {altitude:g} m"
        self.guided = "takeoff"
        self.takeoff_alt = altitude
        self.landed = False
        self._hold_here()
        return None

    def condition_yaw(self, angle: float, speed: float, direction: int, relative: bool) -> bool:
        if not (0 <= angle <= 360 and direction in (-1, 0, 1)):
            return False
        if relative:
            # Relative to the rotation under way, if any (repeated commands add up).
            step = angle * (direction if direction != 0 else 1)
            base = self.target_yaw if self.target_yaw is not None else self.yaw
            self.target_yaw = _wrap360(base + step)
            # The direction gave the offset its sign; the turn itself takes the short
            # way unless the target is half a turn or more away.
            left = _wrap180(self.target_yaw - self.yaw)
            self.yaw_dir = 0 if abs(left) < 179 else (1 if step > 0 else -1)
        else:
            self.target_yaw = _wrap360(angle)
            self.yaw_dir = direction
        self.yaw_speed = speed if speed > 0 else DEFAULT_YAW_RATE_DEG_S
        self.rate_cmd = None
        self.look_ahead = False
        return True

    def guided_velocity(
        self,
        vn: float,
        ve: float,
        vd: float,
        *,
        wall: float,
        yaw: float | None,
        yaw_rate: float | None,
    ) -> None:
        """A velocity setpoint in NED (already rotated from the body frame)."""
        if self.mode != GUIDED or not self.flying or self.guided == "takeoff":
            return
        self.guided = "velocity"
        self.target_vel = (vn, ve, -vd)
        self.target_vel_wall = wall
        self._setpoint_yaw(yaw, yaw_rate)

    def guided_position(
        self, north: float, east: float, up: float, *, yaw: float | None, yaw_rate: float | None
    ) -> bool:
        if self.mode != GUIDED or not self.flying:
            return False
        self.guided = "position"
        self.target_pos = (north, east, max(0.0, up))
        self._setpoint_yaw(yaw, yaw_rate)
        return True

    def _setpoint_yaw(self, yaw: float | None, yaw_rate: float | None) -> None:
        if yaw is not None:
            self.target_yaw, self.yaw_dir = _wrap360(yaw), 0
            self.yaw_speed, self.rate_cmd, self.look_ahead = DEFAULT_YAW_RATE_DEG_S, None, False
        elif yaw_rate is not None:
            self.target_yaw, self.rate_cmd, self.look_ahead = None, yaw_rate, False
        else:
            # ArduCopter: a setpoint without yaw or yaw rate resets yaw to the default
            # behaviour, WP_YAW_BEHAVIOR (1: face the direction of travel).
            self.target_yaw, self.rate_cmd = None, None
            self.look_ahead = self.p("WP_YAW_BEHAVIOR") != 0

    def reposition(self, lat: float, lon: float, alt: float, speed: float | None) -> str | None:
        if not self.flying:
            return "Reposition: not flying"
        north, east = local_offset_m(self.home, (lat, lon))
        if math.hypot(north, east) > 50_000:
            return "Reposition: target too far"
        if self.mode != GUIDED:
            error = self.set_mode(GUIDED)
            if error:
                return error
        self.guided_position(north, east, alt, yaw=None, yaw_rate=None)
        self.target_speed = speed if speed and speed > 0 else None
        return None

    # --- physics ----------------------------------------------------------------------
    def step(self, dt: float, wall: float) -> None:
        """Advance the flight by ``dt`` seconds of flight time (``wall``: wall clock)."""
        self.sim_time += dt
        if not self.origin_set and self.position_ok:
            self.origin_set = True
            self.say(MAV.MAV_SEVERITY_INFO, "EKF3 IMU0 origin set")
        self._battery(dt)
        if not self.armed:
            self.vn = self.ve = 0.0
            self.vu = -5.0 if self.up > 0 else 0.0  # disarmed in the air: it falls
            self._integrate(dt)
            return
        desired = self._desired_velocity(wall)
        horizontal_accel = self.p("WPNAV_ACCEL") / 100.0 * (2.0 if self.mode == BRAKE else 1.0)
        dv = horizontal_accel * dt
        self.vn = _approach(self.vn, desired[0], dv)
        self.ve = _approach(self.ve, desired[1], dv)
        self.vu = _approach(self.vu, desired[2], 5.0 * dt)
        self._integrate(dt)
        self._yaw(dt)
        self._ground(desired[2])
        self._auto_disarm()

    def _integrate(self, dt: float) -> None:
        self.north += self.vn * dt
        self.east += self.ve * dt
        self.up += self.vu * dt
        if self.up <= 0.0:
            self.up = 0.0
            self.vu = max(self.vu, 0.0)

    def _ground(self, climb_wanted: float) -> None:
        if self.up <= 0.02 and climb_wanted <= 0.0:
            if not self.landed:
                self.landed = True
                self.landed_since = self.sim_time
                self.vn = self.ve = 0.0
                if self.mode in (LAND, RTL, SMART_RTL):
                    self._disarm("Land complete, disarming")
        elif self.up > 0.2:
            self.landed = False

    def _auto_disarm(self) -> None:
        # ArduCopter disarms a copter left armed on the ground (DISARM_DELAY seconds).
        delay = self.p("DISARM_DELAY")
        if (
            self.armed
            and self.landed
            and self.guided != "takeoff"
            and delay > 0
            and self.sim_time - self.landed_since > delay
        ):
            self._disarm("Auto disarm: landed")

    def _battery(self, dt: float) -> None:
        per_s = self.drain_pct_per_min / 60.0
        rate = per_s if self.flying else per_s * 0.2 if self.armed else per_s * 0.01
        self.battery_pct = max(0.0, self.battery_pct - rate * dt)

    def _speed_limits(self) -> tuple[float, float, float]:
        horizontal = self.p("WPNAV_SPEED") / 100.0
        return horizontal, self.p("WPNAV_SPEED_UP") / 100.0, self.p("WPNAV_SPEED_DN") / 100.0

    def _towards(
        self, target: tuple[float, float, float], speed: float | None = None
    ) -> tuple[float, float, float]:
        """A velocity that flies to ``target`` and slows down on arrival."""
        h_max, up_max, down_max = self._speed_limits()
        if speed is not None:
            h_max = min(h_max, speed) if speed > 0 else h_max
        gain = 1.0  # 1/s: the last metre is flown at under 1 m/s
        vn, ve = _clamp_norm((target[0] - self.north) * gain, (target[1] - self.east) * gain, h_max)
        vu = max(-down_max, min(up_max, (target[2] - self.up) * gain))
        return vn, ve, vu

    def _desired_velocity(self, wall: float) -> tuple[float, float, float]:
        if self.landed and not (self.mode == GUIDED and self.guided == "takeoff"):
            return (0.0, 0.0, 0.0)
        mode = self.mode
        if mode == GUIDED:
            return self._guided(wall)
        if mode == LAND:
            return self._land()
        if mode in (RTL, SMART_RTL):
            return self._rtl()
        return self._towards(self.hold)  # LOITER, BRAKE, POSHOLD, ALT_HOLD, ...

    def _guided(self, wall: float) -> tuple[float, float, float]:
        h_max, up_max, down_max = self._speed_limits()
        if self.guided == "takeoff":
            target = (self.hold[0], self.hold[1], self.takeoff_alt)
            if self.up >= self.takeoff_alt - 0.05:
                self.guided = "idle"
                self.hold = target
            vn, ve, _ = self._towards(target)
            return vn, ve, min(up_max, max(0.3, (self.takeoff_alt - self.up) * 1.5))
        if self.guided == "velocity":
            if wall - self.target_vel_wall > self.p("GUID_TIMEOUT"):
                # ArduCopter: no setpoint for GUID_TIMEOUT seconds -> stop.
                self.guided = "idle"
                self.rate_cmd = None
                self._hold_here()
                return self._towards(self.hold)
            vn, ve = _clamp_norm(self.target_vel[0], self.target_vel[1], h_max)
            vu = max(-down_max, min(up_max, self.target_vel[2]))
            return vn, ve, vu
        if self.guided == "position" and self.target_pos is not None:
            return self._towards(self.target_pos, self.target_speed)
        return self._towards(self.hold)

    def _land(self) -> tuple[float, float, float]:
        high = self.p("LAND_SPEED_HIGH") or self.p("WPNAV_SPEED_DN")
        speed = high if self.up > self.p("LAND_ALT_LOW") / 100.0 else self.p("LAND_SPEED")
        vn, ve, _ = self._towards(self.hold)
        return vn, ve, -speed / 100.0

    def _rtl(self) -> tuple[float, float, float]:
        rtl_alt = max(self.p("RTL_ALT") / 100.0, self.up + self.p("RTL_CLIMB_MIN") / 100.0)
        if self.rtl_stage == "climb":
            if math.hypot(self.north, self.east) < 2.0:
                self.rtl_stage = "loiter"  # already home: no need to climb
                self.rtl_loiter_until = self.sim_time + self.p("RTL_LOIT_TIME") / 1000.0
            elif self.up >= rtl_alt - 0.2:
                self.rtl_stage = "return"
                self.hold = (0.0, 0.0, self.up)
            else:
                self.hold = (self.north, self.east, rtl_alt)
                return self._towards(self.hold)
        if self.rtl_stage == "return":
            speed = self.p("RTL_SPEED") / 100.0 or None
            if math.hypot(self.north, self.east) < 0.3:
                self.rtl_stage = "loiter"
                self.rtl_loiter_until = self.sim_time + self.p("RTL_LOIT_TIME") / 1000.0
            return self._towards(self.hold, speed)
        if self.rtl_stage == "loiter":
            self.hold = (0.0, 0.0, self.up)
            if self.sim_time >= self.rtl_loiter_until:
                self.rtl_stage = "land"
            return self._towards(self.hold)
        return self._land()

    def _yaw(self, dt: float) -> None:
        before = self.yaw
        if self.target_yaw is not None:
            error = _wrap180(self.target_yaw - self.yaw)
            if self.yaw_dir > 0 and error < 0 and abs(error) > 1:
                error += 360.0
            elif self.yaw_dir < 0 and error > 0 and abs(error) > 1:
                error -= 360.0
            step = self.yaw_speed * dt
            if abs(error) <= step:
                self.yaw = self.target_yaw
                self.target_yaw = None
            else:
                self.yaw = _wrap360(self.yaw + math.copysign(step, error))
        elif self.rate_cmd is not None and self.guided == "velocity":
            self.yaw = _wrap360(self.yaw + self.rate_cmd * dt)
        elif (
            self.look_ahead
            and self.guided == "velocity"
            and math.hypot(self.vn, self.ve) > 0.05 * self.p("WPNAV_SPEED") / 100.0
        ):
            course = math.degrees(math.atan2(self.ve, self.vn))
            error = _wrap180(course - self.yaw)
            step = DEFAULT_YAW_RATE_DEG_S * dt
            self.yaw = _wrap360(self.yaw + max(-step, min(step, error)))
        self.yaw_rate = _wrap180(self.yaw - before) / dt if dt > 0 else 0.0

    def landed_state(self) -> int:
        if not self.armed or self.landed:
            return int(MAV.MAV_LANDED_STATE_ON_GROUND)
        if self.mode == GUIDED and self.guided == "takeoff":
            return int(MAV.MAV_LANDED_STATE_TAKEOFF)
        if self.mode == LAND or (self.mode == RTL and self.rtl_stage == "land"):
            return int(MAV.MAV_LANDED_STATE_LANDING)
        return int(MAV.MAV_LANDED_STATE_IN_AIR)


# --------------------------------------------------------------------------------------
# The autopilot: MAVLink in and out
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SimOptions:
    """Command line options of the simulator (see :func:`cli`)."""

    address: str
    home: tuple[float, float]
    home_alt_amsl: float = 50.0
    heading_deg: float = 0.0
    speedup: float = 1.0
    battery_pct: float = 100.0
    drain_pct_per_min: float = 5.0
    gps_fix: int = 3
    satellites: int = 12
    sysid: int = 1
    params: Mapping[str, float] = field(default_factory=dict)
    parent_pid: int | None = None
    #: Every stream group's rate until a GCS asks otherwise (ArduPilot's SRn_
    #: parameters, see :data:`DEFAULT_STREAM_RATE_HZ`); 0: only what is asked for.
    stream_rate_hz: float = DEFAULT_STREAM_RATE_HZ
    #: Wall-clock seconds from the start until the GPS has its fix (``gps_fix``).
    gps_fix_after_s: float = 0.0
    #: The simulated release, a key of :data:`FIRMWARES` (its parameter names).
    firmware: str = DEFAULT_FIRMWARE


class Autopilot:
    """Serves one simulated copter on one MAVLink link (UDP, TCP or serial).

    Single-threaded: :meth:`run` polls the link, steps the physics at 50 Hz and sends
    heartbeats and the requested streams. :meth:`stop` (any thread or a signal handler)
    ends it. Bad input (bad CRC, garbage, unknown messages) is dropped and counted.
    """

    def __init__(self, options: SimOptions, *, clock: Callable[[], float] = time.monotonic):
        self.options = options
        self.clock = clock
        if options.firmware not in FIRMWARES:
            known = ", ".join(FIRMWARES)
            raise ValueError(f"unknown firmware {options.firmware!r}; one of {known}")
        #: This firmware's parameters: name -> (default, is_integer), in index order.
        self.param_table = firmware_params(options.firmware)
        params = {name: float(default) for name, (default, _) in self.param_table.items()}
        params["MAV_SYSID" if "MAV_SYSID" in params else "SYSID_THISMAV"] = float(options.sysid)
        for name, value in options.params.items():
            if name not in self.param_table:
                raise ValueError(
                    f"unknown parameter {name!r} on ArduCopter {options.firmware}; "
                    f"known: {', '.join(self.param_table)}"
                )
            params[name] = float(value)
        self.copter = Copter(
            params=params,
            home=options.home,
            home_alt_amsl=options.home_alt_amsl,
            yaw=_wrap360(options.heading_deg),
            battery_pct=options.battery_pct,
            drain_pct_per_min=options.drain_pct_per_min,
            gps_fix=options.gps_fix,
            satellites=options.satellites,
        )
        self.gps_fix_at: float | None = None  # wall time the GPS gets its fix, if later
        if options.gps_fix_after_s > 0 and options.gps_fix > 0:
            # A GPS still searching: connected (NO_FIX), no satellites used yet.
            self.copter.gps_fix, self.copter.satellites = 1, 0
            self.gps_fix_at = clock() + options.gps_fix_after_s
        self.conn: Any = None
        self.started = clock()
        self.intervals: dict[str, float] = {}  # message name -> seconds (wall)
        self.next_due: dict[str, float] = {}
        #: What SET_MESSAGE_INTERVAL's "default rate" (0) restores: the stream rates.
        self.default_intervals: dict[str, float] = {}
        self.running = False
        self.bad_frames = 0
        self.unknown_messages = 0
        self.gcs_last: float | None = None  # wall time of the last heartbeat of MYGCS
        self.gcs_failsafe = False
        self.peers: dict[tuple[int, int], float] = {}
        if options.stream_rate_hz > 0:
            for name in DATA_STREAMS[0]:
                interval = 1.0 / min(options.stream_rate_hz, MAX_STREAM_HZ)
                self.default_intervals[name] = interval
                self._stream(name, interval)

    # --- lifecycle --------------------------------------------------------------------
    def open(self) -> str:
        """Open the link; returns a description with the actual port (for udpin:...:0)."""
        self.conn = mavutil.mavlink_connection(
            self.options.address,
            source_system=self.options.sysid,
            source_component=MAV.MAV_COMP_ID_AUTOPILOT1,
            dialect="ardupilotmega",
            autoreconnect=True,
        )
        self.conn.mav.robust_parsing = True
        # The bound socket: a TCP server's listening one, else the link's own.
        port = getattr(self.conn, "listen", None) or getattr(self.conn, "port", None)
        address = self.options.address
        if port is not None and hasattr(port, "getsockname"):
            with contextlib.suppress(OSError):
                host, number = port.getsockname()[:2]
                if address.startswith(("udpin:", "udp:", "tcpin:")):
                    address = f"{address.split(':', 1)[0]}:{host}:{number}"
        return address

    def close(self) -> None:
        if self.conn is not None:
            with contextlib.suppress(Exception):
                self.conn.close()
            self.conn = None

    def stop(self, *_: Any) -> None:
        self.running = False

    def run(self) -> None:
        """Serve until :meth:`stop` (or the parent process, if given, goes away)."""
        if self.conn is None:
            self.open()
        self.running = True
        period = 1.0 / PHYSICS_HZ
        last = self.clock()
        next_heartbeat = last
        next_parent_check = last + 1.0
        while self.running:
            now = self.clock()
            # A paused process (SIGSTOP) or a slow machine: never step more than 0.2 s.
            dt = min(0.2, max(0.0, now - last)) * self.options.speedup
            last = now
            if self.gps_fix_at is not None and now >= self.gps_fix_at:
                self.gps_fix_at = None
                self.copter.gps_fix = self.options.gps_fix
                self.copter.satellites = self.options.satellites
            self.copter.step(dt, now)
            self._gcs_failsafe(now)
            if now >= next_heartbeat:
                self._send(self._heartbeat())
                next_heartbeat = max(next_heartbeat + 1.0, now)
            self._send_streams(now)
            self._send_texts()
            if now >= next_parent_check:
                next_parent_check = now + 1.0
                if self.options.parent_pid and os.getppid() != self.options.parent_pid:
                    log.warning("mavlink sim: parent process gone, stopping")
                    break
            self._poll(max(0.0, now + period - self.clock()))

    # --- receiving --------------------------------------------------------------------
    def _poll(self, timeout: float) -> None:
        """Handle whatever arrives within ``timeout`` seconds (at least one read)."""
        deadline = self.clock() + timeout
        while True:
            try:
                msg = self.conn.recv_match(blocking=False)
            except Exception as exc:  # a broken frame or a dropped TCP peer
                self.bad_frames += 1
                log.debug("mavlink sim: receive error: %s", exc)
                msg = None
            if msg is not None:
                self.handle(msg)
                continue
            remaining = deadline - self.clock()
            if remaining <= 0:
                return
            with contextlib.suppress(Exception):
                self.conn.select(min(remaining, 0.02))

    def handle(self, msg: Any) -> None:
        """Dispatch one received message; never raises for anything a peer sent."""
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.bad_frames += 1
            return
        if kind.startswith("UNKNOWN"):
            self.unknown_messages += 1
            return
        handler = self._handlers.get(kind)
        if kind != "HEARTBEAT":
            log.debug("mavlink sim: %s%s", msg, "" if handler else " (ignored)")
        if handler is None:
            return
        try:
            handler(self, msg)
        except Exception:
            log.exception("mavlink sim: error handling %s", kind)

    def _for_me(self, msg: Any) -> bool:
        target = getattr(msg, "target_system", 0)
        component = getattr(msg, "target_component", 0)
        return target in (0, self.options.sysid) and component in (
            0,
            MAV.MAV_COMP_ID_AUTOPILOT1,
        )

    def _on_heartbeat(self, msg: Any) -> None:
        now = self.clock()
        self.peers[(msg.get_srcSystem(), msg.get_srcComponent())] = now
        if msg.type == MAV.MAV_TYPE_GCS and self.is_gcs(msg.get_srcSystem()):
            self.gcs_last = now
            if self.gcs_failsafe:
                self.gcs_failsafe = False
                self.copter.say(MAV.MAV_SEVERITY_WARNING, "GCS Failsafe Cleared")

    def is_gcs(self, sysid: int) -> bool:
        """Whether heartbeats from ``sysid`` count for the GCS fail-safe: SYSID_MYGCS, or
        from 4.7 MAV_GCS_SYSID, or MAV_GCS_SYSID..MAV_GCS_SYSID_HI when HI is not below it."""
        params = self.copter.params
        if "MAV_GCS_SYSID" not in params:
            return sysid == int(params["SYSID_MYGCS"])
        low, high = int(params["MAV_GCS_SYSID"]), int(params["MAV_GCS_SYSID_HI"])
        return sysid == low or low <= sysid <= high

    def _on_command_long(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6)
        self._command(msg, msg.command, params, msg.param7, frame=None)

    def _on_command_int(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x / 1e7, msg.y / 1e7)
        self._command(msg, msg.command, params, msg.z, frame=msg.frame)

    def _command(
        self, msg: Any, command: int, p: tuple[float, ...], z: float, *, frame: int | None
    ) -> None:
        result, text = self._execute(command, p, z, frame)
        log.debug("mavlink sim: %s -> result %d %s", command, result, text or "")
        if text:
            self.copter.say(
                MAV.MAV_SEVERITY_CRITICAL
                if result != MAV.MAV_RESULT_ACCEPTED
                else MAV.MAV_SEVERITY_INFO,
                text,
            )
            # ArduPilot sends the explanation before the ACK; so do we.
            self._send_texts()
        self._send(
            MAV.MAVLink_command_ack_message(
                command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
            )
        )

    def _execute(
        self, command: int, p: tuple[float, ...], z: float, frame: int | None
    ) -> tuple[int, str | None]:
        c = self.copter
        ok, failed = MAV.MAV_RESULT_ACCEPTED, MAV.MAV_RESULT_FAILED
        if command == MAV.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] == 1:
                return c.arm()
            if p[0] == 0:
                return c.disarm(force=int(p[1]) == 21196)
            return failed, "Arm: bad parameter"
        if command == MAV.MAV_CMD_DO_SET_MODE:
            if not int(p[0]) & MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return MAV.MAV_RESULT_UNSUPPORTED, "Mode change: custom mode flag required"
            error = c.set_mode(int(p[1]))
            return (failed, error) if error else (ok, None)
        if command == MAV.MAV_CMD_NAV_TAKEOFF:
            error = c.takeoff(float(z))
            return (failed, error) if error else (ok, None)
        if command == MAV.MAV_CMD_NAV_LAND:
            error = c.set_mode(LAND)
            return (failed, error) if error else (ok, None)
        if command == MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            error = c.set_mode(RTL)
            return (failed, error) if error else (ok, None)
        if command == MAV.MAV_CMD_CONDITION_YAW:
            if c.condition_yaw(p[0], p[1], int(p[2]), bool(p[3])):
                return ok, None
            return failed, "Yaw: bad parameters"
        if command == MAV.MAV_CMD_DO_REPOSITION:
            if frame is None:
                return MAV.MAV_RESULT_COMMAND_INT_ONLY, None
            if c.mode != GUIDED and not int(p[1]) & 1:
                return failed, "Reposition: not in GUIDED"
            alt = float(z) if frame in (3, 6) else float(z) - c.home_alt_amsl
            error = c.reposition(p[4], p[5], alt, p[0] if p[0] > 0 else None)
            return (failed, error) if error else (ok, None)
        if command in (MAV.MAV_CMD_DO_GRIPPER, MAV.MAV_CMD_DO_SET_SERVO):
            c.payload_released = True
            return ok, "Gripper load released"
        if command == MAV.MAV_CMD_DO_CHANGE_SPEED:
            if p[1] > 0:
                c.params["WPNAV_SPEED"] = min(2000.0, p[1] * 100.0)
            return ok, None
        if command == MAV.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(int(p[0]), p[1])
        if command == MAV.MAV_CMD_GET_MESSAGE_INTERVAL:
            name = self._message_name(int(p[0]))
            interval = self.intervals.get(name or "", -1.0)
            self._send(
                MAV.MAVLink_message_interval_message(
                    int(p[0]), int(interval * 1e6) if interval > 0 else -1
                )
            )
            return ok, None
        if command == MAV.MAV_CMD_REQUEST_MESSAGE:
            name = self._message_name(int(p[0]))
            if name is None or name not in STREAMABLE:
                return MAV.MAV_RESULT_UNSUPPORTED, None
            return self._send_now(name)
        if command == MAV.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return self._send_now("AUTOPILOT_VERSION")
        if command == MAV.MAV_CMD_GET_HOME_POSITION:
            return self._send_now("HOME_POSITION")
        return MAV.MAV_RESULT_UNSUPPORTED, None

    def _send_now(self, name: str) -> tuple[int, str | None]:
        """Send ``name`` once; FAILED when there is nothing to send (no home yet)."""
        msg = self._message(name)
        if msg is None:
            return MAV.MAV_RESULT_FAILED, None
        self._send(msg)
        return MAV.MAV_RESULT_ACCEPTED, None

    def _on_set_mode(self, msg: Any) -> None:
        if msg.target_system not in (0, self.options.sysid):
            return
        error = self.copter.set_mode(int(msg.custom_mode))
        if error:
            self.copter.say(MAV.MAV_SEVERITY_WARNING, error)
            self._send_texts()
        result = MAV.MAV_RESULT_FAILED if error else MAV.MAV_RESULT_ACCEPTED
        # ArduPilot acknowledges SET_MODE with a COMMAND_ACK for command 11 (SET_MODE).
        self._send(
            MAV.MAVLink_command_ack_message(
                MAV.MAVLINK_MSG_ID_SET_MODE,
                result,
                0,
                0,
                msg.get_srcSystem(),
                msg.get_srcComponent(),
            )
        )

    def _on_set_position_target_local_ned(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        c, frame, mask = self.copter, msg.coordinate_frame, msg.type_mask
        if frame not in (1, 7, 8, 9, 12):
            return  # ArduCopter ignores other frames
        yaw, yaw_rate = self._setpoint_yaw(msg, body=frame in BODY_FRAMES)
        heading = math.radians(c.yaw)

        def to_ned(x: float, y: float) -> tuple[float, float]:
            if frame not in BODY_FRAMES:
                return x, y
            return (
                x * math.cos(heading) - y * math.sin(heading),
                x * math.sin(heading) + y * math.cos(heading),
            )

        if not mask & TYPE_MASK_VEL and mask & TYPE_MASK_POS == TYPE_MASK_POS:
            vn, ve = to_ned(msg.vx, msg.vy)
            c.guided_velocity(vn, ve, msg.vz, wall=self.clock(), yaw=yaw, yaw_rate=yaw_rate)
        elif not mask & TYPE_MASK_POS:
            north, east = to_ned(msg.x, msg.y)
            up = -msg.z
            if frame in OFFSET_FRAMES:
                north, east, up = north + c.north, east + c.east, up + c.up
            c.guided_position(north, east, up, yaw=yaw, yaw_rate=yaw_rate)

    def _on_set_position_target_global_int(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        c, mask = self.copter, msg.type_mask
        if msg.coordinate_frame not in (0, 3, 5, 6, 10, 11):
            return
        yaw, yaw_rate = self._setpoint_yaw(msg, body=False)
        if not mask & TYPE_MASK_POS:
            north, east = local_offset_m(c.home, (msg.lat_int / 1e7, msg.lon_int / 1e7))
            alt = msg.alt if msg.coordinate_frame in (3, 6, 10, 11) else msg.alt - c.home_alt_amsl
            c.guided_position(north, east, alt, yaw=yaw, yaw_rate=yaw_rate)
        elif not mask & TYPE_MASK_VEL:
            c.guided_velocity(msg.vx, msg.vy, msg.vz, wall=self.clock(), yaw=yaw, yaw_rate=yaw_rate)

    def _setpoint_yaw(self, msg: Any, *, body: bool) -> tuple[float | None, float | None]:
        yaw = None if msg.type_mask & TYPE_MASK_YAW else math.degrees(msg.yaw)
        if yaw is not None and body:
            yaw += self.copter.yaw  # ArduCopter: yaw in a body frame is relative
        rate = None if msg.type_mask & TYPE_MASK_YAW_RATE else math.degrees(msg.yaw_rate)
        return yaw, rate

    def _on_param_request_read(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        names = list(self.param_table)
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self._send_param(names[msg.param_index])
            return
        name = _param_name(msg.param_id)
        if name in self.param_table:
            self._send_param(name)

    def _on_param_request_list(self, msg: Any) -> None:
        if self._for_me(msg):
            for name in self.param_table:
                self._send_param(name)

    def _on_param_set(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        name = _param_name(msg.param_id)
        if name not in self.param_table or not math.isfinite(msg.param_value):
            return  # ArduPilot ignores unknown parameters
        value = float(msg.param_value)
        self.copter.params[name] = float(round(value)) if self.param_table[name][1] else value
        self._send_param(name)

    def _on_request_data_stream(self, msg: Any) -> None:
        if not self._for_me(msg):
            return
        names = DATA_STREAMS.get(int(msg.req_stream_id), ())
        rate = float(msg.req_message_rate)
        for name in names:
            if msg.start_stop and rate > 0:
                self._stream(name, 1.0 / min(rate, MAX_STREAM_HZ))
            else:
                self._stream(name, None)

    def _on_mission_request_list(self, msg: Any) -> None:
        if self._for_me(msg):
            self._send(
                MAV.MAVLink_mission_count_message(
                    msg.get_srcSystem(), msg.get_srcComponent(), 0, msg.mission_type
                )
            )

    def _on_timesync(self, msg: Any) -> None:
        if msg.tc1 == 0:
            now_ns = int((self.clock() - self.started) * 1e9)
            self._send(MAV.MAVLink_timesync_message(now_ns, msg.ts1))

    _handlers: dict[str, Callable[[Autopilot, Any], None]] = {
        "HEARTBEAT": _on_heartbeat,
        "COMMAND_LONG": _on_command_long,
        "COMMAND_INT": _on_command_int,
        "SET_MODE": _on_set_mode,
        "SET_POSITION_TARGET_LOCAL_NED": _on_set_position_target_local_ned,
        "SET_POSITION_TARGET_GLOBAL_INT": _on_set_position_target_global_int,
        "PARAM_REQUEST_READ": _on_param_request_read,
        "PARAM_REQUEST_LIST": _on_param_request_list,
        "PARAM_SET": _on_param_set,
        "REQUEST_DATA_STREAM": _on_request_data_stream,
        "MISSION_REQUEST_LIST": _on_mission_request_list,
        "TIMESYNC": _on_timesync,
    }

    # --- fail-safe --------------------------------------------------------------------
    def _gcs_failsafe(self, now: float) -> None:
        c = self.copter
        action = int(c.p("FS_GCS_ENABLE"))
        if action == 0 or self.gcs_failsafe or self.gcs_last is None or not c.armed:
            return
        if now - self.gcs_last <= c.p("FS_GCS_TIMEOUT"):
            return
        self.gcs_failsafe = True
        c.say(MAV.MAV_SEVERITY_CRITICAL, "GCS Failsafe")
        if c.landed:
            c.disarm(force=True)
            return
        mode = {1: RTL, 2: RTL, 3: RTL, 4: LAND, 5: LAND, 6: RTL, 7: BRAKE}.get(action, LAND)
        if c.set_mode(mode) is not None:
            c.set_mode(LAND)

    # --- sending ----------------------------------------------------------------------
    def _send(self, msg: Any) -> None:
        if msg is None or self.conn is None:
            return
        try:
            self.conn.mav.send(msg)
        except Exception as exc:  # a TCP peer gone, a serial port pulled
            log.debug("mavlink sim: send failed: %s", exc)

    def _send_texts(self) -> None:
        while self.copter.texts:
            severity, text = self.copter.texts.popleft()
            self._send(MAV.MAVLink_statustext_message(severity, text.encode()))

    def _send_param(self, name: str) -> None:
        names = list(self.param_table)
        kind = MAV.MAV_PARAM_TYPE_INT32 if self.param_table[name][1] else MAV.MAV_PARAM_TYPE_REAL32
        self._send(
            MAV.MAVLink_param_value_message(
                name.encode(), self.copter.params[name], kind, len(names), names.index(name)
            )
        )

    @staticmethod
    def _message_name(msg_id: int) -> str | None:
        cls = MAV.mavlink_map.get(msg_id)
        return None if cls is None else str(cls.msgname)

    def _set_interval(self, msg_id: int, interval_us: float) -> tuple[int, str | None]:
        name = self._message_name(msg_id)
        if name == "HEARTBEAT":
            return MAV.MAV_RESULT_ACCEPTED, None  # always 1 Hz
        if name is None or name not in STREAMABLE:
            return MAV.MAV_RESULT_UNSUPPORTED, None
        if interval_us < 0:
            self._stream(name, None)
        elif interval_us == 0:
            # "Default rate": back to its stream group's rate, or off where that is 0.
            self._stream(name, self.default_intervals.get(name))
        else:
            self._stream(name, max(1.0 / MAX_STREAM_HZ, interval_us / 1e6))
        return MAV.MAV_RESULT_ACCEPTED, None

    def _stream(self, name: str, interval_s: float | None) -> None:
        if interval_s is None:
            self.intervals.pop(name, None)
            self.next_due.pop(name, None)
        else:
            self.intervals[name] = interval_s
            self.next_due[name] = self.clock()

    def _send_streams(self, now: float) -> None:
        for name, interval in list(self.intervals.items()):
            due = self.next_due.get(name, now)
            if now >= due:
                self._send(self._message(name))
                self.next_due[name] = max(due + interval, now)

    def _time_boot_ms(self) -> int:
        return int(self.copter.sim_time * 1000) & 0xFFFFFFFF

    def _heartbeat(self) -> Any:
        c = self.copter
        base = MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MAV.MAV_MODE_FLAG_STABILIZE_ENABLED
        base |= MAV.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if c.mode in POSITION_MODES:
            base |= MAV.MAV_MODE_FLAG_GUIDED_ENABLED
        if c.armed:
            base |= MAV.MAV_MODE_FLAG_SAFETY_ARMED
        if self.gcs_failsafe or c.battery_pct < 5:
            status = MAV.MAV_STATE_CRITICAL
        else:
            status = MAV.MAV_STATE_ACTIVE if c.armed else MAV.MAV_STATE_STANDBY
        return MAV.MAVLink_heartbeat_message(
            MAV.MAV_TYPE_QUADROTOR, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA, base, c.mode, status, 3
        )

    def _message(self, name: str) -> Any:
        """The message ``name`` as of now; None when ArduCopter would send nothing."""
        c = self.copter
        lat, lon = c.latlon
        lat_i, lon_i = round(lat * 1e7), round(lon * 1e7)
        amsl_mm = int((c.home_alt_amsl + c.up) * 1000)
        ground_speed = math.hypot(c.vn, c.ve)
        if name == "GLOBAL_POSITION_INT":
            # Before the EKF has an origin ArduPilot sends the location it starts with,
            # 0/0 at 0 m AMSL; the height above home comes from the barometer.
            known = c.origin_set
            return MAV.MAVLink_global_position_int_message(
                self._time_boot_ms(),
                lat_i if known else 0,
                lon_i if known else 0,
                amsl_mm if known else 0,
                int(c.up * 1000),
                int(c.vn * 100),
                int(c.ve * 100),
                int(-c.vu * 100),
                int(c.yaw * 100) % 36000,
            )
        if name == "LOCAL_POSITION_NED":
            if not c.origin_set:
                return None  # no origin to be local to
            return MAV.MAVLink_local_position_ned_message(
                self._time_boot_ms(), c.north, c.east, -c.up, c.vn, c.ve, -c.vu
            )
        if name == "GPS_RAW_INT":
            fixed = c.gps_fix >= 2
            return MAV.MAVLink_gps_raw_int_message(
                int((self.clock() - self.started) * 1e6),
                c.gps_fix,
                lat_i if fixed else 0,
                lon_i if fixed else 0,
                amsl_mm if fixed else 0,
                80 if fixed else 9999,
                120 if fixed else 9999,
                int(ground_speed * 100),
                int(math.degrees(math.atan2(c.ve, c.vn)) % 360 * 100) if ground_speed > 0.1 else 0,
                c.satellites,
            )
        if name == "ATTITUDE":
            # Tilt as a multicopter leans into its acceleration: small and cosmetic.
            return MAV.MAVLink_attitude_message(
                self._time_boot_ms(),
                0.0,
                0.0,
                math.radians(_wrap180(c.yaw)),
                0.0,
                0.0,
                math.radians(c.yaw_rate),
            )
        if name == "VFR_HUD":
            return MAV.MAVLink_vfr_hud_message(
                ground_speed,
                ground_speed,
                round(c.yaw) % 360,
                55 if c.flying else 0,
                c.home_alt_amsl + c.up,
                c.vu,
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
            health = sensors if c.position_ok else sensors & ~MAV.MAV_SYS_STATUS_SENSOR_GPS
            return MAV.MAVLink_sys_status_message(
                sensors,
                sensors,
                health,
                250,
                self._millivolts(),
                self._centiamps(),
                int(c.battery_pct),
                0,
                0,
                0,
                0,
                0,
                0,
            )
        if name == "BATTERY_STATUS":
            cells = [int(self._millivolts() / 4)] * 4 + [65535] * 6
            used = self.copter.p("BATT_CAPACITY") * (100.0 - c.battery_pct) / 100.0
            return MAV.MAVLink_battery_status_message(
                0,
                MAV.MAV_BATTERY_FUNCTION_ALL,
                MAV.MAV_BATTERY_TYPE_LIPO,
                2500,
                cells,
                self._centiamps(),
                int(used),
                -1,
                int(c.battery_pct),
            )
        if name == "HOME_POSITION":
            if not c.origin_set:
                return None  # ArduCopter sets home with the EKF origin
            home_lat, home_lon = c.home
            return MAV.MAVLink_home_position_message(
                int(home_lat * 1e7),
                int(home_lon * 1e7),
                int(c.home_alt_amsl * 1000),
                0.0,
                0.0,
                0.0,
                [1.0, 0.0, 0.0, 0.0],
                0.0,
                0.0,
                0.0,
            )
        if name == "EXTENDED_SYS_STATE":
            return MAV.MAVLink_extended_sys_state_message(
                MAV.MAV_VTOL_STATE_UNDEFINED, c.landed_state()
            )
        if name == "EKF_STATUS_REPORT":
            flags = 0x1 | 0x2 | 0x4 | 0x8 | 0x20  # attitude, velocity, position, alt
            if c.position_ok:
                flags |= 0x10 | 0x100  # absolute horizontal position, pred pos abs
            return MAV.MAVLink_ekf_status_report_message(flags, 0.1, 0.1, 0.1, 0.05, 0.0)
        if name == "SYSTEM_TIME":
            return MAV.MAVLink_system_time_message(int(time.time() * 1e6), self._time_boot_ms())
        if name == "AUTOPILOT_VERSION":
            capabilities = (
                MAV.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | MAV.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | MAV.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | MAV.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | MAV.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
                | MAV.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION
            )
            uid = abs(hash((c.home, self.options.sysid))) & 0xFFFFFFFFFFFF
            major, minor, patch, kind = FIRMWARES[self.options.firmware]
            return MAV.MAVLink_autopilot_version_message(
                capabilities,
                (major << 24) | (minor << 16) | (patch << 8) | kind,
                0,
                0,
                0,
                [0] * 8,
                [0] * 8,
                [0] * 8,
                0x1209,
                0x5740,
                uid,
            )
        return None

    def _millivolts(self) -> int:
        # A 4S LiPo: 16.8 V full, 14.0 V empty, linear enough for a display.
        return int((14.0 + 2.8 * self.copter.battery_pct / 100.0) * 1000)

    def _centiamps(self) -> int:
        return 1800 if self.copter.flying else 50 if self.copter.armed else 20


def _param_name(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0].strip()


# --------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------


def _latlon(text: str) -> tuple[float, float]:
    try:
        lat_s, lon_s = text.split(",")
        lat, lon = float(lat_s), float(lon_s)
    except ValueError:
        raise argparse.ArgumentTypeError("expected LAT,LON in degrees") from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise argparse.ArgumentTypeError("latitude or longitude out of range")
    return lat, lon


def _param(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    if not sep or name.strip().upper() not in KNOWN_PARAMS:
        raise argparse.ArgumentTypeError(
            f"expected NAME=VALUE with NAME one of {', '.join(sorted(KNOWN_PARAMS))}"
        )
    try:
        return name.strip().upper(), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{name}: not a number") from None


def _positive(text: str) -> float:
    value = float(text)
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError("must be a positive number")
    return value


def parse_args(argv: Iterable[str]) -> SimOptions:
    """Parse the command line into :class:`SimOptions` (argparse exits on errors)."""
    parser = argparse.ArgumentParser(
        prog="python -m agents sim mavlink",
        description="Simulated ArduCopter-like MAVLink autopilot (MAVLink 2 over UDP, TCP "
        "or serial). Point the agent's mavlink adapter, MAVProxy, MAVSDK or QGroundControl "
        "at it.",
    )
    where = parser.add_mutually_exclusive_group()
    where.add_argument(
        "--listen",
        help="wait for ground stations: udpin:HOST:PORT (port 0: any free one) or "
        "tcpin:HOST:PORT (default udpin:127.0.0.1:14550)",
    )
    where.add_argument(
        "--connect",
        help="reach a ground station: udpout:HOST:PORT, tcp:HOST:PORT or a serial device "
        "as DEVICE[,BAUD]",
    )
    parser.add_argument("--home", type=_latlon, default=(40.6306, -8.6588), help="LAT,LON")
    parser.add_argument("--home-alt", type=float, default=50.0, help="home altitude AMSL, m")
    parser.add_argument("--heading", type=float, default=0.0, help="initial heading, degrees")
    parser.add_argument("--speedup", type=_positive, default=1.0, help="flight time factor")
    parser.add_argument("--battery", type=float, default=100.0, help="initial charge, percent")
    parser.add_argument(
        "--drain", type=float, default=5.0, help="battery drain when flying, percent per minute"
    )
    parser.add_argument("--gps", choices=("3d", "2d", "none"), default="3d", help="GPS fix")
    parser.add_argument("--satellites", type=int, default=12)
    parser.add_argument(
        "--gps-fix-after",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="the GPS gets its fix this long after the start (wall clock): until then no "
        "fix, 0 satellites and position 0/0, as ArduCopter before its EKF origin is set",
    )
    parser.add_argument(
        "--firmware",
        choices=tuple(FIRMWARES),
        default=DEFAULT_FIRMWARE,
        help="the ArduCopter release simulated: its version and parameter names (4.7 has "
        "MAV_GCS_SYSID, MAV_GCS_SYSID_HI and MAV_SYSID instead of SYSID_MYGCS and "
        "SYSID_THISMAV)",
    )
    parser.add_argument("--sysid", type=int, default=1, help="MAVLink system id")
    parser.add_argument(
        "--param", type=_param, action="append", default=[], help="NAME=VALUE (repeatable)"
    )
    parser.add_argument(
        "--stream-rate",
        type=float,
        default=DEFAULT_STREAM_RATE_HZ,
        help="every telemetry stream's rate (Hz) until a ground station asks otherwise, "
        "like ArduPilot's SRn_ parameters; default 1 (ArduPlane's and ArduRover's default), "
        "0: only the streams a ground station asks for (ArduCopter's default)",
    )
    parser.add_argument("--parent-pid", type=int, default=None, help="stop when it exits")
    parser.add_argument("--log-level", default="WARNING")
    args = parser.parse_args(list(argv))
    if not 0 <= args.battery <= 100:
        parser.error("--battery must be within 0..100")
    if not 1 <= args.sysid <= 254:
        parser.error("--sysid must be within 1..254")
    if not (math.isfinite(args.gps_fix_after) and args.gps_fix_after >= 0):
        parser.error("--gps-fix-after must be 0 or more seconds")
    params = dict(args.param)
    unknown = set(params) - set(firmware_params(args.firmware))
    if unknown:
        parser.error(
            f"ArduCopter {args.firmware} has no parameter {', '.join(sorted(unknown))} "
            "(see --firmware)"
        )
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    return SimOptions(
        address=args.connect or args.listen or "udpin:127.0.0.1:14550",
        home=args.home,
        home_alt_amsl=args.home_alt,
        heading_deg=args.heading,
        speedup=args.speedup,
        battery_pct=args.battery,
        drain_pct_per_min=max(0.0, args.drain),
        gps_fix={"3d": 3, "2d": 2, "none": 0}[args.gps],
        satellites=max(0, args.satellites) if args.gps != "none" else 0,
        sysid=args.sysid,
        params=params,
        parent_pid=args.parent_pid,
        stream_rate_hz=max(0.0, args.stream_rate),
        gps_fix_after_s=args.gps_fix_after,
        firmware=args.firmware,
    )


def cli(argv: list[str]) -> int:
    """``python -m agents sim mavlink``: serve a simulated copter until stopped.

    Prints ``READY <address>`` on stdout once the link is open (with the actual port for
    ``udpin:HOST:0``). Returns 0 when stopped (Ctrl-C, SIGTERM or the ``--parent-pid``
    process gone), 2 when the link cannot be opened.
    """
    options = parse_args(argv)
    pilot = Autopilot(options)
    try:
        address = pilot.open()
    except Exception as exc:
        print(f"cannot open {options.address}: {exc}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, pilot.stop)
    print(f"READY {address}", flush=True)
    try:
        pilot.run()
    except KeyboardInterrupt:
        pass
    finally:
        pilot.close()
    return 0
