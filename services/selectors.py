"""Reads: what pages, feeds and the API show of sessions and services."""

from __future__ import annotations

from typing import Any

from django.db.models import QuerySet

from fleet.models import Vehicle
from services.models import Service, Session
from services.sessions import FINAL


def session_summary(session: Session) -> dict[str, Any]:
    """A session as JSON for feeds and the monitor dashboard."""
    return {
        "id": str(session.pk),
        "service": session.service.slug,
        "service_name": session.service.name,
        "user": session.user.get_username(),
        "state": session.state,
        "reason": session.reason,
        "relay": session.relay,
        "created_at": session.created_at.isoformat(),
        "started_at": session.started_at.isoformat() if session.started_at else None,
        "ended_at": session.ended_at.isoformat() if session.ended_at else None,
        "vehicles": [
            {"role": a.role, "id": str(a.vehicle_id), "name": a.vehicle.name}
            for a in session.assignments.select_related("vehicle").filter(active=True)
        ],
    }


def sessions_spectatable() -> QuerySet[Session]:
    """Live sessions whose main vehicle streams video: what spectators may watch."""
    return (
        Session.objects.exclude(state__in=FINAL)
        .filter(
            state__in=[Session.State.ASSIGNED, Session.State.ACTIVE],
            assignments__active=True,
            assignments__vehicle__profile__video=True,
        )
        .select_related("service", "user")
        .distinct()
        .order_by("-created_at")
    )


def service_vehicles_matching(service: Service) -> list[Vehicle]:
    """Online idle vehicles that could fill the service's first role now (for the form)."""
    from services.assignment import role_match

    role = service.roles.filter(required=True).first()
    if role is None:
        return []
    ranked = [c.vehicle.pk for c in role_match(role=role).candidates]
    vehicles = Vehicle.objects.select_related("station").in_bulk(ranked)
    return [vehicles[pk] for pk in ranked if pk in vehicles]
