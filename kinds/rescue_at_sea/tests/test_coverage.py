"""The lawnmower planner: the path covers the area with the camera's footprint."""

from __future__ import annotations

import itertools
import math

import pytest

from agents.geo import distance_m, local_offset_m, offset
from kinds.rescue_at_sea.coverage import (
    AreaError,
    area_centroid,
    area_clean,
    coverage_plan,
    footprint_width_m,
    line_spacing_m,
    point_in_area,
)

ORIGIN = (40.6405, -8.7600)


def rectangle(width_m: float, height_m: float, origin=ORIGIN) -> list[tuple[float, float]]:
    return [
        origin,
        offset(origin, 0, width_m),
        offset(origin, height_m, width_m),
        offset(origin, height_m, 0),
    ]


def test_footprint_and_spacing_follow_the_camera() -> None:
    # 57° across from 40 m: about 43.5 m of sea in view; lines 20 % closer than that.
    assert footprint_width_m(40) == pytest.approx(43.45, abs=0.05)
    assert line_spacing_m(40) == pytest.approx(0.8 * footprint_width_m(40))
    assert line_spacing_m(80) == pytest.approx(2 * line_spacing_m(40))


def test_every_point_of_a_rectangle_is_seen() -> None:
    area = rectangle(400, 250)
    plan = coverage_plan(area_clean(area), altitude_m=40)
    half = plan.footprint_m / 2
    # Sample the area on a 10 m grid: each point lies within half a footprint of a pass.
    passes = list(zip(plan.waypoints[::2], plan.waypoints[1::2], strict=True))
    for north in range(5, 250, 10):
        for east in range(5, 400, 10):
            point = offset(ORIGIN, north, east)
            nearest = min(_distance_to_segment(point, a, b) for a, b in passes)
            assert nearest <= half, (north, east, nearest)
    # Lines run along the longest edge (east-west here): few turns.
    assert plan.lines == math.ceil(250 / plan.spacing_m)
    assert plan.length_m == pytest.approx(
        plan.lines * 400 + (plan.lines - 1) * plan.spacing_m, rel=0.05
    )


def test_path_alternates_direction_and_starts_near_the_vehicle() -> None:
    area = area_clean(rectangle(300, 200))
    far_corner = offset(ORIGIN, 200, 300)
    plan = coverage_plan(area, altitude_m=40, start_near=far_corner)
    assert distance_m(plan.waypoints[0], far_corner) < distance_m(plan.waypoints[-1], far_corner)
    east = [local_offset_m(ORIGIN, p)[1] for p in plan.waypoints]
    legs = [(east[i + 1] - east[i]) for i in range(0, len(east) - 1, 2)]
    assert all(a * b < 0 for a, b in itertools.pairwise(legs))


def test_concave_area_is_clipped_not_flown_over() -> None:
    # A U shape: the notch in the middle must not be crossed by a search line.
    u = [
        ORIGIN,
        offset(ORIGIN, 0, 300),
        offset(ORIGIN, 300, 300),
        offset(ORIGIN, 300, 200),
        offset(ORIGIN, 100, 200),
        offset(ORIGIN, 100, 100),
        offset(ORIGIN, 300, 100),
        offset(ORIGIN, 300, 0),
    ]
    plan = coverage_plan(area_clean(u), altitude_m=30)
    notch = offset(ORIGIN, 200, 150)
    passes = list(zip(plan.waypoints[::2], plan.waypoints[1::2], strict=True))
    assert min(_distance_to_segment(notch, a, b) for a, b in passes) > 30
    assert point_in_area(offset(ORIGIN, 50, 150), u)
    assert not point_in_area(notch, u)
    assert point_in_area(offset(ORIGIN, 200, 190), u, margin_m=15)


def test_centroid_of_a_rectangle() -> None:
    c = area_centroid(rectangle(400, 200))
    north, east = local_offset_m(ORIGIN, c)
    assert (north, east) == (pytest.approx(100, abs=0.5), pytest.approx(200, abs=0.5))


@pytest.mark.parametrize(
    ("area", "message"),
    [
        ("north sea", "list of"),
        ([[40.6, -8.7], [40.61, -8.7]], "at least 3"),
        ([[40.6, -8.7], [40.61, -8.7], [91, 0]], "not a valid"),
        ([[40.6, -8.7], [40.61, -8.7], [40.6, "x"]], "point 2"),
        ([[40.6, -8.7], [40.6, -8.69], [40.61, -8.7], [40.61, -8.69]], "cross"),
        ([ORIGIN, offset(ORIGIN, 0, 5), offset(ORIGIN, 5, 5)], "too small"),
        (rectangle(10_000, 5_000), "too large"),
        ([[40.6 + i * 1e-4, -8.7 + (i % 2) * 1e-3] for i in range(70)], "at most"),
        ([[40.6, -8.7], [40.61, -8.7], [40.6, float("nan")]], "not a valid"),
        ([[40.6, -8.7], [40.61, -8.7], [True, -8.69]], "point 2"),
    ],
)
def test_bad_areas_are_refused_with_the_reason(area, message) -> None:
    with pytest.raises(AreaError, match=message):
        area_clean(area)


def test_closing_vertex_is_accepted() -> None:
    area = rectangle(100, 100)
    assert area_clean([*area, area[0]]) == area


def _distance_to_segment(p, a, b) -> float:
    ax, ay = local_offset_m(ORIGIN, a)
    bx, by = local_offset_m(ORIGIN, b)
    px, py = local_offset_m(ORIGIN, p)
    dx, dy = bx - ax, by - ay
    t = max(0.0, min(1.0, ((px - ax) * dx + (py - ay) * dy) / (dx * dx + dy * dy)))
    return math.dist((px, py), (ax + t * dx, ay + t * dy))
