"""The agent's command gate: every command passes here before the adapter sees it.

Order of checks, first failure wins and is reported with its code:

1. ``unknown_command`` - not in the vehicle's vocabulary
2. ``not_allowed``     - not in the task's allowed commands
3. ``bad_args``        - arguments fail the command's arg spec
4. ``latency``         - round trip past the task's hard limit: only stop/land/RTL pass
5. ``altitude_limit``  - the command would take the vehicle above the task's ceiling
6. ``geofence``        - ... or outside the task's geofence
and speeds are clamped to the task's max speed (every speed a command carries: 0, the
vehicle's own cruise speed, becomes the max) and, past the soft latency limit,
lowered linearly down to :data:`MIN_SPEED_FACTOR` at the hard limit.

**Limits, as the vehicle stops.** A command that goes to a point (a take-off, a
waypoint) is refused when the point is past a limit. A movement held by repeats (a
key: its :class:`~agents.vehicles.base.Projection` has a ``velocity``) on a vehicle that
says how it brakes (:meth:`~agents.vehicles.base.Adapter.braking`) is judged by where
the vehicle would come to rest: it goes on at the asked speed for its reaction time,
then brakes. As ArduPilot's own avoidance does (AC_Avoid: ``sqrt(2·a·d)``), the speed
towards a limit is lowered to the one the vehicle can still stop from before the
limit's margin (:func:`agents.envelope.band_for`: where the envelope's corrections aim
too), so a held key slows down and stops there; the command is refused with the
limit's code only when that speed is under :data:`MIN_MOTION_MPS`. A vehicle that says
nothing of its braking is judged by the projected point, as before.

**Latched.** A movement refused at a limit stays refused until the user has let go of
it (a ``stop``, or no repeat for :data:`RELEASE_S`) and the vehicle is not past that
limit (the envelope, ``breached``); while the vehicle is past a limit, any movement
outwards is refused. Movements back inwards always pass.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from agents.envelope import ALTITUDE, GEOFENCE, band_for
from agents.geo import distance_m, local_offset_m, offset
from agents.protocol import Limits, ProtocolError, validate_command_args
from agents.vehicles.base import (
    SAFE_COMMANDS,
    Adapter,
    Braking,
    CommandSpec,
    Projection,
    Stopping,
    VehicleState,
)
from agents.vehicles.plan import PlanItem, Speed, TakeOff, Waypoint

#: At the hard latency limit, speeds are cut to this fraction of what the user asked.
MIN_SPEED_FACTOR = 0.3
#: A movement slowed down below this (m/s) before a limit is refused instead: it would
#: creep, and the vehicle is where the limit lets it be.
MIN_MOTION_MPS = 0.1
#: A held key is repeated every 100 ms to 1 s (the controller follows the round trip):
#: no repeat for longer than this, and the user has let go of it.
RELEASE_S = 1.2
#: The refusal codes of the limits, and the envelope's names for them.
LIMIT_CODES = {ALTITUDE: "altitude_limit", GEOFENCE: "geofence"}


class Refusal(Exception):
    """A command the gate refuses; ``code`` is machine-readable, ``str()`` for people
    and names the command (a user may have several in flight)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Checked:
    """A command that passed: its arguments, and the speed factor applied (1 = none).
    ``slowed_by`` names the limit (``altitude``, ``geofence``) a movement was slowed
    down for, if any."""

    name: str
    args: dict[str, Any]
    speed_factor: float = 1.0
    slowed_by: str | None = None


def latency_speed_factor(limits: Limits, rtt_ms: float | None) -> float:
    """1.0 below the soft threshold, falling linearly to MIN_SPEED_FACTOR at the hard
    one; 0.0 past the hard threshold (only safe commands pass then)."""
    if rtt_ms is None:
        return 1.0
    soft, hard = limits.latency_soft_ms, limits.latency_hard_ms
    if hard is not None and rtt_ms > hard:
        return 0.0
    if soft is None or rtt_ms <= soft:
        return 1.0
    if hard is None:
        return MIN_SPEED_FACTOR
    span = max(1.0, hard - soft)
    return 1.0 - (1.0 - MIN_SPEED_FACTOR) * (rtt_ms - soft) / span


def _held(stopping: Stopping | None, hold_s: float) -> Stopping | None:
    """``stopping`` after a movement's hold: how a held key's movement stops when it is
    let go."""
    if stopping is None:
        return None
    return dataclasses.replace(stopping, reaction_s=stopping.reaction_s + hold_s)


