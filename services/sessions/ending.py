"""Ending sessions: by their user, by a monitor's stop (revoke), by a failure, or by a
workflow; and releasing their vehicles. The agents are told (an ``end_task`` or a
``revoke``, owed until acknowledged); a task that never left is withdrawn instead, and
its vehicle freed at once.
"""

from __future__ import annotations

from typing import Any

from django.db import transaction

from agents.protocol import FAILSAFE_ACTIONS
from agents.protocol.messages import EndTask, Revoke, message_to_dict, message_type
from fleet.feed import fleet_notify
from fleet.models import AgentMessage, Vehicle
from fleet.sending import vehicle_send
from services.models import Session
from services.sessions.log import session_log
from services.sessions.selectors import delivery_entry
from services.sessions.states import session_transition_locked

_HELD = [
    Vehicle.Status.RESERVED,
    Vehicle.Status.IN_SERVICE,
    Vehicle.Status.FAILSAFE,
    Vehicle.Status.IDLE,
]


def vehicle_release(*, vehicle_id: Any, session_id: Any, message: EndTask | Revoke) -> bool:
    """Make the vehicle give up ``session_id``: its agent is told ``message`` (an
    ``end_task`` or a ``revoke``) reliably, and the vehicle is ``releasing`` until the
    agent confirms (fleet.outbox), so no one else is given a vehicle still busy with
    this session. A vehicle whose agent never got the session's task has nothing to
    give up: its undelivered task is withdrawn and it is free at once.

    Call it in the transaction that ends the vehicle's role. Returns True when the
    agent has to confirm, False when the vehicle was freed at once.
    """
    sent = _task_withdraw(vehicle_id=vehicle_id, session_id=session_id)
    vehicle = Vehicle.objects.filter(pk=vehicle_id, maintenance=False)
    if not sent:
        # A vehicle the supervisor marked fail-safe is freed too: if its agent still is
        # in fail-safe, its next heartbeat says so and marks it again.
        changed = vehicle.filter(status__in=_HELD[:3]).update(status=Vehicle.Status.IDLE)
    else:
        vehicle_send(vehicle_id=vehicle_id, message=message)
        # An offline vehicle stays offline: it is told when it reconnects.
        changed = vehicle.filter(status__in=_HELD).update(status=Vehicle.Status.RELEASING)
    if changed:
        fleet_notify([vehicle_id])
    return sent


def _task_withdraw(*, vehicle_id: Any, session_id: Any) -> bool:
    """Withdraw the session's tasks still owed to the vehicle; True when one was ever
    put on its uplink (its agent may have it).

    The rows are locked first, as fleet.outbox takes them to send: a task being sent
    right now is waited for, then counted as sent; one not yet taken is withdrawn and
    the outbox skips it. One read for both questions (what to withdraw, and whether the
    agent may have it); an update only when something is withdrawn.
    """
    tasks = list(
        AgentMessage.objects.select_for_update()
        .filter(vehicle_id=vehicle_id, session_id=session_id, kind=AgentMessage.Kind.TASK)
        .values_list("pk", "state", "attempts")
    )
    pending = [pk for pk, state, _ in tasks if state == AgentMessage.State.PENDING]
    if pending:
        AgentMessage.objects.filter(pk__in=pending).update(state=AgentMessage.State.CANCELLED)
    return any(attempts > 0 for _, _, attempts in tasks)


def _close(
    *,
    session: Session,
    to: str,
    reason: str,
    message: EndTask | Revoke,
    data: dict[str, Any],
    locked: bool = False,
) -> Session:
    """Move ``session`` to the final state ``to`` and release its vehicles with
    ``message``; ``locked``: the caller read ``session`` locked in its transaction (a
    refusal then spoils that transaction: no savepoint is made). The session is left
    with its assignments and its whole log as this transaction leaves them
    (``known_assignments``, ``known_events``)."""
    with transaction.atomic(savepoint=not locked):
        row = (
            session if locked else Session.objects.select_for_update(no_key=True).get(pk=session.pk)
        )
        # The whole log rather than its tail: the answer shows it.
        log = session_log(session=row)
        # The transition validates the move first: nothing is sent for a refused one.
        # The vehicles it takes off the session are settled below, once each.
        released = session_transition_locked(
            session=row, to=to, reason=reason, data=data, free_vehicles=False, log=log
        )
        vehicles = {a.vehicle_id: a.vehicle for a in row.known_assignments or []}
        delivery = []
        for vehicle_id in released:
            if vehicle_release(vehicle_id=vehicle_id, session_id=row.pk, message=message):
                # Owed, not yet confirmed: as session_delivery words it, from the
                # vehicle as read before the release (offline stays offline).
                delivery.append(
                    delivery_entry(
                        vehicle=vehicles[vehicle_id],
                        kind=message_type(message),
                        message=message_to_dict(message),
                    )
                )
    if row is not session:
        # The row as the locked read and the update left it (the caller's instance
        # keeps its related service and user).
        for column in Session._meta.concrete_fields:
            setattr(session, column.attname, getattr(row, column.attname))
        session.known_assignments = row.known_assignments
    session.known_events = log
    session.known_delivery = delivery
    return session


