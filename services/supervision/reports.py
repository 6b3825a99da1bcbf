"""The platform task: supervising sessions from what their vehicles' agents report.

The uplink (``fleet.uplink``) tells what agents say to one listener
(``fleet.vehicle_events``); :class:`Supervisor` here (registered in ``services.apps``)
logs it in the session log and applies the rules:

* ``task_refused``: the session fails with the agent's reason.
* ``user_connected`` (a controller): an assigned session becomes active.
* more than ``IOUV_UNSAFE_REFUSALS_MAX`` commands refused for safety
  (:data:`UNSAFE_REFUSALS`) within ``IOUV_UNSAFE_REFUSALS_WINDOW_S``: revoked.
* ``failsafe``: the user's link dropped and the vehicle acted on its own. Logged at once
  as ``unintentional_end``; unless the controller reconnects within
  ``IOUV_RECONNECT_GRACE_S``, services.supervision.timers ends the session.

The rules that need no report (the grace, the time limit, a task never delivered, a
vehicle lost) run periodically: services.supervision.timers.

Agents are authenticated, not trusted: an agent may only report on sessions its
vehicle is (or was) assigned to; anything else is ignored with a warning.
"""

from __future__ import annotations

import contextlib
import logging
import uuid
from collections.abc import Iterable, Sequence
from datetime import UTC, datetime, timedelta
from typing import Any

from django.conf import settings
from django.db import transaction
from django.db.models import Subquery
from django.utils import timezone

from agents.protocol.messages import EndTask, Event, Revoke, TaskAccepted, TaskRefused
from fleet.feed import fleet_notify
from fleet.models import AgentMessage, Vehicle
from fleet.outbox import (
    ENDING,
    Acked,
    agent_messages_cancel,
    agent_messages_cancel_each,
    agent_messages_withdrawn,
    stored_message,
    vehicle_release_if_settled,
)
from fleet.sending import vehicle_send
from fleet.vehicle_events import AgentState, SessionMessage
from services.models import Assignment, Session, SessionEvent
from services.sessions.deployment import LIVE, vehicle_task_deploy
from services.sessions.ending import session_fail, session_revoke
from services.sessions.log import event_append, events_occurred_at
from services.sessions.signing import platform_jwks, platform_public_key_pem
from services.sessions.states import SessionStateError, session_transition
from services.supervision.situation import REASON_MAX, service_kind

log = logging.getLogger(__name__)

#: command_refused codes that mean the user tried something unsafe (agents/safety.py).
#: Not ``latency``: a movement refused because the round trip is over the service's
#: limit is the link's doing, not the user's. The vehicle already holds still then, and
#: a session revoked for it would end a user's session for a slow network, or for the
#: moments a platform restart slows the relay.
UNSAFE_REFUSALS = frozenset({"altitude_limit", "geofence", "obstacle", "unsafe"})

#: At most one link_quality event per session in this many seconds reaches the log.
LINK_QUALITY_EVERY_S = 10.0


def _assignment_for(*, vehicle_id: Any, session_id: Any) -> Assignment | None:
    """The vehicle's assignment in the session, active first; None (logged) if it has
    none, i.e. the agent talks about a session that is not its own or does not exist."""
    try:
        pk = uuid.UUID(str(session_id))
    except ValueError:
        log.warning("vehicle %s reported on a malformed session id %.40r", vehicle_id, session_id)
        return None
    assignment = (
        Assignment.objects.filter(session_id=pk, vehicle_id=vehicle_id)
        # The session and its service are what every report needs (its log, its kind);
        # the vehicle and the user are read when a message needs them (a refusal's
        # reason, some kinds' handlers). Joined too, they were most of a report's cost.
        .select_related("session__service")
        .order_by("-active", "-created_at")
        .first()
    )
    if assignment is None:
        if Session.objects.filter(pk=pk).exists():
            log.warning("vehicle %s reported on session %s it is not assigned to", vehicle_id, pk)
        else:
            log.warning("vehicle %s reported on unknown session %s", vehicle_id, pk)
    return assignment


def _serving(assignment: Assignment) -> bool:
    """The vehicle still holds its role in a session that is still going."""
    return assignment.active and assignment.session.state in LIVE


# --------------------------------------------------------------------------------------
# Agent messages
# --------------------------------------------------------------------------------------


