"""What the rescue's pages show: the mission as the live map draws it."""

from __future__ import annotations

from typing import Any

from django.utils import timezone

from kinds.rescue_at_sea.models import FINAL_MISSION, WORKING, Mission
from services.models import Assignment


def timeline(mission: Mission) -> dict[str, str]:
    """When each milestone happened (ISO times), for the mission's last log entry."""
    marks: dict[str, str] = {"requested": mission.session.created_at.isoformat()}
    for kind in ("person_detected", "payload_released"):
        first = mission.session.events.filter(kind=kind).order_by("seq").first()
        if first is not None:
            marks[kind] = first.created_at.isoformat()
    marks["completed"] = timezone.now().isoformat()
    return marks


def mission_json(mission: Mission) -> dict[str, Any]:
    """The mission as the live map shows it: area, path, progress, detection, vehicles
    (with where they are now) and the log's milestones."""
    session = mission.session
    assignments = list(
        Assignment.objects.filter(session_id=mission.pk).select_related("vehicle__station")
    )
    vehicles = []
    for a in assignments:
        v = a.vehicle
        vehicles.append(
            {
                "id": str(v.pk),
                "name": v.name,
                "role": a.role,
                "active": a.active,
                "status": v.status,
                "lat": v.lat,
                "lon": v.lon,
                "alt": v.alt,
                "battery": v.battery,
                "station": {"name": v.station.name, "lat": v.station.lat, "lon": v.station.lon},
            }
        )
    shown = (
        "requested",
        "mission_planned",
        "assigned",
        "search_leg",
        "mission_state",
        "person_detected",
        "notice_sent",
        "payload_released",
        "vehicle_released",
        "state",
    )
    timeline = [
        {"seq": e.seq, "at": e.created_at.isoformat(), "kind": e.kind, "data": e.data}
        for e in session.events.filter(kind__in=shown).order_by("seq")
    ]
    return {
        "session": {"id": str(session.pk), "state": session.state, "reason": session.reason},
        "state": mission.state,
        "state_label": Mission.State(mission.state).label,
        "final": mission.state in FINAL_MISSION,
        "working": mission.state in WORKING,
        "status": mission.status_text,
        "area": mission.area,
        "path": mission.path,
        "progress": mission.progress,
        "altitude_m": mission.altitude_m,
        "spacing_m": mission.spacing_m,
        "detection": mission.detection,
        "released": mission.released_at is not None,
        "vehicles": vehicles,
        "timeline": timeline,
    }
