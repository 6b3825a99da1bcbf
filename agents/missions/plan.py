"""The flight kit's plans: a mission, or the part of it that is plain waypoints and
actions, written once as a :class:`FlightPlan` that the vehicle's own mission engine
can fly (:mod:`agents.vehicles.plan`; the runner hands it over with
:meth:`agents.missions.kit.MissionRunner.fly_natively`).

Each step is a plan item and what the platform hears about it, as it hears it from a
mission flown step by step: ``phase``, a ``mission_progress`` when the vehicle starts
the step; ``event``, reported once the vehicle has finished it (moved on past it).

A plan ends with the return home or with a hold (:meth:`FlightPlan.hold`): the runner's
part ends once the vehicle has started it, and nothing may follow a hold, since the
engine never moves past one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Final

from agents.geo import distance_m
from agents.missions.spec import LatLon
from agents.vehicles.plan import Hold, PlanItem, Release, ReturnHome, Speed, TakeOff, Waypoint

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

    def _add(self, step: PlanStep) -> FlightPlan:
        if self.steps and isinstance(self.steps[-1].item, Hold):
            raise ValueError("nothing can follow a hold: the vehicle never moves past it")
        self.steps.append(step)
        return self

    def take_off(self, altitude_m: float) -> FlightPlan:
        """Climb to ``altitude_m`` (done at once when the vehicle is higher)."""
        return self._add(PlanStep(TakeOff(altitude_m)))

    def speed(self, speed_mps: float) -> FlightPlan:
        """The speed of the legs that follow."""
        return self._add(PlanStep(Speed(speed_mps)))

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
        return self._add(PlanStep(Waypoint(point, altitude_m, hold_s), phase, event))

    def release(self, *, event: str = "payload_released") -> FlightPlan:
        """Release the payload where the vehicle is (reported as ``event``)."""
        return self._add(PlanStep(Release(), event=event))

    def return_home(self, *, phase: str = "returning") -> FlightPlan:
        """Go home: the vehicle's own return (a copter lands there)."""
        return self._add(PlanStep(ReturnHome(), phase=phase))

    def hold(self, *, phase: str = "hold") -> FlightPlan:
        """Stay over the last waypoint until told otherwise, as a mission flown step by
        step ends holding where its last leg took it (a copter hovers there, a boat
        keeps station). The plan's last step: raises ValueError if another follows."""
        return self._add(PlanStep(Hold(), phase=phase))

    @property
    def releases(self) -> bool:
        return any(isinstance(step.item, Release) for step in self.steps)

    def time_limit_s(self, start: LatLon | None, altitude_m: float) -> float:
        """How long the vehicle may take to fly the plan up to its return home or its
        hold, from ``start`` at ``altitude_m`` (see :data:`PLAN_MARGIN_S`): neither
        counts, since the runner's part ends once the vehicle has started it."""
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