def agent_message_handle(*, vehicle_id: Any, message: Any) -> None:
    """Log and act on one ``task_accepted``, ``task_refused`` or ``event`` message.

    ``message`` is the struct the uplink parsed (and so validated). Other types are
    not the supervisor's and are ignored.
    """
    if isinstance(message, TaskAccepted):
        _task_accepted(vehicle_id=vehicle_id, message=message)
    elif isinstance(message, TaskRefused):
        _task_refused(vehicle_id=vehicle_id, message=message)
    elif isinstance(message, Event):
        _agent_event(vehicle_id=vehicle_id, message=message)


def _task_accepted(*, vehicle_id: Any, message: TaskAccepted) -> None:
    assignment = _assignment_for(vehicle_id=vehicle_id, session_id=message.session_id)
    if assignment is None:
        return
    session = assignment.session
    event_append(session=session, kind="task_accepted", data={"vehicle": str(vehicle_id)})
    kind = service_kind(session.service)
    if kind is not None:
        kind.task_accepted(assignment=assignment)
    if not _serving(assignment):
        # A late acceptance of a session that is over. Its end normally follows the
        # task in the vehicle's outbox; should none be owed, owe one now.
        _owe_end(vehicle_id=vehicle_id, session_id=session.pk)


def _ending_message(*, vehicle_id: Any, session_id: Any) -> EndTask | Revoke:
    """What makes the vehicle's agent give up ``session_id``: the revoke or end the
    platform already decided for it, else an ``end_task`` with the session's reason."""
    decided = (
        AgentMessage.objects.filter(vehicle_id=vehicle_id, session_id=session_id, kind__in=ENDING)
        .order_by("-id")
        .first()
    )
    if decided is not None:
        message = stored_message(decided.message)
        assert isinstance(message, EndTask | Revoke), message
        return message
    session = _stale_session(session_id)
    if session is None:
        reason = "the platform knows no such session"
    else:
        reason = session.reason or "this vehicle no longer serves the session"
    return EndTask(session_id=str(session_id), reason=reason[:REASON_MAX])


def _owe_end(*, vehicle_id: Any, session_id: Any) -> None:
    """Make sure the agent is owed the end of ``session_id`` (one pending message at
    most); the vehicle's status is left to whatever it serves now."""
    if AgentMessage.objects.filter(
        vehicle_id=vehicle_id,
        session_id=session_id,
        kind__in=ENDING,
        state=AgentMessage.State.PENDING,
    ).exists():
        return
    message = _ending_message(vehicle_id=vehicle_id, session_id=session_id)
    vehicle_send(vehicle_id=vehicle_id, message=message, session_id=session_id)


def _task_refused(*, vehicle_id: Any, message: TaskRefused) -> None:
    if not message.session_id:  # absent or null: the agent could not read the task
        log.warning(
            "vehicle %s refused an unreadable task: %s (%s)",
            vehicle_id,
            message.reason[:REASON_MAX],
            message.code,
        )
        return
    assignment = _assignment_for(vehicle_id=vehicle_id, session_id=message.session_id)
    if assignment is None:
        return
    session = assignment.session
    event_append(
        session=session,
        kind="task_refused",
        data={"vehicle": str(vehicle_id), "code": message.code, "reason": message.reason},
    )
    if _serving(assignment):
        reason = (
            f"vehicle {assignment.vehicle.name} refused its task: "
            f"{message.reason or 'no reason given'} ({message.code})"
        )
        # Suppressed: someone else may have ended the session meanwhile.
        with contextlib.suppress(SessionStateError):
            session_fail(session=session, reason=reason[:REASON_MAX])


def _agent_event(*, vehicle_id: Any, message: Event) -> None:
    name, data = message.event, message.data
    if message.session_id is None:
        log.info("vehicle %s: %.40s outside a session", vehicle_id, name)
        return
    assignment = _assignment_for(vehicle_id=vehicle_id, session_id=message.session_id)
    if assignment is None:
        return
    if name in _LIVE_ONLY and not _serving(assignment):
        return  # a late report of a session that is over: nothing to act on or show
    kind = service_kind(assignment.session.service)
    handler = _EVENT_HANDLERS.get(name) or (kind.event_handlers.get(name) if kind else None)
    # What the report is logged as, and what is logged because of it, carry the time it
    # happened on the vehicle beside the time it is written (a report that waited for
    # the platform or its database is written late).
    with events_occurred_at(_vehicle_time(message)):
        if handler is None:
            event_append(
                session=assignment.session,
                kind="agent_event",
                data={"vehicle": str(vehicle_id), "event": name, "data": data},
            )
            return
        handler(assignment, data)


def _vehicle_time(message: Event) -> datetime | None:
    """When the reported event happened by the vehicle's clock (``at``), if it says."""
    if isinstance(message.at, float | int):
        return datetime.fromtimestamp(message.at, tz=UTC)
    return None


