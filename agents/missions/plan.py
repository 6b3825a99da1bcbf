"""The flight kit's plans: a mission, or the part of it that is plain waypoints and
actions, written once as a :class:`FlightPlan` that the vehicle's own mission engine
can fly (:mod:`agents.vehicles.plan`; the runner hands it over with
:meth:`agents.missions.kit.MissionRunner.fly_natively`).

Each step is a plan item and what the platform hears about it, as it hears it from a
mission flown step by step: ``phase``, a ``mission_progress`` when the vehicle starts
the step; ``event``, reported once the vehicle has finished it (moved on past it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Final

from agents.geo import distance_m
from agents.missions.spec import LatLon
from agents.vehicles.plan import PlanItem, Release, ReturnHome, Speed, TakeOff, Waypoint

#: The time limit of a plan: this much, plus this factor times the time its legs take
#: at its speed (and vertical moves at VERTICAL_RATE_MPS), plus its holds.
PLAN_MARGIN_S: Final = 60.0
PLAN_TIME_FACTOR: Final = 3.0
VERTICAL_RATE_MPS: Final = 1.0


@dataclass(frozen=True)
class PlanStep:
    """One item of a plan, and what to report of it (see the module docstring)."""

    item: PlanItem
    phase: str | None = None
    event: str | None = None


@dataclass
class FlightPlan:
    """A plan, built step by step (see the module docstring)."""

    steps: list[PlanStep] = field(default_factory=list)

    @property
    def items(self) -> list[PlanItem]:
        return [step.item for step in self.steps]

    def take_off(self, altitude_m: float) -> FlightPlan:
        """Climb to ``altitude_m`` (done at once when the vehicle is higher)."""
        self.steps.append(PlanStep(TakeOff(altitude_m)))
        return self

    def speed(self, speed_mps: float) -> FlightPlan:
        """The speed of the legs that follow."""
        self.steps.append(PlanStep(Speed(speed_mps)))
        return self

    def fly_to(
        self,
        point: LatLon,
        altitude_m: float,
        *,
        hold_s: float = 0.0,
        phase: str | None = None,
        event: str | None = None,
    ) -> FlightPlan:
        """Fly to ``point`` at ``altitude_m`` (a descent or a climb over the same point
        too), staying ``hold_s`` seconds there."""
        self.steps.append(PlanStep(Waypoint(point, altitude_m, hold_s), phase, event))
        return self

    def release(self, *, event: str = "payload_released") -> FlightPlan:
        """Release the payload where the vehicle is (reported as ``event``)."""
        self.steps.append(PlanStep(Release(), event=event))
        return self

    def return_home(self, *, phase: str = "returning") -> FlightPlan:
        """Go home: the vehicle's own return (a copter lands there)."""
        self.steps.append(PlanStep(ReturnHome(), phase=phase))
        return self

    @property
    def releases(self) -> bool:
        return any(isinstance(step.item, Release) for step in self.steps)

    def time_limit_s(self, start: LatLon | None, altitude_m: float) -> float:
        """How long the vehicle may take to fly the plan up to its return home, from
        ``start`` at ``altitude_m`` (see :data:`PLAN_MARGIN_S`)."""
        here, alt, speed = start, altitude_m, 1.0
        legs = holds = 0.0
        for step in self.steps:
            item = step.item
            if isinstance(item, Speed):
                speed = max(item.speed_mps, 0.1)
            elif isinstance(item, TakeOff):
                legs += max(0.0, item.altitude_m - alt) / VERTICAL_RATE_MPS
                alt = max(alt, item.altitude_m)
            elif isinstance(item, Waypoint):
                across = distance_m(here, item.point) if here is not None else 1000.0
                legs += across / speed + abs(item.altitude_m - alt) / VERTICAL_RATE_MPS
                here, alt = item.point, item.altitude_m
                holds += item.hold_s
        return PLAN_MARGIN_S + PLAN_TIME_FACTOR * legs + holds
