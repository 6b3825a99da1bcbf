"""Requesting a rescue: the search area drawn by the user, validated and planned.

:func:`rescue_request` checks the area and the altitude, plans the lawnmower path over
it (``coverage``), checks that a search drone of the fleet could ever fly it
(:func:`search_feasible`: from its station and back on a full battery), opens the
session and its mission, and schedules the first step. A search no drone can fly is
refused at once, saying what would work; one whose drone is busy is accepted and waits.
"""

from __future__ import annotations

from datetime import timedelta
from typing import Any

from django.db import transaction
from django.utils import timezone

from accounts.users import User
from agents.geo import distance_m
from kinds.rescue_at_sea.conf import search_timeout_s
from kinds.rescue_at_sea.coverage import (
    CoveragePlan,
    LatLon,
    area_centroid,
    area_clean,
    coverage_plan,
    line_spacing_m,
)
from kinds.rescue_at_sea.missions import SEARCH_SPEED_MPS
from kinds.rescue_at_sea.models import KIND, SEARCH, Mission
from kinds.rescue_at_sea.tasks import mission_schedule
from services.kit import RequestError, event_append, km, role_capable, session_open, trip_m
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


def area_words(m2: float, *, digits: int = 1) -> str:
    """An area for people: "4,000 m²", "0.2 km²" (``digits`` after the point)."""
    if m2 < 100_000:
        return f"{max(100, round(m2, -2)):,.0f} m²"
    return f"{m2 / 1e6:.{digits}f} km²"


def search_feasible(
    *, service: Service, polygon: list[LatLon], altitude_m: float, ceiling_m: float
) -> CoveragePlan:
    """The search's plan, from the end nearest the station of a search drone of the
    fleet that can fly it (there, the whole pattern, and back, on a full battery).

    Raises RescueError saying what would work when none can: the largest area the
    best-placed drone covers there at this altitude (and from the ceiling), or how far
    from its station it reaches."""
    capable = role_capable(service.roles.get(name=SEARCH))
    if not capable.vehicles:
        raise RescueError(f"no rescue can be flown: {capable.unmet}", field="params.area")
    best: tuple[float, str] | None = None  # metres of pattern left, who
    plans = []
    area_m2 = 0.0
    for drone in capable.vehicles:
        plan = coverage_plan(polygon, altitude_m=altitude_m, start_near=drone.home)
        area_m2 = plan.area_m2
        trip = trip_m(drone, plan.waypoints[0], plan.length_m)
        if drone.fits(trip):
            plans.append((distance_m(drone.home, plan.waypoints[0]), plan))
            continue
        left = drone.range_m - 2 * distance_m(drone.home, plan.waypoints[0])
        if best is None or left > best[0]:
            best = (left, f"{drone.name} from {drone.station}")
    if plans:
        return min(plans, key=lambda item: item[0])[1]
    assert best is not None
    left, who = best
    area = area_words(area_m2, digits=2)
    if left <= 0:
        reach = max(capable.vehicles, key=lambda d: d.radius_m())
        raise RescueError(
            f"this area is out of reach: {reach.name} searches at most about "
            f"{km(reach.radius_m())} from {reach.station} and back",
            field="params.area",
        )
    here = left * line_spacing_m(altitude_m)
    text = (
        f"this area ({area}) is larger than any search drone can cover there: the "
        f"largest area {who} can search is about {area_words(here)} at {altitude_m:g} m"
    )
    if ceiling_m > altitude_m:
        higher = left * line_spacing_m(ceiling_m)
        text += f" (about {area_words(higher)} from {ceiling_m:g} m up)"
    raise RescueError(f"{text}. Draw a smaller area or search from higher up.", field="params.area")


def rescue_request(
    *,
    user: User,
    service: Service,
    area: Any,
    altitude_m: float | None = None,
) -> Session:
    """Open a rescue session over ``area`` ([[lat, lon], ...]) and start its workflow.

    Raises RescueError when the area or altitude is unusable or no search drone of the
    fleet could ever fly it (saying what would work), AssignmentError when the
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
    plan = search_feasible(service=service, polygon=polygon, altitude_m=altitude, ceiling_m=ceiling)
    center = area_centroid(polygon)
    with transaction.atomic():
        session = session_open(
            user=user,
            service=service,
            target=center,
            params={"area": [list(p) for p in polygon], "altitude_m": altitude},
        ).session
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