def _log(assignment: Assignment, kind: str, data: dict[str, Any]) -> SessionEvent:
    return event_append(
        session=assignment.session,
        kind=kind,
        data={"vehicle": str(assignment.vehicle_id), **data},
    )


def _on_user_connected(assignment: Assignment, data: dict[str, Any]) -> None:
    _log(assignment, "user_connected", data)
    if data.get("role") == "viewer" or not _serving(assignment):
        return
    with transaction.atomic():
        if assignment.session.state == Session.State.ASSIGNED:
            try:
                session_transition(
                    session=assignment.session, to=Session.State.ACTIVE, reason="user connected"
                )
            except SessionStateError:
                return  # ended meanwhile
        # The vehicle is under the user's control (again, after a fail-safe).
        changed = Vehicle.objects.filter(
            pk=assignment.vehicle_id,
            maintenance=False,
            status__in=[Vehicle.Status.RESERVED, Vehicle.Status.FAILSAFE, Vehicle.Status.IDLE],
        ).update(status=Vehicle.Status.IN_SERVICE)
        if changed:
            fleet_notify([assignment.vehicle_id])


def _unsafe_count(data: Any) -> int:
    """How many of the refusals one ``command_refused`` report stands for were unsafe.

    An agent reports the first refusal of a burst at once and folds the rest into one
    report a second (``count``, and ``codes``: code -> how many)."""
    if not isinstance(data, dict):
        return 0
    codes = data.get("codes")
    if isinstance(codes, dict):
        return sum(int(n) for code, n in codes.items() if code in UNSAFE_REFUSALS and _is_count(n))
    if data.get("code") not in UNSAFE_REFUSALS:
        return 0
    count = data.get("count", 1)
    return int(count) if _is_count(count) else 1


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= 1_000_000


def _on_command_refused(assignment: Assignment, data: dict[str, Any]) -> None:
    event = _log(assignment, "command_refused", data)
    if not _unsafe_count(data) or not _serving(assignment):
        return
    since = event.created_at - timedelta(seconds=settings.IOUV_UNSAFE_REFUSALS_WINDOW_S)
    recent = SessionEvent.objects.filter(
        session=assignment.session, kind="command_refused", created_at__gt=since
    ).values_list("data", flat=True)
    if sum(_unsafe_count(d) for d in recent) > settings.IOUV_UNSAFE_REFUSALS_MAX:
        session = assignment.session
        # Suppressed: a concurrent refusal may have revoked it already.
        with contextlib.suppress(SessionStateError):
            session_revoke(
                session=session,
                reason="repeated unsafe commands",
                action=session.service.failsafe_action,
            )


def _on_failsafe(assignment: Assignment, data: dict[str, Any]) -> None:
    _log(
        assignment,
        "unintentional_end",
        {"cause": str(data.get("cause", "unknown")), "action": str(data.get("action", "unknown"))},
    )
    if not _serving(assignment):
        return
    changed = Vehicle.objects.filter(pk=assignment.vehicle_id, maintenance=False).update(
        status=Vehicle.Status.FAILSAFE
    )
    if changed:
        fleet_notify([assignment.vehicle_id])


def _on_link_recovered(assignment: Assignment, data: dict[str, Any]) -> None:
    """The controller's input came back on the socket it kept open after a fail-safe:
    the user drives again, and the session goes on (see :func:`sessions_expire_grace`)."""
    _log(assignment, "link_recovered", data)
    _back_in_service(assignment)


def _on_control_handover(assignment: Assignment, data: dict[str, Any]) -> None:
    """The user took the controls on another connection (a page back after its relay
    was cut, another device): after a fail-safe the vehicle is in service again."""
    _log(assignment, "control_handover", data)
    _back_in_service(assignment)


def _back_in_service(assignment: Assignment) -> None:
    if Vehicle.objects.filter(
        pk=assignment.vehicle_id, maintenance=False, status=Vehicle.Status.FAILSAFE
    ).update(status=Vehicle.Status.IN_SERVICE):
        fleet_notify([assignment.vehicle_id])


def _on_link_quality(assignment: Assignment, data: dict[str, Any]) -> None:
    # Agents report link quality often; the hash-chained log keeps a sample, not a flood.
    last = (
        SessionEvent.objects.filter(session=assignment.session, kind="link_quality")
        .order_by("-seq")
        .first()
    )
    if last is not None and last.created_at > timezone.now() - timedelta(
        seconds=LINK_QUALITY_EVERY_S
    ):
        return
    _log(assignment, "link_quality", data)


