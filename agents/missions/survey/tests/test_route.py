"""The photographer's judgement of where the drone is on the survey's path
(agents.missions.survey.route), on three lines of 40 m, 12 m apart, a photo every
10 m (places 0-4 eastwards at 30 m north, 5-9 westwards at 42 m, 10-14 eastwards at
54 m)."""

from __future__ import annotations

from agents.geo import offset
from agents.missions.spec import LatLon
from agents.missions.survey.route import TRACK_M, Due, PhotoRoute
from agents.missions.survey.runner import photo_radius_m
from agents.missions.survey.spec import survey_photo_points
from tests.agents.mission_rig import HOME

LINES = (
    (offset(HOME, 30, 20), offset(HOME, 30, 60)),
    (offset(HOME, 42, 60), offset(HOME, 42, 20)),
    (offset(HOME, 54, 20), offset(HOME, 54, 60)),
)
POINTS = survey_photo_points(LINES, 10)


def route(start: int = 0) -> PhotoRoute:
    return PhotoRoute(
        POINTS, start=start, radius_m=photo_radius_m(10), late_m=10, track_m=max(TRACK_M, 5)
    )


def at(north: float, east: float) -> LatLon:
    return offset(HOME, north, east)


def test_a_place_is_due_when_the_drone_is_there_and_not_before() -> None:
    r = route()
    assert r.due(at(30, 21), 0, joined=False) is Due.NOW
    assert r.due(at(30, 36), 2, joined=True) is Due.WAIT  # 4 m before it, along the line
    assert r.due(at(30, 38), 2, joined=True) is Due.NOW


def test_a_place_passed_is_photographed_late_on_its_line_and_missed_beyond_a_spacing() -> None:
    r = route()
    assert r.due(at(30, 46), 2, joined=True) is Due.LATE
    # However late, along its own line: the picture still covers the line.
    assert r.due(at(30, 58), 2, joined=True) is Due.LATE
    # Line 0's end, the drone rounding it to line 1, then along line 1.
    assert r.due(at(36, 60), 4, joined=True) is Due.LATE
    assert r.due(at(36, 60), 3, joined=True) is Due.MISSED  # off its line, 11.7 m away
    assert r.due(at(42, 55), 4, joined=True) is Due.MISSED
    # Line 1's start, 4 m along it: late; its next place is not reached yet.
    assert r.due(at(42, 56), 5, joined=True) is Due.LATE
    assert r.due(at(42, 56), 6, joined=True) is Due.WAIT


def test_before_the_first_photo_only_the_first_places_own_line_counts() -> None:
    r = route()
    # On the way to the area, crossing line 0 and line 1 ahead of their places.
    assert r.due(at(30, 45), 0, joined=False) is Due.WAIT
    assert r.due(at(10, 0), 0, joined=False) is Due.WAIT
    # Just past the first place along its line: it is there, late.
    assert r.due(at(30, 25), 0, joined=False) is Due.LATE
    # A drone taking over at photo 7 flies across line 0 and line 2 on its way.
    resumed = route(start=7)
    assert resumed.due(at(30, 40), 7, joined=False) is Due.WAIT
    assert resumed.due(at(54, 40), 7, joined=False) is Due.WAIT
    assert resumed.due(at(42, 36), 7, joined=False) is Due.LATE


def test_off_the_path_and_at_the_last_place_it_waits_until_the_flight_is_over() -> None:
    r = route()
    assert r.due(at(30 - 8, 40), 2, joined=True) is Due.WAIT  # 8 m to the side
    # Line 2 is further on than the next line: never mistaken for the path from 3.
    assert r.due(at(54, 55), 3, joined=True) is Due.WAIT
    # The last place: only the return home makes it behind the drone.
    assert r.due(at(54, 64), 14, joined=True) is Due.WAIT
    assert r.due(at(54, 64), 14, joined=True, over=True) is Due.LATE
    assert r.due(at(30, 0), 14, joined=True, over=True) is Due.MISSED
