"""Person rescue at sea: the platform task of an asynchronous, multi-vehicle service.

The user draws the search area; :func:`rescue_request` plans a lawnmower path over it
(services.coverage) and opens the session. From then on the mission is an event-driven
state machine kept in the database (``Mission``)::

    waiting_search ──► searching ──► waiting_delivery ──► delivering ──► returning ──► completed
          ▲                │ vehicle lost / low battery / refused: its remaining
          └────────────────┘ lines go to another vehicle
    searching ──► timed_out / not_found;  any state ──► aborted / failed (with the session)

Agents report facts (``mission_progress``, ``person_detected``, ``search_complete``,
``payload_released``, ``mission_failed``); :func:`mission_event` records them and
schedules a step. :func:`mission_advance` is the step: it locks the mission row, looks
at the recorded facts and does what the current state calls for. Steps are idempotent:
they decide from the database only, everything they change is committed with the state
that records it, and a step that runs twice (a worker killed before its ack, a timer
and an event together) finds the work done. Celery runs them (services.tasks) with late
acknowledgement, and a periodic timer re-runs every unfinished mission, so a lost
message delays a mission by one tick at most.

Side effects outside the database are at-least-once and deduplicated: a vehicle task
carries a mission id the agent recognises (a re-sent task never restarts or repeats a
mission, a released payload is never released again); each rescue-team notice is one
row per channel, sent until it succeeds, with a stable ``Idempotency-Key`` header
(webhook) or ``Message-ID`` (email).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import urllib.error
import urllib.request
from datetime import timedelta
from typing import Any

from django.conf import settings
from django.contrib.auth.models import AbstractBaseUser
from django.core.mail import EmailMessage
from django.db import transaction
from django.db.models import F, Q
from django.utils import timezone

from agents.geo import distance_m
from fleet.models import Station, Vehicle
from services.assignment import AssignmentError, role_assign, session_open
from services.coverage import (
    DEFAULT_HFOV_DEG,
    area_centroid,
    area_clean,
    coverage_plan,
    point_in_area,
)
from services.deployment import session_end, vehicle_release, vehicle_task_deploy
from services.eventlog import event_append
from services.grants import user_can_use
from services.models import Assignment, Mission, MissionNotification, Service, Session
from services.sessions import FINAL, SessionStateError, session_transition

log = logging.getLogger(__name__)

WORKFLOW = "rescue_at_sea"
SEARCH = "search"
DELIVERY = "delivery"

#: Search altitude: high enough for a wide thermal footprint, low enough that a head
#: in the water still covers a few pixels (0.3 m per pixel at 40 m with 160 pixels).
DEFAULT_ALTITUDE_M = 40.0
MIN_ALTITUDE_M = 15.0
#: Search speed cap: faster smears the thermal image (about 9 frames per second).
SEARCH_SPEED_MPS = 10.0
DELIVERY_ALTITUDE_M = 25.0
DROP_ALTITUDE_M = 4.0
#: A detection below this confidence is not acted on by the agent.
MIN_CONFIDENCE = 0.6
#: A vehicle this close to its station, on the ground, is home.
HOME_RADIUS_M = 30.0
#: After this long the mission stops waiting for its vehicles to land and completes.
RETURN_WAIT_S = 900
NOTIFY_ATTEMPTS_MAX = 8

S = Mission.State
FINAL_MISSION = {S.COMPLETED, S.NOT_FOUND, S.TIMED_OUT, S.FAILED, S.ABORTED}
#: Mission states in which vehicles are still out working.
_WORKING = {S.WAITING_SEARCH, S.SEARCHING, S.WAITING_DELIVERY, S.DELIVERING}


class RescueError(Exception):
    """The rescue cannot be requested; the message says why. ``over_cap``: the user
    already holds as many live rescue sessions as the service allows."""

    def __init__(self, message: str, *, over_cap: bool = False) -> None:
        super().__init__(message)
        self.over_cap = over_cap


# --------------------------------------------------------------------------------------
# Request
# --------------------------------------------------------------------------------------


def rescue_request(
    *,
    user: AbstractBaseUser,
    service: Service,
    area: Any,
    altitude_m: float | None = None,
) -> Session:
    """Open a rescue session over ``area`` ([[lat, lon], ...]) and start its workflow.

    Raises RescueError when the service is not a rescue service, the user may not use
    it, or the area or altitude is unusable (nothing is recorded then).
    """
    if service.workflow != WORKFLOW:
        raise RescueError(f"{service.name!r} is not a rescue service")
    if not service.is_active or not user_can_use(user, service):
        raise RescueError(f"you may not use the service {service.name!r}")
    try:
        polygon = area_clean(area)
    except ValueError as exc:
        raise RescueError(str(exc)) from None
    ceiling = service.max_altitude_m or 120.0
    altitude = DEFAULT_ALTITUDE_M if altitude_m is None else float(altitude_m)
    if not MIN_ALTITUDE_M <= altitude <= ceiling:
        raise RescueError(f"the search altitude must be {MIN_ALTITUDE_M:g} to {ceiling:g} m")
    plan = coverage_plan(polygon, altitude_m=altitude, hfov_deg=DEFAULT_HFOV_DEG)
    center = area_centroid(polygon)
    with transaction.atomic():
        try:
            session = session_open(
                user=user,
                service=service,
                target=center,
                params={"area": [list(p) for p in polygon], "altitude_m": altitude},
            )
        except AssignmentError as exc:
            raise RescueError(str(exc), over_cap=exc.over_cap) from None
        mission = Mission.objects.create(
            session=session,
            area=[list(p) for p in polygon],
            altitude_m=altitude,
            speed_mps=SEARCH_SPEED_MPS,
            spacing_m=round(plan.spacing_m, 2),
            path=[list(p) for p in plan.waypoints],
            search_deadline=timezone.now()
            + timedelta(seconds=settings.IOUV_MISSION_SEARCH_TIMEOUT_S),
            status_text="looking for a search vehicle",
        )
        event_append(
            session=session,
            kind="mission_planned",
            data={
                "area_m2": round(plan.area_m2),
                "lines": plan.lines,
                "spacing_m": round(plan.spacing_m, 1),
                "footprint_m": round(plan.footprint_m, 1),
                "path_m": round(plan.length_m),
                "waypoints": len(plan.waypoints),
                "altitude_m": altitude,
            },
        )
        mission_schedule(mission.pk)
    return session


def mission_schedule(session_id: Any) -> None:
    """Run a step of the mission after the current transaction commits."""
    from services.tasks import mission_step  # the task module imports this one

    transaction.on_commit(lambda: mission_step.delay(str(session_id)))


# --------------------------------------------------------------------------------------
# Facts reported by agents (called by services.supervision)
# --------------------------------------------------------------------------------------

MISSION_EVENTS = frozenset(
    {"mission_progress", "person_detected", "search_complete", "payload_released", "mission_failed"}
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
    session = assignment.session
    if session.state == Session.State.ASSIGNED and assignment.active:
        with contextlib.suppress(SessionStateError):  # moved on meanwhile
            session_transition(
                session=session,
                to=Session.State.ACTIVE,
                reason=f"{assignment.vehicle.name} accepted its {assignment.role} task",
            )
    mission_schedule(session.pk)


# --------------------------------------------------------------------------------------
# The vehicle tasks' mission documents
# --------------------------------------------------------------------------------------


def vehicle_mission(*, assignment: Assignment) -> dict[str, Any] | None:
    """The ``mission`` signed into ``assignment``'s vehicle task, from the recorded
    state, so a re-sent task carries the same mission (and the same id) as the first.
    None when the session has no mission."""
    mission = Mission.objects.filter(pk=assignment.session_id).first()
    if mission is None:
        return None
    vehicle = assignment.vehicle
    top_speed = float(vehicle.attributes.get("max_speed_mps") or SEARCH_SPEED_MPS)
    # The id names the session, the role and this assignment: the agent keeps one
    # running mission per id and never repeats it.
    mission_id = f"{assignment.session_id}-{assignment.role}-{assignment.pk}"
    if assignment.role == SEARCH:
        start = _start_index(mission, assignment)
        return {
            "kind": "search",
            "id": mission_id,
            "altitude_m": mission.altitude_m,
            "speed_mps": min(top_speed, mission.speed_mps),
            "waypoints": mission.path,
            "start_index": start,
            "min_confidence": MIN_CONFIDENCE,
        }
    if assignment.role == DELIVERY and mission.detection is not None:
        return {
            "kind": "delivery",
            "id": mission_id,
            "target": [mission.detection["lat"], mission.detection["lon"]],
            "altitude_m": DELIVERY_ALTITUDE_M,
            "drop_altitude_m": DROP_ALTITUDE_M,
            "speed_mps": top_speed,
        }
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


# --------------------------------------------------------------------------------------
# The step
# --------------------------------------------------------------------------------------


def mission_advance(session_id: Any) -> str | None:
    """Take the mission's next step, whatever its state; idempotent (see the module
    docstring). Returns the mission state after the step, None for no such mission."""
    with transaction.atomic():
        mission = (
            Mission.objects.select_for_update()
            .select_related("session__service", "session__user")
            .filter(pk=session_id)
            .first()
        )
        if mission is None:
            return None
        if mission.state not in FINAL_MISSION:
            _step(mission)
        state = mission.state
    notifications_send(mission.pk)
    return state


def _step(mission: Mission) -> None:
    session = Session.objects.select_for_update().get(pk=mission.session_id)
    mission.session = session
    if session.state in FINAL and mission.state != S.RETURNING:
        # Ended from outside: a monitor's stop, a refused task, the time limit.
        failed = session.state == Session.State.FAILED
        to = S.FAILED if failed else S.ABORTED
        _set(mission, to, f"the session {session.state}: {session.reason}")
        return
    if mission.state == S.WAITING_SEARCH:
        _assign_search(mission)
    elif mission.state == S.SEARCHING:
        _supervise_search(mission)
    elif mission.state == S.WAITING_DELIVERY:
        _assign_delivery(mission)
    elif mission.state == S.DELIVERING:
        _supervise_delivery(mission)
    elif mission.state == S.RETURNING:
        _check_returned(mission)


def _set(mission: Mission, state: str, text: str, **data: Any) -> None:
    """Move the mission to ``state`` and log it (nothing when nothing changes)."""
    if mission.state == state and mission.status_text == text:
        return
    previous = mission.state
    mission.state = state
    mission.status_text = text[:300]
    mission.save(update_fields=["state", "status_text", "updated_at"])
    event_append(
        session=mission.session,
        kind="mission_state",
        data={"from": previous, "to": state, "text": mission.status_text, **data},
    )


def _active(mission: Mission, role: str) -> Assignment | None:
    return (
        Assignment.objects.filter(session_id=mission.pk, role=role, active=True)
        .select_related("vehicle__station", "session")
        .first()
    )


def _timed_out(mission: Mission) -> bool:
    if mission.search_deadline is None or timezone.now() < mission.search_deadline:
        return False
    minutes = settings.IOUV_MISSION_SEARCH_TIMEOUT_S / 60
    _end(mission, S.TIMED_OUT, f"search timed out after {minutes:g} min without finding the person")
    return True


def _assign_search(mission: Mission) -> None:
    if mission.detection is not None:
        _set(mission, S.WAITING_DELIVERY, "person found: looking for a delivery vehicle")
        _assign_delivery(mission)
        return
    if _timed_out(mission):
        return
    session = mission.session
    role = session.service.roles.get(name=SEARCH)
    start = max(mission.progress, 0)
    remaining = mission.path[start:]
    target = (remaining[0][0], remaining[0][1])
    pattern_m = sum(
        distance_m((a[0], a[1]), (b[0], b[1])) for a, b in itertools.pairwise(remaining)
    )
    tried = _unfit(mission, SEARCH)
    try:
        with transaction.atomic():
            assignment = role_assign(
                session=session,
                role=role,
                target=target,
                extra_distance_m=pattern_m,
                exclude=list(tried),
            )
    except AssignmentError as exc:
        _set(mission, S.WAITING_SEARCH, f"waiting for a search vehicle: {exc}")
        return
    if mission.progress < 0 and mission.search_legs == 0:
        # First vehicle: fly the pattern from the end nearest to it.
        here = assignment.vehicle.position
        if distance_m(here, tuple(mission.path[-1])) < distance_m(here, tuple(mission.path[0])):
            mission.path = list(reversed(mission.path))
            mission.save(update_fields=["path", "updated_at"])
    mission.search_legs += 1
    mission.save(update_fields=["search_legs", "updated_at"])
    event_append(
        session=session,
        kind="search_leg",
        data={
            "role": SEARCH,
            "vehicle": str(assignment.vehicle_id),
            "vehicle_name": assignment.vehicle.name,
            "start_index": start,
            "leg": mission.search_legs,
        },
    )
    if session.state == Session.State.REQUESTED:
        session_transition(
            session=session, to=Session.State.ASSIGNED, reason="search vehicle reserved"
        )
    vehicle_task_deploy(session=session, assignment=assignment)
    what = "searches" if start == 0 else f"continues the search from waypoint {start + 1}"
    _set(
        mission,
        S.SEARCHING,
        f"{assignment.vehicle.name} {what} ({len(mission.path)} waypoints)",
        vehicle=str(assignment.vehicle_id),
    )


#: Why a vehicle left a mission. One that went offline may come back and fly again; one
#: that failed or ran low is not asked again for this mission.
OFFLINE, LOW_BATTERY, FAILED = "offline", "low_battery", "failed"


def _vehicle_trouble(assignment: Assignment) -> tuple[str, str] | None:
    """Why this vehicle cannot go on with its role, as (cause, words), or None."""
    vehicle = Vehicle.objects.get(pk=assignment.vehicle_id)
    now = timezone.now()
    grace = timedelta(seconds=settings.IOUV_MISSION_OFFLINE_GRACE_S)
    # Offline means the platform lost it (its uplink closed, or the sweep found it
    # silent), for longer than the grace. Late heartbeats alone, on a loaded platform,
    # are no reason to call back a drone carrying a life jacket.
    if vehicle.status == Vehicle.Status.OFFLINE:
        seen = vehicle.last_seen or assignment.created_at
        if now - seen > grace:
            return OFFLINE, f"{vehicle.name} went offline"
    if (
        vehicle.battery is not None
        and vehicle.battery < settings.IOUV_MISSION_LOW_BATTERY_PCT
        and assignment.role == SEARCH
    ):
        return LOW_BATTERY, f"{vehicle.name} is low on battery ({vehicle.battery:.0f} %)"
    failed = (
        assignment.session.events.filter(
            kind__in=("mission_failed", "task_refused"),
            data__vehicle=str(vehicle.pk),
            created_at__gte=assignment.created_at,
        )
        .order_by("-seq")
        .first()
    )
    if failed is not None:
        reason = failed.data.get("reason", "no reason given")
        return FAILED, f"{vehicle.name} could not go on: {reason}"
    return None


def _unfit(mission: Mission, role: str) -> list[Any]:
    """Vehicles not to ask again for ``role``: released because they failed or ran low.
    One that only went offline is asked again once it is back and idle: a mission must
    not wait for ever for a vehicle that is standing by."""
    released = mission.session.events.filter(kind="vehicle_released", data__role=role)
    return [
        e.data["vehicle"]
        for e in released
        if isinstance(e.data, dict) and e.data.get("cause") != OFFLINE and "vehicle" in e.data
    ]


def _release(mission: Mission, assignment: Assignment, trouble: tuple[str, str]) -> None:
    """Take ``assignment``'s vehicle off the mission; it returns to its station."""
    cause, words = trouble
    reason = f"replaced: {words}"
    Assignment.objects.filter(pk=assignment.pk).update(active=False, released_at=timezone.now())
    vehicle_release(
        vehicle_id=assignment.vehicle_id,
        session_id=mission.pk,
        message={"type": "end_task", "session_id": str(mission.pk), "reason": reason[:120]},
    )
    event_append(
        session=mission.session,
        kind="vehicle_released",
        data={
            "vehicle": str(assignment.vehicle_id),
            "vehicle_name": assignment.vehicle.name,
            "role": assignment.role,
            "reason": reason,
            "cause": cause,
            "progress": mission.progress,
        },
    )


