"""The rescue's state machine: one idempotent step at a time.

    waiting_search ──► searching ──► waiting_delivery ──► delivering ──► returning ──► completed
          ▲                │ vehicle lost / low battery / refused: its remaining
          └────────────────┘ lines go to another vehicle
    searching ──► timed_out / not_found;  any state ──► aborted / failed (with the session)

:func:`mission_advance` is the step: it locks the mission row, looks at the recorded
facts and does what the current state calls for. Steps decide from the database only,
everything they change is committed with the state that records it, and a step that
runs twice (a worker killed before its ack, a timer and an event together) finds the
work done. Celery runs them (``tasks``) with late acknowledgement, and a periodic timer
re-runs every unfinished mission, so a lost message delays a mission by one tick.

The session stays open while the vehicles fly home (``returning``: each is sent home
with a task of its own), so that its user watches the way back; it ends once they are
home (``completed``).
"""

from __future__ import annotations

import itertools
import logging
from typing import Any

from django.db import transaction
from django.utils import timezone

from agents.geo import distance_m
from fleet.models import Vehicle
from kinds.rescue_at_sea.conf import search_timeout_s
from kinds.rescue_at_sea.models import DELIVERY, FINAL_MISSION, SEARCH, Mission
from kinds.rescue_at_sea.notifications import mission_alert, notices_create
from kinds.rescue_at_sea.presentation import timeline
from services.kit import (
    FINAL,
    AssignmentError,
    assignment_release,
    event_append,
    role_assign,
    role_capable,
    session_close,
    session_transition,
    steps_run,
    task_redeploy_if_unaccepted,
    trip_m,
    vehicle_task_deploy,
    vehicle_trouble,
    vehicles_unfit,
    waiting_words,
    workflow_state_set,
)
from services.models import Assignment, ServiceRole, Session

log = logging.getLogger(__name__)

S = Mission.State
#: States the monitors' dashboard is warned of (once per mission each): the mission
#: waits for a vehicle, or gave up.
_ALERTED = frozenset({S.WAITING_SEARCH, S.WAITING_DELIVERY, S.TIMED_OUT, S.NOT_FOUND})
#: A vehicle this close to its station, on the ground, is home.
HOME_RADIUS_M = 30.0
#: After this long the mission stops waiting for its vehicles to land and completes.
RETURN_WAIT_S = 900


def mission_advance(session_id: Any) -> str | None:
    """Take the mission's next step, whatever its state; idempotent (see the module
    docstring). Returns the mission state after the step, None for no such mission."""
    with transaction.atomic():
        mission = (
            Mission.objects.select_for_update(no_key=True)
            .select_related("session__service", "session__user")
            .filter(pk=session_id)
            .first()
        )
        if mission is None:
            return None
        if mission.state not in FINAL_MISSION:
            _step(mission)
        state = mission.state
    return state


def _step(mission: Mission) -> None:
    session = Session.objects.select_for_update(no_key=True).get(pk=mission.session_id)
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
    changed = workflow_state_set(
        mission, session=mission.session, state=state, text=text, log_kind="mission_state", **data
    )
    if not changed:
        return
    if state in _ALERTED:
        mission_alert(mission, topic=f"mission_{state}", text=mission.status_text)


def _active(mission: Mission, role: str) -> Assignment | None:
    return (
        Assignment.objects.filter(session_id=mission.pk, role=role, active=True)
        .select_related("vehicle__station", "session")
        .first()
    )


def _timed_out(mission: Mission) -> bool:
    if mission.search_deadline is None or timezone.now() < mission.search_deadline:
        return False
    minutes = search_timeout_s() / 60
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
    tried = vehicles_unfit(mission.session, role=SEARCH)
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
        why = _waiting(mission, role, target, pattern_m, tried) or str(exc)
        _set(mission, S.WAITING_SEARCH, f"waiting for a search vehicle: {why}")
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


