"""Task deployment: signed vehicle tasks out on the uplink, user tasks to the browser.

:func:`session_open` opens every session; for a kind the user drives it reserves the
vehicles and signs one vehicle task per assigned vehicle (session, user, allowed
commands, the service's limits, a delivery deadline and a nonce), owes it to the agent,
then returns the *user task*: what the controller page needs, with a short-lived signed
grant the agent verifies offline.
:func:`session_end` and :func:`session_revoke` close a session and tell the agents.

Tokens are never logged: the session log keeps their nonces, which identify them.
"""

from __future__ import annotations

import dataclasses
import time
import uuid
from dataclasses import dataclass
from typing import Any

from django.conf import settings
from django.db import transaction
from django.http import HttpRequest

from accounts.users import User
from agents.missions.spec import MissionError, MissionSpec
from agents.protocol import FAILSAFE_ACTIONS, Limits, ProtocolError, UserGrant, VehicleTask
from agents.protocol.messages import EndTask, Revoke, Task, message_to_dict, message_type
from fleet.feed import fleet_notify
from fleet.models import AgentMessage, Vehicle
from fleet.outbox import agent_messages_cancel
from fleet.sending import vehicle_send
from services.kinds import Opened, UnknownKind, kind_of
from services.models import Assignment, Service, Session
from services.sessions.grants import user_can_use
from services.sessions.ice import ice_servers_for
from services.sessions.log import event_append, events_staged, session_log
from services.sessions.matching import (
    AssignmentError,
    service_grant_require,
    session_record,
    session_roles_assign,
    session_write,
)
from services.sessions.selectors import delivery_entry
from services.sessions.signing import platform_private_key
from services.sessions.states import FINAL, session_transition_locked

#: Session states in which grants can be issued and agents serve the session.
LIVE = (Session.State.ASSIGNED, Session.State.ACTIVE)


class DeploymentError(Exception):
    """The session cannot be deployed or joined now; the message says why."""


class NotAssignedYet(DeploymentError):
    """The session is open but holds no vehicle at the moment (an autonomous kind's
    workflow has not assigned one yet, or is between vehicles): ask again later."""


class InvalidTaskError(DeploymentError):
    """The service's settings (limits, mission) cannot make a valid vehicle task.
    ``session``: the session failed for it, once one was."""

    session: Session | None = None


@dataclass(frozen=True)
class UserTask:
    """What a browser needs to control (or watch) one vehicle of a session.

    ``grant`` is the signed user grant to present in ``auth`` on ``control_url`` (or
    through the platform's relay when ``relay`` is true); it must be used before
    ``expires_at`` (Unix seconds). ``commands`` are the declarations of the commands this
    grant allows, from the vehicle's reported vocabulary, for building the controls.
    """

    session_id: str
    vehicle_id: str
    vehicle_name: str
    control_url: str
    grant: str
    role: str
    expires_at: float
    commands: tuple[dict[str, Any], ...]
    telemetry: tuple[str, ...]
    relay: bool


def service_limits(*, service: Service, center: tuple[float, float] | None) -> Limits:
    """The limits signed into the service's vehicle tasks.

    ``center`` is the geofence centre, used only when the service sets a radius. Raises
    InvalidTaskError when the service's values are not valid limits (for example a zero
    speed or altitude ceiling, which the protocol cannot express).
    """
    fenced = service.geofence_radius_m is not None
    try:
        return Limits(
            max_altitude_m=service.max_altitude_m,
            geofence_center=center if fenced else None,
            geofence_radius_m=service.geofence_radius_m if fenced else None,
            max_speed_mps=service.max_speed_mps,
            link_loss_timeout_ms=service.link_loss_timeout_ms,
            failsafe_action=service.failsafe_action,
            latency_soft_ms=service.latency_soft_ms,
            latency_hard_ms=service.latency_hard_ms,
            session_time_limit_s=service.session_time_limit_s,
        )
    except ProtocolError as exc:
        raise InvalidTaskError(
            f"service {service.slug} has invalid limits: {exc.message}"
        ) from None


