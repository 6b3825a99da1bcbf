"""The session state machine.

    requested ──► assigned ──► active ──► ended
        │            │           │
        └────────────┴───────────┴──► failed / aborted

Every change is logged with its reason; ended, failed and aborted are final and
always carry a reason.
"""

from __future__ import annotations

from typing import Any

from django.db import transaction
from django.utils import timezone

from fleet.feed import fleet_notify
from fleet.models import Vehicle
from services.eventlog import event_append
from services.models import Assignment, Session

S = Session.State
TRANSITIONS: dict[str, set[str]] = {
    S.REQUESTED: {S.ASSIGNED, S.FAILED, S.ABORTED},
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
        locked = Session.objects.select_for_update().get(pk=session.pk)
        if to not in TRANSITIONS[locked.state]:
            raise SessionStateError(f"session {locked.pk} cannot go from {locked.state} to {to}")
        previous = locked.state
        locked.state = to
        locked.reason = reason[:300]
        now = timezone.now()
        fields = ["state", "reason"]
        if to in TIMESTAMP:
            setattr(locked, TIMESTAMP[to], now)
            fields.append(TIMESTAMP[to])
        if to in FINAL:
            locked.ended_at = now
            fields.append("ended_at")
            assignments_release(session=locked)
        locked.save(update_fields=fields)
        event_append(
            session=locked,
            kind="state",
            data={"from": previous, "to": to, "reason": reason, **(data or {})},
        )
    session.refresh_from_db()
    return session


def assignments_release(*, session: Session) -> list[Any]:
    """End ``session``'s active assignments; vehicles still reserved or in service become
    idle again. Returns the released vehicle ids."""
    with transaction.atomic():
        active = list(Assignment.objects.select_for_update().filter(session=session, active=True))
        ids = [a.vehicle_id for a in active]
        if not ids:
            return []
        Assignment.objects.filter(pk__in=[a.pk for a in active]).update(
            active=False, released_at=timezone.now()
        )
        Vehicle.objects.filter(
            pk__in=ids, status__in=[Vehicle.Status.RESERVED, Vehicle.Status.IN_SERVICE]
        ).update(status=Vehicle.Status.IDLE)
        fleet_notify(ids)
    return ids
