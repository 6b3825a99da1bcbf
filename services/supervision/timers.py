"""The supervisor's periodic rules (Celery beat, services.tasks): sessions whose controller
is gone past the grace, that nobody joined, whose vehicle is lost, whose task was never
delivered, or that ran past their time limit. Their state is the session log, so a
restarted worker loses nothing and running one twice changes nothing.
"""

from __future__ import annotations

from collections.abc import Iterable
from datetime import datetime, timedelta
from typing import Any

from django.conf import settings
from django.utils import timezone

from agents.protocol import CLOCK_SKEW_S
from fleet.models import Vehicle
from fleet.servers import vehicles_silence
from services.kinds import kinds_user_driven
from services.models import Assignment, Session, SessionEvent
from services.sessions.deployment import LIVE
from services.sessions.ending import session_end, session_fail, session_revoke
from services.sessions.states import SessionStateError
from services.supervision.situation import (
    CONTROLLER_GONE,
    REASON_MAX,
    controller_gone,
    failsafe_words,
)


def _gone_reason(event: SessionEvent) -> str:
    data = event.data if isinstance(event.data, dict) else {}
    grace = settings.IOUV_RECONNECT_GRACE_S
    if event.kind == "unintentional_end":
        return f"{failsafe_words(data)}; nobody took control again within {grace:g} s"
    if event.kind == "control_released":
        return f"the user released control and did not take it back within {grace:g} s"
    return f"the user left and did not come back within {grace:g} s"


def sessions_expire_grace(
    *, now: datetime | None = None, session_ids: Iterable[Any] | None = None
) -> list[str]:
    """End the live sessions whose controller has been gone for more than
    ``IOUV_RECONNECT_GRACE_S``: after a fail-safe or the controller leaving, no
    controller connected again and no link recovered on the open socket since.

    The reason says what happened, in words (services.sessions.selectors.failsafe_sentence:
    "the driver's link to the vehicle was lost, so quad-1 will ...; nobody took control
    again within 30 s"), or that the user left. ``session_ids`` limits the check. Returns the
    ids of the sessions ended.
    """
    now = now or timezone.now()
    cutoff = now - timedelta(seconds=settings.IOUV_RECONNECT_GRACE_S)
    candidates = Session.objects.filter(
        state__in=LIVE,
        events__kind__in=sorted(CONTROLLER_GONE),
        events__created_at__lte=cutoff,
    ).distinct()
    if session_ids is not None:
        candidates = candidates.filter(pk__in=list(session_ids))
    ended: list[str] = []
    for session in candidates:
        gone = controller_gone(session)
        if gone is None or gone.created_at > cutoff:
            continue  # someone controls it, or the grace is still running
        try:
            session_end(session=session, reason=_gone_reason(gone)[:REASON_MAX], by_user=False)
        except SessionStateError:
            continue  # ended meanwhile
        ended.append(str(session.pk))
    return ended


def sessions_expire_unconnected(*, now: datetime | None = None) -> list[str]:
    """End the sessions of services driven by a user (synchronous) that were assigned
    more than ``IOUV_CONNECT_TIMEOUT_S`` ago and that no controller ever connected to:
    a user who asked and went away must not hold a vehicle. Returns their ids."""
    now = now or timezone.now()
    limit = settings.IOUV_CONNECT_TIMEOUT_S
    cutoff = now - timedelta(seconds=limit)
    ended: list[str] = []
    stale = Session.objects.filter(
        state=Session.State.ASSIGNED,
        service__kind__in=kinds_user_driven(),
        assigned_at__lte=cutoff,
    )
    for session in stale:
        try:
            session_end(
                session=session,
                reason=f"nobody connected to the vehicle within {limit:g} s",
                by_user=False,
            )
        except SessionStateError:
            continue
        ended.append(str(session.pk))
    return ended


