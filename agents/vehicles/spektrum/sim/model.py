"""The simulated plane: a VTOL/airplane model flown with the decoded channels.

VTOL hover and airplane modes, the transition, stall, ground contact, battery, arming and
the FC's own receiver-loss fail-safe (:class:`VtolModel`), with its parameters
(:class:`SimParams`: the envelope shared with the adapter, then the model's own).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from agents.geo import offset
from agents.vehicles.spektrum.frames import (
    AILERON,
    AUX1,
    ELEVATOR,
    GEAR,
    RUDDER,
    SERVO_CENTRE,
    SERVO_LOW,
    THROTTLE,
    servo_to_stick,
    servo_to_throttle,
)

logger = logging.getLogger(__name__)
GRAVITY = 9.81
#: A servo position this far past centre is "switch on" (gear, aux).
SWITCH_THRESHOLD = 200


# --------------------------------------------------------------------------------------
# The flight model
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SimParams:
    """The model's parameters. The first group is shared with the adapter (it projects
    and lands with the same numbers); the rest is the simulator's own."""

    hover_throttle: float = 0.5
    max_climb_mps: float = 4.0  # at full throttle in VTOL mode
    max_descent_mps: float = 4.0  # at idle in VTOL mode
    vtol_max_speed_mps: float = 6.0  # horizontal, full right stick in VTOL mode
    aircraft_climb_mps: float = 5.0  # full elevator in aircraft mode
    transition_s: float = 3.0  # rotors tilting forward
    failsafe_throttle: float = 0.35  # the FC's own descent on receiver loss
    vtol_yaw_rate_dps: float = 90.0
    cruise_speed_mps: float = 22.0  # airspeed at full throttle
    stall_speed_mps: float = 9.0
    stall_sink_mps: float = 6.0
    max_bank_deg: float = 45.0
    rudder_rate_dps: float = 15.0
    hard_landing_mps: float = 3.0
    crash_speed_mps: float = 12.0
    battery_pct: float = 100.0
    battery_drain_pct_per_s: float = 0.25  # at full throttle
    arm_max_throttle: float = 0.1
    failsafe_after_s: float = 0.5  # no good frame for this long: receiver loss
    heading_deg: float = 0.0
    #: Rising air in flight, m/s: the wind the agent's envelope must answer (tests
    #: change :attr:`VtolModel.updraft_mps` while flying, as a gust).
    updraft_mps: float = 0.0

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> SimParams:
        """Parameters from a JSON-friendly mapping; raises ValueError naming an
        unknown key or a non-number."""
        known = {f.name for f in fields(cls)}
        out: dict[str, float] = {}
        for key, value in values.items():
            if key not in known:
                raise ValueError(f"unknown simulator parameter {key!r}")
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"simulator parameter {key}: expected a number")
            if not math.isfinite(value):
                raise ValueError(f"simulator parameter {key}: expected a finite number")
            out[key] = float(value)
        params = cls(**out)
        if not 0 < params.hover_throttle < 1:
            raise ValueError("simulator parameter hover_throttle: between 0 and 1")
        return params


@dataclass(frozen=True)
class Inputs:
    """The FC's view of the sticks: throttle 0..1, aileron/elevator/rudder -1..1
    (elevator +1 = stick back, nose up), the two switches."""

    throttle: float = 0.0
    aileron: float = 0.0
    elevator: float = 0.0
    rudder: float = 0.0
    aircraft: bool = False
    arm: bool = False

    @classmethod
    def from_channels(
        cls, channels: Mapping[int, int], *, mode_channel: int = GEAR, arm_channel: int = AUX1
    ) -> Inputs:
        def get(channel: int, default: int) -> int:
            return channels.get(channel, default)

        return cls(
            throttle=servo_to_throttle(get(THROTTLE, SERVO_LOW)),
            aileron=servo_to_stick(get(AILERON, SERVO_CENTRE)),
            elevator=servo_to_stick(get(ELEVATOR, SERVO_CENTRE)),
            rudder=servo_to_stick(get(RUDDER, SERVO_CENTRE)),
            aircraft=get(mode_channel, SERVO_LOW) > SERVO_CENTRE + SWITCH_THRESHOLD,
            arm=get(arm_channel, SERVO_LOW) > SERVO_CENTRE + SWITCH_THRESHOLD,
        )


