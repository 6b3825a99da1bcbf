"""The scale benchmark's reads and writes of the platform's database, run inside the code
tree under test.

``benchmarks.scale`` drives a platform that may be another commit than its own (its
``--baseline REF`` runs a ``git worktree`` of REF): the driver, the agents and the API
clients are the current code, but rows must be written and read by the platform's own
models, whose schema and helpers may differ. So this file runs as a child process with
the platform's tree first on the path::

    cd TREE && PYTHONPATH=TREE python -P /path/to/benchmarks/scale_probe.py

and answers one JSON request per line on stdin (``{"op": ..., "args": {...}}``) with
one JSON line on stdout (``{"ok": result}`` or ``{"error": "..."}``).
:class:`benchmarks.scale_platform.PlatformQueries` is its client.

It imports nothing from ``benchmarks`` (that package would be the tree's, not this
file's), only the standard library, Django and the platform's apps, and it copes with
the helpers an older tree lacks (``fleet.liveness``: heartbeats read from the vehicle's
row instead).
"""

from __future__ import annotations

import json
import math
import os
import random
import sys
import time
from collections.abc import Callable, Sequence
from datetime import datetime
from typing import Any

HOME = (40.6306, -8.6588)  # the demo's campus station; vehicles are spread around it
LIGHT_TYPE = "Bench light drone"
CAR_TYPE = "Bench car"
LIGHT_SERVICE = "bench-assign"
CAR_SERVICE = "bench-drive"
CAR_COMMANDS = ["forward", "backward", "left", "right", "stop"]
#: PostgreSQL is shared with other work and may refuse a connection for a while ("too
#: many clients"): a request is retried for this long before its error is returned.
RETRY_S = 180.0


def prepare() -> dict[str, Any]:
    """Migrate the database with this tree's migrations and empty it."""
    from django.core.management import call_command

    call_command("migrate", verbosity=0, interactive=False)
    call_command("flush", verbosity=0, interactive=False)
    return {}


def settings_info() -> dict[str, Any]:
    """The platform settings the report names (this tree's defaults, this environment)."""
    from django.conf import settings

    return {
        "var_dir": str(settings.VAR_DIR),
        # A tree older than Django's own ASGI handler limited its HTTP requests at once.
        "http_concurrency": getattr(settings, "IOUV_HTTP_CONCURRENCY", None),
        "heartbeat_s": settings.IOUV_HEARTBEAT_INTERVAL_S,
        "offline_after_s": settings.IOUV_OFFLINE_AFTER_S,
    }


def world_build(
    *, light: int, cars: int, clients: int, link_loss_timeout_ms: int
) -> dict[str, Any]:
    """Register ``light`` drones and ``cars`` cars with fresh credentials, the two
    benchmark services, ``clients`` API users and a driver, each with a token.

    Returns the fields of ``benchmarks.scale.World`` (vehicles as dicts). Light drones
    are spread at random within 2 km of HOME, so concurrent requests for the nearest
    vehicle do not all race for the same one.
    """
    from django.contrib.auth import get_user_model

    from accounts.roles import CLIENT, roles_ensure, user_set_roles
    from accounts.tokens import token_issue
    from agents.geo import offset
    from fleet.credentials import vehicle_issue_credential
    from fleet.models import Station, Vehicle, VehicleType
    from services.models import Service, ServiceGrant, ServiceRole
    from services.sessions.signing import platform_public_key_pem

    rng = random.Random(7)
    groups = roles_ensure()
    station = Station.objects.create(
        name="Bench station", lat=HOME[0], lon=HOME[1], environments=["land", "air"]
    )
    drone_type = VehicleType.objects.create(name=LIGHT_TYPE, kind="aerial", adapter="mavlink")
    car_type = VehicleType.objects.create(name=CAR_TYPE, kind="ground", adapter="car")
    drone_attrs = {
        "endurance_min": 30,
        "max_range_m": 10000,
        "max_altitude_m": 120,
        "max_speed_mps": 12,
        "max_payload_kg": 0.5,
        "cameras": ["rgb"],
        "camera_range_m": 100,
        "environments": ["air", "land"],
        "features": ["gps"],
    }
    car_attrs = {**drone_attrs, "max_altitude_m": 0, "max_speed_mps": 1.5, "environments": ["land"]}
    rows = []
    positions: list[tuple[float, float]] = []  # as given (the model's fields are nullable)
    for i in range(light):
        distance, bearing = 2000 * math.sqrt(rng.random()), rng.uniform(0, 2 * math.pi)
        lat, lon = offset(HOME, distance * math.cos(bearing), distance * math.sin(bearing))
        rows.append(
            Vehicle(
                name=f"bench-light-{i:04d}",
                vehicle_type=drone_type,
                station=station,
                attributes=drone_attrs,
                battery=90.0,
                lat=lat,
                lon=lon,
            )
        )
        positions.append((lat, lon))
    for i in range(cars):
        rows.append(
            Vehicle(
                name=f"bench-car-{i}",
                vehicle_type=car_type,
                station=station,
                attributes=car_attrs,
                battery=90.0,
                lat=HOME[0],
                lon=HOME[1],
            )
        )
        positions.append(HOME)
    Vehicle.objects.bulk_create(rows, batch_size=500)
    specs = [
        {
            "vehicle_id": str(v.pk),
            "credential": vehicle_issue_credential(vehicle=v),
            "name": v.name,
            "lat": lat,
            "lon": lon,
        }
        for v, (lat, lon) in zip(rows, positions, strict=True)
    ]
    # The load's clients each hold many sessions at once: no per-user cap here.
    light_service = Service.objects.create(
        slug=LIGHT_SERVICE,
        name="Bench assignment",
        kind="manual_control",
        allowed_commands=["stop"],
        max_sessions_per_user=100_000,
    )
    ServiceRole.objects.create(
        service=light_service, name="vehicle", kinds=["aerial"], min_battery=20
    )
    car_service = Service.objects.create(
        slug=CAR_SERVICE,
        name="Bench drive",
        kind="manual_control",
        allowed_commands=CAR_COMMANDS,
        link_loss_timeout_ms=link_loss_timeout_ms,
        failsafe_action="stop",
        max_sessions_per_user=100_000,
    )
    ServiceRole.objects.create(service=car_service, name="vehicle", kinds=["ground"])
    for service in (light_service, car_service):
        ServiceGrant.objects.create(service=service, group=groups[CLIENT])

    def client(username: str) -> str:
        user = get_user_model().objects.create_user(username=username, password=None)
        user_set_roles(user=user, roles=[CLIENT])
        return str(token_issue(user=user, name="benchmark"))

    return {
        "public_key": platform_public_key_pem(),
        "light": specs[:light],
        "cars": specs[light:],
        "client_tokens": [client(f"bench-client-{i}") for i in range(clients)],
        "driver_token": client("bench-driver"),
    }