def _supervise_search(mission: Mission) -> None:
    assignment = _active(mission, SEARCH)
    if mission.detection is not None:
        _set(mission, S.WAITING_DELIVERY, "person found: looking for a delivery vehicle")
        _notices_create(mission)
        _assign_delivery(mission)
        return
    if assignment is None:
        _set(mission, S.WAITING_SEARCH, "looking for a search vehicle")
        _assign_search(mission)
        return
    if (
        mission.progress >= len(mission.path) - 1
        and mission.session.events.filter(
            kind="search_complete", data__vehicle=str(assignment.vehicle_id)
        ).exists()
    ):
        _end(mission, S.NOT_FOUND, "the whole area was searched without finding the person")
        return
    if _timed_out(mission):
        return
    trouble = _vehicle_trouble(assignment)
    if trouble:
        _release(mission, assignment, trouble)
        _set(mission, S.WAITING_SEARCH, f"{trouble[1]}: handing its remaining lines to another")
        _assign_search(mission)
        return
    _redeploy_if_unaccepted(mission, assignment)


def _assign_delivery(mission: Mission) -> None:
    if _active(mission, DELIVERY) is not None:
        _set(mission, S.DELIVERING, mission.status_text or "delivering the life jacket")
        return
    session = mission.session
    detection = mission.detection or {}
    target = (detection["lat"], detection["lon"])
    role = session.service.roles.get(name=DELIVERY)
    tried = _unfit(mission, DELIVERY)
    busy = Assignment.objects.filter(session_id=mission.pk, active=True).values_list(
        "vehicle_id", flat=True
    )
    try:
        with transaction.atomic():
            assignment = role_assign(
                session=session, role=role, target=target, exclude=[*tried, *busy]
            )
    except AssignmentError as exc:
        _set(mission, S.WAITING_DELIVERY, f"person found; waiting for a delivery vehicle: {exc}")
        return
    vehicle_task_deploy(session=session, assignment=assignment)
    _set(
        mission,
        S.DELIVERING,
        f"{assignment.vehicle.name} brings the life jacket ({assignment.distance_m:.0f} m away)",
        vehicle=str(assignment.vehicle_id),
    )


