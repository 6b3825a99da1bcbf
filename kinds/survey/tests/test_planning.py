"""The photo grid planned from the area, the resolution, the overlaps and the camera:
its photos cover the whole area with the asked overlaps; and what a user may ask is
checked, naming the field."""

from __future__ import annotations

import itertools
import math
from typing import Any

import pytest

from agents.geo import distance_m, offset
from agents.missions.survey.spec import survey_photo_points
from kinds.survey.geometry import Footprint, coverage, grid_plan
from kinds.survey.request import params_clean
from services.kit import CameraOptics, RequestError

CAMPUS = (40.6306, -8.6588)
#: quad-1's survey camera (services/demo.py).
QUAD = CameraOptics(hfov_deg=73.7, width_px=1024, height_px=768)


def area(*corners: tuple[float, float]) -> list[tuple[float, float]]:
    """Corners given as (north, east) metres from the campus station."""
    return [offset(CAMPUS, n, e) for n, e in corners]


#: An L-shaped field with a slanted side (its longest edge sets the lines).
L_SHAPE = area((60, -40), (60, 50), (120, 70), (150, 20), (110, -10), (110, -40))


def footprints_of(grid, optics: CameraOptics) -> list[Footprint]:
    """The planned photos' footprints, each facing along its line."""
    out = []
    for line, point in survey_photo_points(tuple(grid.lines), grid.spacing_m):
        start, end = grid.lines[line]
        north = distance_m(start, (end[0], start[1])) * (1 if end[0] >= start[0] else -1)
        east = distance_m(start, (start[0], end[1])) * (1 if end[1] >= start[1] else -1)
        heading = math.degrees(math.atan2(east, north)) % 360
        out.append(
            Footprint.of(
                lat=point[0],
                lon=point[1],
                alt=grid.altitude_m,
                heading_deg=heading,
                hfov_deg=optics.hfov_deg,
                width=optics.width_px,
                height=optics.height_px,
            )
        )
    return out


@pytest.mark.parametrize(
    ("gsd_cm", "front", "side"), [(2.0, 0.75, 0.65), (3.0, 0.8, 0.7), (5.0, 0.6, 0.4)]
)
def test_the_grid_covers_the_area_with_the_asked_overlaps(gsd_cm, front, side) -> None:
    grid = grid_plan(L_SHAPE, optics=QUAD, gsd_m=gsd_cm / 100, front=front, side=side)
    # The altitude gives the resolution: 1024 px across the footprint.
    across, along = grid.footprint_m
    assert across / 1024 == pytest.approx(gsd_cm / 100)
    assert grid.altitude_m == pytest.approx(QUAD.altitude_for_m(gsd_cm / 100))
    points = survey_photo_points(tuple(grid.lines), grid.spacing_m)
    # Along a line: neighbours overlap by the front overlap at least.
    for (la, a), (lb, b) in itertools.pairwise(points):
        if la == lb:
            assert 1 - distance_m(a, b) / along >= front - 1e-6
    # Between lines: by the side overlap at least (their distance, perpendicular).
    assert 1 - grid.line_spacing_m / across >= side - 1e-6
    assert len(grid.lines) >= 2
    assert coverage(L_SHAPE, footprints_of(grid, QUAD)) >= 0.95


def test_a_long_narrow_field_is_flown_along_its_length() -> None:
    strip = area((0, 100), (10, 300), (30, 299), (20, 99))  # 200 m long, slanted
    grid = grid_plan(strip, optics=QUAD, gsd_m=0.01, front=0.75, side=0.65)
    # About 20 m wide: a few lines, each the strip's length.
    assert 2 <= len(grid.lines) <= 5
    assert all(distance_m(start, end) > 150 for start, end in grid.lines)
    assert coverage(strip, footprints_of(grid, QUAD)) >= 0.95


def polygon(*corners: tuple[float, float]) -> list[list[float]]:
    return [list(p) for p in area(*corners)]


SQUARE = polygon((0, 0), (0, 50), (40, 50), (40, 0))
GOOD: dict[str, Any] = {"polygon": SQUARE, "gsd_cm": 3}


def test_a_good_request_is_cleaned_with_default_overlaps() -> None:
    cleaned = params_clean(GOOD)
    assert cleaned["front_overlap"] == 75 and cleaned["side_overlap"] == 65
    closed = {**GOOD, "polygon": [*SQUARE, SQUARE[0]]}
    assert params_clean(closed)["polygon"] == cleaned["polygon"]


@pytest.mark.parametrize(
    ("change", "field", "words"),
    [
        ({"polygon": polygon((0, 0), (0, 50))}, "params.polygon", "3 to 60 points"),
        (
            {"polygon": polygon((0, 0), (40, 50), (0, 50), (40, 0))},
            "params.polygon",
            "crosses itself",
        ),
        (
            {"polygon": polygon((0, 0), (0, 5), (5, 5))},
            "params.polygon",
            "an area is 200 m² to 1 km²",
        ),
        (
            {"polygon": polygon((0, 0), (0, 3000), (3000, 3000), (3000, 0))},
            "params.polygon",
            "km across",
        ),
        ({"polygon": [[95, 0], [0, 0], [0, 1]]}, "params.polygon[0][0]", "from -85 to 85"),
        ({"polygon": polygon((0, 0), (0, 50), (0, 0), (40, 0))}, "params.polygon", "twice"),
        ({"gsd_cm": 0.1}, "params.gsd_cm", "from 0.5 to 20 cm a pixel"),
        ({"gsd_cm": "fine"}, "params.gsd_cm", "a number"),
        ({"front_overlap": 95}, "params.front_overlap", "from 50 to 90 %"),
        ({"side_overlap": 10}, "params.side_overlap", "from 30 to 85 %"),
        ({"colour": "red"}, "params.colour", "unknown field"),
    ],
)
def test_a_bad_request_is_refused_naming_the_field(change, field, words) -> None:
    with pytest.raises(RequestError) as refused:
        params_clean({**GOOD, **change})
    assert refused.value.field == field and words in str(refused.value), str(refused.value)
