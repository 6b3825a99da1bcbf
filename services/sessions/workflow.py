"""What every workflow of an autonomous service needs: its vehicles' trouble, their
release and replacement, tasks that never arrived, closing the session.

The kinds that run sessions by themselves (a search, a delivery) keep their
own state machines; these are the steps they share.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from django.conf import settings
from django.utils import timezone

from agents.protocol.messages import EndTask
from fleet.models import Vehicle
from services.models import Assignment, Session
from services.sessions.deployment import vehicle_task_deploy
from services.sessions.ending import session_end, vehicle_release
from services.sessions.log import event_append
from services.sessions.states import FINAL, SessionStateError, session_transition

log = logging.getLogger(__name__)

#: Why a vehicle left a workflow. One that went offline may come back and serve it
#: again; one that failed or ran low is not asked again for this session.
OFFLINE, LOW_BATTERY, FAILED = "offline", "low_battery", "failed"


@dataclass(frozen=True)
class Trouble:
    """Why a vehicle cannot go on: ``cause`` (one of the above) and words for people."""

    cause: str
    words: str


def workflow_state_set(
    row: Any, *, session: Session, state: str, text: str, log_kind: str, **data: Any
) -> bool:
    """Move a workflow's ``row`` (a model with ``state``, ``status_text`` and
    ``updated_at``) to ``state`` with ``text`` for people, and log it as ``log_kind``;
    nothing when nothing changes. Returns whether it changed."""
    if row.state == state and row.status_text == text:
        return False
    previous = row.state
    row.state = state
    row.status_text = text[:300]
    row.save(update_fields=["state", "status_text", "updated_at"])
    event_append(
        session=session,
        kind=log_kind,
        data={"from": previous, "to": state, "text": row.status_text, **data},
    )
    return True


def session_task_accepted(*, assignment: Assignment, reason: str) -> None:
    """A vehicle of an autonomous session accepted its task: an ``assigned`` session
    is under way (``active``); nothing once it moved on."""
    session = assignment.session
    if session.state == Session.State.ASSIGNED and assignment.active:
        with contextlib.suppress(SessionStateError):  # moved on meanwhile
            session_transition(session=session, to=Session.State.ACTIVE, reason=reason)


def vehicle_trouble(assignment: Assignment, *, watch_battery: bool = True) -> Trouble | None:
    """Why ``assignment``'s vehicle cannot go on with its role, or None.

    * offline: the platform lost it (its uplink closed, or the sweep found it silent)
      for longer than ``IOUV_MISSION_OFFLINE_GRACE_S``; late heartbeats alone, on a
      loaded platform, are no reason to call a vehicle back. Not while its autopilot
      flies the mission by itself (:func:`flying_by_itself_until`): a vehicle whose
      agent died flies on, and another sent to the same place would meet it there;
    * low battery: under ``IOUV_MISSION_LOW_BATTERY_PCT`` (when ``watch_battery``);
    * failed: its agent reported ``mission_failed``, or refused its task.
    """
    vehicle = Vehicle.objects.get(pk=assignment.vehicle_id)
    now = timezone.now()
    grace = timedelta(seconds=settings.IOUV_MISSION_OFFLINE_GRACE_S)
    if vehicle.status == Vehicle.Status.OFFLINE:
        seen = vehicle.last_seen or assignment.created_at
        flying = flying_by_itself_until(assignment, silent_since=seen)
        if now - seen > grace and (flying is None or now >= flying):
            return Trouble(OFFLINE, f"{vehicle.name} went offline")
    if (
        watch_battery
        and vehicle.battery is not None
        and vehicle.battery < settings.IOUV_MISSION_LOW_BATTERY_PCT
    ):
        return Trouble(LOW_BATTERY, f"{vehicle.name} is low on battery ({vehicle.battery:.0f} %)")
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
        return Trouble(FAILED, f"{vehicle.name} could not go on: {reason}")
    return None


def flying_by_itself_until(assignment: Assignment, *, silent_since: datetime) -> datetime | None:
    """Until when ``assignment``'s vehicle, silent since ``silent_since``, may still be
    flying its mission on its own autopilot: its agent said it handed the plan over
    (``native_mission_started``, which it may take ``within_s`` to fly) and has reported
    no end of it since (``mission_failed``). Never more than
    ``IOUV_MISSION_FLYING_ALONE_MAX_S`` after it went silent (agents are authenticated,
    not trusted; a vehicle lost for good is replaced after that). None when it flies
    none, or that setting is 0."""
    cap = settings.IOUV_MISSION_FLYING_ALONE_MAX_S
    if cap <= 0:
        return None
    vehicle = str(assignment.vehicle_id)
    events = assignment.session.events.filter(
        data__vehicle=vehicle, created_at__gte=assignment.created_at
    )
    started = events.filter(kind="native_mission_started").order_by("-seq").first()
    if started is None:
        return None
    within = started.data.get("within_s") if isinstance(started.data, dict) else None
    if not isinstance(within, int | float) or isinstance(within, bool) or within <= 0:
        return None
    if events.filter(kind="mission_failed", seq__gt=started.seq).exists():
        return None
    return min(
        started.created_at + timedelta(seconds=float(within)),
        silent_since + timedelta(seconds=cap),
    )


def vehicles_unfit(session: Session, *, role: str | None = None) -> list[Any]:
    """Vehicles not to ask again in ``session`` (for ``role``): those released because
    they failed or ran low. One that only went offline is asked again once it is back
    and idle: a workflow must not wait for ever for a vehicle that is standing by."""
    released = session.events.filter(kind="vehicle_released")
    if role is not None:
        released = released.filter(data__role=role)
    return [
        e.data["vehicle"]
        for e in released
        if isinstance(e.data, dict) and e.data.get("cause") != OFFLINE and "vehicle" in e.data
    ]


def assignment_release(
    *,
    session: Session,
    assignment: Assignment,
    trouble: Trouble,
    data: dict[str, Any] | None = None,
) -> None:
    """Take ``assignment``'s vehicle off the session (it is told to end its task, and
    is free once it confirms) and log why (``vehicle_released``, with the cause)."""
    reason = f"replaced: {trouble.words}"
    Assignment.objects.filter(pk=assignment.pk).update(active=False, released_at=timezone.now())
    vehicle_release(
        vehicle_id=assignment.vehicle_id,
        session_id=session.pk,
        message=EndTask(session_id=str(session.pk), reason=reason[:120]),
    )
    event_append(
        session=session,
        kind="vehicle_released",
        data={
            "vehicle": str(assignment.vehicle_id),
            "vehicle_name": assignment.vehicle.name,
            "role": assignment.role,
            "reason": reason,
            "cause": trouble.cause,
            **(data or {}),
        },
    )


def task_redeploy_if_unaccepted(*, session: Session, assignment: Assignment) -> None:
    """Sign a fresh task for the vehicle if it has none yet, or has not accepted the
    last one by its deadline (the agent recognises the mission id and never repeats)."""
    events = session.events
    vehicle = str(assignment.vehicle_id)
    deployed = events.filter(kind="task_deployed", data__vehicle=vehicle).order_by("-seq").first()
    if deployed is None:
        vehicle_task_deploy(session=session, assignment=assignment)
        return
    if events.filter(kind="task_accepted", data__vehicle=vehicle, seq__gt=deployed.seq).exists():
        return
    if deployed.data.get("exp", 0) < timezone.now().timestamp():
        vehicle_task_deploy(session=session, assignment=assignment)


def session_close(*, session: Session, reason: str) -> None:
    """End the workflow's session with ``reason`` (its vehicles are told and released),
    or fail it if it never had one; nothing when it is already over."""
    if session.state in FINAL:
        return
    try:
        if session.state == Session.State.REQUESTED:
            session_transition(session=session, to=Session.State.FAILED, reason=reason)
        else:
            session_end(session=session, reason=reason, by_user=False)
    except SessionStateError:
        log.info("session %s: already closed", session.pk)
    session.refresh_from_db()


def steps_run(ids: Iterable[Any], step: Any, *, what: str) -> int:
    """Run ``step(id)`` for each id (a timer's pass); one that fails is logged and the
    others still run. Returns how many ran."""
    count = 0
    for pk in ids:
        count += 1
        try:
            step(pk)
        except Exception:
            log.exception("%s %s: step failed", what, pk)
    return count
