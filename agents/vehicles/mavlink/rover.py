"""The MAVLink rover and boat: ArduRover (FRAME_CLASS 1, a rover; 2, a boat).

Driven in GUIDED, the way ArduRover's ground-station interface does it
(``docs/vehicles/boat.md`` has the whole mapping and the safety behaviour):

=====================  ===============================================================
arm / disarm           GUIDED first (arm only), MAV_CMD_COMPONENT_ARM_DISARM; disarm
                       refused while under way
forward/backward       SET_POSITION_TARGET_LOCAL_NED, MAV_FRAME_BODY_NED, velocity and
(speed_mps)            yaw rate (type_mask 1511): vx is the signed speed along the
left/right             heading, the yaw rate the turn (ArduRover's
(rate_deg_s)           set_desired_turn_rate_and_speed); a held "forward" and a held
                       "left" combine into a curve, "left" alone turns on the spot
go_to_waypoint         MAV_CMD_DO_REPOSITION (COMMAND_INT, no speed), then
                       MAV_CMD_DO_CHANGE_SPEED if speed_mps: ArduRover takes a speed only
                       while it drives to a position; it drives there and holds
return_to_home         MAV_CMD_NAV_RETURN_TO_LAUNCH (RTL: home, then it holds)
stop                   zero speed and turn rate in GUIDED
release_payload        MAV_CMD_DO_SET_SERVO or MAV_CMD_DO_GRIPPER (``payload`` option)
=====================  ===============================================================

Like a copter's, each movement setpoint holds ``setpoint_hold_s`` and a held key repeats
it; released, the agent sends a stop at once rather than waiting for ArduRover's own
3 s setpoint timeout. There is no altitude: neither in the state, nor in the envelope.

Holding still: HOLD stops the motors, so a rover stands but a boat drifts with the wind
and the current; the boat holds with LOITER (it keeps its position), the rover with
HOLD (see :mod:`.classes`).
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
from agents.vehicles.mavlink.classes import ROVER_MODES
from agents.vehicles.mavlink.dialect import FRAME_BODY_NED, MAV

logger = logging.getLogger(__name__)

_NUMBER = {name: number for number, name in ROVER_MODES.items()}
GUIDED, HOLD, LOITER = _NUMBER["GUIDED"], _NUMBER["HOLD"], _NUMBER["LOITER"]
RTL, SMART_RTL = _NUMBER["RTL"], _NUMBER["SMART_RTL"]
#: Modes the user may drive the vehicle out of (back to GUIDED), if the user or the
#: agent's own fail-safe put it there.
RESUMABLE_MODES = frozenset({HOLD, LOITER, RTL, SMART_RTL})

#: SET_POSITION_TARGET_LOCAL_NED type_mask: velocity (x, y) and yaw rate; ignore the
#: position, vz, the acceleration and the yaw (ArduRover: "Use Vel+Yaw Rate", 1511).
MASK_VELOCITY_TURN_RATE = 0b0000_0101_1110_0111
#: Under way: faster than this (m/s), a disarm is refused.
UNDER_WAY_MPS = 0.3


class RoverAdapter(MavlinkAdapter):
    """An ArduRover rover or boat; see the module docstring."""

    # It cannot land: "land" holds it, as "stop" does.
    safe_action_words = {
        "stop": "stop and hold its position",
        "land": "stop and hold its position",
        "return_to_home": "go back to its home point and hold there",
    }

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.hold_mode = self._mode(self.vehicle_class.hold_mode)
        #: The user's speed (m/s, negative backwards) and turn rate (deg/s, positive to
        #: the right), each held until its own deadline.
        self._speed = 0.0
        self._speed_until = 0.0
        self._turn = 0.0
        self._turn_until = 0.0

    # --- state -------------------------------------------------------------------------
    def _busy(self) -> bool:
        return bool(self.t.armed)

    def _stop_moving(self) -> None:
        self._moving_until = None
        self._speed = self._turn = 0.0

    def telemetry(self) -> dict[str, Any]:
        """Every topic of the rover's or boat's vocabulary; None until the autopilot
        sent it. No altitude: it drives on the ground or the water."""
        return {**self._telemetry_common(), "mode": self.mode_name(self.t.mode)}

    # --- the envelope ------------------------------------------------------------------
    def project(self, name: str, args: Mapping[str, Any]) -> Projection | None:
        """Where a command takes the vehicle, for the gate's geofence check:
        ``forward``/``backward`` ``setpoint_hold_s`` (1 s) ahead along the heading at the
        commanded speed, with its velocity (the gate predicts where the vehicle comes
        to rest: :meth:`braking`), the waypoint of ``go_to_waypoint``; None for the rest
        (turning on the spot goes nowhere)."""
        t = self.t
        if name == "go_to_waypoint":
            return Projection(lat=float(args["lat"]), lon=float(args["lon"]))
        if name not in ("forward", "backward") or t.lat is None or t.lon is None:
            return None
        if t.heading is None:
            return None
        speed = float(args.get("speed_mps", self.config.move_speed_mps))
        speed *= 1 if name == "forward" else -1
        h = math.radians(t.heading)
        north, east = speed * math.cos(h), speed * math.sin(h)
        hold = self.config.setpoint_hold_s
        lat, lon = offset((t.lat, t.lon), north * hold, east * hold)
        return Projection(lat=lat, lon=lon, velocity=(north, east, 0.0))

    async def stop_motion(self, name: str) -> None:
        """``forward`` or ``backward`` refused at the geofence: the speed under way in
        that direction goes to zero now (a turn held with it goes on). Never raises."""
        if name not in ("forward", "backward") or self._moving_until is None:
            return
        if (self._speed > 0) != (name == "forward") or self._speed == 0:
            return
        self._speed = 0.0
        if self.link.ok and self.t.armed and self.t.mode == GUIDED:
            self._send_drive(0.0, self._turn)

    # --- acting ------------------------------------------------------------------------
    async def execute(self, name: str, args: Mapping[str, Any]) -> None:
        """Carry out a checked command; see the module docstring for the mapping.

        Raises AdapterError: ``autopilot_lost``, ``autopilot_refused``, ``timeout`` (as
        the copter's), ``not_armed`` (moving while disarmed), ``under_way`` (a disarm
        while moving), ``low_battery`` / ``autopilot_mode`` (checked before anything
        is sent), ``not_ready``, ``unknown_command``.
        """
        self.safe_action_done = False
        self._require_link(name)
        now = time.monotonic()
        hold = self.config.setpoint_hold_s
        if name in ("forward", "backward"):
            await self._ensure_guided_drive(name)
            speed = float(args.get("speed_mps", self.config.move_speed_mps))
            self._speed = speed if name == "forward" else -speed
            self._speed_until = now + hold
            self._drive()
        elif name in ("left", "right"):
            await self._ensure_guided_drive(name)
            rate = float(args.get("rate_deg_s", self.config.turn_rate_deg_s))
            self._turn = rate if name == "right" else -rate
            self._turn_until = now + hold
            self._drive()
        elif name == "stop":
            self._stop_moving()
            if self.t.armed and self.t.mode == GUIDED:
                self._send_drive(0.0, 0.0)
        elif name == "arm":
            await self._arm()
        elif name == "disarm":
            await self._disarm()
        elif name == "return_to_home":
            self._stop_moving()
            await self._command_mode(MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH, RTL, owner="user")
        elif name == "go_to_waypoint":
            await self._ensure_guided_drive("go_to_waypoint")
            self._stop_moving()
            speed = min(float(args.get("speed_mps") or 0), self.config.max_speed_mps)
            lat, lon = float(args["lat"]), float(args["lon"])
            await self._go_to_position(lat, lon, 0.0, speed=speed or None)
        elif name == "release_payload" and self.config.payload is not None:
            await self._release_payload()
        else:
            raise AdapterError(
                f"{name!r} is not a command of this {self.vehicle_class.name}",
                code="unknown_command",
            )

    async def _disarm(self) -> None:
        if self.t.armed is False:
            return
        speed = self.t.speed
        if speed is not None and speed > UNDER_WAY_MPS:
            raise AdapterError(
                f"the {self.vehicle_class.name} is under way ({speed:.1f} m/s): stop first, "
                "then disarm",
                code="under_way",
            )
        self._stop_moving()
        await self._disarm_now()

    async def _ensure_guided_drive(self, what: str) -> None:
        """Refuse unless the vehicle is armed; take it back to GUIDED from a hold or a
        return that the user (or the agent's fail-safe) started."""
        t = self.t
        if not t.armed:
            raise AdapterError(f"arm first ({what})", code="not_armed")
        if t.mode == GUIDED:
            return
        if self._mode_owner == "low_battery":
            battery = "" if t.battery is None else f" (battery {t.battery:.0f}%)"
            raise AdapterError(
                f"low battery{battery}: the {self.vehicle_class.name} is returning home; "
                f"{what} is refused",
                code="low_battery",
            )
        if t.mode in RESUMABLE_MODES and self._mode_owner in ("user", "failsafe"):
            await self._set_mode(GUIDED, owner="user")
            return
        raise AdapterError(
            f"the autopilot is in {self.mode_name(t.mode)} on its own (e.g. its own "
            f"fail-safe): {what} is refused",
            code="autopilot_mode",
        )

    def _drive(self) -> None:
        """Send the user's speed and turn rate as they stand now."""
        self._send_drive(self._speed, self._turn)
        self._moving_until = max(self._speed_until, self._turn_until)

    def _send_drive(self, speed: float, turn_deg_s: float) -> None:
        """A body-frame velocity (``speed`` along the heading) and yaw-rate setpoint."""
        target = self.link.target_or_default()
        self.link.send(
            MAV.MAVLink_set_position_target_local_ned_message(
                self.link.boot_ms(self._started_at), target[0], target[1], FRAME_BODY_NED,
                MASK_VELOCITY_TURN_RATE, 0.0, 0.0, 0.0, speed, 0.0, 0.0, 0.0, 0.0, 0.0,
                0.0, math.radians(turn_deg_s),
            )
        )  # fmt: skip
        self.link.stats["setpoints"] += 1

    def _tick(self, now: float) -> None:
        """A released key (no repeat within the hold time) stops its part of the
        movement at once; the other part carries on."""
        if self._moving_until is None:
            return
        changed = False
        if self._speed and now > self._speed_until:
            self._speed, changed = 0.0, True
        if self._turn and now > self._turn_until:
            self._turn, changed = 0.0, True
        if now > self._moving_until:
            self._moving_until = None
            changed = True
        if changed and self.link.ok and self.t.armed and self.t.mode == GUIDED:
            self._send_drive(self._speed, self._turn)

    def _expected_text(self, text: str) -> bool:
        """ArduRover's "target not received last 3.0 secs, stopping" once the agent
        has stopped sending setpoints (a stop, a key let go): its last setpoint timing
        out is what it should do. While the user's movement is held the same words mean
        setpoints are lost on the way, and they go to the platform."""
        return text.startswith("target not received last") and self._moving_until is None

    # --- safety ------------------------------------------------------------------------
    async def _hold(self, owner: str) -> None:
        """Zero speed in GUIDED at once, then the class's hold mode (a boat's LOITER,
        falling back to HOLD)."""
        if self.t.mode == GUIDED:
            self._send_drive(0.0, 0.0)
        await self._try_in_turn(
            "stop",
            [
                lambda: self._set_mode(self.hold_mode, owner=owner),
                lambda: self._set_mode(HOLD, owner=owner),
            ],
        )

    async def safe_action(self, action: str) -> None:
        """Make the vehicle safe; never raises (a failure is logged and reported as the
        ``safe_action_failed`` event).

        ``return_to_home``: RTL (drive home, then hold there), falling back to
        SMART_RTL, then the hold mode; ``stop`` and ``land`` (it cannot land: it holds):
        a zero setpoint, then the hold mode (boat: LOITER, else HOLD). Disarmed: nothing
        to do. Without a link nothing can be sent: the autopilot's own GCS fail-safe
        (see :meth:`check_failsafe_params`) acts.
        """
        self.safe_action_done = True
        self._stop_moving()
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
            if action != "return_to_home":
                if action != "stop":
                    logger.info("mavlink: safe action %r carried out as a hold", action)
                await self._hold("failsafe")
                return
            await self._try_in_turn(
                action,
                [
                    lambda: self._set_mode(RTL, owner="failsafe"),
                    lambda: self._set_mode(SMART_RTL, owner="failsafe"),
                    lambda: self._set_mode(self.hold_mode, owner="failsafe"),
                ],
            )
        except Exception:
            logger.exception("mavlink: safe action %s failed", action)
            self.emit("safe_action_failed", {"action": action, "reason": "internal error"})

    async def envelope_recover(self, breach: Breach) -> str:
        """Bring the vehicle back inside a limit it crossed, whatever crossed it.

        * speed: the user's movement under way (velocity setpoints, which ArduRover
          takes no speed change for): a zero setpoint. Else DO_CHANGE_SPEED to
          ``breach.target`` (on its way to a waypoint or home); where ArduRover refuses
          it (holding, loitering), the hold mode;
        * geofence: drive back to ``breach.target`` from the centre, on the line to
          where it is, and hold there (GUIDED); nothing while it returns home;
        * altitude: nothing: it has none.

        Raises AdapterError when the autopilot refuses (reported as the action).
        """
        t = self.t
        if breach.limit == "altitude":
            return f"none: a {self.vehicle_class.name} has no altitude"
        if not self.link.ok:
            return "none: no link to the autopilot"
        if not t.armed:
            return "none: disarmed"
        if breach.limit == "speed":
            if self._moving_until is not None and t.mode == GUIDED:
                # Driven by the user's setpoints (whose speed the gate caps): ArduRover
                # takes no speed change then. Stop them.
                self._stop_moving()
                self._send_drive(0.0, 0.0)
                return "stop"
            try:
                await self._change_speed(breach.target)
            except AdapterError as exc:
                if exc.code != "autopilot_refused":
                    raise
                # Holding or loitering (ArduRover takes a speed only on its way to a
                # position or home): what moves it is no speed of its own. Hold.
                await self._hold("failsafe")
                return "hold: the autopilot takes no speed now"
            return f"{breach.target:.1f} m/s at most"
        if t.mode in (RTL, SMART_RTL):
            return "none: returning home"
        if t.lat is None or t.lon is None:
            return "none: position unknown"
        lat, lon = t.lat, t.lon
        centre = breach.centre or (lat, lon)
        out = distance_m(centre, (lat, lon))
        if out > 0:
            north, east = local_offset_m(centre, (lat, lon))
            share = max(0.0, breach.target) / out
            lat, lon = offset(centre, north * share, east * share)
        self._stop_moving()
        if t.mode != GUIDED:
            await self._set_mode(GUIDED, owner="failsafe")
        await self._reposition(lat, lon, 0.0)
        return "drive back inside the geofence and hold"

    async def neutral(self) -> None:
        """Stop: a zero setpoint if the vehicle drives in GUIDED. Never raises."""
        self._stop_moving()
        if self.link.ok and self.t.armed and self.t.mode == GUIDED:
            self._send_drive(0.0, 0.0)