def sessions_end_vehicle_lost(*, now: datetime | None = None) -> list[str]:
    """End the live sessions of services driven by a user whose vehicle has been
    offline for more than ``IOUV_VEHICLE_LOST_S`` (its agent stopped, or its uplink
    is down): the platform can no longer supervise them.

    The vehicle is not freed: it stays offline until its agent reconnects and says
    what it is doing, and is then told the session is over (fleet.outbox). Asynchronous
    workflows replace their lost vehicles themselves. Returns the ids ended.
    """
    now = now or timezone.now()
    lost_s = settings.IOUV_VEHICLE_LOST_S
    offline = list(
        Assignment.objects.filter(
            active=True,
            session__state__in=LIVE,
            session__service__kind__in=kinds_user_driven(),
            vehicle__status=Vehicle.Status.OFFLINE,
        ).select_related("session", "vehicle")
    )
    # Silence the platform caused (its process holding the uplink gone) does not count.
    silence = vehicles_silence(
        ((a.vehicle_id, a.vehicle.last_seen, a.vehicle.uplink_server) for a in offline), now
    )
    ended: list[str] = []
    for assignment in offline:
        silent_s = silence[assignment.vehicle_id]
        if str(assignment.session_id) in ended or (silent_s is not None and silent_s <= lost_s):
            continue
        reason = (
            f"vehicle {assignment.vehicle.name} went offline (no word from it for {lost_s:g} s)"
        )
        try:
            session_end(session=assignment.session, reason=reason, by_user=False)
        except SessionStateError:
            continue
        ended.append(str(assignment.session_id))
    return ended


def sessions_expire_undelivered(*, now: datetime | None = None) -> list[str]:
    """Fail the ``assigned`` sessions with a vehicle that neither accepted its latest
    task before that task's deadline (``exp`` plus the protocol's clock skew) nor
    refused it in a way the platform could attribute (an agent that cannot read a task
    refuses with a null session id). Their vehicles would otherwise stay reserved.

    Returns the ids of the sessions failed.
    """
    now = now or timezone.now()
    late = now.timestamp() - CLOCK_SKEW_S
    failed: list[str] = []
    assigned = Session.objects.filter(
        state=Session.State.ASSIGNED, events__kind="task_deployed"
    ).distinct()
    for session in assigned:
        for assignment in session.assignments.filter(active=True).select_related("vehicle"):
            vehicle = str(assignment.vehicle_id)
            deployed = (
                session.events.filter(kind="task_deployed", data__vehicle=vehicle)
                .order_by("-seq")
                .first()
            )
            if deployed is None or deployed.data.get("exp", late) >= late:
                continue
            if session.events.filter(
                kind="task_accepted", data__vehicle=vehicle, seq__gt=deployed.seq
            ).exists():
                continue
            reason = f"vehicle {assignment.vehicle.name} did not accept its task in time"
            try:
                session_fail(session=session, reason=reason)
            except SessionStateError:
                break
            failed.append(str(session.pk))
            break
    return failed


def sessions_expire_time_limit(*, now: datetime | None = None) -> list[str]:
    """Revoke the active sessions that ran past their service's ``session_time_limit_s``
    (counted from activation), with reason ``time limit reached`` and the service's
    fail-safe action. Returns the ids of the sessions revoked.
    """
    now = now or timezone.now()
    revoked: list[str] = []
    active = Session.objects.filter(
        state=Session.State.ACTIVE,
        service__session_time_limit_s__isnull=False,
        started_at__isnull=False,
    ).select_related("service")
    for session in active:
        started, limit_s = session.started_at, session.service.session_time_limit_s
        if started is None or limit_s is None:  # the query leaves these out
            continue
        deadline = started + timedelta(seconds=limit_s)
        if deadline > now:
            continue
        try:
            session_revoke(
                session=session,
                reason="time limit reached",
                action=session.service.failsafe_action,
            )
        except SessionStateError:
            continue
        revoked.append(str(session.pk))
    return revoked