def _supervise_delivery(mission: Mission) -> None:
    if mission.released_at is not None:
        _end(mission, S.RETURNING, "life jacket delivered; vehicles returning to their stations")
        return
    assignment = _active(mission, DELIVERY)
    if assignment is None:
        _set(mission, S.WAITING_DELIVERY, "looking for a delivery vehicle")
        _assign_delivery(mission)
        return
    trouble = _vehicle_trouble(assignment)
    if trouble:
        _release(mission, assignment, trouble)
        _set(mission, S.WAITING_DELIVERY, f"{trouble[1]}: looking for another delivery vehicle")
        _assign_delivery(mission)
        return
    _redeploy_if_unaccepted(mission, assignment)


def _redeploy_if_unaccepted(mission: Mission, assignment: Assignment) -> None:
    """Send the task again if the vehicle has not accepted it by its deadline (the
    push may have been lost with a worker); the agent recognises the mission id."""
    events = mission.session.events
    vehicle = str(assignment.vehicle_id)
    deployed = events.filter(kind="task_deployed", data__vehicle=vehicle).order_by("-seq").first()
    if deployed is None:
        vehicle_task_deploy(session=mission.session, assignment=assignment)
        return
    if events.filter(kind="task_accepted", data__vehicle=vehicle, seq__gt=deployed.seq).exists():
        return
    if deployed.data.get("exp", 0) < timezone.now().timestamp():
        vehicle_task_deploy(session=mission.session, assignment=assignment)


