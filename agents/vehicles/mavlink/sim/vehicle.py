"""What every simulated vehicle shares: its state, arming, modes and battery. The flight
or driving logic is each class's (:mod:`.copter`, :mod:`.boat`).

A vehicle does no I/O: the autopilot (:mod:`.autopilot`) decodes what ground stations
send, hands it over (:meth:`SimVehicle.command`, :meth:`SimVehicle.local_target`, ...),
steps the vehicle (:meth:`SimVehicle.step`) and reports it. Positions are metres
north/east/up of home; velocities m/s in the same axes; yaw in degrees clockwise from
north. ``params`` is the live parameter table, in the firmware's units. Commands return
None on success or the refusal text ArduPilot would show; MAV_CMDs return
``(MAV_RESULT, text)``, the text going out as a STATUSTEXT before the COMMAND_ACK.
"""

from __future__ import annotations

import abc
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar

from agents.geo import offset
from agents.vehicles.mavlink.classes import VehicleClass
from agents.vehicles.mavlink.dialect import MAV
from agents.vehicles.mavlink.sim.fence import SimFence, fence_names
from agents.vehicles.mavlink.sim.mission import SimMission

#: SET_POSITION_TARGET_* type_mask bits; a bit set means "ignore this field".
TYPE_MASK_POS = 0b111
TYPE_MASK_VEL = 0b111000
TYPE_MASK_ACC = 0b111000000
TYPE_MASK_YAW = 1024
TYPE_MASK_YAW_RATE = 2048
BODY_FRAMES = frozenset({8, 9, 12})  # BODY_NED, BODY_OFFSET_NED, BODY_FRD
OFFSET_FRAMES = frozenset({7, 8, 9, 12})

#: A MAV_CMD's outcome: (MAV_RESULT, the text ArduPilot says with it, or None).
CommandResult = tuple[int, str | None]


def wrap360(deg: float) -> float:
    return deg % 360.0