def _on_control_path(assignment: Assignment, data: dict[str, Any]) -> None:
    """A user's messages changed path (WebRTC direct or through TURN, the relay, the
    direct WebSocket): the controller's is kept on the session, then logged (the feeds
    show the session as it is after the change)."""
    path = data.get("path")
    if path not in Session.ControlPath.values:
        log.warning("vehicle %s: unknown control path %.40r", assignment.vehicle_id, path)
        return
    if data.get("role") == "controller":
        Session.objects.filter(pk=assignment.session_id).exclude(control_path=path).update(
            control_path=path
        )
    _log(
        assignment,
        "control_path",
        {"path": path, "user": data.get("user"), "role": data.get("role")},
    )


def _logged_as(kind: str) -> Any:
    def handler(assignment: Assignment, data: dict[str, Any]) -> None:
        _log(assignment, kind, data)

    return handler


#: Events that only mean something while the session runs; late ones are dropped.
_LIVE_ONLY = frozenset(
    {
        "command_refused",
        "link_quality",
        "link_recovered",
        "control_handover",
        "control_released",
        "control_path",
    }
)

_EVENT_HANDLERS = {
    "user_connected": _on_user_connected,
    "user_disconnected": _logged_as("user_disconnected"),
    "command_refused": _on_command_refused,
    "failsafe": _on_failsafe,
    "task_ended": _logged_as("task_ended"),
    "link_recovered": _on_link_recovered,
    "control_handover": _on_control_handover,
    "control_released": _logged_as("control_released"),
    "link_quality": _on_link_quality,
    "control_path": _on_control_path,
}


# --------------------------------------------------------------------------------------
# Agents coming and going
# --------------------------------------------------------------------------------------


def _serving_assignments(vehicle_id: Any) -> list[Assignment]:
    return list(
        Assignment.objects.filter(
            vehicle_id=vehicle_id, active=True, session__state__in=LIVE
        ).select_related("session__service", "session__user", "vehicle__station")
    )


def agent_connected_handle(*, vehicle_id: Any, state: dict[str, Any] | None = None) -> None:
    """A vehicle's agent (re)registered and said what it is doing (``state``, from its
    profile): converge it to what the platform wants it to do.

    * It runs a session it should not (ended meanwhile, or unknown): it is owed that
      session's end (the revoke or end decided for it, else ``end_task``).
    * Messages that no longer apply are withdrawn: tasks of other sessions, and ends of
      sessions it does not run (a restarted agent has nothing to give up).
    * It should serve a session: ``vehicle_online`` is logged (with whether a user
      controls it), the vehicle gets back its session status, and if it lacks the task
      it had been sent, it gets a fresh one (a restarted agent lost it; the task sent
      earlier may have expired).
    * It serves nothing: a ``releasing`` vehicle with nothing left to confirm is idle.

    Runs in the transaction that stored the profile (fleet.uplink).
    """
    state = state or {}
    reported = state.get("session_id")
    with transaction.atomic():
        serving = _serving_assignments(vehicle_id)
        assignment = serving[0] if serving else None
        desired = str(assignment.session_id) if assignment is not None else None
        if reported is not None and reported != desired:
            try:
                _owe_end(vehicle_id=vehicle_id, session_id=uuid.UUID(str(reported)))
            except ValueError:  # not even a session id: nothing the platform could end
                log.warning("vehicle %s runs a task of session %.40r", vehicle_id, reported)
        agent_messages_cancel_each(
            vehicle_id=vehicle_id,
            withdrawn=[
                agent_messages_withdrawn(["task"], except_session=desired),
                # Ends of sessions it does not run are moot (all of them when it runs none).
                agent_messages_withdrawn(ENDING, except_session=reported),
            ],
        )
        if assignment is None:
            vehicle_release_if_settled(vehicle_id=vehicle_id)
            return
        session = assignment.session
        _log(assignment, "vehicle_online", {"controller": bool(state.get("controller"))})
        held = (
            Vehicle.Status.IN_SERVICE
            if session.state == Session.State.ACTIVE
            else Vehicle.Status.RESERVED
        )
        # Its session holds it, whatever the agent says it is doing: an agent back after
        # a platform process restarted reports a fail-safe its user may well recover from
        # (the session decides that, from the events), and nobody else may have the
        # vehicle meanwhile.
        if Vehicle.objects.filter(
            pk=vehicle_id,
            maintenance=False,
            status__in=[Vehicle.Status.IDLE, Vehicle.Status.RELEASING, Vehicle.Status.FAILSAFE],
        ).update(status=held):
            fleet_notify([vehicle_id])
        if reported == desired:
            return
        agent_messages_cancel(vehicle_id=vehicle_id, kinds=["task"])
        deployed = session.events.filter(
            kind="task_deployed", data__vehicle=str(vehicle_id)
        ).exists()
        if deployed:
            vehicle_task_deploy(session=session, assignment=assignment)