def _end(mission: Mission, state: str, text: str) -> None:
    """Close the session (every vehicle gets ``end_task`` and returns to its station,
    the service's fail-safe action) and move the mission to ``state``."""
    session = mission.session
    if session.state not in FINAL:
        try:
            if session.state == Session.State.REQUESTED:
                session_transition(session=session, to=Session.State.FAILED, reason=text)
            else:
                session_end(session=session, reason=text, by_user=False)
        except SessionStateError:
            log.info("mission %s: session already closed", mission.pk)
        session.refresh_from_db()
    _set(mission, state, text)


def _check_returned(mission: Mission) -> None:
    """Complete the mission once every vehicle that flew it is home and on the ground."""
    ids = set(Assignment.objects.filter(session_id=mission.pk).values_list("vehicle_id", flat=True))
    away = []
    for vehicle in Vehicle.objects.filter(pk__in=ids).select_related("station"):
        home = (vehicle.station.lat, vehicle.station.lon)
        landed = vehicle.alt is None or vehicle.alt < 1.0
        near = vehicle.lat is None or distance_m(vehicle.position, home) <= HOME_RADIUS_M
        out = vehicle.status == Vehicle.Status.RETURNING or not (landed and near)
        if out and vehicle.status != Vehicle.Status.OFFLINE:
            away.append(vehicle.name)
    waited = (timezone.now() - mission.updated_at).total_seconds()
    if away and waited < RETURN_WAIT_S:
        return
    text = "mission completed: person found, life jacket delivered, vehicles home"
    if away:
        text = f"mission completed; not yet back: {', '.join(sorted(away))}"
    _set(mission, S.COMPLETED, text, timeline=_timeline(mission))


