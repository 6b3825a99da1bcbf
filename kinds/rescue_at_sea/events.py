"""Facts reported by the rescue's vehicles: recorded, then left to the next step.

:func:`mission_event` writes what an agent reported (progress, a detection, a released
payload, a failure) on the mission and schedules a step; the step decides what it
means (``workflow``).
"""

from __future__ import annotations

from typing import Any

from django.db import transaction
from django.utils import timezone

from kinds.rescue_at_sea.coverage import point_in_area
from kinds.rescue_at_sea.models import DELIVERY, FINAL_MISSION, SEARCH, Mission
from kinds.rescue_at_sea.tasks import mission_schedule
from services.kit import event_append, session_task_accepted
from services.models import Assignment

#: ``native_mission_refused``: the autopilot refused the delivery's plan, the agent
#: flies it step by step (logged: what the drone would do without its agent changes).
#: ``native_mission_started``: the autopilot flies the plan itself (``within_s`` at most):
#: a vehicle gone silent meanwhile flies on, and is not replaced before that time.
MISSION_EVENTS = frozenset(
    {
        "mission_progress",
        "native_mission_refused",
        "native_mission_started",
        "person_detected",
        "search_complete",
        "payload_released",
        "mission_failed",
    }
)


def mission_event(*, assignment: Assignment, name: str, data: dict[str, Any]) -> None:
    """Record one mission event an agent reported and schedule a step.

    Only the facts are written here (the step decides what they mean). Reports from a
    vehicle that no longer holds its role are logged and otherwise ignored.
    """
    vehicle = str(assignment.vehicle_id)
    with transaction.atomic():
        mission = Mission.objects.select_for_update().filter(pk=assignment.session_id).first()
        session = assignment.session
        if mission is None:
            event_append(
                session=session,
                kind="agent_event",
                data={"vehicle": vehicle, "event": name, "data": data},
            )
            return
        entry: dict[str, Any] = {"vehicle": vehicle, "role": assignment.role, **_clean(data)}
        current = assignment.active and mission.state not in FINAL_MISSION
        if name == "mission_progress":
            waypoint = data.get("waypoint")
            if (
                current
                and assignment.role == SEARCH
                and isinstance(waypoint, int)
                and not isinstance(waypoint, bool)
                and 0 <= waypoint < len(mission.path)
                and waypoint > mission.progress
            ):
                mission.progress = waypoint
                mission.save(update_fields=["progress", "updated_at"])
        elif name == "person_detected":
            point = _latlon(data)
            if current and mission.detection is None and point is not None:
                mission.detection = {
                    "lat": point[0],
                    "lon": point[1],
                    "confidence": _number(data.get("confidence")),
                    "temperature_c": _number(data.get("temperature_c")),
                    "area_m2": _number(data.get("area_m2")),
                    "vehicle": vehicle,
                    "vehicle_name": assignment.vehicle.name,
                }
                mission.detected_at = timezone.now()
                mission.save(update_fields=["detection", "detected_at", "updated_at"])
                entry["inside_area"] = point_in_area(point, mission.area, margin_m=50)
        elif name == "search_complete":
            if current and assignment.role == SEARCH:
                mission.progress = len(mission.path) - 1
                mission.save(update_fields=["progress", "updated_at"])
        elif (
            name == "payload_released"
            and assignment.role == DELIVERY
            and mission.released_at is None
        ):
            mission.released_at = timezone.now()
            mission.save(update_fields=["released_at", "updated_at"])
        event_append(session=session, kind=name, data=entry)
        mission_schedule(mission.pk)


def _clean(data: dict[str, Any]) -> dict[str, Any]:
    # What the agent said, minus the fields the log keeps elsewhere.
    return {k: v for k, v in data.items() if k not in ("vehicle", "role")}


def _number(value: Any) -> float | None:
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    return None


def _latlon(data: dict[str, Any]) -> tuple[float, float] | None:
    lat, lon = _number(data.get("lat")), _number(data.get("lon"))
    if lat is None or lon is None or abs(lat) > 90 or abs(lon) > 180:
        return None
    return (lat, lon)


def mission_task_accepted(*, assignment: Assignment) -> None:
    """A vehicle of a rescue accepted its task: the session is under way."""
    session_task_accepted(
        assignment=assignment,
        reason=f"{assignment.vehicle.name} accepted its {assignment.role} task",
    )
    mission_schedule(assignment.session_id)