def wrap180(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def approach(value: float, target: float, step: float) -> float:
    """Move ``value`` towards ``target`` by at most ``step``."""
    if abs(target - value) <= step:
        return target
    return value + math.copysign(step, target - value)


def clamp_norm(x: float, y: float, limit: float) -> tuple[float, float]:
    """``(x, y)`` shortened to length ``limit`` if longer."""
    norm = math.hypot(x, y)
    if norm <= limit or norm == 0:
        return x, y
    return x * limit / norm, y * limit / norm


@dataclass(frozen=True)
class PositionTarget:
    """A SET_POSITION_TARGET_LOCAL_NED or SET_POSITION_TARGET_GLOBAL_INT as it came:
    each firmware reads it its own way. Local: ``x``, ``y``, ``z`` in metres (north,
    east, down; forward, right, down in a body frame); global: latitude and longitude in
    degrees and altitude in metres. ``yaw`` in radians, ``yaw_rate`` in rad/s."""

    frame: int
    type_mask: int
    x: float
    y: float
    z: float
    vx: float
    vy: float
    vz: float
    yaw: float
    yaw_rate: float


@dataclass
class SimVehicle(abc.ABC):
    """The state and the logic every simulated vehicle shares (see the module
    docstring). A class sets the ClassVars and implements the abstract methods."""

    #: Its class (firmware, modes), the MAV_TYPE of its heartbeat, the modes that need a
    #: position (refused while armed without one; "guided" in the heartbeat) and those
    #: it will not arm in.
    VEHICLE_CLASS: ClassVar[VehicleClass]
    MAV_TYPE: ClassVar[int]
    POSITION_MODES: ClassVar[frozenset[int]]
    NOT_ARMABLE: ClassVar[frozenset[int]]

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
    mode: int = 0  # STABILIZE on ArduCopter, MANUAL on ArduRover: what both boot in
    battery_pct: float = 100.0
    drain_pct_per_min: float = 5.0  # at full effort: a 20-minute battery
    gps_fix: int = 3  # GPS_FIX_TYPE: 0 no GPS, 1 no fix, 2 2D, 3 3D
    satellites: int = 12
    # The EKF's origin (and home) is set at the first good fix; before it ArduPilot
    # knows no position and sends 0/0.
    origin_set: bool = False
    sim_time: float = 0.0
    payload_released: bool = False
    texts: deque[tuple[int, str]] = field(default_factory=lambda: deque(maxlen=32))
    fence: SimFence = field(default_factory=SimFence)
    mission: SimMission = field(default_factory=SimMission)

    # --- helpers ----------------------------------------------------------------------
    @property
    def modes(self) -> Mapping[int, str]:
        return self.VEHICLE_CLASS.modes

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
    @abc.abstractmethod
    def active(self) -> bool:
        """Out and working (a copter in the air, a boat under way): it draws current,
        and a copter's GCS fail-safe acts instead of disarming it."""

    def _origin_check(self) -> None:
        """Set the EKF origin (and home) at the first good fix, as ArduPilot does."""
        if not self.origin_set and self.position_ok:
            self.origin_set = True
            self.say(MAV.MAV_SEVERITY_INFO, "EKF3 IMU0 origin set")

    # --- modes and arming ---------------------------------------------------------------
    def set_mode(self, mode: int) -> str | None:
        """Change mode; ArduPilot checks a mode's needs only while armed."""
        name = self.modes.get(mode)
        if name is None:
            return f"Mode change failed: unknown mode {mode}"
        if self.armed and mode in self.POSITION_MODES and not self.position_ok:
            return f"Mode change failed: {name} requires position"
        if mode == self.mode:
            return None
        if name == "AUTO":
            refusal = self._auto_refusal()
            if refusal is not None:
                return refusal
        self.mode = mode
        self._entered(name)
        return None

    @abc.abstractmethod
    def _auto_refusal(self) -> str | None:
        """Why AUTO is refused now (None: it is not), in the firmware's words."""

    def mission_set_current(self, seq: int) -> bool:
        """MAV_CMD_DO_SET_MISSION_CURRENT: the item AUTO flies next (now, in AUTO, as
        ArduPilot starts it at once; the next time it starts or resumes, else). False for
        an item that does not exist."""
        if not 1 <= seq < self.mission.count:
            return False
        self.mission.set_current(seq)
        if self.mission.state != "running":
            self.mission.state = "stopped"  # resumed from there, not restarted
        elif self.modes.get(self.mode) == "AUTO":
            self._auto_advance(seq)
        return True

    def _auto_start_or_resume(self) -> None:
        """Start the mission (MIS_RESTART 1, a finished or never started one) or resume
        it at its current navigation item (AP_Mission::start_or_resume)."""
        m = self.mission
        resume = (
            not self.p("MIS_RESTART")
            and m.state != "complete"
            and m.current is not None
            and m.current < m.count
        )
        m.state = "running"
        if resume and m.current is not None:
            self._auto_start_nav(m.current)
        else:
            self._auto_advance(1)

    @abc.abstractmethod
    def _auto_advance(self, index: int) -> None:
        """From item ``index`` on: perform the "do" items and start the next navigation
        item the vehicle drives; none left: the mission is complete."""

    @abc.abstractmethod
    def _auto_start_nav(self, index: int) -> None:
        """Start navigation item ``index``."""

    @abc.abstractmethod
    def _entered(self, mode: str) -> None:
        """The vehicle has just switched to ``mode`` (its name): reset what the mode
        before it left behind."""

    def arm(self) -> CommandResult:
        """Arm, if the mode, the GPS and the battery allow it."""
        if self.armed:
            return MAV.MAV_RESULT_ACCEPTED, None
        if self.mode in self.NOT_ARMABLE:
            return MAV.MAV_RESULT_DENIED, f"Arm: Mode not armable ({self.modes[self.mode]})"
        if self.p("ARMING_CHECK") != 0:
            if self.mode in self.POSITION_MODES and not self.position_ok:
                reason = "no 3D fix" if self.gps_fix < 3 else f"{self.satellites} satellites"
                return MAV.MAV_RESULT_TEMPORARILY_REJECTED, f"PreArm: GPS: {reason}"
            if self.battery_pct < 10:
                return (
                    MAV.MAV_RESULT_TEMPORARILY_REJECTED,
                    f"PreArm: Battery 1 low capacity ({self.battery_pct:.0f}%)",
                )
            refusal = self._arming_refusal()
            if refusal is not None:
                return MAV.MAV_RESULT_TEMPORARILY_REJECTED, refusal
        self.armed = True
        self._on_armed()
        self.say(MAV.MAV_SEVERITY_INFO, "Arming motors")
        return MAV.MAV_RESULT_ACCEPTED, None

    def _arming_refusal(self) -> str | None:
        """A class's own pre-arm check: its refusal text, or None."""
        return None

    @abc.abstractmethod
    def _on_armed(self) -> None:
        """Just armed: where it holds from now."""

    def disarm(self, *, force: bool = False) -> CommandResult:
        """Disarm (``force``: MAVLink's 21196 magic, past any refusal)."""
        if not self.armed:
            return MAV.MAV_RESULT_ACCEPTED, None
        refusal = None if force else self._disarm_refusal()
        if refusal is not None:
            return MAV.MAV_RESULT_DENIED, refusal
        self._disarm("Disarming motors")
        return MAV.MAV_RESULT_ACCEPTED, None

    def _disarm_refusal(self) -> str | None:
        """Why a disarm is refused now (None: it is not)."""
        return None

    def _disarm(self, why: str) -> None:
        self.armed = False
        self.vn = self.ve = self.vu = 0.0
        self._on_disarmed()
        self.say(MAV.MAV_SEVERITY_INFO, why)

    @abc.abstractmethod
    def _on_disarmed(self) -> None:
        """Just disarmed: forget what it was doing."""

    # --- what ground stations send ------------------------------------------------------
    def command(
        self, command: int, p: tuple[float, ...], z: float, frame: int | None
    ) -> CommandResult:
        """A MAV_CMD of the firmware's own (take-off, repositioning, speed...), with its
        params 1-6 (COMMAND_INT's x and y already in degrees), its z (param 7) and its
        frame (None for COMMAND_LONG). The autopilot handles arming, modes, messages
        and the payload; everything else comes here. Default: NAV_RETURN_TO_LAUNCH
        (mode RTL); UNSUPPORTED for the rest."""
        if command == MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            error = self.set_mode(self.VEHICLE_CLASS.mode_number("RTL"))
            return (MAV.MAV_RESULT_FAILED, error) if error else (MAV.MAV_RESULT_ACCEPTED, None)
        return MAV.MAV_RESULT_UNSUPPORTED, None

    @abc.abstractmethod
    def local_target(self, target: PositionTarget, wall: float) -> None:
        """SET_POSITION_TARGET_LOCAL_NED addressed to it (``wall``: the wall clock,
        which times a setpoint out)."""

    @abc.abstractmethod
    def global_target(self, target: PositionTarget, wall: float) -> None:
        """SET_POSITION_TARGET_GLOBAL_INT addressed to it."""

    # --- the GCS fail-safe ----------------------------------------------------------------
    @abc.abstractmethod
    def gcs_failsafe_after_s(self) -> float | None:
        """How long the GCS may be silent (wall clock) before the GCS fail-safe acts;
        None while it is disabled."""

    @abc.abstractmethod
    def gcs_failsafe(self) -> bool:
        """The GCS is silent past :meth:`gcs_failsafe_after_s` while armed: act as the
        firmware's parameters say. False when the firmware holds off for now (ArduRover
        in RTL): the autopilot asks again at its next step."""

    # --- the fence ---------------------------------------------------------------------
    def fence_check(self) -> bool:
        """Check the fence (see :mod:`.fence`) and act on a new breach; True when its
        state changed (FENCE_STATUS is due)."""
        before = self.fence.breached
        new, distance = self.fence.check(
            self.params, self.north, self.east, self.up, flies=self.VEHICLE_CLASS.flies
        )
        if not self.armed:
            return self.fence.breached != before
        if new:
            self.fence.breach_time_ms = int(self.sim_time * 1000)
            if self.active:
                self.say(MAV.MAV_SEVERITY_NOTICE, f"{fence_names(new)} breached")
            if int(self.p("FENCE_ACTION")) != 0:
                self._fence_breached(int(self.p("FENCE_ACTION")), distance)
        elif before and not self.fence.breached and self.active:
            self.say(MAV.MAV_SEVERITY_NOTICE, "Fence breach cleared")
        return self.fence.breached != before

    @abc.abstractmethod
    def _fence_breached(self, action: int, distance: float) -> None:
        """A new breach, ``distance`` m out: do what FENCE_ACTION ``action`` says."""

    def _modes_in_turn(self, *names: str) -> None:
        """The first of the modes ``names`` it can switch to."""
        for name in names:
            if self.set_mode(self.VEHICLE_CLASS.mode_number(name)) is None:
                return

    # --- physics ----------------------------------------------------------------------
    @abc.abstractmethod
    def step(self, dt: float, wall: float) -> None:
        """Advance ``dt`` seconds of simulated time (``wall``: the wall clock)."""

    def _battery(self, dt: float, effort: float) -> None:
        """Drain: ``effort`` 1 at full work; a hundredth of it when disarmed."""
        per_s = self.drain_pct_per_min / 60.0
        rate = per_s * effort if self.armed else per_s * 0.01
        self.battery_pct = max(0.0, self.battery_pct - rate * dt)

    # --- what the autopilot reports ---------------------------------------------------
    def landed_state(self) -> int:
        """EXTENDED_SYS_STATE's landed_state."""
        return int(MAV.MAV_LANDED_STATE_UNDEFINED)

    def throttle_pct(self) -> int:
        """VFR_HUD's throttle."""
        return 55 if self.active else 0

    def current_ca(self) -> int:
        """The battery current, cA."""
        return 1800 if self.active else 50 if self.armed else 20
