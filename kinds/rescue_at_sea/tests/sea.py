"""The sea the rescue tests search, and the demo's sea fleet that searches it.

Areas over the water; the fleet online as rows (the workflow's tests play the agents);
or the fleet running as real agents on their MAVLink simulators, with the platform and
a Celery worker (the end-to-end tests, the map tests, tests/tour.py), on simulators at
10x (tests.demo.mission_agent_config) so that a search takes seconds, not minutes.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from django.contrib.auth import get_user_model
from django.utils import timezone

from agents.geo import offset
from fleet.models import Vehicle
from kinds.rescue_at_sea.request import rescue_request
from services.demo import CASTAWAY
from services.models import Service, Session
from tests.demo import Demo, mission_agent_config, missions_running

#: About 900 m west of Costa Nova station, over the water.
SEA = (40.6420, -8.7560)


def area(width_m: float = 300, height_m: float = 200) -> list[list[float]]:
    """A ``width_m`` by ``height_m`` area at sea, from :data:`SEA` north-east."""
    return [
        list(SEA),
        list(offset(SEA, 0, width_m)),
        list(offset(SEA, height_m, width_m)),
        list(offset(SEA, height_m, 0)),
    ]


def online(*names: str) -> None:
    """The demo vehicles ``names`` online, idle at their station with a full battery, as
    their agents would report them."""
    for vehicle in Vehicle.objects.filter(name__in=names).select_related("station"):
        vehicle.status = Vehicle.Status.IDLE
        vehicle.last_seen = timezone.now()
        vehicle.lat, vehicle.lon, vehicle.alt = vehicle.station.lat, vehicle.station.lon, 0.0
        vehicle.battery = 95.0
        vehicle.save()


# --- the fleet running for real -------------------------------------------------------------

#: The centre of :func:`search_area`: the castaway is inside, off its centre.
CENTER = offset(CASTAWAY, 25, -50)


def search_area(width_m: float = 200, height_m: float = 120) -> list[list[float]]:
    """A ``width_m`` by ``height_m`` area around :data:`CENTER` (200 x 120 m: the
    castaway inside, off its centre)."""
    corner = offset(CENTER, -height_m / 2, -width_m / 2)
    return [
        list(corner),
        list(offset(corner, 0, width_m)),
        list(offset(corner, height_m, width_m)),
        list(offset(corner, height_m, 0)),
    ]


def sea(
    directory: Path, names: tuple[str, ...], *, video: bool = False, spare: bool = False
) -> contextlib.AbstractAsyncContextManager[Demo]:
    """The sea vehicles ``names`` running for real on the seeded demo, with the platform
    and a worker (tests.demo.missions_running); ``spare``: with search-2, a second search
    drone like search-1."""
    return missions_running(
        directory,
        names,
        lambda path, base: mission_agent_config(path, base, video=video),
        spares={"search-2": "search-1"} if spare else None,
        what="the sea fleet online",
    )


def client_requests_rescue(area: list[list[float]], altitude: float = 30) -> Session:
    """The demo's client asks for a rescue in ``area``, as the request form does."""
    client = get_user_model().objects.get(username="client")
    service = Service.objects.get(slug="rescue-at-sea")
    return rescue_request(user=client, service=service, area=area, altitude_m=altitude)