def _timeline(mission: Mission) -> dict[str, str]:
    """When each milestone happened (ISO times), for the mission's last log entry."""
    marks: dict[str, str] = {"requested": mission.session.created_at.isoformat()}
    for kind in ("person_detected", "payload_released"):
        first = mission.session.events.filter(kind=kind).order_by("seq").first()
        if first is not None:
            marks[kind] = first.created_at.isoformat()
    marks["completed"] = timezone.now().isoformat()
    return marks


# --------------------------------------------------------------------------------------
# The rescue team
# --------------------------------------------------------------------------------------


def _team_station(mission: Mission) -> Station | None:
    first = (
        Assignment.objects.filter(session_id=mission.pk, role=SEARCH)
        .select_related("vehicle__station")
        .order_by("created_at")
        .first()
    )
    return first.vehicle.station if first else None


def _notices_create(mission: Mission) -> None:
    """One notice per channel, created with the state that calls for it; existing
    ones are left alone (a step that runs twice pages nobody twice)."""
    detection = mission.detection or {}
    station = _team_station(mission)
    lat, lon = detection.get("lat"), detection.get("lon")
    confidence = detection.get("confidence")
    text = (
        f"Person in the water at {lat:.5f}, {lon:.5f}"
        + (f" (detection confidence {confidence:.2f})" if confidence is not None else "")
        + f", found by {detection.get('vehicle_name', 'a search drone')}. "
        "A life jacket is on its way."
    )
    payload = {
        "event": "person_in_water",
        "mission": str(mission.pk),
        "lat": lat,
        "lon": lon,
        "confidence": confidence,
        "detected_at": mission.detected_at.isoformat() if mission.detected_at else None,
        "station": station.name if station else None,
        "team": station.rescue_team_name if station else None,
        "message": text,
    }
    channels = [(MissionNotification.Channel.DASHBOARD, "monitors")]
    if station is not None and station.rescue_team_email:
        channels.append((MissionNotification.Channel.EMAIL, station.rescue_team_email))
    if station is not None and station.rescue_team_webhook:
        channels.append((MissionNotification.Channel.WEBHOOK, station.rescue_team_webhook))
    for channel, target in channels:
        MissionNotification.objects.get_or_create(
            mission=mission, channel=channel, defaults={"target": target, "payload": payload}
        )