class CommandGate:
    """Checks commands for one vehicle task against its vocabulary and limits.

    ``breached`` tells which limits (``altitude``, ``geofence``) the vehicle is past now
    (the hub's envelope watch); ``clock`` is monotonic seconds (tests move it).
    """

    def __init__(
        self,
        adapter: Adapter,
        *,
        allowed: tuple[str, ...],
        limits: Limits,
        breached: Callable[[], Collection[str]] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.adapter = adapter
        self.vocabulary: dict[str, CommandSpec] = {c.name: c for c in adapter.commands()}
        # Explicit lists only: an empty list is a view-only task, and the safe commands
        # (stop, land, return home) are always accepted.
        self.allowed = frozenset(allowed)
        self.limits = limits
        self.breached = breached or (lambda: ())
        self.clock = clock
        #: Movements refused at a limit: name -> the limit (see the module docstring).
        self.latched: dict[str, str] = {}
        self._seen: dict[str, float] = {}
        self._stopped_at = -math.inf

    def is_motion(self, name: str) -> bool:
        """Whether ``name`` is a movement of this vehicle (held by repeats)."""
        spec = self.vocabulary.get(name)
        return spec is not None and spec.motion

    def check(self, name: str, args: Mapping[str, Any], *, rtt_ms: float | None = None) -> Checked:
        """Return the command ready for the adapter, or raise Refusal."""
        spec = self.vocabulary.get(name)
        if spec is None:
            raise Refusal("unknown_command", f"{name!r} is not a command of this vehicle")
        if name not in self.allowed and name not in SAFE_COMMANDS:
            raise Refusal("not_allowed", f"{name!r} is not allowed in this session")
        try:
            clean = validate_command_args(spec.args, args)
        except ProtocolError as exc:
            raise Refusal("bad_args", f"{name}: {exc.message}") from None

        factor = latency_speed_factor(self.limits, rtt_ms)
        if factor == 0.0 and spec.motion and name not in SAFE_COMMANDS:
            raise Refusal(
                "latency",
                f"{name} refused: round trip {rtt_ms:.0f} ms is over the "
                f"{self.limits.latency_hard_ms} ms limit: only stop, land and return home "
                "are accepted",
            )
        if spec.speed_arg and spec.speed_arg in clean:
            clean[spec.speed_arg] = self._speed(spec, clean[spec.speed_arg], factor)
        self._cap_speeds(spec, clean)
        slowed = self._check_envelope(name, clean, spec)
        return Checked(name, clean, factor if spec.speed_arg else 1.0, slowed)

    def _speed(self, spec: CommandSpec, value: float, factor: float) -> float:
        speed = float(value) * max(factor, MIN_SPEED_FACTOR)
        unit = spec.args[spec.speed_arg or ""].get("unit")
        if self.limits.max_speed_mps is not None and unit == "m/s":
            speed = min(speed, self.limits.max_speed_mps)
        return speed

    def _cap_speeds(self, spec: CommandSpec, args: dict[str, Any]) -> None:
        """Every speed a command carries (an argument in m/s: a waypoint's, a mission
        leg's) at most the task's maximum; 0, which asks for the vehicle's own cruise
        speed (an autopilot's WPNAV_SPEED, faster than any limit may be), becomes the
        maximum itself."""
        limit = self.limits.max_speed_mps
        if limit is None:
            return
        for arg, arg_spec in spec.args.items():
            if arg_spec.get("unit") == "m/s" and isinstance(args.get(arg), int | float):
                value = float(args[arg])
                args[arg] = limit if value == 0 else min(value, limit)

    # --- the limits ----------------------------------------------------------------------
    def _check_envelope(self, name: str, args: dict[str, Any], spec: CommandSpec) -> str | None:
        """Refuse (Refusal) or slow down (``args`` changed in place; returns the limit)
        a command at the task's ceiling and geofence."""
        now = self.clock()
        if name in SAFE_COMMANDS:
            self._stopped_at = now  # a stop: the user let go of what they held
            return None
        projection = self.adapter.project(name, args)
        if spec.motion:
            seen, self._seen[name] = self._seen.get(name), now
        if projection is None:
            return None
        state = self.adapter.state()
        try:
            if spec.motion:
                self._check_latch(name, projection, state, now, seen)
            braking = self.adapter.braking() if projection.velocity is not None else None
            if braking is not None and spec.motion:
                return self._limit_motion(name, args, spec, projection, state, braking)
            self._check_point(name, projection, state)
        except Refusal as refusal:
            if spec.motion and refusal.code in LIMIT_CODES.values():
                self.latched[name] = refusal.code
            raise
        return None

    def _check_latch(
        self,
        name: str,
        projection: Projection,
        state: VehicleState,
        now: float,
        seen: float | None,
    ) -> None:
        """A latched movement, or one outwards while past a limit: Refusal."""
        breached = set(self.breached())
        code = self.latched.get(name)
        if code is not None:
            released = seen is None or now - seen > RELEASE_S or self._stopped_at >= seen
            limit = next(k for k, v in LIMIT_CODES.items() if v == code)
            if released and limit not in breached:
                del self.latched[name]
            else:
                raise Refusal(
                    code, f"{name} stays refused at the {self._words(limit)}: let go of it first"
                )
        for limit in breached:
            if limit in LIMIT_CODES and self._outwards(limit, projection, state):
                raise Refusal(
                    LIMIT_CODES[limit],
                    f"{name} refused: the vehicle is past the {self._words(limit)}; only "
                    "movements back inside are accepted",
                )

    def _words(self, limit: str) -> str:
        if limit == ALTITUDE:
            return f"{self.limits.max_altitude_m:g} m altitude limit"
        return f"geofence (limit {self.limits.geofence_radius_m:g} m)"

    def _outwards(self, limit: str, projection: Projection, state: VehicleState) -> bool:
        """Whether ``projection`` takes the vehicle further past ``limit``."""
        velocity = projection.velocity
        if limit == ALTITUDE:
            if velocity is not None:
                return velocity[2] > 0
            return (
                projection.alt is not None and state.alt is not None and projection.alt > state.alt
            )
        centre, here = self.limits.geofence_center, state.position
        if centre is None or here is None:
            return False
        if velocity is not None:
            north, east = local_offset_m(centre, here)
            return north * velocity[0] + east * velocity[1] > 0
        if projection.lat is None or projection.lon is None:
            return False
        return distance_m(centre, (projection.lat, projection.lon)) > distance_m(centre, here)

    def _check_point(self, name: str, projection: Projection, state: VehicleState) -> None:
        """A command's projected point against the ceiling and the fence."""
        ceiling = self.limits.max_altitude_m
        if ceiling is not None and projection.alt is not None and projection.alt > ceiling:
            raise Refusal(
                "altitude_limit",
                f"{name} would climb to {projection.alt:.1f} m, above the {ceiling:g} m limit",
            )
        centre, radius = self.limits.geofence_center, self.limits.geofence_radius_m
        if (
            centre is not None
            and radius is not None
            and projection.lat is not None
            and projection.lon is not None
        ):
            out = distance_m(centre, (projection.lat, projection.lon))
            if out > radius:
                here = state.position
                # Moving back towards the fence from outside is always allowed.
                if here is None or out >= distance_m(centre, here):
                    raise Refusal(
                        "geofence",
                        f"{name} would leave the geofence ({out:.0f} m from its centre, "
                        f"limit {radius:g} m)",
                    )

    def _limit_motion(
        self,
        name: str,
        args: dict[str, Any],
        spec: CommandSpec,
        projection: Projection,
        state: VehicleState,
        braking: Braking,
    ) -> str | None:
        """A held movement against where the vehicle would come to rest: slowed down to
        the speed it can still stop from before each limit's margin, refused when that
        is under :data:`MIN_MOTION_MPS` (see the module docstring)."""
        assert projection.velocity is not None
        north, east, up = projection.velocity
        speed = math.sqrt(north * north + east * east + up * up)
        if speed <= 0:
            return None
        allowed: dict[str, float] = {}
        ceiling = self.limits.max_altitude_m
        # Let go of, the movement goes on for its hold before it is stopped.
        vertical = _held(braking.vertical, braking.hold_s)
        if ceiling is not None and up > 0 and state.alt is not None and vertical is not None:
            room = ceiling - band_for(ALTITUDE, ceiling).margin - state.alt
            allowed[ALTITUDE] = speed * vertical.speed_within(room) / up
        room_out = self._room_in_fence(state, north, east)
        horizontal = _held(braking.horizontal, braking.hold_s)
        if room_out is not None and horizontal is not None:
            allowed[GEOFENCE] = speed * horizontal.speed_within(room_out) / math.hypot(north, east)
        if not allowed:
            return None
        limit = min(allowed, key=lambda k: allowed[k])
        if allowed[limit] >= speed - 1e-6:
            return None
        floor = MIN_MOTION_MPS
        if spec.speed_arg is not None:
            floor = max(floor, float(spec.args[spec.speed_arg].get("min", 0.0)))
        if spec.speed_arg is None or spec.speed_arg not in args or allowed[limit] < floor:
            raise self._stop_refusal(name, limit, projection, state, braking, speed)
        args[spec.speed_arg] = float(args[spec.speed_arg]) * allowed[limit] / speed
        return limit

    def _room_in_fence(self, state: VehicleState, north: float, east: float) -> float | None:
        """Metres the vehicle can go along (``north``, ``east``) before it leaves the
        circle the geofence's margin draws inside it; None when it does not apply."""
        centre, radius = self.limits.geofence_center, self.limits.geofence_radius_m
        here = state.position
        h = math.hypot(north, east)
        if centre is None or radius is None or here is None or h <= 0:
            return None
        inner = radius - band_for(GEOFENCE, radius).margin
        x, y = local_offset_m(centre, here)
        ux, uy = north / h, east / h
        along = x * ux + y * uy  # > 0: moving away from the centre
        reach = along * along - (x * x + y * y) + inner * inner
        if x * x + y * y <= inner * inner:
            return -along + math.sqrt(max(0.0, reach))
        if along >= 0:
            return 0.0  # outside the inner circle and not heading in
        # Heading in from outside it: up to where the line leaves it again, or, when the
        # line misses it, up to the point nearest the centre.
        return -along + math.sqrt(reach) if reach > 0 else -along

    def _stop_refusal(
        self,
        name: str,
        limit: str,
        projection: Projection,
        state: VehicleState,
        braking: Braking,
        speed: float,
    ) -> Refusal:
        """The refusal of a movement that could not stop before ``limit``'s margin: where
        the vehicle would come to rest at the asked speed."""
        assert projection.velocity is not None
        north, east, up = projection.velocity
        if limit == ALTITUDE:
            ceiling = self.limits.max_altitude_m or 0.0
            margin = band_for(ALTITUDE, ceiling).margin
            vertical = _held(braking.vertical, braking.hold_s)
            assert vertical is not None and state.alt is not None
            rest = state.alt + vertical.distance(up)
            return Refusal(
                "altitude_limit",
                f"{name} would take the vehicle to {rest:.1f} m before it could stop: it "
                f"must stay {margin:.1f} m under the {ceiling:g} m limit",
            )
        centre, radius = self.limits.geofence_center, self.limits.geofence_radius_m or 0.0
        margin = band_for(GEOFENCE, radius).margin
        horizontal = _held(braking.horizontal, braking.hold_s)
        assert horizontal is not None and centre is not None
        here = state.position
        assert here is not None
        h = math.hypot(north, east)
        ahead = horizontal.distance(h) / h
        rest = distance_m(centre, offset(here, north * ahead, east * ahead))
        return Refusal(
            "geofence",
            f"{name} would take the vehicle {rest:.0f} m from the geofence's centre before "
            f"it could stop: it must stay {margin:.0f} m inside its {radius:g} m limit",
        )


def plan_within(items: Sequence[PlanItem], limits: Limits) -> list[PlanItem]:
    """A plan the vehicle's own engine will fly without the gate (see
    :mod:`agents.vehicles.plan`), checked whole against the task's ``limits``: every
    waypoint and take-off at most the ceiling, every waypoint inside the geofence
    (Refusal ``altitude_limit``, ``geofence``, naming the item); every speed lowered to
    the task's maximum. Returns the plan to fly."""
    ceiling = limits.max_altitude_m
    centre, radius = limits.geofence_center, limits.geofence_radius_m
    checked: list[PlanItem] = []
    for index, item in enumerate(items):
        high = isinstance(item, TakeOff | Waypoint) and item.altitude_m > (ceiling or math.inf)
        if high:
            raise Refusal(
                "altitude_limit",
                f"mission item {index} goes above the {ceiling:g} m altitude limit",
            )
        if isinstance(item, Waypoint) and centre is not None and radius is not None:
            out = distance_m(centre, item.point)
            if out > radius:
                raise Refusal(
                    "geofence",
                    f"mission item {index} is {out:.0f} m from the geofence's centre "
                    f"(limit {radius:g} m)",
                )
        if isinstance(item, Speed) and limits.max_speed_mps is not None:
            item = Speed(min(item.speed_mps, limits.max_speed_mps))
        checked.append(item)
    return checked
