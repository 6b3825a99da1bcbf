"""The simulated multicopter: ArduCopter's flight modes and kinematics, no I/O.

AUTO (:meth:`Copter._auto`, after ArduCopter's ``mode_auto.cpp`` and AP_Mission: the
uploaded mission, :mod:`.mission`), GUIDED (take-off, velocity and position
setpoints, CONDITION_YAW, DO_REPOSITION, whose speed ArduCopter ignores, and
DO_CHANGE_SPEED, taken in GUIDED and AUTO only and forgotten when GUIDED starts
flying to a position from another sub-mode), LAND (fast
then slow descent, disarm on touchdown), RTL (climb to ``RTL_ALT``, fly home, loiter
``RTL_LOIT_TIME``, land, disarm), BRAKE/LOITER (hold at the stopping point); speed
limits (``WPNAV_SPEED*``), ground contact, auto-disarm after ``DISARM_DELAY`` s armed
on the ground, battery drain (faster when flying). As in ArduCopter a velocity
setpoint lapses after ``GUID_TIMEOUT`` s, and one that ignores both yaw and yaw rate
hands yaw to ``WP_YAW_BEHAVIOR`` (by default the nose turns into the direction of
travel; in AUTO, towards the next waypoint). The GCS fail-safe acts after
``FS_GCS_TIMEOUT`` s as ArduCopter 4.x's ``Copter::failsafe_gcs_on_event`` and
``do_failsafe_action`` (``ArduCopter/events.cpp``) do (:meth:`Copter.gcs_failsafe`):
``FS_GCS_ENABLE`` picks the action, ``FS_OPTIONS`` the exceptions (continue a landing,
a mission in AUTO, a pilot-controlled mode) and whether the gripper lets go too.

AUTO: refused without a mission beyond home, and armed on the ground unless the
mission starts with a take-off ("Auto: Missing Takeoff Cmd"); it is not armable.
Entering it starts the mission at item 1, or, with ``MIS_RESTART`` 0 (the default),
resumes an interrupted one at its current navigation item. A navigation item runs
until verified (NAV_TAKEOFF: the altitude; NAV_WAYPOINT and NAV_LOITER_TIME: within
``WPNAV_RADIUS`` of the point, then their hold time, param 1; NAV_LAND: landed;
NAV_RETURN_TO_LAUNCH: RTL's climb, return, loiter and landing, the mode staying AUTO;
NAV_LOITER_UNLIM: never, as ModeAuto::verify_loiter_unlimited: it flies to its point,
or with latitude and longitude 0 to its stopping point, at its altitude, or with 0 at
the one it has, and holds there in AUTO, the mission never going past it, with no
MISSION_ITEM_REACHED);
the "do" items after it (DO_CHANGE_SPEED, DO_SET_SERVO, DO_GRIPPER, the camera's) run
when it is verified, before the next navigation item starts, as AP_Mission runs them.
Each start says "Mission: <n> <name>"; a waypoint or a loiter verified sends
MISSION_ITEM_REACHED. After the last item: landed, it disarms; flying, it holds there
in AUTO.

Kinematics: every mode's velocity goes through the position controller's jerk-limited
shaping (:mod:`.shaping`) within ``WPNAV_ACCEL`` and ``WPNAV_ACCEL_Z`` (BRAKE: three
times the horizontal one) and ``PSC_JERK_XY``/``PSC_JERK_Z`` (``PSC_JERK_NE``/
``PSC_JERK_D`` from 4.7): a climb at 2.5 m/s takes some 3.4 m to stop, 5 m/s across
some 6.3 m, as on ArduCopter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from agents.geo import local_offset_m
from agents.vehicles.mavlink.classes import COPTER
from agents.vehicles.mavlink.dialect import MAV
from agents.vehicles.mavlink.sim.fence import ALT_MAX, GIVE_UP_DISTANCE_M
from agents.vehicles.mavlink.sim.mission import (
    DO_CHANGE_SPEED,
    DO_GRIPPER,
    DO_SET_SERVO,
    NAV_LAND,
    NAV_LOITER_TIME,
    NAV_LOITER_UNLIM,
    NAV_RETURN_TO_LAUNCH,
    NAV_TAKEOFF,
    NAV_WAYPOINT,
    RELATIVE_FRAMES,
    Item,
)
from agents.vehicles.mavlink.sim.shaping import (
    position_speed,
    position_velocity_xy,
    shape_vel_accel,
    shape_vel_accel_xy,
    stopping_distance,
)
from agents.vehicles.mavlink.sim.vehicle import (
    BODY_FRAMES,
    OFFSET_FRAMES,
    TYPE_MASK_POS,
    TYPE_MASK_VEL,
    TYPE_MASK_YAW,
    TYPE_MASK_YAW_RATE,
    CommandResult,
    PositionTarget,
    SimVehicle,
    clamp_norm,
    wrap180,
    wrap360,
)

STABILIZE, ALT_HOLD, AUTO, GUIDED, LOITER, RTL, LAND = 0, 2, 3, 4, 5, 6, 9
POSHOLD, BRAKE, SMART_RTL, AUTO_RTL = 16, 17, 21, 27
#: FS_GCS_ENABLE -> the FailsafeAction ArduCopter's failsafe_gcs_on_event picks
#: (ArduCopter/events.cpp, 4.x). 2 was "RTL, or continue a mission in AUTO" until 3.6:
#: since 4.0 it is one case with 1 (RTL), the continuing being FS_OPTIONS bit 1's; the
#: boot-time conversion of 2 into 1 plus that bit (convert_fs_options_params, 4.0 to
#: 4.3) is gone since 4.4 (ArduPilot PR 22637), and a pre-arm check says "FS_GCS_ENABLE=2
#: removed, see FS_OPTIONS" without refusing to arm (AP_Arming_Copter::parameter_checks).
#: Any other value: RTL (the switch's default).
FS_GCS_ACTIONS = {
    1: "RTL", 2: "RTL", 3: "SMARTRTL", 4: "SMARTRTL_LAND", 5: "LAND",
    6: "AUTO_DO_LAND_START", 7: "BRAKE_LAND",
}  # fmt: skip
#: FS_OPTIONS bits (Copter::FailsafeOption, ArduCopter/Copter.h) the GCS fail-safe reads:
#: go on landing (any fail-safe), go on with a mission in AUTO, go on in a mode the
#: pilot flies (the default, 16, since ArduCopter 4.1), release the gripper with the
#: action. Bits 0 and 2 (continue in AUTO, in GUIDED) are the radio fail-safe's only:
#: no bit keeps the GCS fail-safe from acting in GUIDED.
FS_OPTION_CONTINUE_IF_LANDING = 8
FS_OPTION_GCS_CONTINUE_IF_AUTO = 2
FS_OPTION_GCS_CONTINUE_IF_PILOT_CONTROL = 16
FS_OPTION_RELEASE_GRIPPER = 32
#: The modes whose Mode::is_autopilot() is true (ArduCopter/mode.h): AUTO, GUIDED, RTL,
#: CIRCLE, LAND, AVOID_ADSB, GUIDED_NOGPS, SMART_RTL, FOLLOW, ZIGZAG, AUTOROTATE,
#: AUTO_RTL. The rest (LOITER, BRAKE, POSHOLD, ALT_HOLD...) are the pilot's.
AUTOPILOT_MODES = frozenset({AUTO, GUIDED, RTL, 7, LAND, 19, 20, SMART_RTL, 23, 24, 26, AUTO_RTL})
#: set_mode_land_with_pause: a fail-safe's LAND holds this long before descending
#: (ArduCopter's LAND_WITH_DELAY_MS).
LAND_PAUSE_S = 4.0
DEFAULT_YAW_RATE_DEG_S = 60.0
#: The physics' longest step (s): ArduCopter's shaping runs at 400 Hz, this at 200 Hz.
STEP_S = 0.005
#: BRAKE mode stops harder than WPNAV_ACCEL (ArduCopter's BRAKE_MODE_DECEL_RATE).
BRAKE_ACCEL_FACTOR = 3.0
#: An AUTO take-off is done this close (m) under its altitude.
TAKEOFF_DONE_M = 0.2
#: A waypoint's altitude counts as reached within this much (m).
WP_ALT_TOLERANCE_M = 1.0
#: What AP_Mission calls each command in its "Mission: <n> <name>" text.
COMMAND_NAMES = {
    NAV_WAYPOINT: "WP", NAV_LOITER_TIME: "LoitTime", NAV_LOITER_UNLIM: "LoitUnlim",
    NAV_RETURN_TO_LAUNCH: "RTL",
    NAV_LAND: "Land", NAV_TAKEOFF: "Takeoff", DO_CHANGE_SPEED: "ChangeSpeed",
    DO_SET_SERVO: "SetServo", DO_GRIPPER: "Gripper",
}  # fmt: skip


@dataclass
class Copter(SimVehicle):
    """State and flight logic of the simulated copter; :meth:`step` advances it (see
    the module docstring; units as in :mod:`.vehicle`, parameters as ArduCopter's)."""

    VEHICLE_CLASS = COPTER
    MAV_TYPE = int(MAV.MAV_TYPE_QUADROTOR)
    #: Modes that need a position estimate (refused while armed without one).
    POSITION_MODES = frozenset({AUTO, GUIDED, LOITER, RTL, 7, POSHOLD, BRAKE, SMART_RTL, 23})
    #: Modes ArduCopter will not arm in.
    NOT_ARMABLE = frozenset({AUTO, RTL, 7, LAND, SMART_RTL, 27})

    landed: bool = True
    # GUIDED sub-mode: "idle" (hold), "takeoff", "velocity", "position"
    guided: str = "idle"
    hold: tuple[float, float, float] = (0.0, 0.0, 0.0)
    target_vel: tuple[float, float, float] = (0.0, 0.0, 0.0)
    target_vel_wall: float = 0.0
    target_pos: tuple[float, float, float] | None = None
    #: DO_CHANGE_SPEED's speed (m/s) for positions in GUIDED; None: WPNAV_SPEED.
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
    #: LAND: when it was entered, and whether a fail-safe's pause holds the descent.
    land_started: float = 0.0
    land_pause: bool = False
    #: The shaped acceleration (m/s² north, east, up): ArduCopter's is jerk-limited.
    an: float = 0.0
    ae: float = 0.0
    au: float = 0.0
    #: AUTO: the navigation item flown (None: the mission is over, holding), where it
    #: goes, whether it got there and until when it holds there (simulated time).
    auto_item: Item | None = None
    auto_target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    auto_reached: bool = False
    auto_hold_until: float = 0.0
    #: NAV_LAND: "approach" (to the point at its altitude), then "descend".
    auto_land_stage: str = ""

    # --- state ------------------------------------------------------------------------
    @property
    def flying(self) -> bool:
        return self.armed and not self.landed

    @property
    def active(self) -> bool:
        return self.flying

    def _hold_here(self) -> None:
        """Hold at the stopping point, as ArduCopter's position modes start: where the
        copter comes to rest from its velocity, not where it was when asked."""
        accel_h, accel_z = self._accel_limits()
        jerk_h, jerk_z = self._jerk()
        speed = math.hypot(self.vn, self.ve)
        ahead = stopping_distance(speed, accel_h, jerk_h) / speed if speed > 0.01 else 0.0
        rise = math.copysign(stopping_distance(self.vu, accel_z, jerk_z), self.vu)
        self.hold = (self.north + self.vn * ahead, self.east + self.ve * ahead, self.up + rise)

    # --- modes and arming -------------------------------------------------------------
    def _entered(self, mode: str) -> None:
        self._hold_here()
        self.guided = "idle"
        self.target_yaw = None
        self.rate_cmd = None
        self.look_ahead = False
        if mode in ("RTL", "SMART_RTL"):
            self.rtl_stage = "climb"
        if mode == "LAND":
            self.land_started, self.land_pause = self.sim_time, False
        if mode == "AUTO":
            self._auto_enter()
        elif self.mission.state == "running":
            self.mission.state = "stopped"  # left: resumed from here next time
            self.auto_item = None

    def set_mode(self, mode: int) -> str | None:
        """As :meth:`SimVehicle.set_mode`; AUTO_RTL (ModeAuto's DO_LAND_START or
        DO_RETURN_PATH_START sequence) is always refused: this simulator stores neither
        item (an upload with one is refused UNSUPPORTED), so it never finds one."""
        if mode == AUTO_RTL:
            return "Mode change to AUTO RTL failed: No landing sequence found"
        return super().set_mode(mode)

    # --- AUTO -------------------------------------------------------------------------
    def _auto_refusal(self) -> str | None:
        if not self.mission.flyable():
            return "Mode change failed: AUTO: no mission"
        if self.armed and self.landed and not self._starts_with_takeoff():
            return "Auto: Missing Takeoff Cmd"
        return None

    def _starts_with_takeoff(self) -> bool:
        """AP_Mission::starts_with_takeoff_cmd: the first navigation item flown (from 1,
        or the current one when resuming) is a take-off."""
        m = self.mission
        start = 1 if self.p("MIS_RESTART") or m.current is None else m.current
        nav = next((i for i in m.items[start:] if i.is_nav), None)
        return nav is not None and nav.command == NAV_TAKEOFF

    def _auto_enter(self) -> None:
        self.target_speed = None  # WPNAV_SPEED until a DO_CHANGE_SPEED
        self._auto_start_or_resume()

    def _auto_advance(self, index: int) -> None:
        """From item ``index`` on: perform the "do" items, start the next navigation item
        (AP_Mission::advance_current_nav_cmd); none left: the mission is complete."""
        items = self.mission.items
        while index < len(items):
            item = items[index]
            if item.is_nav:
                self._auto_start_nav(index)
                return
            self._auto_do(index, item)
            index += 1
        self._auto_complete()

    def _auto_do(self, index: int, item: Item) -> None:
        self.say(MAV.MAV_SEVERITY_INFO, f"Mission: {index} {COMMAND_NAMES.get(item.command, 'Do')}")
        if item.command == DO_CHANGE_SPEED and item.params[1] > 0:
            self.target_speed = item.params[1]
        elif item.command == DO_SET_SERVO or (
            item.command == DO_GRIPPER and int(item.params[1]) == MAV.GRIPPER_ACTION_RELEASE
        ):
            self.payload_released = True
            self.say(MAV.MAV_SEVERITY_INFO, "Gripper load released")
        # The camera's items are taken and do nothing here: this copter has no camera.

    def _auto_start_nav(self, index: int) -> None:
        item = self.mission.items[index]
        self.mission.set_current(index)
        self.say(MAV.MAV_SEVERITY_INFO, f"Mission: {index} {COMMAND_NAMES[item.command]}")
        self.auto_item, self.auto_reached = item, False
        if item.has_position:
            north, east = local_offset_m(self.home, (item.lat, item.lon))
        else:
            north, east = self.hold[0], self.hold[1]
        alt = item.alt if item.frame in RELATIVE_FRAMES else item.alt - self.home_alt_amsl
        if item.command == NAV_TAKEOFF:
            # Straight up from where it is; already higher: done at once.
            self.auto_target = (self.north, self.east, max(alt, 0.0))
            if self.landed and alt > 0:
                self.landed = False
        elif item.command == NAV_LAND:
            self.auto_land_stage = "approach" if item.has_position else "descend"
            self.auto_target = (north, east, self.up)
            self.hold = self.auto_target
        elif item.command == NAV_RETURN_TO_LAUNCH:
            self.rtl_stage = "climb"
        elif item.command == NAV_LOITER_UNLIM:
            # ModeAuto::do_loiter_unlimited: no position, the stopping point; no
            # altitude, the current one.
            if not item.has_position:
                self._hold_here()
                north, east = self.hold[0], self.hold[1]
            self.auto_target = (north, east, self.up if item.alt == 0 else max(alt, 0.0))
        else:
            self.auto_target = (north, east, max(alt, 0.0))

    def _auto_complete(self) -> None:
        """The mission is over (ModeAuto::exit_mission): landed, disarm; else hold."""
        self.mission.state = "complete"
        self.mission.current_changed = True  # MISSION_CURRENT says so at once
        self.auto_item = None
        if self.armed and self.landed:
            self._disarm("Mission complete, disarming")
        else:
            self._hold_here()

    def _auto_landing(self) -> bool:
        item = self.auto_item
        if self.mode != AUTO or item is None:
            return False
        if item.command == NAV_LAND:
            return self.auto_land_stage == "descend"
        return item.command == NAV_RETURN_TO_LAUNCH and self.rtl_stage == "land"

    def _auto(self) -> tuple[float, float, float]:
        """AUTO's velocity now, the current navigation item verified on the way."""
        item = self.auto_item
        if item is None:
            return self._towards(self.hold)
        if item.command == NAV_RETURN_TO_LAUNCH:
            return self._rtl()  # lands; touchdown (_ground) ends the mission
        if item.command == NAV_LAND:
            if self.auto_land_stage == "approach":
                radius = self.p("WPNAV_RADIUS") / 100.0
                north, east, _ = self.auto_target
                if math.hypot(north - self.north, east - self.east) <= radius:
                    self.auto_land_stage = "descend"
                    self.hold = (north, east, self.up)
                return self._towards(self.auto_target, self.target_speed)
            return self._land()
        if item.command == NAV_LOITER_UNLIM:
            return self._towards(self.auto_target, self.target_speed)  # never verified
        target = self.auto_target
        if not self.auto_reached and self._auto_arrived(item, target):
            self.auto_reached = True
            hold = item.params[0] if item.command in (NAV_WAYPOINT, NAV_LOITER_TIME) else 0.0
            self.auto_hold_until = self.sim_time + max(0.0, hold)
            if item.command != NAV_TAKEOFF and self.mission.current is not None:
                self.mission.reached.append(self.mission.current)
        if self.auto_reached and self.sim_time >= self.auto_hold_until:
            current = self.mission.current
            self._auto_advance((current or 0) + 1)
        velocity = self._towards(target, self.target_speed)
        if item.command == NAV_TAKEOFF and self.landed:
            return velocity[0], velocity[1], max(0.3, velocity[2])
        return velocity

    def _auto_arrived(self, item: Item, target: tuple[float, float, float]) -> bool:
        if item.command == NAV_TAKEOFF:
            return self.up >= target[2] - TAKEOFF_DONE_M
        radius = self.p("WPNAV_RADIUS") / 100.0
        horizontal = math.hypot(target[0] - self.north, target[1] - self.east)
        return horizontal <= radius and abs(target[2] - self.up) <= WP_ALT_TOLERANCE_M

    def _on_armed(self) -> None:
        self.landed = True
        self.landed_since = self.sim_time
        self._hold_here()

    def _arming_refusal(self) -> str | None:
        """AP_Arming_Copter::parameter_checks: FS_GCS_ENABLE 2 is named, as check_failed
        says it, but that check returns nothing: it never keeps the copter from arming."""
        if int(self.p("FS_GCS_ENABLE")) == 2:
            self.say(MAV.MAV_SEVERITY_CRITICAL, "PreArm: FS_GCS_ENABLE=2 removed, see FS_OPTIONS")
        return None

    def _disarm_refusal(self) -> str | None:
        return "Disarm: vehicle is flying" if self.flying else None

    def _on_disarmed(self) -> None:
        self.guided = "idle"

    # --- commands ---------------------------------------------------------------------
    def command(
        self, command: int, p: tuple[float, ...], z: float, frame: int | None
    ) -> CommandResult:
        """NAV_TAKEOFF, NAV_LAND, CONDITION_YAW, DO_REPOSITION, DO_CHANGE_SPEED, and
        the shared ones (see :meth:`SimVehicle.command`)."""
        ok, failed = MAV.MAV_RESULT_ACCEPTED, MAV.MAV_RESULT_FAILED
        if command == MAV.MAV_CMD_NAV_TAKEOFF:
            error = self.takeoff(float(z))
            return (failed, error) if error else (ok, None)
        if command == MAV.MAV_CMD_NAV_LAND:
            error = self.set_mode(LAND)
            return (failed, error) if error else (ok, None)
        if command == MAV.MAV_CMD_CONDITION_YAW:
            if self.condition_yaw(p[0], p[1], int(p[2]), bool(p[3])):
                return ok, None
            return failed, "Yaw: bad parameters"
        if command == MAV.MAV_CMD_DO_REPOSITION:
            if frame is None:
                return MAV.MAV_RESULT_COMMAND_INT_ONLY, None
            if self.mode != GUIDED and not int(p[1]) & 1:
                return failed, "Reposition: not in GUIDED"
            alt = float(z) if frame in (3, 6) else float(z) - self.home_alt_amsl
            # ArduCopter ignores DO_REPOSITION's speed (param 1).
            error = self.reposition(p[4], p[5], alt)
            return (failed, error) if error else (ok, None)
        if command == MAV.MAV_CMD_DO_CHANGE_SPEED:
            # ArduCopter: a speed > 0 for the mode's position controller; only GUIDED
            # and AUTO take one (set_speed_NE), and GUIDED forgets it when it starts
            # flying to a position from another sub-mode (pva_control_start).
            if p[1] <= 0:
                return MAV.MAV_RESULT_DENIED, None
            if self.mode not in (GUIDED, AUTO):
                return failed, None
            self.target_speed = float(p[1])
            return ok, None
        return super().command(command, p, z, frame)

    def takeoff(self, altitude: float) -> str | None:
        if self.mode != GUIDED:
            return f"Takeoff: not in GUIDED ({self.modes.get(self.mode, self.mode)})"
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
            self.target_yaw = wrap360(base + step)
            # The direction gave the offset its sign; the turn itself takes the short
            # way unless the target is half a turn or more away.
            left = wrap180(self.target_yaw - self.yaw)
            self.yaw_dir = 0 if abs(left) < 179 else (1 if step > 0 else -1)
        else:
            self.target_yaw = wrap360(angle)
            self.yaw_dir = direction
        self.yaw_speed = speed if speed > 0 else DEFAULT_YAW_RATE_DEG_S
        self.rate_cmd = None
        self.look_ahead = False
        return True

    def reposition(self, lat: float, lon: float, alt: float) -> str | None:
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
        return None

    # --- setpoints --------------------------------------------------------------------
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
        if self.guided != "position":
            self.target_speed = None  # WPNAV_SPEED again, as pva_control_start sets it
        self.guided = "position"
        self.target_pos = (north, east, max(0.0, up))
        self._setpoint_yaw(yaw, yaw_rate)
        return True

    def _setpoint_yaw(self, yaw: float | None, yaw_rate: float | None) -> None:
        if yaw is not None:
            self.target_yaw, self.yaw_dir = wrap360(yaw), 0
            self.yaw_speed, self.rate_cmd, self.look_ahead = DEFAULT_YAW_RATE_DEG_S, None, False
        elif yaw_rate is not None:
            self.target_yaw, self.rate_cmd, self.look_ahead = None, yaw_rate, False
        else:
            # ArduCopter: a setpoint without yaw or yaw rate resets yaw to the default
            # behaviour, WP_YAW_BEHAVIOR (1: face the direction of travel).
            self.target_yaw, self.rate_cmd = None, None
            self.look_ahead = self.p("WP_YAW_BEHAVIOR") != 0

    def _target_yaw(
        self, target: PositionTarget, *, body: bool
    ) -> tuple[float | None, float | None]:
        yaw = None if target.type_mask & TYPE_MASK_YAW else math.degrees(target.yaw)
        if yaw is not None and body:
            yaw += self.yaw  # ArduCopter: yaw in a body frame is relative
        rate = None if target.type_mask & TYPE_MASK_YAW_RATE else math.degrees(target.yaw_rate)
        return yaw, rate

    def local_target(self, target: PositionTarget, wall: float) -> None:
        frame, mask = target.frame, target.type_mask
        if frame not in (1, 7, 8, 9, 12):
            return  # ArduCopter ignores other frames
        yaw, yaw_rate = self._target_yaw(target, body=frame in BODY_FRAMES)
        heading = math.radians(self.yaw)

        def to_ned(x: float, y: float) -> tuple[float, float]:
            if frame not in BODY_FRAMES:
                return x, y
            return (
                x * math.cos(heading) - y * math.sin(heading),
                x * math.sin(heading) + y * math.cos(heading),
            )

        if not mask & TYPE_MASK_VEL and mask & TYPE_MASK_POS == TYPE_MASK_POS:
            vn, ve = to_ned(target.vx, target.vy)
            self.guided_velocity(vn, ve, target.vz, wall=wall, yaw=yaw, yaw_rate=yaw_rate)
        elif not mask & TYPE_MASK_POS:
            north, east = to_ned(target.x, target.y)
            up = -target.z
            if frame in OFFSET_FRAMES:
                north, east, up = north + self.north, east + self.east, up + self.up
            self.guided_position(north, east, up, yaw=yaw, yaw_rate=yaw_rate)

    def global_target(self, target: PositionTarget, wall: float) -> None:
        mask = target.type_mask
        if target.frame not in (0, 3, 5, 6, 10, 11):
            return
        yaw, yaw_rate = self._target_yaw(target, body=False)
        if not mask & TYPE_MASK_POS:
            north, east = local_offset_m(self.home, (target.x, target.y))
            relative = target.frame in (3, 6, 10, 11)
            alt = target.z if relative else target.z - self.home_alt_amsl
            self.guided_position(north, east, alt, yaw=yaw, yaw_rate=yaw_rate)
        elif not mask & TYPE_MASK_VEL:
            self.guided_velocity(
                target.vx, target.vy, target.vz, wall=wall, yaw=yaw, yaw_rate=yaw_rate
            )

    # --- the GCS fail-safe --------------------------------------------------------------
    def gcs_failsafe_after_s(self) -> float | None:
        """FS_GCS_TIMEOUT, while FS_GCS_ENABLE is not 0."""
        return None if self.p("FS_GCS_ENABLE") == 0 else self.p("FS_GCS_TIMEOUT")

    def gcs_failsafe(self) -> bool:
        """ArduCopter 4.x's Copter::failsafe_gcs_on_event (ArduCopter/events.cpp), armed:
        on the ground (should_disarm_on_failsafe), disarm; landing with FS_OPTIONS bit 3,
        go on landing (LAND); in AUTO with bit 1, or in a mode the pilot flies
        (is_autopilot false) with bit 4, nothing; else the action FS_GCS_ENABLE names
        (:data:`FS_GCS_ACTIONS`). Every text is a warning, as announce_failsafe sends it."""
        options = int(self.p("FS_OPTIONS"))
        action = FS_GCS_ACTIONS.get(int(self.p("FS_GCS_ENABLE")), "RTL")
        warn = MAV.MAV_SEVERITY_WARNING
        if self.landed:
            self.say(warn, "GCS Failsafe - Disarming")
            self.disarm(force=True)
            return True
        if self._is_landing() and options & FS_OPTION_CONTINUE_IF_LANDING:
            self.say(warn, "GCS Failsafe - Continuing Landing")
            action = "LAND"
        elif self.mode == AUTO and options & FS_OPTION_GCS_CONTINUE_IF_AUTO:
            self.say(warn, "GCS Failsafe - Continuing Auto Mode")
            return True
        elif options & FS_OPTION_GCS_CONTINUE_IF_PILOT_CONTROL and self.mode not in AUTOPILOT_MODES:
            self.say(warn, "GCS Failsafe - Continuing Pilot Control")
            return True
        else:
            self.say(warn, "GCS Failsafe")
        self._failsafe_action(action)
        if options & FS_OPTION_RELEASE_GRIPPER:
            # do_failsafe_action releases it after any action but none.
            self.payload_released = True
            self.say(MAV.MAV_SEVERITY_INFO, "Gripper load released")
        return True

    def _failsafe_action(self, action: str) -> None:
        """Copter::do_failsafe_action, each action falling back as its set_mode_*
        helper does (the texts are theirs)."""
        warn = MAV.MAV_SEVERITY_WARNING
        if action == "SMARTRTL":
            if self.set_mode(SMART_RTL) is None:
                return
            self.say(warn, "SmartRTL Unavailable, Trying RTL Mode")
            action = "RTL"
        elif action == "SMARTRTL_LAND":
            if self.set_mode(SMART_RTL) is None:
                return
            self.say(warn, "SmartRTL Unavailable, Using Land Mode")
            action = "LAND"
        elif action == "AUTO_DO_LAND_START":
            refusal = self.set_mode(AUTO_RTL)
            if refusal is None:
                return
            self.say(warn, refusal)
            self.say(warn, "Trying RTL Mode")
            action = "RTL"
        elif action == "BRAKE_LAND":
            if self.set_mode(BRAKE) is None:
                return
            self.say(warn, "Trying Land Mode")
            action = "LAND"
        if action == "RTL" and self.set_mode(RTL) is None:
            return
        self._land_with_pause()

    def _land_with_pause(self) -> None:
        """set_mode_land_with_pause: LAND, the descent held until LAND_WITH_DELAY_MS after
        LAND began (already landing: no new pause)."""
        self.set_mode(LAND)
        if self.mode == LAND:
            self.land_pause = True

    def _is_landing(self) -> bool:
        """Mode::is_landing: LAND; RTL's and SmartRTL's final landing; AUTO's NAV_LAND
        (its approach too: ModeAuto's LAND sub-mode) and its RTL's landing."""
        if self.mode == LAND:
            return True
        if self.mode in (RTL, SMART_RTL):
            return self.rtl_stage == "land"
        item = self.auto_item
        if self.mode != AUTO or item is None:
            return False
        if item.command == NAV_LAND:
            return True
        return item.command == NAV_RETURN_TO_LAUNCH and self.rtl_stage == "land"

    # --- the fence -------------------------------------------------------------------
    def _fence_breached(self, action: int, distance: float) -> None:
        """ArduCopter's fence_check: landed, disarm; more than 100 m out, LAND; else as
        FENCE_ACTION says (see :mod:`.fence`)."""
        if self.landed:
            self.disarm(force=True)
        elif distance > GIVE_UP_DISTANCE_M:
            self._modes_in_turn("LAND")
        else:
            modes = {
                2: ("LAND",),
                3: ("SMART_RTL", "RTL", "LAND"),
                4: ("BRAKE", "LAND"),
                5: ("SMART_RTL", "LAND"),
            }
            self._modes_in_turn(*modes.get(action, ("RTL", "LAND")))

    def _rtl_alt_cap(self) -> float | None:
        """With the altitude fence enabled, ArduCopter's return stays FENCE_MARGIN under
        FENCE_ALT_MAX (ModeRTL::compute_return_target)."""
        if self.p("FENCE_ENABLE") and int(self.p("FENCE_TYPE")) & ALT_MAX:
            return self.p("FENCE_ALT_MAX") - self.p("FENCE_MARGIN")
        return None

    # --- physics ----------------------------------------------------------------------
    def step(self, dt: float, wall: float) -> None:
        """Advance the flight by ``dt`` seconds of flight time (``wall``: wall clock), in
        steps of at most :data:`STEP_S` (ArduCopter's shaping runs at 400 Hz; a coarse
        step would stop it short or overshoot)."""
        pieces = max(1, math.ceil(dt / STEP_S - 1e-9))
        for _ in range(pieces):
            self._step(dt / pieces, wall)

    def _step(self, dt: float, wall: float) -> None:
        self.sim_time += dt
        self._origin_check()
        self._battery(dt, 1.0 if self.flying else 0.2)
        if not self.armed:
            self.vn = self.ve = 0.0
            self.vu = -5.0 if self.up > 0 else 0.0  # disarmed in the air: it falls
            self.an = self.ae = self.au = 0.0
            self._integrate(dt)
            return
        desired = self._desired_velocity(wall)
        self._shape(desired, dt)
        self._integrate(dt)
        self._yaw(dt)
        self._ground(desired[2])
        self._auto_disarm()

    def _accel_limits(self) -> tuple[float, float]:
        """The horizontal and vertical acceleration limits (m/s²) of the shaping: the
        mode's (WPNAV_ACCEL; BRAKE brakes harder) and WPNAV_ACCEL_Z."""
        brake = BRAKE_ACCEL_FACTOR if self.mode == BRAKE else 1.0
        horizontal = self.p("WPNAV_ACCEL") / 100.0 * brake
        return max(horizontal, 0.1), max(self.p("WPNAV_ACCEL_Z") / 100.0, 0.1)

    def _jerk(self) -> tuple[float, float]:
        """PSC_JERK_XY and PSC_JERK_Z (m/s³), PSC_JERK_NE and PSC_JERK_D from 4.7."""
        params = self.params
        horizontal = params["PSC_JERK_NE"] if "PSC_JERK_NE" in params else params["PSC_JERK_XY"]
        vertical = params["PSC_JERK_D"] if "PSC_JERK_D" in params else params["PSC_JERK_Z"]
        return max(float(horizontal), 0.1), max(float(vertical), 0.1)

    def _shape(self, desired: tuple[float, float, float], dt: float) -> None:
        """The acceleration of the next ``dt`` on the jerk-limited path to ``desired``,
        as ArduCopter's position controller shapes every mode's velocity."""
        accel_h, accel_z = self._accel_limits()
        jerk_h, jerk_z = self._jerk()
        self.an, self.ae = shape_vel_accel_xy(
            (desired[0], desired[1]), (self.vn, self.ve), (self.an, self.ae), accel_h, jerk_h, dt
        )
        self.au = shape_vel_accel(desired[2], self.vu, self.au, -accel_z, accel_z, jerk_z, dt)

    def _integrate(self, dt: float) -> None:
        self.north += self.vn * dt + 0.5 * self.an * dt * dt
        self.east += self.ve * dt + 0.5 * self.ae * dt * dt
        self.up += self.vu * dt + 0.5 * self.au * dt * dt
        self.vn += self.an * dt
        self.ve += self.ae * dt
        self.vu += self.au * dt
        if self.up <= 0.0:
            self.up = 0.0
            self.vu = max(self.vu, 0.0)
            self.au = max(self.au, 0.0)

    def _ground(self, climb_wanted: float) -> None:
        if self.up <= 0.02 and climb_wanted <= 0.0:
            if not self.landed:
                self.landed = True
                self.landed_since = self.sim_time
                self.vn = self.ve = self.vu = 0.0
                self.an = self.ae = self.au = 0.0
                if self.mode in (LAND, RTL, SMART_RTL) or self._auto_landing():
                    self._disarm("Land complete, disarming")
                    if self.mode == AUTO:
                        self._auto_advance((self.mission.current or 0) + 1)
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

    def _speed_limits(self) -> tuple[float, float, float]:
        horizontal = self.p("WPNAV_SPEED") / 100.0
        return horizontal, self.p("WPNAV_SPEED_UP") / 100.0, self.p("WPNAV_SPEED_DN") / 100.0

    def _towards(
        self, target: tuple[float, float, float], speed: float | None = None
    ) -> tuple[float, float, float]:
        """A velocity that flies to ``target`` and stops there, as ArduCopter's
        position shaping asks for it (half the acceleration limit for the approach)."""
        h_max, up_max, down_max = self._speed_limits()
        if speed is not None:
            h_max = min(h_max, speed) if speed > 0 else h_max
        accel_h, accel_z = self._accel_limits()
        jerk_h, jerk_z = self._jerk()
        error = (target[0] - self.north, target[1] - self.east)
        vn, ve = clamp_norm(*position_velocity_xy(error, accel_h, jerk_h, 0.0), h_max)
        vu = position_speed(target[2] - self.up, accel_z, jerk_z, 0.0)
        return vn, ve, max(-down_max, min(up_max, vu))

    def _desired_velocity(self, wall: float) -> tuple[float, float, float]:
        auto_takeoff = (
            self.mode == AUTO
            and self.auto_item is not None
            and self.auto_item.command == NAV_TAKEOFF
        )
        if (
            self.landed
            and not (self.mode == GUIDED and self.guided == "takeoff")
            and not auto_takeoff
        ):
            return (0.0, 0.0, 0.0)
        mode = self.mode
        if mode == GUIDED:
            return self._guided(wall)
        if mode == AUTO:
            return self._auto()
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
            vn, ve, vu = self._towards(target)
            return vn, ve, max(0.3, vu) if self.landed else vu
        if self.guided == "velocity":
            if wall - self.target_vel_wall > self.p("GUID_TIMEOUT"):
                # ArduCopter: no setpoint for GUID_TIMEOUT seconds -> a zero velocity
                # target (it brakes and stays in velocity control).
                self.target_vel = (0.0, 0.0, 0.0)
                self.rate_cmd = None
            vn, ve = clamp_norm(self.target_vel[0], self.target_vel[1], h_max)
            vu = max(-down_max, min(up_max, self.target_vel[2]))
            return vn, ve, vu
        if self.guided == "position" and self.target_pos is not None:
            return self._towards(self.target_pos, self.target_speed)
        return self._towards(self.hold)

    def _land(self) -> tuple[float, float, float]:
        vn, ve, vu = self._towards(self.hold)
        if self.land_pause and self.mode == LAND:
            if self.sim_time - self.land_started < LAND_PAUSE_S:
                return vn, ve, vu  # ModeLand's pause: it holds where LAND began
            self.land_pause = False
        high = self.p("LAND_SPEED_HIGH") or self.p("WPNAV_SPEED_DN")
        speed = high if self.up > self.p("LAND_ALT_LOW") / 100.0 else self.p("LAND_SPEED")
        return vn, ve, -speed / 100.0

    def _rtl(self) -> tuple[float, float, float]:
        rtl_alt = max(self.p("RTL_ALT") / 100.0, self.up + self.p("RTL_CLIMB_MIN") / 100.0)
        cap = self._rtl_alt_cap()
        if cap is not None:
            rtl_alt = min(rtl_alt, cap)
        if self.rtl_stage == "climb":
            if math.hypot(self.north, self.east) < 2.0:
                self.rtl_stage = "loiter"  # already home: no need to climb
                self.rtl_loiter_until = self.sim_time + self.p("RTL_LOIT_TIME") / 1000.0
            elif self.up >= rtl_alt - 0.2:
                self.rtl_stage = "return"
                # Above the fence's cap (it was breached): back down to it on the way.
                self.hold = (0.0, 0.0, self.up if cap is None else min(self.up, rtl_alt))
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

    def _auto_course(self) -> float | None:
        """Where the nose turns in AUTO, on the way to a waypoint (ArduCopter's
        WP_YAW_BEHAVIOR, not 0: towards the next waypoint; within 2 m of it, or 0,
        where it points); None otherwise."""
        item = self.auto_item
        if (
            self.mode != AUTO
            or item is None
            or item.command not in (NAV_WAYPOINT, NAV_LOITER_UNLIM)
            or self.auto_reached
            or self.p("WP_YAW_BEHAVIOR") == 0
        ):
            return None
        north, east, _ = self.auto_target
        if math.hypot(north - self.north, east - self.east) < 2.0:
            return None
        return math.degrees(math.atan2(east - self.east, north - self.north))

    def _yaw(self, dt: float) -> None:
        before = self.yaw
        if self.target_yaw is not None:
            error = wrap180(self.target_yaw - self.yaw)
            if self.yaw_dir > 0 and error < 0 and abs(error) > 1:
                error += 360.0
            elif self.yaw_dir < 0 and error > 0 and abs(error) > 1:
                error -= 360.0
            step = self.yaw_speed * dt
            if abs(error) <= step:
                self.yaw = self.target_yaw
                self.target_yaw = None
            else:
                self.yaw = wrap360(self.yaw + math.copysign(step, error))
        elif self.rate_cmd is not None and self.guided == "velocity":
            self.yaw = wrap360(self.yaw + self.rate_cmd * dt)
        elif (
            self.look_ahead
            and self.guided == "velocity"
            and math.hypot(self.vn, self.ve) > 0.05 * self.p("WPNAV_SPEED") / 100.0
        ):
            course = math.degrees(math.atan2(self.ve, self.vn))
            error = wrap180(course - self.yaw)
            step = DEFAULT_YAW_RATE_DEG_S * dt
            self.yaw = wrap360(self.yaw + max(-step, min(step, error)))
        elif (towards := self._auto_course()) is not None:
            error = wrap180(towards - self.yaw)
            step = DEFAULT_YAW_RATE_DEG_S * dt
            self.yaw = wrap360(self.yaw + max(-step, min(step, error)))
        self.yaw_rate = wrap180(self.yaw - before) / dt if dt > 0 else 0.0

    # --- what the autopilot reports ---------------------------------------------------
    def landed_state(self) -> int:
        if not self.armed or self.landed:
            return int(MAV.MAV_LANDED_STATE_ON_GROUND)
        if self.mode == GUIDED and self.guided == "takeoff":
            return int(MAV.MAV_LANDED_STATE_TAKEOFF)
        if (
            self.mode == LAND
            or (self.mode == RTL and self.rtl_stage == "land")
            or self._auto_landing()
        ):
            return int(MAV.MAV_LANDED_STATE_LANDING)
        return int(MAV.MAV_LANDED_STATE_IN_AIR)
