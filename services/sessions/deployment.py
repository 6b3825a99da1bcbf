"""Task deployment: signed vehicle tasks out on the uplink, user tasks to the browser.

For a session whose vehicles are reserved, :func:`session_tasks_deploy` signs one
vehicle task per assigned vehicle (session, user, allowed commands, the service's
limits, a delivery deadline and a nonce), owes it to the agent, then returns the *user
task*: what the controller page needs, with a short-lived signed grant the agent
verifies offline (:func:`grant_issue` gives a fresh one). Opening a session is
services.sessions.opening; ending one, services.sessions.ending.

Tokens are never logged: the session log keeps their nonces, which identify them.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

from django.conf import settings
from django.db import transaction
from django.http import HttpRequest

from accounts.users import User
from agents.missions.spec import MissionError, MissionSpec
from agents.protocol import Limits, ProtocolError, UserGrant, VehicleTask
from agents.protocol.messages import Task
from fleet.models import Vehicle
from fleet.outbox import agent_messages_cancel
from fleet.sending import vehicle_send
from services.kinds import UnknownKind, kind_of
from services.models import Assignment, Service, Session
from services.sessions.grants import user_can_use
from services.sessions.ice import ice_servers_for
from services.sessions.log import event_append
from services.sessions.signing import platform_private_key
from services.sessions.states import FINAL
from services.sfu import sfu_publish_for, sfu_room_schedule, sfu_viewer_for

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
    #: A viewer's: where to watch the video at the platform's SFU (services.sfu), when
    #: one is configured and the vehicle publishes there; None otherwise.
    sfu: dict[str, Any] | None = None


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


def _publishes(vehicle: Vehicle) -> bool:
    """Whether the vehicle sends its camera to the SFU: it has one, and its agent
    understands a task's ``sfu`` section (older agents would refuse the task)."""
    profile = vehicle.profile or {}
    return bool(profile.get("video") and profile.get("sfu"))


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
            sfu=sfu_publish_for(session_id=session.pk) if _publishes(vehicle) else None,
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
    if task.sfu is not None:
        sfu_room_schedule(session_id=session.pk)  # where the vehicle will publish


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
    sfu = None
    if role == "viewer" and _publishes(vehicle):
        sfu = sfu_viewer_for(session_id=session.pk)
        if sfu is not None:
            # Made again if a restarted SFU lost it (idempotent).
            sfu_room_schedule(session_id=session.pk)
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
        sfu=sfu,
    )


def session_tasks_deploy(
    *, session: Session, assignments: list[Assignment], supersede: bool
) -> UserTask:
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