def _active_assignments(session: Session) -> list[Assignment]:
    return list(
        Assignment.objects.filter(session=session, active=True).select_related(
            "vehicle__vehicle_type", "vehicle__station"
        )
    )


def _primary(assignments: list[Assignment]) -> Assignment:
    """The assignment the user controls: role ``vehicle``, else the first."""
    for assignment in assignments:
        if assignment.role == "vehicle":
            return assignment
    return assignments[0]


def _mission_for(*, session: Session, assignment: Assignment) -> MissionSpec | None:
    """The autonomous mission of this vehicle's task: its kind's (from the workflow's
    recorded state), else none."""
    try:
        kind = kind_of(session.service)
    except UnknownKind:
        return None
    mission = kind.vehicle_mission(assignment=assignment)
    if mission is not None and not isinstance(mission, kind.missions):
        # A kind deploys only the missions it declares (ServiceKind.missions).
        raise InvalidTaskError(
            f"cannot make a vehicle task: the {kind.name} service does not deploy "
            f"{type(mission).mission_kind()!r} missions"
        )
    return mission


def _vehicle_task_sign(*, session: Session, assignment: Assignment) -> tuple[VehicleTask, str]:
    """A fresh signed task for ``assignment``'s vehicle (a new nonce every call), and its
    token; nothing is written. Raises InvalidTaskError as :func:`vehicle_task_deploy`."""
    service = session.service
    vehicle = assignment.vehicle
    limits = service_limits(service=service, center=session.target or vehicle.position)
    now = time.time()
    try:
        task = VehicleTask(
            session_id=str(session.pk),
            vehicle_id=str(vehicle.pk),
            user=session.user.get_username(),
            allowed_commands=tuple(service.allowed_commands),
            limits=limits,
            issued_at=now,
            expires_at=now + settings.IOUV_TASK_TTL_S,
            mission=_mission_for(session=session, assignment=assignment),
        )
    except ProtocolError as exc:
        raise InvalidTaskError(f"cannot make a vehicle task: {exc.message}") from None
    except MissionError as exc:
        raise InvalidTaskError(f"cannot make a vehicle task: {exc}") from None
    return task, task.sign(platform_private_key())


def _vehicle_task_send(
    *,
    session: Session,
    assignment: Assignment,
    task: VehicleTask,
    token: str,
    supersede: bool = True,
    locked: bool = False,
) -> None:
    """Owe the signed ``task`` to the vehicle's agent and log it, in the caller's
    transaction. ``supersede``: withdraw a task still owed for this session first
    (there is none for a session created in this transaction). ``locked``: the caller
    holds the session's row lock."""
    vehicle = assignment.vehicle
    if supersede:
        # A fresh task supersedes one still owed for this session: delivered late, that
        # one's deadline could have passed, and the agent would refuse it.
        agent_messages_cancel(vehicle_id=vehicle.pk, kinds=["task"], session_id=session.pk)
    event_append(
        session=session,
        kind="task_deployed",
        data={
            "vehicle": str(vehicle.pk),
            "vehicle_name": vehicle.name,
            "role": assignment.role,
            "nonce": task.nonce,
            "exp": task.expires_at,
        },
        locked=locked,
    )
    vehicle_send(vehicle_id=vehicle.pk, message=Task(token=token), session_id=session.pk)


def vehicle_task_deploy(*, session: Session, assignment: Assignment) -> VehicleTask:
    """Sign a fresh task for ``assignment``'s vehicle, push it and log it.

    Every call makes a new nonce: a task is never re-sent (docs/protocol.md, "Replay
    rule"). The push happens after the surrounding transaction commits. Raises
    InvalidTaskError when the service's limits or the mission its kind flies cannot go
    into a task.
    """
    task, token = _vehicle_task_sign(session=session, assignment=assignment)
    # No savepoint: nothing in here is caught and carried on from.
    with transaction.atomic(savepoint=False):
        _vehicle_task_send(session=session, assignment=assignment, task=task, token=token)
    return task


