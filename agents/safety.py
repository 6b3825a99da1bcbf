"""The agent's command gate: every command passes here before the adapter sees it.

Order of checks, first failure wins and is reported with its code:

1. ``unknown_command`` - not in the vehicle's vocabulary
2. ``not_allowed``     - not in the task's allowed commands
3. ``bad_args``        - arguments fail the command's arg spec
4. ``latency``         - round trip past the task's hard limit: only stop/land/RTL pass
5. ``altitude_limit``  - the command would take the vehicle above the task's ceiling
6. ``geofence``        - ... or outside the task's geofence
and speeds are clamped to the task's max speed and, past the soft latency limit,
lowered linearly down to :data:`MIN_SPEED_FACTOR` at the hard limit.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from agents.geo import distance_m
from agents.protocol import Limits, ProtocolError, validate_command_args
from agents.vehicles.base import SAFE_COMMANDS, Adapter, CommandSpec

#: At the hard latency limit, speeds are cut to this fraction of what the user asked.
MIN_SPEED_FACTOR = 0.3


class Refusal(Exception):
    """A command the gate refuses; ``code`` is machine-readable, ``str()`` for people
    and names the command (a user may have several in flight)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Checked:
    """A command that passed: its arguments, and the speed factor applied (1 = none)."""

    name: str
    args: dict[str, Any]
    speed_factor: float = 1.0


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


class CommandGate:
    """Checks commands for one vehicle task against its vocabulary and limits."""

    def __init__(self, adapter: Adapter, *, allowed: tuple[str, ...], limits: Limits) -> None:
        self.adapter = adapter
        self.vocabulary: dict[str, CommandSpec] = {c.name: c for c in adapter.commands()}
        # Explicit lists only: an empty list is a view-only task, and the safe commands
        # (stop, land, return home) are always accepted.
        self.allowed = frozenset(allowed)
        self.limits = limits

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
        self._check_envelope(name, clean)
        return Checked(name, clean, factor if spec.speed_arg else 1.0)

    def _speed(self, spec: CommandSpec, value: float, factor: float) -> float:
        speed = float(value) * max(factor, MIN_SPEED_FACTOR)
        unit = spec.args[spec.speed_arg or ""].get("unit")
        if self.limits.max_speed_mps is not None and unit == "m/s":
            speed = min(speed, self.limits.max_speed_mps)
        return speed

    def _check_envelope(self, name: str, args: Mapping[str, Any]) -> None:
        if name in SAFE_COMMANDS:
            return
        projection = self.adapter.project(name, args)
        if projection is None:
            return
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
                here = self.adapter.state().position
                # Moving back towards the fence from outside is always allowed.
                if here is None or out >= distance_m(centre, here):
                    raise Refusal(
                        "geofence",
                        f"{name} would leave the geofence ({out:.0f} m from its centre, "
                        f"limit {radius:g} m)",
                    )
