"""What the survey's page shows: the area, the planned lines, the photos' footprints as
they arrive, the drone, and the mosaic once made."""

from __future__ import annotations

from typing import Any

from django.urls import reverse

from agents.missions.survey.spec import survey_photo_points
from kinds.survey.models import FINAL_SURVEY, SURVEYOR, Survey
from kinds.survey.planning import plan_lines
from kinds.survey.workflow import footprints, photos
from services.kit import session_consequence
from services.models import Assignment

#: The log entries the timeline shows.
SHOWN = (
    "requested",
    "survey_planned",
    "assigned",
    "survey_state",
    "native_mission_refused",
    "native_mission_started",
    "survey_flown",
    "photo_missed",
    "mission_failed",
    "vehicle_released",
    "state",
)


def survey_json(survey: Survey) -> dict[str, Any]:
    """The survey as its live map shows it."""
    session = survey.session
    assignments = list(
        Assignment.objects.filter(session_id=survey.pk).select_related("vehicle__station")
    )
    vehicles = [
        {
            "id": str(a.vehicle_id),
            "name": a.vehicle.name,
            "role": a.role,
            "active": a.active,
            "status": a.vehicle.status,
            "lat": a.vehicle.lat,
            "lon": a.vehicle.lon,
            "battery": a.vehicle.battery,
            "station": {
                "name": a.vehicle.station.name,
                "lat": a.vehicle.station.lat,
                "lon": a.vehicle.station.lon,
            },
        }
        for a in assignments
        if a.role == SURVEYOR
    ]
    stored = photos(survey)
    plan = survey.plan
    points = (
        [list(p) for _, p in survey_photo_points(plan_lines(plan), plan["spacing_m"])]
        if plan is not None
        else []
    )
    out: dict[str, Any] = {
        "session": {"id": str(session.pk), "state": session.state, "reason": session.reason},
        "state": survey.state,
        "state_label": Survey.State(survey.state).label,
        "final": survey.state in FINAL_SURVEY,
        "status": survey.status_text,
        "polygon": survey.polygon,
        "gsd_cm": survey.gsd_cm,
        "overlap": {"front": survey.front_overlap, "side": survey.side_overlap},
        "plan": plan,
        "photo_points": points,
        "photo_count": survey.photo_count,
        "next_photo": survey.next_photo,
        "photos": [
            {"name": a.name, "corners": [list(c) for c in f.corners]}
            for a, f in zip(stored, footprints(survey, stored), strict=False)
        ],
        "coverage": survey.coverage,
        "mosaic": (
            {
                "url": reverse("survey_mosaic", args=[session.pk]),
                "kmz": reverse("survey_kmz", args=[session.pk]),
                "bounds": survey.mosaic_bounds,
            }
            if survey.mosaic is not None
            else None
        ),
        "vehicles": vehicles,
    }
    active = [a.vehicle for a in assignments if a.active]
    out["consequence"] = session_consequence(session, active)
    out["timeline"] = [
        {"seq": e.seq, "at": e.created_at.isoformat(), "kind": e.kind, "data": e.data}
        for e in session.events.filter(kind__in=SHOWN).order_by("seq")
    ]
    return out