def _user_task(
    *, session: Session, assignment: Assignment, user: User, role: str, locked: bool = False
) -> UserTask:
    vehicle: Vehicle = assignment.vehicle
    allowed = tuple(session.service.allowed_commands) if role == "controller" else ()
    now = time.time()
    grant = UserGrant(
        session_id=str(session.pk),
        vehicle_id=str(vehicle.pk),
        user=user.get_username(),
        role=role,
        allowed_commands=allowed,
        issued_at=now,
        expires_at=now + settings.IOUV_GRANT_TTL_S,
    )
    token = grant.sign(platform_private_key())
    event_append(
        session=session,
        kind="grant_issued",
        data={
            "vehicle": str(vehicle.pk),
            "user": grant.user,
            "role": role,
            "nonce": grant.nonce,
            "exp": grant.expires_at,
        },
        locked=locked,
    )
    declared = vehicle.profile.get("commands") or vehicle.vehicle_type.commands or []
    return UserTask(
        session_id=str(session.pk),
        vehicle_id=str(vehicle.pk),
        vehicle_name=vehicle.name,
        control_url=vehicle.control_url,
        grant=token,
        role=role,
        expires_at=grant.expires_at,
        commands=tuple(
            c for c in declared if isinstance(c, dict) and c.get("name") in set(allowed)
        ),
        telemetry=tuple(vehicle.profile.get("telemetry") or ()),
        # Without a control URL the vehicle is reachable only through the platform.
        relay=session.relay or not vehicle.control_url,
    )


def _tasks_deploy(*, session: Session, assignments: list[Assignment], supersede: bool) -> UserTask:
    """Sign every vehicle's task, then owe and log them, then the controller's grant
    (in the caller's transaction, which holds the session's row). Every task is signed
    before anything is written: InvalidTaskError leaves nothing to take back."""
    signed = [
        (assignment, *_vehicle_task_sign(session=session, assignment=assignment))
        for assignment in assignments
    ]
    for assignment, task, token in signed:
        _vehicle_task_send(
            session=session,
            assignment=assignment,
            task=task,
            token=token,
            supersede=supersede,
            locked=True,
        )
    return _user_task(
        session=session,
        assignment=_primary(assignments),
        user=session.user,
        role="controller",
        locked=True,
    )


def session_open(
    *,
    user: User,
    service: Service,
    target: tuple[float, float] | None = None,
    params: dict[str, Any] | None = None,
    relay: bool = False,
    preferences: dict[str, Any] | None = None,
    deploy: bool = False,
    grant_checked: bool = False,
) -> Opened:
    """Open a session of ``service`` for ``user``: the one way every kind opens one
    (from :meth:`ServiceKind.open <services.kinds.ServiceKind.open>`, which
    services.sessions.request.service_request calls for the portal and the API alike).

    The grant is checked (unless ``grant_checked``: the caller has just checked it), and
    the user's live sessions of the service counted against ``max_sessions_per_user``
    under the user's row lock; the session is recorded with its ``requested`` event.

    ``deploy=False`` (a kind whose workflow finds its vehicles as it goes): that is all,
    in the caller's transaction; ``Opened.task`` is None.

    ``deploy=True`` (a kind the user drives): in one transaction, with the session's log
    written in one go at its end, the service's required roles are reserved
    (``preferences`` narrowing them), every vehicle's signed task is owed to its agent,
    and the controller's user task is returned in ``Opened.task``.

    Raises AssignmentError when the user may not use the service or holds as many live
    sessions of it as it allows (``over_cap``): nothing is recorded. With ``deploy``:
    AssignmentError when a role cannot be filled (the session is recorded as failed,
    no vehicle stays reserved); InvalidTaskError (with ``session``) when the service's
    settings cannot make a valid task: the session is recorded as assigned, then failed
    with that reason, its vehicles released and nothing sent.
    """
    if not grant_checked:
        service_grant_require(user=user, service=service)
    if not deploy:
        with transaction.atomic():
            session = session_record(
                user=user,
                service=service,
                target=target,
                params=params,
                relay=relay,
                preferences=preferences,
            )
        return Opened(session=session)
    refused: AssignmentError | InvalidTaskError | None = None
    pk = uuid.uuid4()
    # The session written once, as the block leaves it (session_record's write).
    with transaction.atomic(), events_staged(session_id=pk) as log:
        session = session_record(
            user=user,
            service=service,
            target=target,
            params=params,
            relay=relay,
            preferences=preferences,
            pk=pk,
            write=False,
        )
        try:
            assignments = session_roles_assign(
                session=session, service=service, target=target, preferences=preferences
            )
            if not assignments:
                raise DeploymentError(f"session {session.pk} has no assigned vehicle")
            # A new session: no earlier task of it can be owed to supersede.
            task = _tasks_deploy(session=session, assignments=assignments, supersede=False)
        except AssignmentError as exc:
            refused = exc  # the failed session is committed, then the refusal raised
        except InvalidTaskError as exc:
            session_transition_locked(session=session, to=Session.State.FAILED, reason=str(exc))
            exc.session = session
            refused = exc
        session_write(session)
    if refused is not None:
        raise refused
    # A new session: these are all its assignments, and its whole log.
    session.known_assignments, session.known_events = assignments, log
    return Opened(session=session, task=task)