def notifications_send(session_id: Any) -> int:
    """Send the mission's pending notices; returns how many were sent now.

    Each notice is claimed first with a conditional UPDATE (only one worker can win it,
    on any database) for a lease longer than one delivery attempt; the claim and the
    attempt count are committed before sending, so a worker killed while sending
    leaves a trace and, once the lease lapses, the notice is sent again with the same
    idempotency key. A failed attempt releases the claim for the timer's retry.
    """
    sent = 0
    pending = MissionNotification.objects.filter(
        mission_id=session_id, sent_at__isnull=True, attempts__lt=NOTIFY_ATTEMPTS_MAX
    ).values_list("pk", flat=True)
    lease = timedelta(seconds=2 * settings.IOUV_WEBHOOK_TIMEOUT_S + 5)
    for pk in list(pending):
        now = timezone.now()
        claimed = (
            MissionNotification.objects.filter(pk=pk, sent_at__isnull=True)
            .filter(Q(claimed_until__isnull=True) | Q(claimed_until__lt=now))
            .update(claimed_until=now + lease, attempts=F("attempts") + 1)
        )
        if not claimed:
            continue  # sent, or another worker is sending it right now
        notice = MissionNotification.objects.select_related("mission__session").get(pk=pk)
        try:
            _deliver(notice)
        except Exception as exc:
            log.warning("rescue notice %s (%s) failed: %s", notice.pk, notice.channel, exc)
            MissionNotification.objects.filter(pk=pk).update(
                last_error=str(exc)[:300], claimed_until=None
            )
            continue
        with transaction.atomic():
            MissionNotification.objects.filter(pk=pk).update(
                sent_at=timezone.now(), last_error="", claimed_until=None
            )
            event_append(
                session=notice.mission.session,
                kind="rescue_team_notified",
                data={
                    "channel": notice.channel,
                    "target": notice.target,
                    "message": notice.payload.get("message", ""),
                    "lat": notice.payload.get("lat"),
                    "lon": notice.payload.get("lon"),
                },
            )
        sent += 1
    return sent


