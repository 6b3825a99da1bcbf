"""What the rescue's pages show: the mission as the live map draws it."""

from __future__ import annotations

from typing import Any

from django.utils import timezone

from agents.geo import distance_m
from kinds.rescue_at_sea.missions import SEARCH_SPEED_MPS, vehicle_speed
from kinds.rescue_at_sea.models import DELIVERY, FINAL_MISSION, SEARCH, WORKING, Mission
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


def _speed(assignment: Assignment, cap: float | None = None) -> float:
    """How fast ``assignment``'s vehicle flies its part, as its mission tells it to
    (never taken as standing still, whatever its declared speed)."""
    return max(0.5, vehicle_speed(assignment.vehicle, cap))


def _where(assignment: Assignment) -> tuple[float, float] | None:
    v = assignment.vehicle
    return (v.lat, v.lon) if v.lat is not None and v.lon is not None else None


def mission_phase(mission: Mission, assignments: list[Assignment]) -> dict[str, Any]:
    """What is happening now, honestly, with how far there is to go and when it should
    be done: on the way to the area (not "0 of 12 waypoints"), searching with the
    pattern left, bringing the life jacket, flying home. ``eta_s`` is None when nothing
    is moving towards a goal (waiting, over) or the vehicle has not said where it is.
    """
    active = {a.role: a for a in assignments if a.active}
    state = mission.state
    total = len(mission.path)
    label, detail, remaining = Mission.State(state).label, "", None
    speed = SEARCH_SPEED_MPS
    search = active.get(SEARCH)
    if state == Mission.State.SEARCHING and search is not None and total:
        speed = _speed(search, mission.speed_mps)
        here = _where(search)
        nxt = max(0, mission.progress + 1)
        if here is not None and nxt < total:
            legs = sum(
                distance_m(tuple(mission.path[i]), tuple(mission.path[i + 1]))
                for i in range(nxt, total - 1)
            )
            to_next = distance_m(here, tuple(mission.path[nxt]))
            if mission.progress < 0:
                label = "on the way to the search area"
                detail = f"{to_next:,.0f} m to the first of {total} waypoints"
            else:
                label = "searching"
                detail = f"waypoint {mission.progress + 1} of {total} reached"
            remaining = to_next + legs
    delivery = active.get(DELIVERY)
    if state == Mission.State.DELIVERING and delivery is not None and mission.detection:
        speed = _speed(delivery)
        here = _where(delivery)
        if here is not None:
            label = "bringing the life jacket"
            remaining = distance_m(here, (mission.detection["lat"], mission.detection["lon"]))
            detail = f"{delivery.vehicle.name} is {remaining:,.0f} m from the person"
    if state == Mission.State.RETURNING:
        away = []
        for a in assignments:
            here, station = _where(a), (a.vehicle.station.lat, a.vehicle.station.lon)
            home_m = distance_m(here, station) if here is not None else 0.0
            if home_m > 30:
                away.append((a, home_m))
        if away:
            farthest, remaining = max(away, key=lambda item: item[1])
            speed = _speed(farthest)
            label = "flying home"
            detail = ", ".join(f"{a.vehicle.name} {d:,.0f} m from its station" for a, d in away)
    eta = remaining / speed if remaining is not None else None
    return {
        "label": label,
        "detail": detail,
        "remaining_m": round(remaining) if remaining is not None else None,
        "eta_s": round(eta) if eta is not None else None,
    }


def vehicle_doing(assignment: Assignment, mission: Mission) -> str:
    """What a vehicle of the mission is doing, in words: its status while it works the
    mission, "flying home, 895 m from Costa Nova station" once its part is done (the
    agent may call itself idle on its way back), "home" once there."""
    v = assignment.vehicle
    if v.status == v.Status.OFFLINE:
        return "offline"
    working = assignment.active and mission.state in WORKING
    if working:
        return v.get_status_display()
    station = (v.station.lat, v.station.lon)
    here = _where(assignment)
    away_m = distance_m(here, station) if here is not None else 0.0
    flying = v.alt is not None and v.alt > 1.0
    if away_m > 30 or flying:
        return f"flying home, {away_m:,.0f} m from {v.station.name}"
    return "home"


def mission_headline(mission: Mission, phase: dict[str, Any], search_name: str | None) -> str:
    """The mission's banner: its status, but while the search drone flies it, what the
    phase says (on its way, searching), so the banner and "Now" never disagree."""
    if (
        mission.state == Mission.State.SEARCHING
        and search_name
        and phase.get("label")
        in (
            "on the way to the search area",
            "searching",
        )
    ):
        return f"{search_name} is {phase['label']}"
    return mission.status_text


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
                "doing": vehicle_doing(a, mission),
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
        "native_mission_refused",
        "native_mission_started",
        "payload_released",
        "vehicle_released",
        "state",
    )
    timeline = [
        {"seq": e.seq, "at": e.created_at.isoformat(), "kind": e.kind, "data": e.data}
        for e in session.events.filter(kind__in=shown).order_by("seq")
    ]
    phase = mission_phase(mission, assignments)
    search = next((a.vehicle.name for a in assignments if a.active and a.role == SEARCH), None)
    return {
        "session": {"id": str(session.pk), "state": session.state, "reason": session.reason},
        "state": mission.state,
        "state_label": Mission.State(mission.state).label,
        "final": mission.state in FINAL_MISSION,
        "working": mission.state in WORKING,
        "status": mission_headline(mission, phase, search),
        "area": mission.area,
        "path": mission.path,
        "progress": mission.progress,
        "altitude_m": mission.altitude_m,
        "spacing_m": mission.spacing_m,
        "detection": mission.detection,
        "released": mission.released_at is not None,
        "vehicles": vehicles,
        "phase": phase,
        "timeline": timeline,
    }