def grant_issue(
    *,
    session: Session,
    user: User,
    role: str = "controller",
    allowed_by: Service | None = None,
) -> UserTask:
    """A fresh grant for ``user`` on ``session``'s primary vehicle (e.g. after a reload).

    ``controller``: only the session's own user. ``viewer``: the session's user or anyone
    allowed to use the service (or ``allowed_by``, e.g. a service for watching others'
    sessions); a viewer's grant allows no command. Raises
    NotAssignedYet while the open session holds no vehicle, and DeploymentError when the
    session is final, the user may not have that role, or the role is unknown.
    """
    if role not in ("controller", "viewer"):
        raise DeploymentError(f"unknown role {role!r}")
    with transaction.atomic():
        session = (
            Session.objects.select_for_update(no_key=True)
            .select_related("service", "user")
            .get(pk=session.pk)
        )
        if session.state in FINAL:
            raise DeploymentError(f"the session has {session.state}: {session.reason}")
        if session.state not in LIVE:
            raise NotAssignedYet("the session has no vehicle yet")
        owner = user.pk == session.user_id
        if role == "controller" and not owner:
            raise DeploymentError("only the session's user may control its vehicle")
        permit = allowed_by or session.service
        if role == "viewer" and not owner and not user_can_use(user, permit):
            raise DeploymentError(f"you may not use the service {permit.name!r}")
        assignments = _active_assignments(session)
        if not assignments:
            raise NotAssignedYet("the session has no vehicle at the moment")
        return _user_task(session=session, assignment=_primary(assignments), user=user, role=role)


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


def user_task_json(task: UserTask, *, request: HttpRequest) -> dict[str, Any]:
    """The user task as JSON for a page or an API client.

    ``relay_url`` is the platform's relay socket on the host the request came to: the
    path that always works, and where a WebRTC connection is signalled. A relayed
    session's ``control_url`` is that socket too. ``ice_servers`` are the STUN/TURN
    servers for the user's side of that WebRTC connection (TURN credentials of its
    own, expiring with the grant: services.sessions.ice)."""
    data = dataclasses.asdict(task)
    scheme = "wss" if request.is_secure() else "ws"
    data["relay_url"] = f"{scheme}://{request.get_host()}/ws/relay/{task.session_id}/"
    if task.relay:
        data["control_url"] = data["relay_url"]
    data["ice_servers"] = ice_servers_for(task.session_id, expires_at=task.expires_at)
    return data
