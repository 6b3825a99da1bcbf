"""The virtual transmitter: stick positions, switches, the landing sequence and the
envelope corrections, ticked into servo positions (:class:`FlightControls`).

Shared by the event loop (commands) and the control thread (every 10 ms): every method
takes the lock; none blocks or does I/O under it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass

from agents.geo import local_offset_m
from agents.vehicles.base import Breach
from agents.vehicles.spektrum.config import SpektrumConfig
from agents.vehicles.spektrum.frames import (
    CHANNEL_COUNT,
    SERVO_CENTRE,
    SERVO_HIGH,
    SERVO_LOW,
    STICK_AXES,
    THROTTLE,
    clamp_servo,
    stick_to_servo,
    throttle_to_servo,
)
from agents.vehicles.spektrum.report import FcReport

logger = logging.getLogger(__name__)


@dataclass
class _Landing:
    cause: str
    phase: str  # "to_vtol", "descend", "cut"
    since: float


#: An envelope correction descends at this rate (VTOL and aircraft mode alike) ...
RECOVERY_DESCENT_MPS = 1.0
#: ... and flies back towards the geofence at this speed (VTOL mode).
RECOVERY_RETURN_MPS = 2.0
#: How fast a correction's descent setting adapts when the plane does not sink at
#: RECOVERY_DESCENT_MPS (an updraft): the change of vertical speed asked for per second,
#: per m/s of error (an integral controller; 2/s settles in about a second and stays
#: well damped with the FC's own lag and 20 Hz telemetry).
RECOVERY_SINK_GAIN = 2.0


@dataclass
class _Recovery:
    """An envelope correction the control thread flies until ``target`` is reached (see
    :meth:`FlightControls.recover`): ``limit`` is "altitude", "geofence" or "speed".
    ``throttle_cap`` (VTOL mode) and ``elevator_cap`` (aircraft mode) hold the descent;
    they adapt while the plane does not sink as it should."""

    limit: str
    target: float
    centre: tuple[float, float] | None
    throttle_cap: float
    elevator_cap: float


class FlightControls:
    """The virtual transmitter: stick positions, switches and the landing sequence.

    Shared by the event loop (commands) and the control thread (:meth:`tick` every
    10 ms; with the thread writer, once per frame). Every method takes :attr:`lock`
    (callers that mutate fields directly hold it too); none blocks or does I/O under it.

    Values: ``throttle`` 0..1, stick axes -1..1 (aileron +right, elevator +nose up i.e.
    stick back, rudder +right). Every one of them returns to its neutral once its hold
    time passes without a repeat (the key was released, the browser went away): the
    stick axes to centre, the throttle to :meth:`throttle_neutral` for the flight mode
    (VTOL mode: the hover setting in the air, idle on the ground; aircraft mode: the
    cruise setting). Nothing a user sends stays applied after the user stops sending.
    ``mode`` "vtol"/"aircraft"; ``armed``.
    """

    def __init__(self, config: SpektrumConfig) -> None:
        self.config = config
        self.lock = threading.Lock()
        #: Notified (under ``lock``) when the landing sequence disarms.
        self.landed = threading.Condition(self.lock)
        self.throttle = 0.0
        #: Where the throttle returns to, as of the last tick.
        self.neutral_throttle = 0.0
        self.axes = dict.fromkeys(STICK_AXES, 0.0)
        self._expires = dict.fromkeys(STICK_AXES, 0.0)
        # Until then the throttle keeps a user's setting; after, it follows the neutral.
        self._throttle_expires = 0.0
        # Hold-time bookkeeping per stick axis and for the throttle.
        self._last_press: dict[str, tuple[float, int]] = dict.fromkeys(
            (*STICK_AXES, "throttle"), (-1e9, 0)
        )
        self._repeat_s: dict[str, float | None] = dict.fromkeys((*STICK_AXES, "throttle"))
        # Whether the plane may be in the air, for when telemetry cannot tell.
        self._lifted = False
        self.mode = "vtol"
        self.armed = False
        self.landing: _Landing | None = None
        self.landings = 0
        self.last_cause: str | None = None
        #: Envelope corrections under way, by limit.
        self.recoveries: dict[str, _Recovery] = {}
        self.loop_beat = time.monotonic()
        self.servos: list[int] = self._servos()
        self._last_tick: float | None = None

    # --- the event loop's side ---------------------------------------------------------
    def _hold_locked(self, key: str, direction: int, now: float) -> float:
        """The hold time of a press of ``key`` (a stick axis or "throttle") in
        ``direction``: ``stick_hold_ms``, or longer when the client repeats a held key
        less often. The browser's repeat interval follows the round trip (100 ms at
        best), and a stick that returned to neutral between two repeats would stutter.
        It adapts to 1.5 x the observed repeat interval + 50 ms (a moving average of
        the gaps between same-direction presses), at most ``stick_hold_max_ms``."""
        cfg = self.config
        last_at, last_direction = self._last_press[key]
        gap = now - last_at
        if direction and direction == last_direction and gap < cfg.stick_hold_max_ms / 1000:
            seen = self._repeat_s[key]
            self._repeat_s[key] = gap if seen is None else 0.7 * seen + 0.3 * gap
        elif direction != last_direction:
            self._repeat_s[key] = None
        self._last_press[key] = (now, direction)
        hold = cfg.stick_hold_ms / 1000
        repeat = self._repeat_s[key]
        if repeat is not None:
            hold = min(max(hold, 1.5 * repeat + 0.05), cfg.stick_hold_max_ms / 1000)
        return hold

    def set_axis(self, axis: str, value: float, now: float) -> None:
        """Deflect ``axis`` to ``value`` for the hold time (a repeat extends it; see
        :meth:`_hold_locked`)."""
        value = max(-1.0, min(1.0, value)) if math.isfinite(value) else 0.0
        direction = (value > 0) - (value < 0)
        with self.lock:
            hold = self._hold_locked(axis, direction, now)
            self.axes[axis] = value
            self._expires[axis] = now + hold

    def throttle_after(self, delta: float) -> float:
        """The throttle one press of ``delta`` would set: a step from the current
        setting, or from the neutral when the press goes the other way (``s`` right
        after ``w`` descends at once instead of first undoing the climb)."""
        base = self.throttle
        if (delta > 0 and base < self.neutral_throttle) or (
            delta < 0 and base > self.neutral_throttle
        ):
            base = self.neutral_throttle
        return max(0.0, min(1.0, base + delta))

    def move_throttle_locked(self, delta: float, now: float) -> None:
        """Step the throttle by ``delta`` for the hold time of a press; after it the
        throttle returns to its neutral. The caller holds :attr:`lock`."""
        direction = (delta > 0) - (delta < 0)
        hold = self._hold_locked("throttle", direction, now)
        self.throttle = self.throttle_after(delta)
        self._throttle_expires = now + hold
        if self.mode == "vtol" and self.throttle > self.config.hover_throttle:
            self._lifted = True

    def centre(self) -> None:
        """Centre aileron, elevator and rudder at once."""
        with self.lock:
            self.centre_locked()

    def centre_locked(self) -> None:
        """:meth:`centre` for a caller that holds :attr:`lock`."""
        for axis in self.axes:
            self.axes[axis] = 0.0
            self._expires[axis] = 0.0

    def neutral_locked(self, fc: FcReport | None) -> None:
        """Sticks centred and the throttle at its neutral now (the caller holds
        :attr:`lock`); ``fc`` is the latest fresh report, or None."""
        self.centre_locked()
        self._throttle_expires = 0.0
        if self.landing is None:
            self.neutral_throttle = self.throttle_neutral(fc)
            self.throttle = self.neutral_throttle

    def throttle_neutral(self, fc: FcReport | None) -> float:
        """Where the throttle rests for the flight mode: VTOL mode in the air, the hover
        setting (the altitude holds); on the ground, idle; aircraft mode, the cruise
        setting (level flight); disarmed, idle. In the air or not: from telemetry, or
        without, from whether the throttle went past the hover setting since arming."""
        cfg = self.config
        if not self.armed:
            return 0.0
        if self.mode == "aircraft":
            return cfg.cruise_throttle
        if fc is not None and fc.on_ground is not None:
            self._lifted = not fc.on_ground
        return cfg.hover_throttle if self._lifted else 0.0

    def wait_disarmed(self, timeout: float) -> bool:
        """Block until disarmed (at most ``timeout`` s); True if disarmed."""
        with self.landed:
            return self.landed.wait_for(lambda: not self.armed, timeout)

    def beat(self, now: float) -> None:
        """The event loop is alive (see ``loop_watchdog_s``)."""
        with self.lock:
            self.loop_beat = now

    def start_landing(self, cause: str, now: float) -> bool:
        """Begin the landing sequence; False when there is nothing to land (disarmed)
        or it already runs. In aircraft mode: back to VTOL at the hover setting first."""
        with self.lock:
            return self._start_landing(cause, now)

    def _start_landing(self, cause: str, now: float) -> bool:
        self.centre_locked()
        self.recoveries.clear()  # the landing descends anyway, and owns the throttle
        if not self.armed:
            self.throttle = 0.0
            return False
        if self.landing is not None:
            return False
        self.last_cause = cause
        if self.mode == "aircraft":
            # Throttle means airspeed in aircraft mode; back in VTOL mode the hover
            # setting holds the altitude while the rotors tilt up, and the descent
            # ramp starts from there.
            self.mode = "vtol"
            self.throttle = self.config.hover_throttle
            self.landing = _Landing(cause, "to_vtol", now)
        else:
            self.landing = _Landing(cause, "descend", now)
        logger.warning("spektrum: landing (%s)", cause)
        return True

    def recover(self, breach: Breach, fc: FcReport | None, now: float) -> str:
        """Start (or keep up) the correction of an envelope breach; returns what it
        does, in words. The control thread flies it (:meth:`tick`) until the breach's
        target is reached, telemetry is lost or a landing starts.

        * altitude: the climb is cut at once (throttle to its neutral, elevator no
          higher than centre), then the plane descends at RECOVERY_DESCENT_MPS (VTOL
          mode: the throttle held below the hover setting; aircraft mode: the elevator
          held down) until it is ``breach.target`` high;
        * geofence: back to VTOL mode, sticks centred, then flown back towards the
          centre at RECOVERY_RETURN_MPS until ``breach.target`` from it;
        * speed: VTOL mode: the right stick centred until slower than the target;
          aircraft mode: back to VTOL mode (a plane cannot fly slower than it stalls).
        """
        cfg = self.config
        with self.lock:
            if self.landing is not None:
                return "none: the plane is landing"
            if not self.armed:
                return "none: the motors are disarmed"
            mode = self.mode
            again = breach.limit in self.recoveries
            if not again:
                self.recoveries[breach.limit] = _Recovery(
                    limit=breach.limit,
                    target=breach.target,
                    centre=breach.centre,
                    throttle_cap=self._throttle_for(-RECOVERY_DESCENT_MPS),
                    elevator_cap=-min(1.0, RECOVERY_DESCENT_MPS / cfg.aircraft_climb_mps),
                )
            if breach.limit == "altitude":
                self._throttle_expires = 0.0
                self.neutral_throttle = self.throttle_neutral(fc)
                self.throttle = min(self.throttle, self.neutral_throttle)
                self.axes["elevator"] = min(0.0, self.axes["elevator"])
                self._apply_recoveries(now, 0.0, fc)
                level = "hover" if mode == "vtol" else "level flight"
                return f"{level}, descending to {breach.target:.1f} m"
            if breach.limit == "geofence":
                self._apply_recoveries(now, 0.0, fc)
                what = "back to VTOL mode, " if mode == "aircraft" else ""
                return f"{what}flying back inside the geofence"
            self._apply_recoveries(now, 0.0, fc)
            if mode == "aircraft":
                return "back to VTOL mode: slowing down"
            return "sticks centred: slowing down"

    def _throttle_for(self, vz: float) -> float:
        """The VTOL throttle for vertical speed ``vz`` (inverse of the climb model)."""
        cfg = self.config
        if vz >= 0:
            return cfg.hover_throttle + vz / cfg.max_climb_mps * (1 - cfg.hover_throttle)
        return max(0.0, cfg.hover_throttle * (1 + vz / cfg.max_descent_mps))

    def _to_vtol_locked(self) -> None:
        if self.mode == "aircraft":
            logger.warning("spektrum: envelope: back to VTOL mode")
            self.mode = "vtol"
            self._throttle_expires = 0.0
            self.throttle = self.config.hover_throttle

    def _apply_recoveries(self, now: float, dt: float, fc: FcReport | None) -> None:
        """Fly the envelope corrections for one tick (the caller holds the lock)."""
        cfg = self.config
        for limit, rec in list(self.recoveries.items()):
            if fc is None:
                # Blind, a correction could fly the plane into the ground: level off
                # and let the agent's envelope start it again once telemetry is back.
                logger.warning("spektrum: envelope %s correction ends: no telemetry", limit)
                del self.recoveries[limit]
                continue
            if limit == "altitude":
                if fc.alt is None or fc.alt <= rec.target:
                    del self.recoveries[limit]
                    continue
                sink_error = 0.0 if fc.vz is None else fc.vz + RECOVERY_DESCENT_MPS
                if self.mode == "vtol":
                    per_throttle = cfg.max_descent_mps / cfg.hover_throttle  # m/s per unit
                    rec.throttle_cap -= RECOVERY_SINK_GAIN * sink_error / per_throttle * dt
                    rec.throttle_cap = max(0.0, min(cfg.hover_throttle, rec.throttle_cap))
                    self.throttle = min(self.throttle, rec.throttle_cap)
                else:
                    rec.elevator_cap -= (
                        RECOVERY_SINK_GAIN * sink_error / cfg.aircraft_climb_mps * dt
                    )
                    rec.elevator_cap = max(-1.0, min(0.0, rec.elevator_cap))
                    self.axes["elevator"] = min(self.axes["elevator"], rec.elevator_cap)
            elif limit == "speed":
                if fc.speed is None or fc.speed <= rec.target:
                    del self.recoveries[limit]
                    continue
                self._to_vtol_locked()
                self.axes["aileron"] = self.axes["elevator"] = 0.0
            else:
                if rec.centre is None or fc.lat is None or fc.lon is None:
                    del self.recoveries[limit]
                    continue
                north, east = local_offset_m((fc.lat, fc.lon), rec.centre)
                if math.hypot(north, east) <= rec.target:
                    self.axes["aileron"] = self.axes["elevator"] = 0.0
                    del self.recoveries[limit]
                    continue
                self._to_vtol_locked()
                if fc.heading is None:
                    self.axes["aileron"] = self.axes["elevator"] = 0.0
                    continue
                # Body-frame stick towards the centre: forward is stick forward
                # (elevator -), right is aileron +.
                bearing = math.atan2(east, north) - math.radians(fc.heading)
                amount = min(1.0, RECOVERY_RETURN_MPS / cfg.vtol_max_speed_mps)
                self.axes["elevator"] = -math.cos(bearing) * amount
                self.axes["aileron"] = math.sin(bearing) * amount

    # --- the writer thread's side ------------------------------------------------------
    def tick(self, now: float, fc: FcReport | None) -> list[int]:
        """Advance time to ``now`` (hold timeouts, landing, envelope corrections, loop
        watchdog) and return the eight servo positions to send. ``fc`` is the latest
        fresh report from the far end, or None when there is none."""
        cfg = self.config
        with self.lock:
            dt = 0.0 if self._last_tick is None else min(0.1, max(0.0, now - self._last_tick))
            self._last_tick = now
            for axis, expires in self._expires.items():
                if now >= expires:
                    self.axes[axis] = 0.0
            if not self.armed:
                self._lifted = False
            self.neutral_throttle = self.throttle_neutral(fc)
            if self.landing is None and now >= self._throttle_expires:
                # Released (or never pressed): the throttle rests at its neutral.
                self.throttle = self.neutral_throttle
            if (
                self.armed
                and self.landing is None
                and cfg.loop_watchdog_s > 0
                and now - self.loop_beat > cfg.loop_watchdog_s
            ):
                # The agent's event loop has hung: nobody would run the link-loss
                # fail-safe, so the thread lands the plane itself (the paper's
                # dedicated microcontroller does the same).
                self._start_landing("agent_stalled", now)
            if self.landing is not None:
                self._advance_landing(now, dt, fc)
            elif self.recoveries and self.armed:
                self._apply_recoveries(now, dt, fc)
            self.servos = self._servos()
            return list(self.servos)

    def _advance_landing(self, now: float, dt: float, fc: FcReport | None) -> None:
        cfg = self.config
        landing = self.landing
        assert landing is not None
        self.centre_locked()
        if not self.armed:
            self.landing = None
            return
        grounded = fc is not None and fc.on_ground is True
        if landing.phase == "to_vtol":
            if grounded:
                landing.phase, landing.since = "cut", now
            elif now - landing.since >= cfg.transition_s:
                landing.phase, landing.since = "descend", now
        if landing.phase == "descend":
            # Smoothly towards the descent setting (down from a climb, or up from a
            # faster descent), never a step.
            step = cfg.land_ramp_per_s * dt
            target = cfg.land_throttle
            self.throttle += max(-step, min(step, target - self.throttle))
            # Without telemetry (real plane, no sensor) ground contact is unknowable:
            # cut after land_timeout_s of descent.
            timed_out = fc is None and now - landing.since >= cfg.land_timeout_s
            if grounded or timed_out:
                landing.phase, landing.since = "cut", now
        if landing.phase == "cut":
            self.throttle = 0.0
            # Motors at idle for a moment before disarming, like a pilot would.
            if now - landing.since >= 0.3:
                self.armed = False
                self.landing = None
                self.landings += 1
                self.landed.notify_all()
                logger.warning("spektrum: landed and disarmed (%s)", landing.cause)

    def _servos(self) -> list[int]:
        cfg = self.config
        values = [SERVO_CENTRE] * CHANNEL_COUNT
        values[THROTTLE] = throttle_to_servo(self.throttle if self.armed else 0.0)
        for axis, channel in STICK_AXES.items():
            values[channel] = stick_to_servo(self.axes[axis])
        values[cfg.mode_channel] = SERVO_HIGH if self.mode == "aircraft" else SERVO_LOW
        values[cfg.arm_channel] = SERVO_HIGH if self.armed else SERVO_LOW
        for channel in cfg.reversed_channels:
            values[channel] = 2 * SERVO_CENTRE - values[channel]
        return [clamp_servo(v) for v in values]
