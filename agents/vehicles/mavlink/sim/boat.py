"""The simulated boat: ArduRover with FRAME_CLASS 2, its driving modes and a surface
kinematics, no I/O.

What it does, as ArduRover does it for a boat (``docs/vehicles/boat.md``):

* GUIDED: body-frame velocity with a yaw rate (``set_desired_turn_rate_and_speed``:
  the speed along the heading, signed by vx, and a turn rate) or with a heading, and
  positions (SET_POSITION_TARGET_*, DO_REPOSITION). A velocity setpoint lapses after
  3 s ("target not received last 3secs, stopping"); a position reached (``WP_RADIUS``)
  is held. A boat holds a position as LOITER does, never by stopping its motors;
* LOITER: back towards its point when farther than ``LOIT_RADIUS`` (faster the
  farther, reversing to a point behind it), drifting inside it;
* HOLD (and MANUAL, with no pilot): motors off: it coasts to a stop and drifts with the
  current;
* RTL, SMART_RTL: straight home at ``RTL_SPEED`` (else ``WP_SPEED``), then it holds
  there as in LOITER (SmartRTL's retracing of the way out is not modelled);
* AUTO (``Rover/mode_auto.cpp``): refused without a mission ("No Mission. Can't set
  AUTO."); entered, it starts the mission at item 1 or (``MIS_RESTART`` 0) resumes it
  at its current navigation item. NAV_WAYPOINT is reached within ``WP_RADIUS`` ("Reached
  waypoint #n", MISSION_ITEM_REACHED), then held param 1 seconds; NAV_LOITER_TIME the
  same; NAV_LOITER_UNLIM drives to its point (latitude and longitude 0: where the boat
  is) and keeps station there as LOITER does, "Reached waypoint #n" but never verified
  (ArduRover's verify_loiter_unlimited: no MISSION_ITEM_REACHED, the mission never
  goes past it); NAV_RETURN_TO_LAUNCH drives home; the "do" items after a navigation item
  (DO_CHANGE_SPEED, DO_SET_SERVO, DO_GRIPPER) run when it is done. Take-offs and
  landings are skipped ("Skipping invalid cmd"). After the last item it holds where it
  is, as LOITER, still in AUTO ("Mission Complete");
* DO_CHANGE_SPEED as ArduRover's ``set_desired_speed`` takes it: accepted while
  GUIDED drives to a position (its WP sub-mode) and in RTL, SMART_RTL and AUTO, where
  it is the speed of positions and returns until the next mode change; FAILED
  everywhere else: GUIDED holding (its Loiter sub-mode: just armed, a position
  reached, a velocity setpoint timed out) or driven by velocity setpoints, LOITER,
  HOLD, MANUAL. DO_REPOSITION's own speed (param 1) is set the same way before the
  position, so it fails unless GUIDED already drives to one. Velocity setpoints are
  capped at ``WP_SPEED`` (``CRUISE_SPEED`` when 0);
* the GCS fail-safe (``FS_GCS_ENABLE``): after ``FS_GCS_TIMEOUT`` s of silence (a fixed
  2 s before ArduRover 4.7) and ``FS_TIMEOUT`` s more, ``FS_ACTION``; never in RTL, nor
  in HOLD unless ``FS_OPTIONS`` bit 0;
* no altitude (``up`` is 0), acceleration (``ATC_ACCEL_MAX``, ``ATC_DECEL_MAX``), turn
  rate and turn acceleration (``ATC_STR_RAT_MAX``, ``ATC_STR_ACC_MAX``) limits; it
  turns on the spot (two thrusters). A disarm is never refused (ArduRover's is not:
  the agent refuses one while under way);
* it stays on water: a move that would end on land (:mod:`agents.geography`) is not
  made; the boat stops at the shore ("Ran aground", a warning) and may leave the way it
  came. Where the packaged land mask has no data the boat goes anywhere.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from agents.geo import local_offset_m, offset
from agents.geography import land_at
from agents.vehicles.mavlink.classes import BOAT, MAV_TYPE_SURFACE_BOAT, ROVER_MODES
from agents.vehicles.mavlink.dialect import MAV
from agents.vehicles.mavlink.sim.fence import GIVE_UP_DISTANCE_M
from agents.vehicles.mavlink.sim.mission import (
    DO_CHANGE_SPEED,
    DO_GRIPPER,
    DO_SET_SERVO,
    NAV_LOITER_TIME,
    NAV_LOITER_UNLIM,
    NAV_RETURN_TO_LAUNCH,
    NAV_WAYPOINT,
)
from agents.vehicles.mavlink.sim.vehicle import (
    BODY_FRAMES,
    OFFSET_FRAMES,
    TYPE_MASK_ACC,
    TYPE_MASK_YAW,
    TYPE_MASK_YAW_RATE,
    CommandResult,
    PositionTarget,
    SimVehicle,
    approach,
    wrap180,
    wrap360,
)

_NUMBER = {name: number for number, name in ROVER_MODES.items()}
MANUAL, HOLD, LOITER, AUTO = _NUMBER["MANUAL"], _NUMBER["HOLD"], _NUMBER["LOITER"], _NUMBER["AUTO"]
RTL, SMART_RTL, GUIDED = _NUMBER["RTL"], _NUMBER["SMART_RTL"], _NUMBER["GUIDED"]
#: The navigation items ArduRover drives (the others are skipped).
DRIVEN = frozenset({NAV_WAYPOINT, NAV_LOITER_TIME, NAV_LOITER_UNLIM, NAV_RETURN_TO_LAUNCH})
#: Modes whose set_desired_speed takes a speed whatever they do (ArduRover's ModeRTL,
#: ModeSmartRTL, ModeAuto); GUIDED takes one only while it drives to a position.
SPEED_MODES = frozenset({RTL, SMART_RTL, AUTO})
#: Modes whose motors the autopilot drives; in the others (HOLD, MANUAL without a
#: pilot...) the motors are off.
POWERED = frozenset(
    {
        GUIDED,
        LOITER,
        RTL,
        SMART_RTL,
        AUTO,
        *(_NUMBER[m] for m in ("FOLLOW", "SIMPLE", "DOCK", "CIRCLE")),
    }
)

#: ArduRover drops a velocity or heading setpoint not renewed within this (wall clock).
SETPOINT_TIMEOUT_S = 3.0
#: ArduRover before 4.7: the GCS counts as lost after this much silence.
GCS_SILENCE_S = 2.0
#: Heading controller: turn rate (deg/s) per degree of heading error.
STEER_GAIN = 2.0
#: Approaching a point: at most this speed (m/s) per metre left, so it arrives slowly.
ARRIVE_GAIN = 0.5
#: Motors off, the water slows the boat by this much (m/s per second).
COAST_DECEL_MPS2 = 0.5
#: Moves are checked against the land mask every this many metres.
LAND_CHECK_M = 2.0
#: Under way: faster than this (m/s), or turning.
UNDER_WAY_MPS = 0.1


def _bearing(dn: float, de: float) -> float:
    return math.degrees(math.atan2(de, dn)) % 360.0


@dataclass
class Boat(SimVehicle):
    """State and driving logic of the simulated boat; :meth:`step` advances it (see
    the module docstring; units as in :mod:`.vehicle`, parameters as ArduRover's)."""

    VEHICLE_CLASS = BOAT
    MAV_TYPE = MAV_TYPE_SURFACE_BOAT
    POSITION_MODES = frozenset(
        _NUMBER[m]
        for m in (
            "AUTO",
            "GUIDED",
            "LOITER",
            "RTL",
            "SMART_RTL",
            "FOLLOW",
            "SIMPLE",
            "DOCK",
            "CIRCLE",
        )
    )
    NOT_ARMABLE = frozenset({RTL, SMART_RTL, _NUMBER["INITIALISING"]})

    home_alt_amsl: float = 0.0
    #: Speed through the water along the heading, m/s (negative astern).
    speed: float = 0.0
    #: The water's own motion, m/s north and east: the boat drifts with it.
    current: tuple[float, float] = (0.0, 0.0)
    #: GUIDED sub-mode: "hold" (as LOITER, at ``target``), "wp" (to ``target``),
    #: "drive" (speed and turn rate), "heading" (speed and heading).
    guided: str = "hold"
    #: The point of GUIDED's "wp" and "hold", of LOITER, and home (0, 0) in RTL.
    target: tuple[float, float] = (0.0, 0.0)
    #: RTL, SMART_RTL: home reached, holding there.
    home_reached: bool = False
    drive_speed: float = 0.0
    drive_turn: float = 0.0  # deg/s, positive clockwise
    drive_heading: float = 0.0
    drive_wall: float = 0.0
    #: DO_CHANGE_SPEED's (or DO_REPOSITION's) speed for this mode; None: the default.
    nav_speed: float | None = None
    aground: bool = False
    #: AUTO: the navigation item's index (None: the mission is over, holding), whether
    #: it got there, and until when it holds there (simulated time).
    auto_index: int | None = None
    auto_reached: bool = False
    auto_hold_until: float = 0.0
    #: Land (True), water (False) or unknown (None) at a point: the land mask.
    land_at: Callable[[float, float], bool | None] = field(
        default_factory=lambda: land_at, repr=False
    )

    # --- state ------------------------------------------------------------------------
    @property
    def active(self) -> bool:
        return self.armed and (abs(self.speed) > UNDER_WAY_MPS or abs(self.yaw_rate) > 1.0)

    def default_speed(self) -> float:
        """ArduRover's default navigation speed: WP_SPEED, else CRUISE_SPEED."""
        return self.p("WP_SPEED") or self.p("CRUISE_SPEED")

    def _decel(self) -> float:
        return self.p("ATC_DECEL_MAX") or self._accel()

    def _accel(self) -> float:
        return self.p("ATC_ACCEL_MAX") or 100.0  # 0: no limit

    def _stopping_point(self) -> tuple[float, float]:
        """Where the boat stops if it slows down now (ArduRover holds there)."""
        ahead = self.speed * abs(self.speed) / (2.0 * self._decel())
        heading = math.radians(self.yaw)
        return self.north + ahead * math.cos(heading), self.east + ahead * math.sin(heading)

    # --- modes and arming -------------------------------------------------------------
    def _entered(self, mode: str) -> None:
        self.nav_speed = None  # ArduRover: the default speed again in every new mode
        self.home_reached = False
        self.guided = "hold"
        self.target = (0.0, 0.0) if mode in ("RTL", "SMART_RTL") else self._stopping_point()
        if mode == "AUTO":
            self._auto_start_or_resume()
        elif self.mission.state == "running":
            self.mission.state = "stopped"  # left: resumed from here next time
            self.auto_index = None

    # --- AUTO -------------------------------------------------------------------------
    def _auto_refusal(self) -> str | None:
        return None if self.mission.flyable() else "No Mission. Can't set AUTO."

    def _auto_advance(self, index: int) -> None:
        """The "do" items from ``index`` on, then the next navigation item it drives
        (others skipped); none left: the mission is complete and it holds there."""
        items = self.mission.items
        while index < len(items):
            item = items[index]
            if item.command in DRIVEN:
                self._auto_start_nav(index)
                return
            if item.is_nav:
                self.say(MAV.MAV_SEVERITY_WARNING, f"Skipping invalid cmd #{index}")
            elif item.command == DO_CHANGE_SPEED and item.params[1] > 0:
                self.nav_speed = item.params[1]
            elif item.command == DO_SET_SERVO or (
                item.command == DO_GRIPPER and int(item.params[1]) == MAV.GRIPPER_ACTION_RELEASE
            ):
                self.payload_released = True
                self.say(MAV.MAV_SEVERITY_INFO, "Gripper load released")
            index += 1
        self.mission.state = "complete"
        self.mission.current_changed = True
        self.auto_index = None
        self.target = self._stopping_point()
        self.say(MAV.MAV_SEVERITY_INFO, "Mission Complete")

    def _auto_start_nav(self, index: int) -> None:
        item = self.mission.items[index]
        self.mission.set_current(index)
        self.auto_index, self.auto_reached = index, False
        if item.command == NAV_RETURN_TO_LAUNCH:
            self.target = (0.0, 0.0)
        elif item.has_position:
            self.target = local_offset_m(self.home, (item.lat, item.lon))
        else:
            self.target = (self.north, self.east)

    def _auto(self) -> tuple[float, float]:
        index = self.auto_index
        if index is None:
            return self._loiter()
        item = self.mission.items[index]
        unlimited = item.command == NAV_LOITER_UNLIM
        if not self.auto_reached and self._arrived():
            self.auto_reached = True
            hold = item.params[0] if item.command != NAV_RETURN_TO_LAUNCH else 0.0
            self.auto_hold_until = self.sim_time + max(0.0, hold)
            if item.command != NAV_RETURN_TO_LAUNCH:
                self.say(MAV.MAV_SEVERITY_INFO, f"Reached waypoint #{index}")
                if not unlimited:  # reached, but never verified: no MISSION_ITEM_REACHED
                    self.mission.reached.append(index)
            else:
                self.say(MAV.MAV_SEVERITY_INFO, "Reached destination")
        if self.auto_reached:
            if not unlimited and self.sim_time >= self.auto_hold_until:
                self._auto_advance(index + 1)
            return self._loiter()
        return self._navigate(self.nav_speed or self.default_speed())

    def _arming_refusal(self) -> str | None:
        lat, lon = self.latlon
        return "PreArm: the boat is on land" if self.land_at(lat, lon) else None

    def _on_armed(self) -> None:
        self.guided = "hold"
        self.target = (self.north, self.east)

    def _on_disarmed(self) -> None:
        self.speed = 0.0
        self.yaw_rate = 0.0
        self.guided = "hold"

    # --- commands ---------------------------------------------------------------------
    def command(
        self, command: int, p: tuple[float, ...], z: float, frame: int | None
    ) -> CommandResult:
        """DO_REPOSITION and DO_CHANGE_SPEED as ArduRover answers them, and the shared
        ones (see :meth:`SimVehicle.command`); a take-off, a landing or a yaw command
        is UNSUPPORTED, as on ArduRover."""
        ok, failed = MAV.MAV_RESULT_ACCEPTED, MAV.MAV_RESULT_FAILED
        if command == MAV.MAV_CMD_DO_REPOSITION:
            if frame is None:
                return MAV.MAV_RESULT_COMMAND_INT_ONLY, None
            return self.reposition(p[4], p[5], speed=p[0], change_mode=bool(int(p[1]) & 1))
        if command == MAV.MAV_CMD_DO_CHANGE_SPEED:
            return (ok, None) if self.set_desired_speed(float(p[1])) else (failed, None)
        return super().command(command, p, z, frame)

    def set_desired_speed(self, speed: float) -> bool:
        """ArduRover's ``control_mode->set_desired_speed``: False (FAILED) unless the
        mode takes a speed now (see the module docstring)."""
        takes = self.mode in SPEED_MODES or (self.mode == GUIDED and self.guided == "wp")
        if not takes or speed < 0:
            return False
        self.nav_speed = speed or None
        return True

    def reposition(
        self, lat: float, lon: float, *, speed: float, change_mode: bool
    ) -> CommandResult:
        """DO_REPOSITION, in the order ArduRover checks it (no words with its refusals)."""
        if self.mode != GUIDED and not change_mode:
            return MAV.MAV_RESULT_DENIED, None
        if not (-90 <= lat <= 90 and -180 <= lon <= 180) or (lat, lon) == (0, 0):
            return MAV.MAV_RESULT_DENIED, None
        north, east = local_offset_m(self.home, (lat, lon))
        if math.hypot(north, east) > 50_000:
            return MAV.MAV_RESULT_DENIED, "Reposition: target too far"
        if self.mode != GUIDED:
            error = self.set_mode(GUIDED)
            if error:
                return MAV.MAV_RESULT_FAILED, error
        # ArduRover sets the speed before the position: holding, it has none to take.
        if speed > 0 and not self.set_desired_speed(float(speed)):
            return MAV.MAV_RESULT_FAILED, None
        self._go_to(north, east)
        return MAV.MAV_RESULT_ACCEPTED, None

    def _go_to(self, north: float, east: float) -> None:
        self.guided = "wp"
        self.target = (north, east)

    # --- setpoints --------------------------------------------------------------------
    def local_target(self, target: PositionTarget, wall: float) -> None:
        """As ArduRover's GCS_MAVLINK_Rover: GUIDED only; local and body frames; an
        acceleration must be ignored; a position, else a velocity with a turn rate or
        a heading (or neither: the heading of the velocity)."""
        frame = target.frame
        if self.mode != GUIDED or frame not in (1, 7, 8, 9):
            return
        if target.type_mask & TYPE_MASK_ACC != TYPE_MASK_ACC:
            self.say(MAV.MAV_SEVERITY_WARNING, "Ignoring SET_POSITION_TARGET; set ACC ignore flags")
            return
        heading = math.radians(self.yaw)
        body = frame in BODY_FRAMES
        if not target.type_mask & 0b011:
            x, y = target.x, target.y
            if body:
                x, y = (
                    x * math.cos(heading) - y * math.sin(heading),
                    x * math.sin(heading) + y * math.cos(heading),
                )
            if frame in OFFSET_FRAMES:
                x, y = x + self.north, y + self.east
            self._go_to(x, y)
            return
        self._velocity_target(target, wall, body=body)

    def global_target(self, target: PositionTarget, wall: float) -> None:
        """GUIDED only; a position (latitude, longitude), else a velocity (north, east)."""
        if self.mode != GUIDED or target.frame not in (0, 3, 5, 6, 10, 11):
            return
        if target.type_mask & TYPE_MASK_ACC != TYPE_MASK_ACC:
            return
        if not target.type_mask & 0b011:
            self._go_to(*local_offset_m(self.home, (target.x, target.y)))
            return
        self._velocity_target(target, wall, body=False)

    def _velocity_target(self, target: PositionTarget, wall: float, *, body: bool) -> None:
        mask = target.type_mask
        use_vel = not mask & 0b011000
        use_yaw = not mask & TYPE_MASK_YAW
        use_rate = not mask & TYPE_MASK_YAW_RATE
        if use_yaw and use_rate:
            return  # ArduRover takes one or the other, never both
        speed = 0.0
        if use_vel:
            speed = min(math.hypot(target.vx, target.vy), self.default_speed())
            # With a yaw or a yaw rate, the sign of vx says ahead or astern.
            if (use_yaw or use_rate) and target.vx < 0:
                speed = -speed
        if use_rate:
            self.guided, self.drive_turn = "drive", math.degrees(target.yaw_rate)
        elif use_yaw:
            yaw = math.degrees(target.yaw) + (self.yaw if body else 0.0)
            self.guided, self.drive_heading = "heading", wrap360(yaw)
        elif use_vel:
            course = _bearing(target.vx, target.vy) + (self.yaw if body else 0.0)
            self.guided, self.drive_heading = "heading", wrap360(course)
        else:
            return
        self.drive_speed = speed
        self.drive_wall = wall

    # --- the GCS fail-safe --------------------------------------------------------------
    def gcs_failsafe_after_s(self) -> float | None:
        """The GCS's silence (FS_GCS_TIMEOUT, 2 s before 4.7), then FS_TIMEOUT more."""
        if self.p("FS_GCS_ENABLE") == 0:
            return None
        silence = self.p("FS_GCS_TIMEOUT") if "FS_GCS_TIMEOUT" in self.params else GCS_SILENCE_S
        return silence + self.p("FS_TIMEOUT")

    def gcs_failsafe(self) -> bool:
        """FS_ACTION, as ArduRover's Rover::failsafe_trigger (Rover/failsafe.cpp): not in
        RTL, nor in HOLD unless FS_OPTIONS bit 0; in AUTO with FS_GCS_ENABLE 2 ("Enabled
        Continue with Mission in Auto", which ArduRover, unlike ArduCopter, still has)
        nothing; else 0 nothing, 1 RTL, 2 Hold, 3 SmartRTL, 4 SmartRTL or Hold,
        5 Terminate (disarm), 6 Loiter or Hold, each falling back to the next mode it
        names (RTL to Hold), and any other value nothing (the switch has no default)."""
        if self.mode == RTL or (self.mode == HOLD and not int(self.p("FS_OPTIONS")) & 1):
            return False
        self.say(MAV.MAV_SEVERITY_WARNING, "GCS Failsafe")
        if self.mode == AUTO and self.p("FS_GCS_ENABLE") == 2:
            self.say(MAV.MAV_SEVERITY_WARNING, "Failsafe - Continuing Auto Mode")
            return True
        action = int(self.p("FS_ACTION"))
        if action == 5:
            self.disarm(force=True)
            return True
        modes = {1: [RTL, HOLD], 2: [HOLD], 3: [SMART_RTL, RTL, HOLD], 4: [SMART_RTL, HOLD]}
        for mode in modes.get(action, [LOITER, HOLD] if action == 6 else []):
            if self.set_mode(mode) is None:
                break
        return True

    # --- the fence -------------------------------------------------------------------
    def _fence_breached(self, action: int, distance: float) -> None:
        """ArduRover's fence_check (see :mod:`.fence`)."""
        if distance > GIVE_UP_DISTANCE_M:
            self._modes_in_turn("HOLD")
        elif action == 5:
            self.disarm(force=True)
        else:
            modes = {2: ("HOLD",), 3: ("SMART_RTL", "RTL", "HOLD"), 4: ("SMART_RTL", "HOLD")}
            self._modes_in_turn(*modes.get(action, ("RTL", "HOLD")))

    # --- physics ----------------------------------------------------------------------
    def step(self, dt: float, wall: float) -> None:
        """Advance ``dt`` seconds of driving time (``wall``: wall clock, for setpoints)."""
        self.sim_time += dt
        self._origin_check()
        powered, speed, turn = False, 0.0, 0.0
        if self.armed and self.mode in POWERED:
            powered = True
            speed, turn = self._control(wall)
        rate_max = self.p("ATC_STR_RAT_MAX") or 360.0
        turn = max(-rate_max, min(rate_max, turn))
        self.yaw_rate = approach(self.yaw_rate, turn, (self.p("ATC_STR_ACC_MAX") or 1e3) * dt)
        if powered:
            slowing = speed * self.speed < 0 or abs(speed) < abs(self.speed)
            self.speed = approach(
                self.speed, speed, (self._decel() if slowing else self._accel()) * dt
            )
        else:
            self.speed = approach(self.speed, 0.0, COAST_DECEL_MPS2 * dt)
        self.yaw = wrap360(self.yaw + self.yaw_rate * dt)
        heading = math.radians(self.yaw)
        self.vn = self.speed * math.cos(heading) + self.current[0]
        self.ve = self.speed * math.sin(heading) + self.current[1]
        self._move(self.vn * dt, self.ve * dt)
        share = min(1.0, abs(self.speed) / max(self.default_speed(), 0.1))
        self._battery(dt, 0.2 + 0.8 * share)

    def _move(self, dn: float, de: float) -> None:
        """Move by (dn, de) metres unless that ends on land: then stop at the shore."""
        distance = math.hypot(dn, de)
        if distance == 0:
            return
        pieces = max(1, math.ceil(distance / LAND_CHECK_M))
        north, east = self.north, self.east
        for i in range(1, pieces + 1):
            n, e = self.north + dn * i / pieces, self.east + de * i / pieces
            if self._on_land(*offset(self.home, n, e)):
                self._run_aground(north, east)
                return
            north, east = n, e
        self.north, self.east = north, east
        self.aground = False

    def _on_land(self, lat: float, lon: float) -> bool:
        """Land here, or where the position is reported: GLOBAL_POSITION_INT carries
        1e-7 degrees, so a point a few millimetres off the shore could be reported on
        the other side of it."""
        reported = (round(lat * 1e7) / 1e7, round(lon * 1e7) / 1e7)
        return bool(self.land_at(lat, lon) or self.land_at(*reported))

    def _run_aground(self, north: float, east: float) -> None:
        self.north, self.east = north, east
        self.speed = 0.0
        self.vn = self.ve = 0.0
        if not self.aground:
            self.aground = True
            self.say(MAV.MAV_SEVERITY_WARNING, "Ran aground: stopped at the shore")

    def _control(self, wall: float) -> tuple[float, float]:
        """The speed (m/s) and turn rate (deg/s) the mode asks for now."""
        if self.mode in (RTL, SMART_RTL):
            if not self.home_reached and self._arrived():
                self.home_reached = True
                self.say(MAV.MAV_SEVERITY_INFO, "Reached destination")
            if self.home_reached:
                return self._loiter()
            default = self.p("RTL_SPEED") or self.default_speed()
            return self._navigate(self.nav_speed or default)
        if self.mode == AUTO:
            return self._auto()
        if self.mode != GUIDED:
            return self._loiter()  # LOITER, and the position modes not modelled
        if self.guided in ("drive", "heading") and wall - self.drive_wall > SETPOINT_TIMEOUT_S:
            self.say(MAV.MAV_SEVERITY_WARNING, "target not received last 3secs, stopping")
            self.guided, self.target = "hold", self._stopping_point()
        if self.guided == "drive":
            return self.drive_speed, self.drive_turn
        if self.guided == "heading":
            return self.drive_speed, STEER_GAIN * wrap180(self.drive_heading - self.yaw)
        if self.guided == "wp":
            if self._arrived():
                self.guided = "hold"
                self.say(MAV.MAV_SEVERITY_INFO, "Reached destination")
            else:
                return self._navigate(self.nav_speed or self.default_speed())
        return self._loiter()

    def _arrived(self) -> bool:
        dn, de = self.target[0] - self.north, self.target[1] - self.east
        return math.hypot(dn, de) <= self.p("WP_RADIUS")

    def _navigate(self, cruise: float) -> tuple[float, float]:
        """Towards ``target``: turn to it (on the spot when it is abeam or behind) and
        slow down on the way in."""
        dn, de = self.target[0] - self.north, self.target[1] - self.east
        distance = math.hypot(dn, de)
        error = wrap180(_bearing(dn, de) - self.yaw)
        speed = min(cruise, math.sqrt(2.0 * self._decel() * distance), ARRIVE_GAIN * distance)
        return speed * max(0.0, math.cos(math.radians(error))), STEER_GAIN * error

    def _loiter(self) -> tuple[float, float]:
        """ArduRover's ModeLoiter: nothing inside LOIT_RADIUS; outside, back at a speed
        growing with the distance, astern to a point behind (LOIT_TYPE 0)."""
        dn, de = self.target[0] - self.north, self.target[1] - self.east
        distance = math.hypot(dn, de)
        radius = self.p("LOIT_RADIUS")
        if distance <= radius:
            return 0.0, 0.0
        speed = min((distance - radius) * self.p("LOIT_SPEED_GAIN"), self.default_speed())
        bearing = _bearing(dn, de)
        error = wrap180(bearing - self.yaw)
        kind = int(self.p("LOIT_TYPE"))
        if (abs(error) > 90 and kind == 0) or kind == 2:
            error = wrap180(bearing + 180.0 - self.yaw)
            speed = -speed
        # ArduRover: 45 degrees off slows it to 75 %, 90 degrees to 50 %.
        speed *= 1.0 - min(abs(error) / 90.0, 1.0) * 0.5
        return speed, STEER_GAIN * error