def _seen(ids: Sequence[str]) -> dict[str, datetime]:
    """When each vehicle of ``ids`` was last heard from, as this tree records it."""
    try:
        from fleet.liveness import vehicles_seen
    except ImportError:
        # A tree from before fleet.liveness kept heartbeats on the vehicle's row only.
        from fleet.models import Vehicle

        rows = Vehicle.objects.filter(pk__in=ids, last_seen__isnull=False)
        pairs = rows.values_list("pk", "last_seen")
        return {str(pk): seen for pk, seen in pairs if seen is not None}
    return {str(k): v for k, v in vehicles_seen(ids).items()}


def fleet_check(*, names: Sequence[str], ages: bool = False) -> dict[str, Any]:
    """How many of the vehicles named ``names`` the platform counts online (its own
    ``vehicles_online``, and heard from lately by its ``vehicles_fresh``), the database
    connections open (to this database, to the server), how many vehicle rows
    PostgreSQL has updated so far (its statistics counter) and, with ``ages``, how old
    each vehicle's last heartbeat is (seconds, as the platform records it; vehicles
    never heard from left out)."""
    from django.db import connection
    from django.utils import timezone

    from fleet.models import Vehicle
    from fleet.status import vehicles_online

    now = timezone.now()
    counted = vehicles_online(now).filter(name__in=names)
    try:
        from fleet.liveness import vehicles_fresh
    except ImportError:
        online = counted.count()  # a tree whose vehicles_online read last_seen itself
    else:
        # The status says online; the benchmark runs no sweep, so silence is checked
        # here the way assignment checks it.
        online = len(vehicles_fresh(counted.values_list("pk", flat=True), now))
    out: dict[str, Any] = {"online": online, "of": len(names)}
    if ages:
        ids = [
            str(pk) for pk in Vehicle.objects.filter(name__in=names).values_list("pk", flat=True)
        ]
        out["ages"] = [(now - seen).total_seconds() for seen in _seen(ids).values()]
    with connection.cursor() as cursor:
        cursor.execute(
            "SELECT count(*) FILTER (WHERE datname = current_database()), count(*) "
            "FROM pg_stat_activity WHERE backend_type = 'client backend'"
        )
        out["db_conns"], out["db_conns_all"] = (int(v) for v in cursor.fetchone())
        # Rows updated in the vehicle table so far: heartbeats, profiles, status changes.
        cursor.execute(
            "SELECT n_tup_upd FROM pg_stat_user_tables WHERE relname = %s",
            [Vehicle._meta.db_table],
        )
        row = cursor.fetchone()
    out["vehicle_updates"] = int(row[0]) if row else 0
    return out


def sessions_check(*, session_ids: Sequence[str]) -> dict[str, int]:
    """Of ``session_ids``: how many had a task deployed, accepted by the agent (in the
    session log), and are over."""
    from services.models import Session, SessionEvent
    from services.sessions.states import FINAL

    events = SessionEvent.objects.filter(session_id__in=session_ids)
    return {
        "sessions": len(session_ids),
        "task_deployed": events.filter(kind="task_deployed").values("session").distinct().count(),
        "task_accepted": events.filter(kind="task_accepted").values("session").distinct().count(),
        "final": Session.objects.filter(pk__in=session_ids, state__in=FINAL).count(),
    }


def failsafes_logged(*, session_id: str) -> int:
    """How many fail-safes the session's log holds (``unintentional_end`` events)."""
    from services.models import SessionEvent

    return SessionEvent.objects.filter(session_id=session_id, kind="unintentional_end").count()


OPS: dict[str, Callable[..., Any]] = {
    "prepare": prepare,
    "settings": settings_info,
    "world_build": world_build,
    "fleet_check": fleet_check,
    "sessions_check": sessions_check,
    "failsafes_logged": failsafes_logged,
}


def answer(request: dict[str, Any]) -> dict[str, Any]:
    """Run one request; its database connection is closed after, so nothing lingers."""
    from django.db import OperationalError, connections

    fn = OPS[request["op"]]
    deadline = time.monotonic() + RETRY_S
    while True:
        try:
            return {"ok": fn(**request.get("args", {}))}
        except OperationalError:
            if time.monotonic() > deadline:
                raise
            time.sleep(1.0)
        finally:
            connections.close_all()


def main() -> None:
    """Answer requests from stdin until it closes."""
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "iouv.settings")
    import django

    django.setup()
    for line in sys.stdin:
        try:
            reply = answer(json.loads(line))
        except Exception as exc:  # the driver raises it; this process goes on
            reply = {"error": f"{type(exc).__name__}: {exc}"}
        sys.stdout.write(json.dumps(reply) + "\n")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