def _approach(value: float, target: float, dt: float, tau: float) -> float:
    """First-order lag of time constant ``tau``."""
    return value + (target - value) * min(1.0, dt / tau)


class VtolModel:
    """A point-mass VTOL plane, good enough to make telemetry respond sensibly.

    VTOL mode: throttle sets the vertical speed (hover at ``hover_throttle``), the
    right stick a horizontal velocity in the body frame, the rudder a yaw rate.
    Transition: the rotors tilt forward over ``transition_s`` while the altitude holds
    and the plane accelerates past the stall speed. Aircraft mode: throttle sets the
    airspeed, the elevator the climb rate, the ailerons a bank and so a coordinated turn
    (rate g*tan(bank)/v); below ``stall_speed_mps`` it stalls (sinks, controls dead).
    Disarmed or with an empty battery the motors are off. Arming needs the throttle at
    idle when the arm switch goes on (else it stays disarmed until the switch cycles).
    Touch-downs faster than ``hard_landing_mps`` vertically are hard landings; in
    aircraft mode faster than ``crash_speed_mps`` a crash. In the air, ``updraft_mps``
    adds to the vertical speed whatever the controls say.
    Conventions: metres north/east of the origin, heading clockwise from north.
    """

    def __init__(self, params: SimParams, origin: tuple[float, float]) -> None:
        self.p = params
        self.origin = origin
        self.north = 0.0
        self.east = 0.0
        self.alt = 0.0
        self.vz = 0.0
        self.v_forward = 0.0
        self.v_right = 0.0
        self.heading = params.heading_deg % 360.0
        self.mode = "vtol"  # vtol, transition, aircraft
        self.transition_t = 0.0
        self.armed = False
        self.arm_refused = 0
        self._arm_blocked = False
        self.battery = params.battery_pct
        self.on_ground = True
        self.stalled = False
        self.crashed = False
        self.hard_landings = 0
        self.fc_failsafe = False
        self.updraft_mps = params.updraft_mps

    @property
    def position(self) -> tuple[float, float]:
        return offset(self.origin, self.north, self.east)

    @property
    def speed(self) -> float:
        return math.hypot(self.v_forward, self.v_right)

    def climb_rate(self, throttle: float) -> float:
        p = self.p
        if throttle >= p.hover_throttle:
            return (throttle - p.hover_throttle) / (1 - p.hover_throttle) * p.max_climb_mps
        return (throttle - p.hover_throttle) / p.hover_throttle * p.max_descent_mps

    def step(self, dt: float, inputs: Inputs, *, link_ok: bool = True) -> None:
        """Advance ``dt`` seconds with ``inputs``; without a link the FC's own
        fail-safe flies (VTOL, sticks centred, descend, disarm on the ground)."""
        if dt <= 0 or self.crashed:
            return
        p = self.p
        self.fc_failsafe = not link_ok
        if not link_ok:
            inputs = Inputs(
                throttle=p.failsafe_throttle if not self.on_ground else 0.0,
                arm=self.armed and not self.on_ground,
            )
        self._arming(inputs)
        self._mode(dt, inputs)
        power = self.armed and self.battery > 0.0
        throttle = inputs.throttle if power else 0.0
        if power:
            self.battery = max(
                0.0, self.battery - (0.02 + throttle * p.battery_drain_pct_per_s) * dt
            )
        if self.mode == "aircraft":
            vz_target, turn = self._aircraft(dt, inputs, power)
        elif self.mode == "transition":
            vz_target, turn = self._transition(dt, inputs, power)
        else:
            vz_target, turn = self._vtol(dt, inputs, power)
        if not self.on_ground:
            vz_target += self.updraft_mps
        if self.on_ground and vz_target <= 0:
            vz_target = 0.0
        self.vz = _approach(self.vz, vz_target, dt, 0.3)
        if self.on_ground:
            turn = 0.0 if self.speed < 0.5 else turn
        mid = math.radians(self.heading + turn * dt / 2)
        self.heading = (self.heading + turn * dt) % 360.0
        self.north += (self.v_forward * math.cos(mid) - self.v_right * math.sin(mid)) * dt
        self.east += (self.v_forward * math.sin(mid) + self.v_right * math.cos(mid)) * dt
        self.alt += self.vz * dt
        if self.alt <= 0.0:
            self._touch_down()
        else:
            self.on_ground = False

    def _arming(self, inputs: Inputs) -> None:
        if not inputs.arm:
            self.armed = False
            self._arm_blocked = False
        elif not self.armed and not self._arm_blocked:
            if inputs.throttle <= self.p.arm_max_throttle:
                self.armed = True
            else:
                # Real FCs refuse to arm with the throttle up; cycle the switch.
                self._arm_blocked = True
                self.arm_refused += 1

    def _mode(self, dt: float, inputs: Inputs) -> None:
        if not inputs.aircraft:
            self.mode = "vtol"
            self.transition_t = 0.0
        elif self.mode == "vtol":
            self.mode = "transition"
            self.transition_t = 0.0
        if self.mode == "transition":
            self.transition_t += dt
            if self.transition_t >= self.p.transition_s:
                self.mode = "aircraft"

    def _vtol(self, dt: float, inputs: Inputs, power: bool) -> tuple[float, float]:
        p = self.p
        self.stalled = False
        if not power:
            self.v_forward = _approach(self.v_forward, 0.0, dt, 2.0)
            self.v_right = _approach(self.v_right, 0.0, dt, 2.0)
            return -2 * p.max_descent_mps, 0.0
        if self.on_ground and self.climb_rate(inputs.throttle) <= 0:
            self.v_forward = self.v_right = 0.0  # on its skids
            return 0.0, 0.0
        self.v_forward = _approach(self.v_forward, -inputs.elevator * p.vtol_max_speed_mps, dt, 0.6)
        self.v_right = _approach(self.v_right, inputs.aileron * p.vtol_max_speed_mps, dt, 0.6)
        return self.climb_rate(inputs.throttle), inputs.rudder * p.vtol_yaw_rate_dps

    def _transition(self, dt: float, inputs: Inputs, power: bool) -> tuple[float, float]:
        p = self.p
        self.stalled = False
        if not power:
            return self._vtol(dt, inputs, power)
        # The tilting rotors still carry the weight; thrust goes into speed.
        target = max(1.2 * p.stall_speed_mps, inputs.throttle * p.cruise_speed_mps)
        accel = target / max(p.transition_s, 0.1)
        self.v_forward = min(target, self.v_forward + accel * dt)
        self.v_right = _approach(self.v_right, 0.0, dt, 0.5)
        return inputs.elevator * p.aircraft_climb_mps * 0.5, inputs.rudder * p.rudder_rate_dps

    def _aircraft(self, dt: float, inputs: Inputs, power: bool) -> tuple[float, float]:
        p = self.p
        thrust = inputs.throttle if power else 0.0
        drag_tau = 2.0 if not self.on_ground else 1.0
        self.v_forward = _approach(self.v_forward, thrust * p.cruise_speed_mps, dt, drag_tau)
        self.v_right = 0.0
        self.stalled = self.v_forward < p.stall_speed_mps and not self.on_ground
        if self.stalled:
            return -p.stall_sink_mps, 0.0
        if self.on_ground and self.v_forward < p.stall_speed_mps:
            return 0.0, 0.0
        bank = math.radians(inputs.aileron * p.max_bank_deg)
        turn = math.degrees(GRAVITY * math.tan(bank) / max(self.v_forward, 1.0))
        return inputs.elevator * p.aircraft_climb_mps, turn + inputs.rudder * p.rudder_rate_dps

    def _touch_down(self) -> None:
        self.alt = 0.0
        if not self.on_ground:
            if self.mode == "aircraft" and self.v_forward > self.p.crash_speed_mps:
                logger.warning("simulated VTOL crashed at %.1f m/s", self.v_forward)
                self.crashed = True
                self.armed = False
                self.v_forward = self.v_right = 0.0
            elif self.vz < -self.p.hard_landing_mps:
                self.hard_landings += 1
                logger.warning("simulated VTOL landed hard at %.1f m/s", -self.vz)
        self.vz = max(0.0, self.vz)
        self.on_ground = True
        if self.mode != "aircraft":
            self.v_forward = self.v_right = 0.0
