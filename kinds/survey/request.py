"""Requesting a survey: the area, the ground resolution, the overlaps.

:func:`params_clean` validates what was asked (a simple polygon of a sensible size, a
resolution and overlaps in range); :func:`survey_request` checks that a drone of the
fleet could ever fly it (a camera giving that resolution within its altitude limit,
the range for the lines), then opens the survey. What no drone can ever fly is refused
at once, saying what would work; a survey whose drone is busy is accepted and waits.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from django.db import transaction

from accounts.users import User
from kinds.survey.geometry import area_m2, self_crossing, to_local
from kinds.survey.models import KIND, Survey
from kinds.survey.planning import (
    altitude_limit_m,
    candidates,
    gsd_range_m,
    surveyor_role,
)
from kinds.survey.tasks import survey_schedule
from services.kit import RequestError, camera_optics, event_append, role_capable, session_open
from services.models import Service, Session

MAX_VERTICES = 60
MIN_AREA_M2 = 200.0
MAX_AREA_M2 = 1_000_000.0
#: The widest an area may be, any way.
MAX_EXTENT_M = 2000.0
#: Ground resolution, cm a pixel.
MIN_GSD_CM, MAX_GSD_CM = 0.5, 20.0
#: Overlaps, percent: front (along a line) and side (between lines).
FRONT_RANGE = (50.0, 90.0)
SIDE_RANGE = (30.0, 85.0)
DEFAULT_FRONT, DEFAULT_SIDE = 75.0, 65.0

FIELDS = {"polygon", "gsd_cm", "front_overlap", "side_overlap"}


def _number(value: Any, field: str, low: float, high: float, unit: str) -> float:
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or not low <= value <= high
    ):
        raise RequestError(f"must be a number from {low:g} to {high:g}{unit}", field=field)
    return float(value)


def _polygon(value: Any) -> list[tuple[float, float]]:
    field = "params.polygon"
    if not isinstance(value, list) or not 3 <= len(value) <= MAX_VERTICES:
        raise RequestError(f"must be a list of 3 to {MAX_VERTICES} points [lat, lon]", field=field)
    points: list[tuple[float, float]] = []
    for i, point in enumerate(value):
        if not isinstance(point, list | tuple) or len(point) != 2:
            raise RequestError("must be [lat, lon]", field=f"{field}[{i}]")
        lat = _number(point[0], f"{field}[{i}][0]", -85, 85, "")
        lon = _number(point[1], f"{field}[{i}][1]", -180, 180, "")
        points.append((lat, lon))
    if points[0] == points[-1]:
        points.pop()  # closed by repeating the first: the same area
    if len(set(points)) != len(points) or len(points) < 3:
        raise RequestError("has a point twice: each corner once", field=field)
    lons = [lon for _, lon in points]
    if max(lons) - min(lons) > 180:
        raise RequestError("must not cross the 180th meridian", field=field)
    local = to_local(points[0], points)
    extent = max(
        max(n for n, _ in local) - min(n for n, _ in local),
        max(e for _, e in local) - min(e for _, e in local),
    )
    if extent > MAX_EXTENT_M:
        raise RequestError(
            f"is {extent / 1000:.1f} km across; an area is at most {MAX_EXTENT_M / 1000:g} km",
            field=field,
        )
    crossing = self_crossing(local)
    if crossing is not None:
        i, j = crossing
        raise RequestError(
            f"crosses itself: the side from point {i + 1} and the side from point "
            f"{j + 1} meet; draw the corners in order around the area",
            field=field,
        )
    area = area_m2(local)
    if not MIN_AREA_M2 <= area <= MAX_AREA_M2:
        raise RequestError(
            f"covers {area:,.0f} m²; an area is {MIN_AREA_M2:g} m² to {MAX_AREA_M2 / 1e6:g} km²",
            field=field,
        )
    return points


def params_clean(params: Mapping[str, Any]) -> dict[str, Any]:
    """A survey request's ``params``, validated (the one validation for the portal's
    form and the API); raises RequestError naming the field."""
    unknown = sorted(set(params) - FIELDS)
    if unknown:
        raise RequestError("unknown field", field=f"params.{unknown[0]}")
    for name in ("polygon", "gsd_cm"):
        if name not in params:
            raise RequestError("is required", field=f"params.{name}")
    polygon = _polygon(params["polygon"])
    gsd = _number(params["gsd_cm"], "params.gsd_cm", MIN_GSD_CM, MAX_GSD_CM, " cm a pixel")
    front = _number(
        params.get("front_overlap", DEFAULT_FRONT), "params.front_overlap", *FRONT_RANGE, " %"
    )
    side = _number(
        params.get("side_overlap", DEFAULT_SIDE), "params.side_overlap", *SIDE_RANGE, " %"
    )
    return {
        "polygon": [[lat, lon] for lat, lon in polygon],
        "gsd_cm": gsd,
        "front_overlap": front,
        "side_overlap": side,
    }


def _feasible(survey: Survey) -> None:
    """Raises RequestError, naming the field and what would work, when no drone of the
    fleet could ever fly ``survey`` (unsaved)."""
    role = surveyor_role(survey.session.service)
    drones = role_capable(role).vehicles
    if not drones:
        raise RequestError(
            f"no drone of the fleet declares a camera to survey with: {role_capable(role).unmet}",
            field="service",
        )
    if candidates(survey):
        return
    gsd = survey.gsd_cm / 100
    ranges = []
    for drone in drones:
        optics = camera_optics(drone.attributes)
        assert optics is not None  # the role asks for them
        low, high = gsd_range_m(optics, altitude_limit_m(drone))
        ranges.append((low, high, drone))
    if not any(low - 1e-9 <= gsd <= high + 1e-9 for low, high, _ in ranges):
        words = "; ".join(
            f"{d.name} {low * 100:.1f} to {high * 100:.1f}" for low, high, d in ranges
        )
        raise RequestError(
            f"no drone's camera gives {survey.gsd_cm:g} cm a pixel within its altitude "
            f"limits (cm a pixel: {words})",
            field="params.gsd_cm",
        )
    raise RequestError(
        "the area is too far, or its lines too long, for the drones' range "
        f"({', '.join(f'{d.name} from {d.station}' for d in drones)})",
        field="params.polygon",
    )


def survey_request(*, user: User, service: Service, params: Mapping[str, Any]) -> Session:
    """Open a survey of ``params`` (cleaned by :func:`params_clean`) and start its
    workflow. Raises services.kit.AssignmentError when the user may not use the
    service or is at its session limit; RequestError for another kind of service or a
    survey no drone of the fleet could ever fly."""
    if service.kind != KIND:
        raise RequestError(f"{service.name!r} is not a survey service", field="service")
    polygon = [(p[0], p[1]) for p in params["polygon"]]
    with transaction.atomic():
        session = session_open(
            user=user, service=service, target=polygon[0], params=dict(params)
        ).session
        survey = Survey(
            session=session,
            polygon=[list(p) for p in polygon],
            gsd_cm=params["gsd_cm"],
            front_overlap=params["front_overlap"] / 100,
            side_overlap=params["side_overlap"] / 100,
            status_text="looking for a drone",
        )
        # Inside the transaction: a refusal rolls the session back with it.
        _feasible(survey)
        survey.save()
        event_append(
            session=session,
            kind="survey_planned",
            data={
                "area_m2": round(area_m2(to_local(polygon[0], polygon))),
                "gsd_cm": survey.gsd_cm,
                "front_overlap": params["front_overlap"],
                "side_overlap": params["side_overlap"],
            },
        )
        survey_schedule(session.pk)
    return session
