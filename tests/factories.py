"""Rows for tests, built with the same defaults the demo fleet uses."""

from __future__ import annotations

import itertools
from typing import Any

from django.contrib.auth import get_user_model
from django.utils import timezone

from accounts.roles import CLIENT, roles_ensure, user_set_roles
from fleet.models import Station, Vehicle, VehicleType
from services.models import Service, ServiceGrant, ServiceRole

_counter = itertools.count(1)

HOME = (40.6306, -8.6588)  # a station on land
COAST = (40.6443, -8.7455)  # a station on the beach

DRONE_ATTRS: dict[str, Any] = {
    "endurance_min": 20,
    "max_range_m": 5000,
    "max_altitude_m": 120,
    "max_speed_mps": 12,
    "max_payload_kg": 0.5,
    "cameras": ["rgb"],
    "camera_range_m": 100,
    "environments": ["air", "land"],
}


def station(name: str = "", lat_lon: tuple[float, float] = HOME, **kw: Any) -> Station:
    return Station.objects.create(
        name=name or f"station-{next(_counter)}",
        lat=lat_lon[0],
        lon=lat_lon[1],
        environments=kw.pop("environments", ["land", "air"]),
        **kw,
    )


def vehicle_type(kind: str = "aerial", adapter: str = "mavlink", name: str = "") -> VehicleType:
    return VehicleType.objects.create(
        name=name or f"{kind}-{adapter}-{next(_counter)}", kind=kind, adapter=adapter
    )


def vehicle(
    *,
    station: Station,
    vtype: VehicleType,
    name: str = "",
    online: bool = True,
    status: str = Vehicle.Status.IDLE,
    battery: float | None = 90.0,
    at: tuple[float, float] | None = None,
    **attrs: Any,
) -> Vehicle:
    """A vehicle; ``online`` sets last_seen to now, ``at`` its reported position (an
    online vehicle's agent reports one: by default, its station's)."""
    if at is None and online:
        at = (station.lat, station.lon)
    v = Vehicle(
        name=name or f"vehicle-{next(_counter)}",
        vehicle_type=vtype,
        station=station,
        attributes={**DRONE_ATTRS, **attrs},
        status=status if online else Vehicle.Status.OFFLINE,
        last_seen=timezone.now() if online else None,
        battery=battery,
        lat=at[0] if at else None,
        lon=at[1] if at else None,
    )
    v.full_clean()
    v.save()
    return v


def user(username: str = "", roles: tuple[str, ...] = (CLIENT,)) -> Any:
    u = get_user_model().objects.create_user(
        username=username or f"user-{next(_counter)}", password="pw-for-tests"
    )
    user_set_roles(user=u, roles=roles)
    return u


def service(
    slug: str = "",
    *,
    roles: list[dict[str, Any]] | None = None,
    grant_clients: bool = True,
    **kw: Any,
) -> Service:
    """A service with the given role constraints, granted to the client role; of the
    manual-control kind unless ``kind`` says otherwise."""
    kw.setdefault("kind", "manual_control")
    svc = Service.objects.create(slug=slug or f"svc-{next(_counter)}", name=slug or "svc", **kw)
    for spec in roles if roles is not None else [{"name": "vehicle"}]:
        ServiceRole.objects.create(service=svc, **spec)
    if grant_clients:
        ServiceGrant.objects.create(service=svc, group=roles_ensure()[CLIENT])
    return svc