def _stale_session(session_id: Any) -> Session | None:
    try:
        pk = uuid.UUID(str(session_id))
    except ValueError:
        return None
    return Session.objects.filter(pk=pk).first()


def agent_acked_handle(*, vehicle_id: Any, acked: Acked) -> None:
    """An agent confirmed the end (or revoke) of a session: the session log says the
    platform's word reached the vehicle, and when."""
    if acked.kind not in ENDING or acked.session_id is None:
        return
    # The session with the vehicle's name, in one query.
    session = (
        Session.objects.filter(pk=acked.session_id)
        .annotate(vehicle_name=Subquery(Vehicle.objects.filter(pk=vehicle_id).values("name")[:1]))
        .first()
    )
    if session is None:
        return
    name = session.vehicle_name
    event_append(
        session=session,
        kind="stop_delivered" if acked.kind == "revoke" else "end_delivered",
        data={
            "vehicle": str(vehicle_id),
            "vehicle_name": name,
            "action": acked.message.action if isinstance(acked.message, Revoke) else None,
            "ok": acked.ok,
            "detail": acked.detail,
            "released": acked.released,
        },
    )


def vehicles_back_handle(*, vehicle_ids: Iterable[Any]) -> None:
    """Vehicles found silent (marked offline) are heard from again on their open
    uplink: those still serving a session get their session status back, so none is
    given to anyone else meanwhile."""
    with transaction.atomic():
        serving = Assignment.objects.filter(
            vehicle_id__in=list(vehicle_ids), active=True, session__state__in=LIVE
        ).select_related("session__service", "vehicle")
        for assignment in serving:
            held = (
                Vehicle.Status.IN_SERVICE
                if assignment.session.state == Session.State.ACTIVE
                else Vehicle.Status.RESERVED
            )
            Vehicle.objects.filter(
                pk=assignment.vehicle_id,
                maintenance=False,
                status__in=[Vehicle.Status.IDLE, Vehicle.Status.FAILSAFE],
            ).update(status=held)
            _log(assignment, "vehicle_online", {"after": "silence"})
            fleet_notify([assignment.vehicle_id])


def agent_disconnected_handle(*, vehicle_id: Any, code: int | None = None) -> None:
    """A vehicle's uplink closed: log ``vehicle_offline`` in the sessions it serves.

    What that means for the session is decided by the agent's own reports (it keeps
    serving a connected user point-to-point) and by the periodic rules.
    """
    for assignment in _serving_assignments(vehicle_id):
        _log(assignment, "vehicle_offline", {"close_code": code})


# --------------------------------------------------------------------------------------
# Periodic rules (Celery beat)
# --------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------
# What fleet's uplink tells the platform (registered in services.apps)
# --------------------------------------------------------------------------------------


class Supervisor:
    """The services app's answer to what vehicles say: fleet's
    :class:`fleet.vehicle_events.VehicleEvents`, registered once in services.apps."""

    def agent_connected(self, *, vehicle_id: str, state: AgentState) -> None:
        agent_connected_handle(vehicle_id=vehicle_id, state=dict(state))

    def agent_disconnected(self, *, vehicle_id: str, code: int | None) -> None:
        agent_disconnected_handle(vehicle_id=vehicle_id, code=code)

    def agent_welcome(self, *, vehicle_id: str) -> dict[str, Any]:
        # The JWKS is how a key rotation reaches enrolled agents: they adopt it from the
        # welcome of an uplink whose server they authenticated (wss, or loopback in
        # development).
        return {"platform_public_key": platform_public_key_pem(), "platform_jwks": platform_jwks()}

    def agent_acked(self, *, vehicle_id: str, acked: Acked) -> None:
        agent_acked_handle(vehicle_id=vehicle_id, acked=acked)

    def agent_message(self, *, vehicle_id: str, message: SessionMessage) -> None:
        agent_message_handle(vehicle_id=vehicle_id, message=message)

    def vehicles_back(self, *, vehicle_ids: Sequence[str]) -> None:
        vehicles_back_handle(vehicle_ids=vehicle_ids)
