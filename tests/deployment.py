"""A session deployed on a registered vehicle, as the services, platform and kinds tests
set it up, and what a page carrying its grant must be.

The vehicle has registered (its control URL and profile are known) and the service has
the limits of :data:`LIMITS`, so a deployed task carries every one of them.
"""

from __future__ import annotations

import json
from typing import Any

from accounts.users import User
from agents.protocol import UserGrant
from fleet.models import Vehicle
from services.kinds import Opened, Request
from services.models import Service, Session
from services.sessions.request import service_request
from services.sessions.signing import platform_public_key
from tests import factories as f

#: The commands the registered vehicle declares.
COMMANDS = [
    {"name": "up", "args": {}},
    {"name": "down", "args": {}},
    {"name": "stop", "args": {}},
]
#: Where the user asks the vehicle to go: the centre of the task's geofence.
TARGET = (40.6310, -8.6590)
#: The service's limits, every one set.
LIMITS: dict[str, Any] = {
    "max_altitude_m": 50.0,
    "geofence_radius_m": 300.0,
    "max_speed_mps": 5.0,
    "link_loss_timeout_ms": 800,
    "failsafe_action": "land",
    "latency_soft_ms": 150,
    "latency_hard_ms": 400,
    "session_time_limit_s": 600,
}


def registered_vehicle(name: str = "", at: tuple[float, float] | None = None) -> Vehicle:
    """An idle vehicle whose agent has registered: its control URL and its profile (the
    :data:`COMMANDS`, position and battery telemetry, video)."""
    vehicle = f.vehicle(station=f.station(), vtype=f.vehicle_type(), name=name, at=at)
    Vehicle.objects.filter(pk=vehicle.pk).update(
        control_url="ws://10.0.0.7:8765/control",
        profile={"commands": COMMANDS, "telemetry": ["position", "battery"], "video": True},
    )
    vehicle.refresh_from_db()
    return vehicle


def limited_service(**fields: Any) -> Service:
    """A service allowing "up" and "stop", with :data:`LIMITS` (``fields`` override)."""
    return f.service(allowed_commands=["up", "stop"], **{**LIMITS, **fields})


def session_requested(
    *,
    user: User,
    service: Service,
    target: tuple[float, float] | None = None,
    relay: bool = False,
    preferences: dict[str, Any] | None = None,
) -> Opened:
    """A session of ``service`` (a kind the user drives) requested by ``user`` the way
    the portal and the API request one (services.sessions.request.service_request): its
    vehicles reserved, their tasks owed to their agents, and the controller's user task
    in ``task``. Raises what a request raises (AssignmentError, DeploymentError)."""
    opened = service_request(
        user=user,
        service=service,
        request=Request(target=target, relay=relay, preferences=preferences or {}),
    )
    assert opened.task is not None, "a session the user drives comes with its user task"
    return opened


def alices_session() -> tuple[Session, Vehicle]:
    """alice's session of a :func:`limited_service` towards :data:`TARGET`, assigned to
    a :func:`registered_vehicle` and deployed (its task owed to the agent); and that
    vehicle."""
    vehicle = registered_vehicle()
    opened = session_requested(
        user=f.user(username="alice"), service=limited_service(), target=TARGET
    )
    return opened.session, vehicle


def uncacheable(response: Any) -> None:
    """Assert that ``response`` is a 200 no cache may keep (it carries a grant)."""
    assert response.status_code == 200
    assert "no-store" in response.get("Cache-Control", ""), response.get("Cache-Control")


def page_grant(html: str, vehicle_id: str) -> UserGrant:
    """The grant in the page's user-task JSON (it must verify: a real grant)."""
    start = html.index('<script id="user-task" type="application/json">')
    task = json.loads(html[html.index(">", start) + 1 : html.index("</script>", start)])
    return UserGrant.verify(task["grant"], platform_public_key(), vehicle_id=vehicle_id)
