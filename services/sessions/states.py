"""The session state machine.

    requested ──► assigned ──► active ──► ended
        │  │         │           │
        │  └─────────┴───────────┴──► failed / aborted
        └──────────────────────────► ended (withdrawn before any vehicle was sent)

Every change is logged with its reason; ended, failed and aborted are final and
always carry a reason. A user may end their session in any live state: a request
still waiting for a vehicle (an autonomous kind's workflow finds one after the
request) is withdrawn, and nothing was sent to any vehicle.
"""

from __future__ import annotations

from typing import Any

from django.db import transaction
from django.utils import timezone

from fleet.feed import fleet_notify
from fleet.models import Vehicle
from services.models import Assignment, Session, SessionEvent
from services.sessions.log import event_append
from services.sessions.video import session_video_end_schedule

S = Session.State
TRANSITIONS: dict[str, set[str]] = {
    S.REQUESTED: {S.ASSIGNED, S.ENDED, S.FAILED, S.ABORTED},
    S.ASSIGNED: {S.ACTIVE, S.ENDED, S.FAILED, S.ABORTED},
    S.ACTIVE: {S.ENDED, S.FAILED, S.ABORTED},
    S.ENDED: set(),
    S.FAILED: set(),
    S.ABORTED: set(),
}
FINAL = {S.ENDED, S.FAILED, S.ABORTED}
TIMESTAMP: dict[str, str] = {S.ASSIGNED: "assigned_at", S.ACTIVE: "started_at"}


class SessionStateError(Exception):
    """A transition the state machine does not allow."""


def session_transition(
    *, session: Session, to: str, reason: str = "", data: dict[str, Any] | None = None
) -> Session:
    """Move ``session`` to state ``to`` and log it; releases vehicles on a final state.

    Raises SessionStateError for a transition not in TRANSITIONS, or a final state
    without a reason. Returns the updated session.
    """
    if to in FINAL and not reason:
        raise SessionStateError(f"a session cannot become {to} without a reason")
    with transaction.atomic():
        locked = Session.objects.select_for_update(no_key=True).get(pk=session.pk)
        session_transition_locked(session=locked, to=to, reason=reason, data=data)
    # What the locked read and the update left: the row as it is now, without reading
    # it again.
    for column in Session._meta.concrete_fields:
        setattr(session, column.attname, getattr(locked, column.attname))
    return session


def session_transition_locked(
    *,
    session: Session,
    to: str,
    reason: str = "",
    data: dict[str, Any] | None = None,
    free_vehicles: bool = True,
    log: list[SessionEvent] | None = None,
) -> list[Any]:
    """:func:`session_transition` for a caller that holds ``session``'s row (locked in
    its transaction, or created there) and read it: nothing is read again, and no
    savepoint is made. ``session`` is updated in place. On a final state its active
    assignments end (see :func:`assignments_release`); with ``free_vehicles`` their
    vehicles become idle again, else the caller settles them (see
    services.sessions.ending.vehicle_release). ``log``: the session's whole log, read under
    the lock (services.sessions.log.event_append).

    Returns the ids of the vehicles released. Raises SessionStateError, before any
    write, as :func:`session_transition`.
    """
    if to in FINAL and not reason:
        raise SessionStateError(f"a session cannot become {to} without a reason")
    if to not in TRANSITIONS[session.state]:
        raise SessionStateError(f"session {session.pk} cannot go from {session.state} to {to}")
    previous = session.state
    session.state = to
    session.reason = reason[:300]
    now = timezone.now()
    fields = ["state", "reason"]
    if to in TIMESTAMP:
        setattr(session, TIMESTAMP[to], now)
        fields.append(TIMESTAMP[to])
    released: list[Any] = []
    if to in FINAL:
        session.ended_at = now
        fields.append("ended_at")
        released = assignments_release(session=session, free_vehicles=free_vehicles)
        # The SFU's room closes and its recording is converted and chained into the
        # log (nothing without an SFU).
        session_video_end_schedule(session_id=session.pk)
    # A session not written yet (services.sessions.matching.session_record's ``write``) is
    # written with its changes.
    if not session._state.adding:
        session.save(update_fields=fields)
    event_append(
        session=session,
        kind="state",
        data={"from": previous, "to": to, "reason": reason, **(data or {})},
        locked=True,
        log=log,
    )
    return released


def assignments_release(*, session: Session, free_vehicles: bool = True) -> list[Any]:
    """End ``session``'s active assignments; with ``free_vehicles``, vehicles still
    reserved or in service become idle again. Returns the released vehicle ids.

    Reads all the session's assignments (locked), with their vehicles, and leaves them
    on ``session.known_assignments`` as they are once released."""
    # No savepoint: nothing is caught in here; outside a transaction it makes one.
    with transaction.atomic(savepoint=False):
        assignments = list(
            Assignment.objects.select_for_update(of=("self",))
            .select_related("vehicle")
            .filter(session_id=session.pk)
        )
        session.known_assignments = assignments
        active = [a for a in assignments if a.active]
        if not active:
            return []
        now = timezone.now()
        # Under the locks of all the session's assignments: the active ones are those
        # just read.
        Assignment.objects.filter(session_id=session.pk, active=True).update(
            active=False, released_at=now
        )
        for assignment in active:
            assignment.active, assignment.released_at = False, now
        ids = [a.vehicle_id for a in active]
        if free_vehicles:
            Vehicle.objects.filter(
                pk__in=ids, status__in=[Vehicle.Status.RESERVED, Vehicle.Status.IN_SERVICE]
            ).update(status=Vehicle.Status.IDLE)
            fleet_notify(ids)
    return ids