def session_end(*, session: Session, reason: str, by_user: bool, locked: bool = False) -> Session:
    """End ``session`` on purpose: its agents get ``end_task`` and its vehicles are
    released (see :func:`vehicle_release`). ``by_user`` records whether the user asked
    (else the platform did). ``locked``: the caller read ``session`` locked, in the
    transaction this joins (see :func:`_close`).

    Raises services.sessions.states.SessionStateError when the session cannot end (already
    final) or ``reason`` is empty.
    """
    return _close(
        session=session,
        to=Session.State.ENDED,
        reason=reason,
        message=EndTask(session_id=str(session.pk), reason=reason),
        data={"by_user": by_user},
        locked=locked,
    )


#: Why a session ended when its user ended it: the same words on the page and through
#: the API. A request still waiting for a vehicle is withdrawn: nothing went out.
WITHDRAWN = "withdrawn by the user while it waited for a vehicle; no vehicle was sent"


ENDED_BY_USER = "ended by the user"


def session_end_by_user(*, session: Session, reason: str = "", locked: bool = False) -> Session:
    """The user ends their own ``session``, in any live state (the portal's button and
    the API's ``end`` both come here): one still waiting for a vehicle is withdrawn
    (:data:`WITHDRAWN`), one under way ends (:data:`ENDED_BY_USER`, or ``reason`` if
    given) and its vehicles perform the end as :func:`session_end` says. ``locked``: as
    :func:`session_end`.

    Raises services.sessions.states.SessionStateError when the session is already over.
    """
    if not reason:
        waiting = session.state == Session.State.REQUESTED
        reason = WITHDRAWN if waiting else ENDED_BY_USER
    return session_end(session=session, reason=reason, by_user=True, locked=locked)


def session_ended_words(session: Session) -> str:
    """What the user is told once :func:`session_end_by_user` ended ``session``."""
    if session.reason == WITHDRAWN:
        return (
            f"{session.service.name}: your request was withdrawn while it waited for a "
            "vehicle; no vehicle had been sent."
        )
    return f"{session.service.name}: session ended ({session.reason})."


def session_revoke(*, session: Session, reason: str, action: str) -> Session:
    """Stop ``session`` now (a supervisor rule or a monitor's kill switch): its agents
    get ``revoke`` and perform ``action`` (stop, land or return_to_home); the session is
    aborted with ``reason`` and its vehicles are released once their agents confirm
    (see :func:`vehicle_release`; :func:`services.sessions.selectors.session_delivery` says
    whether the revoke has reached each vehicle).

    Raises SessionStateError as :func:`session_end`; ValueError for an unknown action.
    """
    if action not in FAILSAFE_ACTIONS:
        raise ValueError(f"action must be one of {sorted(FAILSAFE_ACTIONS)}, not {action!r}")
    return _close(
        session=session,
        to=Session.State.ABORTED,
        reason=reason,
        message=Revoke(session_id=str(session.pk), reason=reason, action=action),  # type: ignore[arg-type]
        data={"action": action},
    )


def session_fail(*, session: Session, reason: str) -> Session:
    """Fail ``session`` (e.g. a vehicle refused its task): agents that did accept a
    task get ``end_task``; the vehicles are released. Raises SessionStateError as
    :func:`session_end`."""
    return _close(
        session=session,
        to=Session.State.FAILED,
        reason=reason,
        message=EndTask(session_id=str(session.pk), reason=reason),
        data={},
    )
