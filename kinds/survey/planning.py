"""Which drone flies a survey, and the grid it flies.

The surveyor is the service's ``surveyor`` role narrowed for the survey: a camera whose
optics it declares (``camera_hfov_deg``, ``camera_width_px``, ``camera_height_px``),
flying high enough for the asked ground resolution (the altitude it needs is within its
``max_altitude_m`` and :data:`CEILING_M`), with the range for the way there, the lines
and back. The grid is planned for the first surveyor's camera and kept: a drone that
takes over must fly it, so its camera must see at least as much ground from that
altitude, as sharply (:func:`camera_fits`).
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Sequence
from typing import Any

from agents.geo import distance_m
from kinds.survey.geometry import Grid, Point, grid_plan
from kinds.survey.models import SURVEYOR, Survey
from services.kit import CameraOptics, Reach, camera_optics, role_assign, role_capable
from services.models import Assignment, Service, ServiceRole

#: The highest and lowest a survey is flown (the usual limit for drones in open
#: airspace; below, a picture covers too little to be worth a photo).
CEILING_M = 120.0
FLOOR_M = 10.0


def surveyor_role(service: Service) -> ServiceRole:
    """The service's surveyor role, narrowed to drones declaring their camera's optics
    (an unsaved copy)."""
    role = service.roles.get(name=SURVEYOR)
    tight = copy.copy(role)
    minimums = dict(role.min_attributes or {})
    for name in ("camera_hfov_deg", "camera_width_px", "camera_height_px"):
        minimums[name] = max(float(minimums.get(name, 0)), 1.0)
    tight.min_attributes = minimums
    return tight


def altitude_limit_m(reach: Reach) -> float:
    """The highest this drone may survey from."""
    declared = reach.attributes.get("max_altitude_m")
    return min(CEILING_M, float(declared)) if declared else CEILING_M


def gsd_range_m(optics: CameraOptics, limit_m: float) -> tuple[float, float]:
    """The ground resolutions (m a pixel) a camera gives between FLOOR_M and ``limit_m``."""
    per_m = optics.footprint_m(1.0)[0] / optics.width_px
    return FLOOR_M * per_m, limit_m * per_m


def can_survey(reach: Reach, gsd_m: float) -> bool:
    """The drone's camera gives ``gsd_m`` between FLOOR_M and its altitude limit."""
    optics = camera_optics(reach.attributes)
    if optics is None:
        return False
    low, high = gsd_range_m(optics, altitude_limit_m(reach))
    return low - 1e-9 <= gsd_m <= high + 1e-9


def camera_fits(reach: Reach, plan: dict[str, Any], gsd_m: float) -> bool:
    """The drone can fly ``plan`` (planned for another camera): from its altitude, its
    pictures cover at least the planned footprint at ``gsd_m`` or sharper, and the
    altitude is within its limit."""
    optics = camera_optics(reach.attributes)
    if optics is None or plan["altitude_m"] > altitude_limit_m(reach) + 1e-6:
        return False
    across, along = optics.footprint_m(plan["altitude_m"])
    planned_across, planned_along = plan["footprint_m"]
    return (
        across >= planned_across - 1e-6
        and along >= planned_along - 1e-6
        and across / optics.width_px <= gsd_m * 1.0001
    )


def plan_for(
    polygon: Sequence[Point], optics: CameraOptics, *, gsd_m: float, front: float, side: float
) -> Grid:
    return grid_plan(polygon, optics=optics, gsd_m=gsd_m, front=front, side=side)


def plan_json(grid: Grid) -> dict[str, Any]:
    return {
        "lines": [[list(a), list(b)] for a, b in grid.lines],
        "spacing_m": grid.spacing_m,
        "altitude_m": grid.altitude_m,
        "footprint_m": list(grid.footprint_m),
        "line_spacing_m": grid.line_spacing_m,
    }


def plan_lines(plan: dict[str, Any]) -> tuple[tuple[Point, Point], ...]:
    return tuple(((a[0], a[1]), (b[0], b[1])) for a, b in plan["lines"])


def plan_length_m(plan: dict[str, Any]) -> float:
    return Grid(
        lines=list(plan_lines(plan)),
        spacing_m=plan["spacing_m"],
        altitude_m=plan["altitude_m"],
        footprint_m=tuple(plan["footprint_m"]),
        line_spacing_m=plan["line_spacing_m"],
    ).length_m()


def candidates(survey: Survey, *, exclude: Iterable[Any] = ()) -> list[Reach]:
    """The drones of the fleet that could fly this survey from where it stands, on a
    full battery: camera, altitude, and range for the way to the next photo, the rest
    of the lines and back."""
    role = surveyor_role(survey.session.service)
    gsd = survey.gsd_cm / 100
    start = tuple(survey.polygon[0])
    out = []
    for reach in role_capable(role, exclude=exclude).vehicles:
        if survey.plan is not None:
            if not camera_fits(reach, survey.plan, gsd):
                continue
            work = plan_length_m(survey.plan)
        else:
            optics = camera_optics(reach.attributes)
            if optics is None or not can_survey(reach, gsd):
                continue
            grid = plan_for(
                [tuple(p) for p in survey.polygon],
                optics,
                gsd_m=gsd,
                front=survey.front_overlap,
                side=survey.side_overlap,
            )
            work = grid.length_m()
        if reach.fits(2 * distance_m(reach.home, start) + work):
            out.append(reach)
    return out


def surveyor_assign(survey: Survey, *, exclude: Iterable[Any] = ()) -> Assignment:
    """Reserve the drone that arrives first among those that could fly the survey;
    raises services.kit.AssignmentError naming the unmet requirement."""
    excluded = {str(pk) for pk in exclude}
    fit = {str(r.pk) for r in candidates(survey, exclude=excluded)}
    role = surveyor_role(survey.session.service)
    unfit = [r.pk for r in role_capable(role).vehicles if str(r.pk) not in fit]
    work = plan_length_m(survey.plan) if survey.plan is not None else 0.0
    return role_assign(
        session=survey.session,
        role=role,
        target=(survey.polygon[0][0], survey.polygon[0][1]),
        extra_distance_m=work,
        exclude=[*excluded, *unfit],
    )
