"""Reads: what pages, feeds and the API show of sessions and services."""

from __future__ import annotations

from typing import Any

from fleet.liveness import vehicles_fresh
from fleet.models import AgentMessage, Vehicle
from fleet.outbox import ENDING, agent_messages_owed
from services.models import Service, ServiceRole, Session
from services.sessions.states import FINAL


def vehicle_consequence(vehicle: Vehicle, action: str) -> str:
    """What ``vehicle`` does when its task ends with the fail-safe ``action``, as
    "<name> will <words>", in the words its agent declared (profile ``safe_actions``),
    else the action's own name."""
    words = (vehicle.profile or {}).get("safe_actions", {}).get(action)
    return f"{vehicle.name} will {words or action.replace('_', ' ')}"


#: Why a vehicle acted on its own (the cause of an agent's ``failsafe``), for people.
FAILSAFE_CAUSES = {"link_lost": "the driver's link to the vehicle was lost"}


def failsafe_sentence(*, cause: str, action: str, vehicle: Vehicle | None) -> str:
    """What a fail-safe was, as a sentence without a code: "the driver's link to the
    vehicle was lost, so quad-1 will climb to its return altitude, fly back to its home
    point and land" (the vehicle's own words for ``action``, see
    :func:`vehicle_consequence`)."""
    why = FAILSAFE_CAUSES.get(
        cause, f"the vehicle had to act on its own ({cause.replace('_', ' ')})"
    )
    if vehicle is None:
        return f"{why}, so it performed its fail-safe ({action.replace('_', ' ')})"
    return f"{why}, so {vehicle_consequence(vehicle, action)}"


def session_consequence(session: Session, vehicles: list[Vehicle]) -> str:
    """What ending or stopping ``session`` makes its ``vehicles`` do, in one sentence
    for the person about to press the button."""
    if not vehicles:
        return "No vehicle has been sent out for it yet."
    action = session.service.failsafe_action
    return "; ".join(vehicle_consequence(v, action) for v in vehicles) + "."


def session_summary(session: Session) -> dict[str, Any]:
    """A session as JSON for feeds and the monitor dashboard."""
    active = list(session.assignments.select_related("vehicle").filter(active=True))
    return {
        "id": str(session.pk),
        "service": session.service.slug,
        "service_name": session.service.name,
        "user": session.user.get_username(),
        "state": session.state,
        "reason": session.reason,
        "relay": session.relay,
        "control_path": session.control_path,
        "failsafe_action": session.service.failsafe_action,
        "created_at": session.created_at.isoformat(),
        "started_at": session.started_at.isoformat() if session.started_at else None,
        "ended_at": session.ended_at.isoformat() if session.ended_at else None,
        "vehicles": [
            {"role": a.role, "id": str(a.vehicle_id), "name": a.vehicle.name} for a in active
        ],
        "consequence": session_consequence(session, [a.vehicle for a in active]),
        "delivery": session_delivery(session) if session.state in FINAL else [],
    }


def session_delivery(session: Session) -> list[dict[str, Any]]:
    """Whether the platform's last word on the session (the revoke or end of each
    vehicle's task) has reached each vehicle, in words a monitor can act on.

    One entry per vehicle told: ``state`` is ``delivered`` (its agent confirmed, at
    ``at``), ``sending`` (its agent is online and has not confirmed yet) or
    ``vehicle_offline`` (its own fail-safe, ``action``, holds; it is told when it
    reconnects). Vehicles whose agent never had the session's task are not listed.
    The function that just ended the session leaves what it sent on it
    (``known_delivery``): that is the answer then, without reading it back.
    """
    if session.known_delivery is not None:
        return session.known_delivery
    latest: dict[Any, AgentMessage] = {}
    for row in agent_messages_owed(session_id=session.pk):
        if row.kind in ENDING and row.state != AgentMessage.State.CANCELLED:
            latest[row.vehicle_id] = row
    return [
        delivery_entry(
            vehicle=row.vehicle,
            kind=row.kind,
            message=row.message,
            acked_at=row.acked_at if row.state == AgentMessage.State.ACKED else None,
        )
        for row in latest.values()
    ]


def delivery_entry(
    *, vehicle: Vehicle, kind: str, message: dict[str, Any], acked_at: Any = None
) -> dict[str, Any]:
    """One entry of :func:`session_delivery`: the ``kind`` (end_task or revoke) of
    ``message`` sent to ``vehicle``, confirmed by its agent at ``acked_at`` (None: not
    yet)."""
    action = message.get("action") or "end"
    word = "stop" if kind == AgentMessage.Kind.REVOKE else "end of the session"
    if acked_at is not None:
        state = "delivered"
        text = f"The {word} reached {vehicle.name}"
        if kind == AgentMessage.Kind.REVOKE:
            text += f": it performs {action.replace('_', ' ')}"
    elif vehicle.status == Vehicle.Status.OFFLINE:
        state = "vehicle_offline"
        failsafe = action if kind == AgentMessage.Kind.REVOKE else "its fail-safe"
        text = (
            f"{vehicle.name} is offline: its own fail-safe ({failsafe.replace('_', ' ')}) "
            f"holds; the {word} is delivered when it reconnects"
        )
    else:
        state = "sending"
        text = f"Sending the {word} to {vehicle.name}…"
    return {
        "vehicle": {"id": str(vehicle.pk), "name": vehicle.name},
        "message": kind,
        "action": message.get("action"),
        "state": state,
        "at": acked_at.isoformat() if acked_at else None,
        "text": text,
    }


def service_vehicles_matching(service: Service, role: ServiceRole | None = None) -> list[Vehicle]:
    """Online idle vehicles that could fill ``role`` now (default: the service's first
    required role), for the request page: heard from within the offline delay, as
    assignment will check (a vehicle that went quiet since the last sweep is not
    offered)."""
    from services.sessions.matching import role_match

    if role is None:
        role = service.roles.filter(required=True).first()
    if role is None:
        return []
    ranked = [c.vehicle.pk for c in role_match(role=role).candidates]
    fresh = vehicles_fresh(ranked)
    ranked = [pk for pk in ranked if str(pk) in fresh]
    vehicles = Vehicle.objects.select_related("station").in_bulk(ranked)
    return [vehicles[pk] for pk in ranked if pk in vehicles]
