"""Requesting a rescue: the search area drawn by the user, validated and planned.

:func:`rescue_request` checks the area and the altitude, plans the lawnmower path over
it (``coverage``), opens the session and its mission, and schedules the first step.
"""

from __future__ import annotations

from datetime import timedelta
from typing import Any

from django.db import transaction
from django.utils import timezone

from accounts.users import User
from kinds.rescue_at_sea.conf import search_timeout_s
from kinds.rescue_at_sea.coverage import (
    DEFAULT_HFOV_DEG,
    area_centroid,
    area_clean,
    coverage_plan,
)
from kinds.rescue_at_sea.missions import SEARCH_SPEED_MPS
from kinds.rescue_at_sea.models import KIND, Mission
from kinds.rescue_at_sea.tasks import mission_schedule
from services.assignment import session_open
from services.eventlog import event_append
from services.kinds import RequestError
from services.models import Service, Session

#: Search altitude: high enough for a wide thermal footprint, low enough that a head
#: in the water still covers a few pixels (0.3 m per pixel at 40 m with 160 pixels).
DEFAULT_ALTITUDE_M = 40.0
MIN_ALTITUDE_M = 15.0


#: The highest altitude a request may name (the service's ceiling may be lower).
MAX_ALTITUDE_M = 500.0


class RescueError(RequestError):
    """The rescue cannot be requested as given; ``field`` names what is wrong
    (``params.area``, ``params.altitude_m``) and ``str()`` says why."""


def rescue_request(
    *,
    user: User,
    service: Service,
    area: Any,
    altitude_m: float | None = None,
) -> Session:
    """Open a rescue session over ``area`` ([[lat, lon], ...]) and start its workflow.

    Raises RescueError when the area or altitude is unusable, AssignmentError when the
    user may not use the service or already holds as many live sessions of it as it
    allows (``over_cap``); nothing is recorded then.
    """
    if service.kind != KIND:
        raise RescueError(f"{service.name!r} is not a rescue service", field="service")
    try:
        polygon = area_clean(area)
    except ValueError as exc:
        raise RescueError(str(exc), field="params.area") from None
    ceiling = min(service.max_altitude_m or 120.0, MAX_ALTITUDE_M)
    altitude = DEFAULT_ALTITUDE_M if altitude_m is None else float(altitude_m)
    if not MIN_ALTITUDE_M <= altitude <= ceiling:
        raise RescueError(
            f"the search altitude must be {MIN_ALTITUDE_M:g} to {ceiling:g} m",
            field="params.altitude_m",
        )
    plan = coverage_plan(polygon, altitude_m=altitude, hfov_deg=DEFAULT_HFOV_DEG)
    center = area_centroid(polygon)
    with transaction.atomic():
        session = session_open(
            user=user,
            service=service,
            target=center,
            params={"area": [list(p) for p in polygon], "altitude_m": altitude},
        )
        mission = Mission.objects.create(
            session=session,
            area=[list(p) for p in polygon],
            altitude_m=altitude,
            speed_mps=SEARCH_SPEED_MPS,
            spacing_m=round(plan.spacing_m, 2),
            path=[list(p) for p in plan.waypoints],
            search_deadline=timezone.now() + timedelta(seconds=search_timeout_s()),
            status_text="looking for a search vehicle",
        )
        event_append(
            session=session,
            kind="mission_planned",
            data={
                "area_m2": round(plan.area_m2),
                "lines": plan.lines,
                "spacing_m": round(plan.spacing_m, 1),
                "footprint_m": round(plan.footprint_m, 1),
                "path_m": round(plan.length_m),
                "waypoints": len(plan.waypoints),
                "altitude_m": altitude,
            },
        )
        mission_schedule(mission.pk)
    return session
