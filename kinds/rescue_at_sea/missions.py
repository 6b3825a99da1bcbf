"""The missions signed into the rescue vehicles' tasks, built from the recorded state,
so a re-sent task carries the same mission (and the same id) as the first.

Each is a spec of the agent's mission (agents/missions/<name>/spec.py): ``search``
for the search drones, ``delivery`` for the one bringing the life ring, ``return`` for
the way home; building one checks it as the agent will (MissionError naming the field).
"""

from __future__ import annotations

from agents.missions.delivery.spec import DeliverySpec
from agents.missions.return_home.spec import ReturnSpec
from agents.missions.search.spec import SearchSpec
from agents.missions.spec import MissionSpec
from fleet.models import Vehicle
from kinds.rescue_at_sea.models import DELIVERY, SEARCH, Mission
from services.models import Assignment

#: Search speed cap: faster smears the thermal image (about 9 frames per second).
SEARCH_SPEED_MPS = 10.0
DELIVERY_ALTITUDE_M = 25.0
DROP_ALTITUDE_M = 4.0
#: A detection below this confidence is not acted on by the agent.
MIN_CONFIDENCE = 0.6


def vehicle_speed(vehicle: Vehicle, cap: float | None = None) -> float:
    """How fast ``vehicle`` is told to fly its part: its top speed, under ``cap``."""
    top = float(vehicle.attributes.get("max_speed_mps") or SEARCH_SPEED_MPS)
    return min(top, cap) if cap is not None else top


#: The missions this kind deploys (:attr:`services.kinds.ServiceKind.missions`).
MISSIONS: tuple[type[MissionSpec], ...] = (SearchSpec, DeliverySpec, ReturnSpec)


def vehicle_mission(*, assignment: Assignment) -> MissionSpec | None:
    """The ``mission`` signed into ``assignment``'s vehicle task, from the recorded
    state, so a re-sent task carries the same mission (and the same id) as the first.
    None when the session has no mission."""
    mission = Mission.objects.filter(pk=assignment.session_id).first()
    if mission is None:
        return None
    vehicle = assignment.vehicle
    # The id names the session, the role and this assignment: the agent keeps one
    # running mission per id and never repeats it.
    mission_id = f"{assignment.session_id}-{assignment.role}-{assignment.pk}"
    if mission.state == Mission.State.RETURNING:
        # The last leg, with the session open: home, watched by the user.
        return ReturnSpec(id=f"{mission_id}-home")
    if assignment.role == SEARCH:
        start = _start_index(mission, assignment)
        return SearchSpec(
            id=mission_id,
            altitude_m=mission.altitude_m,
            speed_mps=vehicle_speed(vehicle, mission.speed_mps),
            waypoints=tuple((lat, lon) for lat, lon in mission.path),
            start_index=start,
            min_confidence=MIN_CONFIDENCE,
        )
    if assignment.role == DELIVERY and mission.detection is not None:
        return DeliverySpec(
            id=mission_id,
            target=(mission.detection["lat"], mission.detection["lon"]),
            altitude_m=DELIVERY_ALTITUDE_M,
            drop_altitude_m=DROP_ALTITUDE_M,
            speed_mps=vehicle_speed(vehicle),
        )
    return None


def _start_index(mission: Mission, assignment: Assignment) -> int:
    """Where a search vehicle starts: where the pattern stood when it was assigned.

    A replacement re-flies the leg its predecessor was on (from the last waypoint
    reached), so no strip of the area is skipped.
    """
    start = (
        assignment.session.events.filter(
            kind="search_leg", data__vehicle=str(assignment.vehicle_id)
        )
        .order_by("-seq")
        .first()
    )
    if start is not None and isinstance(start.data.get("start_index"), int):
        return int(start.data["start_index"])
    return max(mission.progress, 0)