def _idempotency_key(notice: MissionNotification) -> str:
    return f"iouv-rescue-{notice.mission_id}-{notice.channel}"


def _deliver(notice: MissionNotification) -> None:
    payload = notice.payload
    if notice.channel == MissionNotification.Channel.DASHBOARD:
        return  # the rescue_team_notified log entry reaches the monitors' dashboard
    if notice.channel == MissionNotification.Channel.EMAIL:
        message = EmailMessage(
            subject=f"[IoUV rescue] Person in the water at {payload['lat']:.5f}, "
            f"{payload['lon']:.5f}",
            body=payload["message"] + f"\n\nPosition: {payload['lat']:.6f}, {payload['lon']:.6f}\n"
            f"Mission: {payload['mission']}\n",
            to=[notice.target],
            headers={"Message-ID": f"<{_idempotency_key(notice)}@iouv>"},
        )
        message.send(fail_silently=False)
        return
    request = urllib.request.Request(
        notice.target,
        data=json.dumps(payload).encode(),
        headers={
            "Content-Type": "application/json",
            "Idempotency-Key": _idempotency_key(notice),
            "User-Agent": "IoUV-rescue/1",
        },
        method="POST",
    )
    try:
        with urllib.request.urlopen(request, timeout=settings.IOUV_WEBHOOK_TIMEOUT_S) as response:
            if not 200 <= response.status < 300:
                raise RuntimeError(f"webhook answered {response.status}")
    except urllib.error.HTTPError as exc:
        raise RuntimeError(f"webhook answered {exc.code}") from None


# --------------------------------------------------------------------------------------
# Timer
# --------------------------------------------------------------------------------------


def missions_tick() -> int:
    """One step for every unfinished mission (Celery beat): time-outs, waiting for a
    vehicle, vehicles gone quiet, lost pushes, notices to retry. Returns how many ran."""
    ids = list(Mission.objects.exclude(state__in=FINAL_MISSION).values_list("pk", flat=True))
    for pk in ids:
        try:
            mission_advance(pk)
        except Exception:  # one broken mission must not stop the others' timers
            log.exception("mission %s: step failed", pk)
    retry = MissionNotification.objects.filter(
        sent_at__isnull=True, attempts__lt=NOTIFY_ATTEMPTS_MAX
    ).values_list("mission_id", flat=True)
    for pk in set(retry) - set(ids):
        notifications_send(pk)
    return len(ids)


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
        "rescue_team_notified",
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
        "working": mission.state in _WORKING,
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
