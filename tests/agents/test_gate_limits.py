"""The command gate's limits as the vehicle brakes (agents.safety), on a stand-in
vehicle and a clock the tests move: held movements slow down before a limit's margin
and are refused there, stay refused until let go, and only move inwards while the
vehicle is past a limit. Measured on the simulators in test_mavlink_limits.py.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import pytest

from agents.geo import offset
from agents.protocol import Limits
from agents.safety import MIN_MOTION_MPS, RELEASE_S, CommandGate, Refusal
from agents.vehicles.base import (
    Adapter,
    Braking,
    CommandSpec,
    Projection,
    Stopping,
    VehicleState,
)

CENTRE = (40.0, -8.0)
SPEED = {"speed_mps": {"type": "number", "min": 0.1, "max": 10, "default": 1, "unit": "m/s"}}
#: A copter's defaults: 1 m/s² up, 2.5 m/s² across, a 1 s hold, 0.3 s to react.
BRAKING = Braking(
    horizontal=Stopping(decel_mps2=2.5, reaction_s=0.3),
    vertical=Stopping(decel_mps2=1.0, reaction_s=0.3),
    hold_s=1.0,
)


class Vehicle(Adapter):
    """Goes up or north at the asked speed; where it is, the tests say."""

    name = "stand-in"

    def __init__(self) -> None:
        super().__init__({})
        self.alt = 10.0
        self.north = 0.0
        self.braking_known = True

    def commands(self) -> list[CommandSpec]:
        return [
            CommandSpec("up", args=SPEED, motion=True, speed_arg="speed_mps"),
            CommandSpec("down", args=SPEED, motion=True, speed_arg="speed_mps"),
            CommandSpec("north", args=SPEED, motion=True, speed_arg="speed_mps"),
            CommandSpec("south", args=SPEED, motion=True, speed_arg="speed_mps"),
            CommandSpec("stop"),
        ]

    def telemetry_topics(self) -> list[str]:
        return []

    def telemetry(self) -> dict[str, Any]:
        return {}

    def state(self) -> VehicleState:
        lat, lon = offset(CENTRE, self.north, 0.0)
        return VehicleState(lat=lat, lon=lon, alt=self.alt, heading_deg=0.0)

    def project(self, name: str, args: Mapping[str, Any]) -> Projection | None:
        speed = float(args["speed_mps"]) if "speed_mps" in args else 0.0
        velocity = {
            "up": (0.0, 0.0, speed),
            "down": (0.0, 0.0, -speed),
            "north": (speed, 0.0, 0.0),
            "south": (-speed, 0.0, 0.0),
        }.get(name)
        if velocity is None:
            return None
        lat, lon = offset(CENTRE, self.north + velocity[0], 0.0)
        return Projection(lat=lat, lon=lon, alt=self.alt + velocity[2], velocity=velocity)

    def braking(self) -> Braking | None:
        return BRAKING if self.braking_known else None

    async def execute(self, name: str, args: Mapping[str, Any]) -> None:
        pass

    async def safe_action(self, action: str) -> None:
        pass


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def gate_for(vehicle: Vehicle, limits: Limits, breached: list[str] | None = None) -> CommandGate:
    names = tuple(c.name for c in vehicle.commands())
    return CommandGate(vehicle, allowed=names, limits=limits, breached=lambda: breached or [])


def test_a_climb_slows_down_as_the_ceiling_nears_and_stops_at_its_margin():
    vehicle, clock = Vehicle(), Clock()
    gate = gate_for(vehicle, Limits(max_altitude_m=15))
    gate.clock = clock
    # 15 m ceiling, 2 m margin: it must be able to stop at 13 m. From 10 m, 3 m of room:
    # 1 s of hold, 0.3 s to react, 1 m/s²: about 1.5 m/s at most.
    checked = gate.check("up", {"speed_mps": 2.5})
    assert checked.slowed_by == "altitude"
    speed = checked.args["speed_mps"]
    stopping = Stopping(decel_mps2=1.0, reaction_s=1.3)
    assert speed == pytest.approx(stopping.speed_within(3.0))
    assert stopping.distance(speed) == pytest.approx(3.0)
    # Far below: the asked speed.
    vehicle.alt = 2.0
    assert gate.check("up", {"speed_mps": 2.5}).args["speed_mps"] == 2.5
    # At the margin: refused, in words that name the limit.
    vehicle.alt = 13.0
    with pytest.raises(Refusal) as refused:
        gate.check("up", {"speed_mps": 2.5})
    assert refused.value.code == "altitude_limit"
    assert "15 m limit" in str(refused.value) and "2.0 m under" in str(refused.value)
    # Down is always fine.
    assert gate.check("down", {"speed_mps": 2.5}).args["speed_mps"] == 2.5


def test_a_movement_too_slow_to_matter_is_refused_not_crept():
    vehicle = Vehicle()
    gate = gate_for(vehicle, Limits(max_altitude_m=15))
    vehicle.alt = 13.0 - 0.005  # room for a few cm/s only
    with pytest.raises(Refusal):
        gate.check("up", {"speed_mps": 1.0})
    assert Stopping(1.0, 1.3).speed_within(0.005) < MIN_MOTION_MPS


def test_the_geofence_slows_a_movement_out_and_lets_one_in():
    vehicle = Vehicle()
    gate = gate_for(vehicle, Limits(geofence_center=CENTRE, geofence_radius_m=40))
    vehicle.north = 28.0  # 7 m to the margin (35 m)
    checked = gate.check("north", {"speed_mps": 5.0})
    assert checked.slowed_by == "geofence"
    assert checked.args["speed_mps"] == pytest.approx(Stopping(2.5, 1.3).speed_within(7.0))
    vehicle.north = 35.5
    with pytest.raises(Refusal) as refused:
        gate.check("north", {"speed_mps": 5.0})
    assert refused.value.code == "geofence" and "40 m limit" in str(refused.value)
    assert gate.check("south", {"speed_mps": 5.0}).args["speed_mps"] == 5.0


def test_a_refused_movement_stays_refused_until_let_go():
    vehicle, clock = Vehicle(), Clock()
    gate = gate_for(vehicle, Limits(max_altitude_m=15))
    gate.clock = clock
    vehicle.alt = 13.0
    with pytest.raises(Refusal):
        gate.check("up", {"speed_mps": 1.0})
    assert gate.latched == {"up": "altitude_limit"}
    # Lower now (it sank), the key still held: still refused.
    vehicle.alt = 5.0
    clock.now += 0.1
    with pytest.raises(Refusal) as refused:
        gate.check("up", {"speed_mps": 1.0})
    assert "let go of it first" in str(refused.value)
    # Let go (no repeat for longer than the controller's slowest repeat): it works.
    clock.now += RELEASE_S + 0.1
    assert gate.check("up", {"speed_mps": 1.0}).args["speed_mps"] == 1.0
    # A stop from the browser is a release too.
    vehicle.alt = 13.0
    with pytest.raises(Refusal):
        gate.check("up", {"speed_mps": 1.0})
    vehicle.alt = 5.0
    clock.now += 0.1
    gate.check("stop", {})
    clock.now += 0.1
    assert gate.check("up", {"speed_mps": 1.0}).args["speed_mps"] == 1.0


def test_past_a_limit_only_movements_inwards_pass_and_the_latch_waits_for_inside():
    vehicle, clock = Vehicle(), Clock()
    breached = ["geofence"]
    gate = gate_for(vehicle, Limits(geofence_center=CENTRE, geofence_radius_m=40), breached)
    gate.clock = clock
    vehicle.north = 42.0
    with pytest.raises(Refusal) as refused:
        gate.check("north", {"speed_mps": 1.0})
    assert refused.value.code == "geofence" and "only movements back inside" in str(refused.value)
    assert gate.check("south", {"speed_mps": 3.0}).args["speed_mps"] == 3.0
    # Back in, let go, but the envelope still says outside: still refused.
    vehicle.north = 10.0
    clock.now += RELEASE_S + 0.1
    with pytest.raises(Refusal):
        gate.check("north", {"speed_mps": 1.0})
    breached.clear()
    clock.now += RELEASE_S + 0.1
    assert gate.check("north", {"speed_mps": 1.0}).args["speed_mps"] == 1.0


def test_a_vehicle_that_says_nothing_of_its_braking_is_judged_by_the_projected_point():
    vehicle = Vehicle()
    vehicle.braking_known = False
    gate = gate_for(vehicle, Limits(max_altitude_m=15))
    vehicle.alt = 13.0
    assert gate.check("up", {"speed_mps": 1.5}).args["speed_mps"] == 1.5  # 14.5 m
    with pytest.raises(Refusal) as refused:
        gate.check("up", {"speed_mps": 2.5})  # 15.5 m
    assert str(refused.value) == "up would climb to 15.5 m, above the 15 m limit"


def test_every_speed_a_command_carries_is_capped_and_the_vehicles_own_becomes_the_limit():
    """A waypoint's speed above the task's maximum is capped; speed 0 (the vehicle's
    own cruise speed, which may be faster than any limit) becomes the maximum."""
    waypoint = CommandSpec(
        "go_to_waypoint",
        args={
            "lat": {"type": "number", "min": -90, "max": 90},
            "lon": {"type": "number", "min": -180, "max": 180},
            "speed_mps": {"type": "number", "min": 0, "max": 20, "default": 0, "unit": "m/s"},
        },
    )

    class Waypoints(Vehicle):
        def commands(self) -> list[CommandSpec]:
            return [*super().commands(), waypoint]

    limited = CommandGate(
        Waypoints(), allowed=("go_to_waypoint",), limits=Limits(max_speed_mps=2.0)
    )
    here = {"lat": CENTRE[0], "lon": CENTRE[1]}
    assert limited.check("go_to_waypoint", {**here, "speed_mps": 15}).args["speed_mps"] == 2.0
    assert limited.check("go_to_waypoint", {**here, "speed_mps": 0}).args["speed_mps"] == 2.0
    assert limited.check("go_to_waypoint", {**here, "speed_mps": 1.5}).args["speed_mps"] == 1.5
    free = CommandGate(Waypoints(), allowed=("go_to_waypoint",), limits=Limits())
    assert free.check("go_to_waypoint", {**here, "speed_mps": 0}).args["speed_mps"] == 0
