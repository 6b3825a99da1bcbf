"""The MAVLink multicopter (the paper's Navio2/ArduPilot quadcopter, 4.2.2): ArduCopter.

The paper's Table 3 commands in MAVLink (``docs/vehicles/quadcopter.md`` has the whole
mapping and the safety behaviour):

=====================  ===============================================================
arm / disarm           GUIDED first (arm only), MAV_CMD_COMPONENT_ARM_DISARM
take_off(altitude_m)   GUIDED, arm if needed, MAV_CMD_NAV_TAKEOFF
front/back/left/right  SET_POSITION_TARGET_LOCAL_NED, MAV_FRAME_BODY_OFFSET_NED,
up/down(speed_mps)     velocity only, yaw rate 0 (hold the heading)
rotate_left/right      MAV_CMD_CONDITION_YAW, relative, direction -1/+1
go_to_waypoint         MAV_CMD_DO_REPOSITION (COMMAND_INT, relative altitude), then
                       MAV_CMD_DO_CHANGE_SPEED if speed_mps (ArduCopter forgets a speed
                       sent before it)
land                   MAV_CMD_NAV_LAND
return_to_home         MAV_CMD_NAV_RETURN_TO_LAUNCH
stop                   zero velocity setpoint (hover) in GUIDED
release_payload        MAV_CMD_DO_GRIPPER or MAV_CMD_DO_SET_SERVO (``payload`` option)
=====================  ===============================================================

Velocity setpoints have no ACK in MAVLink: their ack means "accepted by the agent and
sent", after the agent checked that the drone is flying in GUIDED (or switched it back
to GUIDED, with an ACK, from a hold/return the user asked for).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from typing import Any

from agents.geo import distance_m, local_offset_m, offset
from agents.vehicles.base import AdapterError, Breach, Projection
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.mavlink.classes import COPTER_MODES
from agents.vehicles.mavlink.config import VELOCITY_FRAMES
from agents.vehicles.mavlink.dialect import (
    MASK_VELOCITY_YAW,
    MASK_VELOCITY_YAW_RATE,
    MAV,
    body_to_ned,
    wrap180,
)

logger = logging.getLogger(__name__)

_NUMBER = {name: number for number, name in COPTER_MODES.items()}
GUIDED, LOITER, RTL, LAND = _NUMBER["GUIDED"], _NUMBER["LOITER"], _NUMBER["RTL"], _NUMBER["LAND"]
BRAKE, SMART_RTL = _NUMBER["BRAKE"], _NUMBER["SMART_RTL"]
#: Modes in which the drone holds or flies on its own and the user may take it back by
#: moving, if the user (or a user-link fail-safe) put it there.
RESUMABLE_MODES = frozenset(
    {LOITER, BRAKE, RTL, LAND, SMART_RTL, _NUMBER["POSHOLD"], _NUMBER["ALT_HOLD"]}
)

#: Movement commands as (forward, right, up) unit vectors in the body frame.
BODY_AXES: dict[str, tuple[float, float, float]] = {
    "front": (1.0, 0.0, 0.0),
    "back": (-1.0, 0.0, 0.0),
    "left": (0.0, -1.0, 0.0),
    "right": (0.0, 1.0, 0.0),
    "up": (0.0, 0.0, 1.0),
    "down": (0.0, 0.0, -1.0),
}


class CopterAdapter(MavlinkAdapter):
    """An ArduCopter multicopter; see the module docstring."""

    safe_action_words = {
        "stop": "stop and hover where it is",
        "land": "land where it is",
        "return_to_home": "climb to its return altitude, fly back to its home point and land",
    }

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self._takeoff_at = 0.0
        self._yaw_target: float | None = None
        self._yaw_deadline = 0.0
        #: The user's velocity setpoint under way (forward, right, up; m/s), while
        #: ``_moving_until`` holds it.
        self._setpoint: tuple[float, float, float] | None = None

    # --- state -------------------------------------------------------------------------
    def _in_air(self) -> bool:
        t = self.t
        if not t.armed:
            return False
        if time.monotonic() - self._takeoff_at < 5.0:
            return True  # the autopilot accepted a takeoff; its streams lag behind
        if t.landed_state in (2, 3, 4):  # IN_AIR, TAKEOFF, LANDING
            return True
        if t.landed_state == 1:  # ON_GROUND
            return False
        return t.alt is not None and t.alt > 0.5

    def _busy(self) -> bool:
        return self._in_air()

    def _stop_moving(self) -> None:
        self._moving_until = None
        if not self.t.armed:
            self._yaw_target = None

    def telemetry(self) -> dict[str, Any]:
        """Every topic of the copter's vocabulary; None until the autopilot sent it."""
        t = self.t
        return {
            **self._telemetry_common(),
            "altitude": None if t.alt is None else round(t.alt, 2),
            "flight_mode": self.mode_name(t.mode),
            "in_air": self._in_air() if t.armed is not None else None,
        }

    # --- the envelope ------------------------------------------------------------------
    def project(self, name: str, args: Mapping[str, Any]) -> Projection | None:
        """Where a command takes the drone, for the gate's ceiling and geofence checks:
        a movement ``setpoint_hold_s`` (1 s) ahead at the commanded speed (body axes
        turned by the heading), with its velocity, so that the gate predicts where the
        drone comes to rest (:meth:`braking`); the target altitude of ``take_off``, the
        waypoint of ``go_to_waypoint``; None for the rest."""
        t = self.t
        if name == "take_off":
            return Projection(lat=t.lat, lon=t.lon, alt=float(args.get("altitude_m", 0)))
        if name == "go_to_waypoint":
            return Projection(
                lat=float(args["lat"]), lon=float(args["lon"]), alt=float(args["alt_m"])
            )
        body = BODY_AXES.get(name)
        if body is None:
            return None
        speed = float(args.get("speed_mps", self.config.move_speed_mps))
        forward, right, up = (axis * speed for axis in body)
        hold = self.config.setpoint_hold_s
        alt = None if t.alt is None else max(0.0, t.alt + up * hold)
        if forward == right == 0:
            return Projection(alt=alt, velocity=(0.0, 0.0, up))
        if t.lat is None or t.lon is None or t.heading is None:
            return Projection(alt=alt)
        north, east = body_to_ned(forward, right, t.heading)
        lat, lon = offset((t.lat, t.lon), north * hold, east * hold)
        return Projection(lat=lat, lon=lon, alt=alt, velocity=(north, east, up))

    async def stop_motion(self, name: str) -> None:
        """The movement ``name`` was refused at a limit: take its axis out of the
        setpoint under way now (a climb refused at the ceiling hovers at once; the rest
        of the setpoint keeps its hold). Never raises."""
        axis = BODY_AXES.get(name)
        setpoint = self._setpoint
        if axis is None or setpoint is None or self._moving_until is None:
            return
        along = sum(a * v for a, v in zip(axis, setpoint, strict=True))
        if along <= 0:
            return  # not moving that way
        rest = tuple(v - along * a for a, v in zip(axis, setpoint, strict=True))
        forward, right, up = rest
        self._setpoint = (forward, right, up)
        if self.link.ok and self.t.mode == GUIDED and self._in_air():
            self._send_velocity(forward, right, up)

    # --- acting ------------------------------------------------------------------------
    async def execute(self, name: str, args: Mapping[str, Any]) -> None:
        """Carry out a checked command; see the module docstring for the mapping.

        Raises AdapterError: ``autopilot_lost`` (no heartbeat), ``autopilot_refused`` (a
        COMMAND_ACK other than ACCEPTED, with its words), ``timeout`` (no COMMAND_ACK in
        ``command_timeout_s``), ``not_flying`` / ``in_air`` / ``low_battery`` /
        ``autopilot_mode`` (checked here before anything is sent), ``not_ready``,
        ``unknown_command``.
        """
        self.safe_action_done = False
        self._require_link(name)
        body = BODY_AXES.get(name)
        if body is not None:
            speed = float(args.get("speed_mps", self.config.move_speed_mps))
            await self._move(name, *(axis * speed for axis in body))
        elif name in ("rotate_left", "rotate_right"):
            await self._rotate(name, float(args.get("angle_deg", self.config.rotate_default_deg)))
        elif name == "take_off":
            await self._take_off(float(args.get("altitude_m", self.config.takeoff_default_m)))
        elif name == "arm":
            await self._arm()
        elif name == "disarm":
            await self._disarm()
        elif name == "land":
            await self._command_mode(MAV.MAV_CMD_NAV_LAND, LAND, owner="user")
        elif name == "return_to_home":
            await self._command_mode(MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH, RTL, owner="user")
        elif name == "go_to_waypoint":
            speed = min(float(args.get("speed_mps") or 0), self.config.max_speed_mps)
            await self._go_to(
                float(args["lat"]), float(args["lon"]), float(args["alt_m"]), speed=speed or None
            )
        elif name == "stop":
            # Stop moving and turning: yaw rate 0 also ends a rotation under way.
            self._moving_until = None
            self._yaw_target = None
            if self.t.mode == GUIDED and self._in_air():
                self._send_velocity(0.0, 0.0, 0.0)
        elif name == "release_payload" and self.config.payload is not None:
            await self._release_payload()
        else:
            raise AdapterError(f"{name!r} is not a command of this drone", code="unknown_command")

    async def _disarm(self) -> None:
        if self.t.armed is False:
            return
        if self._in_air():
            raise AdapterError("the drone is flying: land first, then disarm", code="in_air")
        await self._disarm_now()

    async def _take_off(self, altitude: float) -> None:
        if self._in_air():
            alt = self.t.alt
            where = f" at {alt:.1f} m" if alt is not None else ""
            raise AdapterError(f"already flying{where}: use up and down", code="in_air")
        self._check_battery_for("take-off")
        await self._set_mode(GUIDED, owner="user")
        if not self.t.armed:
            await self.link.command_long(MAV.MAV_CMD_COMPONENT_ARM_DISARM, (1,))
            self._assume(armed=True)
        await self.link.command_long(MAV.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, math.nan, 0, 0, altitude))
        self._takeoff_at = time.monotonic()

    async def _ensure_guided_flight(self, what: str) -> None:
        """Refuse unless the drone flies in GUIDED; take it back to GUIDED from a hold,
        return or landing that the user (or the user-link fail-safe) started."""
        t = self.t
        if not t.armed or not self._in_air():
            raise AdapterError(
                f"the drone is on the ground: take off first ({what})", code="not_flying"
            )
        if t.mode == GUIDED:
            return
        mode = self.mode_name(t.mode)
        if self._mode_owner == "low_battery":
            battery = "" if t.battery is None else f" (battery {t.battery:.0f}%)"
            raise AdapterError(
                f"low battery{battery}: the drone is returning home; {what} is refused",
                code="low_battery",
            )
        if t.mode in RESUMABLE_MODES and self._mode_owner in ("user", "failsafe"):
            await self._set_mode(GUIDED, owner="user")
            return
        raise AdapterError(
            f"the autopilot is in {mode} on its own (e.g. its own fail-safe): {what} is refused",
            code="autopilot_mode",
        )

    async def _move(self, name: str, forward: float, right: float, up: float) -> None:
        await self._ensure_guided_flight(name)
        self._send_velocity(forward, right, up)
        self._setpoint = (forward, right, up)
        self._moving_until = time.monotonic() + self.config.setpoint_hold_s

    def _tick(self, now: float) -> None:
        if self._moving_until is not None and now > self._moving_until:
            # The user stopped repeating the command (key released, browser gone): hover
            # now rather than when the autopilot's own setpoint timeout (3 s) ends it.
            self._moving_until = None
            if self.link.ok and self.t.mode == GUIDED:
                self._send_velocity(0.0, 0.0, 0.0)

    def _send_velocity(self, forward: float, right: float, up: float) -> None:
        """A body-frame velocity setpoint. Yaw: rate 0 (hold the heading), or the rest
        of a rotation still under way (relative yaw), never "ignored": ArduCopter then
        falls back to WP_YAW_BEHAVIOR and turns the nose into the direction of travel,
        which in a body frame sends "right" round in circles."""
        target = self.link.target_or_default()
        yaw_left = self._yaw_remaining()
        mask, yaw = MASK_VELOCITY_YAW_RATE, 0.0
        if yaw_left is not None:
            mask, yaw = MASK_VELOCITY_YAW, math.radians(yaw_left)
        self.link.send(
            MAV.MAVLink_set_position_target_local_ned_message(
                self.link.boot_ms(self._started_at), target[0], target[1],
                VELOCITY_FRAMES[self.config.velocity_frame],
                mask, 0.0, 0.0, 0.0, forward, right, -up, 0.0, 0.0, 0.0, yaw, 0.0,
            )
        )  # fmt: skip
        self.link.stats["setpoints"] += 1

    def _yaw_remaining(self) -> float | None:
        if self._yaw_target is None or self.t.heading is None:
            return None
        left = wrap180(self._yaw_target - self.t.heading)
        if abs(left) < 2.0 or time.monotonic() > self._yaw_deadline:
            self._yaw_target = None
            return None
        return left

    async def _rotate(self, name: str, angle: float) -> None:
        """CONDITION_YAW, relative. A held key repeats the command, and the autopilot
        adds a relative yaw to the rotation still under way: sending the full angle
        each time would pile targets up and keep the drone turning long after the key
        is released. So the target is kept ``angle`` ahead of the current heading: only
        the shortfall is sent (nothing, when the target is already far enough ahead)."""
        await self._ensure_guided_flight(name)
        direction = -1 if name == "rotate_left" else 1
        heading = self.t.heading
        pending = self._yaw_remaining() or 0.0
        delta = direction * angle - pending
        rate = self.config.rotate_rate_deg_s
        if abs(delta) >= 1.0:
            turn = 1 if delta > 0 else -1
            await self.link.command_long(MAV.MAV_CMD_CONDITION_YAW, (abs(delta), rate, turn, 1))
        if heading is not None:
            self._yaw_target = (heading + direction * angle) % 360.0
            self._yaw_deadline = time.monotonic() + angle / rate + 3.0

    async def _go_to(
        self, lat: float, lon: float, alt: float, *, speed: float | None = None
    ) -> None:
        await self._ensure_guided_flight("go_to_waypoint")
        await self._go_to_position(lat, lon, alt, speed=speed)

    # --- safety ------------------------------------------------------------------------
    async def safe_action(self, action: str) -> None:
        """Make the drone safe; never raises (a failure is logged and reported as the
        ``safe_action_failed`` event).

        ``return_to_home``: RTL (the autopilot climbs to RTL_ALT, flies home, lands and
        disarms), falling back to LAND; ``land``: LAND; ``stop``: hover (zero velocity),
        then BRAKE, falling back to LOITER, then LAND. Already landing (LAND): it goes on
        landing, whatever the action (a return would climb back up from the last
        metres). Armed on the ground: disarm. Disarmed: nothing to do. Without a link to
        the autopilot nothing can be sent: the autopilot's own GCS fail-safe (see
        :meth:`check_failsafe_params`) acts.
        """
        self.safe_action_done = True
        self._moving_until = None
        self._yaw_target = None
        try:
            if not self.link.ok:
                logger.error("mavlink: safe action %s impossible: no autopilot link", action)
                self.emit(
                    "safe_action_failed",
                    {"action": action, "reason": "no link to the autopilot"},
                )
                return
            if not self.t.armed:
                return
            if not self._in_air():
                await self._disarm_now()
                return
            if self.t.mode == LAND:
                return  # landing already: finishing that is the safe thing
            steps: list[Any]
            if action == "land":
                steps = [lambda: self._set_mode(LAND, owner="failsafe")]
            elif action == "stop":
                if self.t.mode == GUIDED:
                    self._send_velocity(0.0, 0.0, 0.0)
                steps = [
                    lambda: self._set_mode(BRAKE, owner="failsafe"),
                    lambda: self._set_mode(LOITER, owner="failsafe"),
                    lambda: self._set_mode(LAND, owner="failsafe"),
                ]
            else:
                steps = [
                    lambda: self._set_mode(RTL, owner="failsafe"),
                    lambda: self.link.command_long(MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH, ()),
                    lambda: self._set_mode(LAND, owner="failsafe"),
                ]
            await self._try_in_turn(action, steps)
        except Exception:
            logger.exception("mavlink: safe action %s failed", action)
            self.emit("safe_action_failed", {"action": action, "reason": "internal error"})

    def safe_action_now(self, action: str) -> str | None:
        """A drone landing goes on landing; one on the ground stops its motors (see
        :meth:`safe_action`)."""
        t = self.t
        if not t.armed:
            return "stay where it is (its motors are off)"
        if not self._in_air():
            return "stop its motors where it is"
        if t.mode == LAND:
            return "go on landing where it is"
        return None

    async def envelope_recover(self, breach: Breach) -> str:
        """Bring the drone back inside a limit it crossed, whatever crossed it.

        * altitude: a position target right here, ``breach.target`` high (GUIDED):
          the climb stops and the drone descends below the ceiling and holds; in RTL
          (its climb to RTL_ALT crossed the ceiling) LAND instead, as ArduCopter's
          own fence does when breached during a return; in LAND nothing to do;
        * geofence: a position target ``breach.target`` from the centre on the line to
          where it is, at its altitude (GUIDED); nothing in LAND or RTL (on its way
          down or home);
        * speed (GUIDED only: ArduCopter takes no speed in its own modes): a zero
          velocity setpoint if the user's movement is under way, and DO_CHANGE_SPEED
          to ``breach.target`` (the speed of the position it flies to).

        Flying is what the user's own commands see afterwards, in GUIDED. Raises
        AdapterError when the autopilot refuses (the hub reports it as the action).
        """
        t = self.t
        moving = self._moving_until is not None
        if not self.link.ok:
            return "none: no link to the autopilot"
        if not t.armed or not self._in_air():
            return "none: not flying"
        if breach.limit == "speed":
            if t.mode != GUIDED:
                # ArduCopter takes DO_CHANGE_SPEED in GUIDED and AUTO only; a return
                # flies at RTL_SPEED.
                return f"none: {self.mode_name(t.mode)} flies at the autopilot's own speed"
            if moving:
                self._moving_until = None
                self._send_velocity(0.0, 0.0, 0.0)
            await self._change_speed(breach.target)
            return f"slow down to {breach.target:.1f} m/s"
        if t.mode == LAND:
            return "none: landing"
        if t.mode in (RTL, SMART_RTL):
            if breach.limit == "geofence":
                return "none: returning home"
            owner = "low_battery" if self._mode_owner == "low_battery" else "failsafe"
            await self._set_mode(LAND, owner=owner)
            return "land: the return climbs above the ceiling"
        if t.lat is None or t.lon is None or t.alt is None:
            return "none: position unknown"
        lat, lon, alt = t.lat, t.lon, t.alt
        if breach.limit == "altitude":
            alt = breach.target
            action = f"descend to {alt:.1f} m and hold"
        else:
            centre = breach.centre or (lat, lon)
            out = distance_m(centre, (lat, lon))
            if out > 0:
                north, east = local_offset_m(centre, (lat, lon))
                share = max(0.0, breach.target) / out
                lat, lon = offset(centre, north * share, east * share)
            action = "fly back inside the geofence and hold"
        self._moving_until = None
        self._yaw_target = None
        if t.mode != GUIDED:
            await self._set_mode(GUIDED, owner="failsafe")
        await self._reposition(lat, lon, alt)
        return action

    async def neutral(self) -> None:
        """Hover: a zero velocity setpoint if the drone flies in GUIDED. Never raises."""
        self._moving_until = None
        if self.link.ok and self.t.mode == GUIDED and self._in_air():
            self._send_velocity(0.0, 0.0, 0.0)