def _waiting(
    mission: Mission,
    role: ServiceRole,
    target: tuple[float, float],
    work_m: float,
    exclude: list[Any],
) -> str:
    """Why the mission waits for a vehicle for ``role`` that the fleet has (busy,
    offline, charging), with its place in the queue; "" when none of the fleet's
    could fly it (the matching's own words then say why)."""
    capable = role_capable(role, exclude=exclude)
    serving = [
        (drone, trip)
        for drone in capable.vehicles
        if drone.fits(trip := trip_m(drone, target, work_m))
    ]
    return waiting_words(session=mission.session, role=role, serving=serving)


def _supervise_search(mission: Mission) -> None:
    assignment = _active(mission, SEARCH)
    if mission.detection is not None:
        _set(mission, S.WAITING_DELIVERY, "person found: looking for a delivery vehicle")
        notices_create(mission)
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
    trouble = vehicle_trouble(assignment)
    if trouble:
        assignment_release(
            session=mission.session,
            assignment=assignment,
            trouble=trouble,
            data={"progress": mission.progress},
        )
        _set(mission, S.WAITING_SEARCH, f"{trouble.words}: handing its remaining lines to another")
        _assign_search(mission)
        return
    task_redeploy_if_unaccepted(session=mission.session, assignment=assignment)


def _assign_delivery(mission: Mission) -> None:
    if _active(mission, DELIVERY) is not None:
        _set(mission, S.DELIVERING, mission.status_text or "delivering the life jacket")
        return
    session = mission.session
    detection = mission.detection or {}
    target = (detection["lat"], detection["lon"])
    role = session.service.roles.get(name=DELIVERY)
    tried = vehicles_unfit(mission.session, role=DELIVERY)
    busy = Assignment.objects.filter(session_id=mission.pk, active=True).values_list(
        "vehicle_id", flat=True
    )
    try:
        with transaction.atomic():
            assignment = role_assign(
                session=session, role=role, target=target, exclude=[*tried, *busy]
            )
    except AssignmentError as exc:
        why = _waiting(mission, role, target, 0.0, [*tried, *busy]) or str(exc)
        _set(mission, S.WAITING_DELIVERY, f"person found; waiting for a delivery vehicle: {why}")
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
        _return_home(mission)
        return
    assignment = _active(mission, DELIVERY)
    if assignment is None:
        _set(mission, S.WAITING_DELIVERY, "looking for a delivery vehicle")
        _assign_delivery(mission)
        return
    # A delivery vehicle low on battery finishes the short trip it is on.
    trouble = vehicle_trouble(assignment, watch_battery=False)
    if trouble:
        assignment_release(
            session=mission.session,
            assignment=assignment,
            trouble=trouble,
            data={"progress": mission.progress},
        )
        _set(mission, S.WAITING_DELIVERY, f"{trouble.words}: looking for another delivery vehicle")
        _assign_delivery(mission)
        return
    task_redeploy_if_unaccepted(session=mission.session, assignment=assignment)


def _return_home(mission: Mission) -> None:
    """The life jacket is out: every vehicle still on the session is sent home with a
    task of its own (mission ``return``), the session staying open so that its user
    watches them fly back; it ends once they are home (:func:`_check_returned`)."""
    _set(mission, S.RETURNING, "life jacket delivered; the vehicles fly home")
    for assignment in Assignment.objects.filter(session_id=mission.pk, active=True).select_related(
        "vehicle__vehicle_type", "vehicle__station"
    ):
        vehicle_task_deploy(session=mission.session, assignment=assignment)


def _end(mission: Mission, state: str, text: str) -> None:
    """Close the session (every vehicle gets ``end_task`` and returns to its station,
    the service's fail-safe action) and move the mission to ``state``."""
    session_close(session=mission.session, reason=text)
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
    session_close(session=mission.session, reason=text)
    _set(mission, S.COMPLETED, text, timeline=timeline(mission))


def missions_tick() -> int:
    """One step for every unfinished mission (Celery beat): time-outs, waiting for a
    vehicle, vehicles gone quiet, lost messages. Returns how many ran."""
    ids = Mission.objects.exclude(state__in=FINAL_MISSION).values_list("pk", flat=True)
    return steps_run(list(ids), mission_advance, what="mission")
