"""The ``survey`` mission's spec: a grid of photo lines flown at one altitude.

The photos' places are a function of the spec (:func:`SurveySpec.photo_points`), which
the platform and the agent both call: a photo's index names the same place on both
sides, and a survey handed over resumes at an index.
"""

from __future__ import annotations

import math
from typing import Annotated, Final

from msgspec import Meta

from agents.geo import distance_m
from agents.missions.spec import Altitude, LatLon, MissionSpec, Speed, spec_invalid

MAX_LINES: Final = 200
MAX_PHOTOS: Final = 2000

#: A photo line: where it starts and where it ends, flown in that order.
Line = tuple[LatLon, LatLon]


class SurveySpec(MissionSpec, frozen=True, kw_only=True, tag="survey"):
    """Fly ``lines`` in order at ``altitude_m``, photographing straight down every
    ``spacing_m`` along each (both ends included), from photo ``start_photo`` on; then
    go home."""

    lines: Annotated[tuple[Line, ...], Meta(min_length=1, max_length=MAX_LINES)]
    spacing_m: Annotated[float, Meta(ge=0.5, le=1000)]
    altitude_m: Altitude
    speed_mps: Speed = 5.0
    #: The photos before this one were taken already (by a vehicle that gave up).
    start_photo: Annotated[int, Meta(ge=0)] = 0

    def check(self) -> None:
        count = len(self.photo_points())
        if count > MAX_PHOTOS:
            raise spec_invalid("spacing_m", f"makes {count} photos; at most {MAX_PHOTOS}")
        if self.start_photo >= count:
            raise spec_invalid("start_photo", f"an integer in [0, {count - 1}]")

    def photo_points(self) -> list[tuple[int, LatLon]]:
        """Every photo's place, in flight order, as ``(line index, [lat, lon])``."""
        return survey_photo_points(self.lines, self.spacing_m)


def survey_photo_points(lines: tuple[Line, ...], spacing_m: float) -> list[tuple[int, LatLon]]:
    """Photos along each of ``lines``, evenly, no further apart than ``spacing_m``, both
    ends included (a line shorter than that: one photo at each end, or one if it is a
    point)."""
    points: list[tuple[int, LatLon]] = []
    for number, (start, end) in enumerate(lines):
        length = distance_m(start, end)
        gaps = max(1, math.ceil(length / spacing_m - 1e-9)) if length > 0.01 else 0
        north = (end[0] - start[0]) / max(gaps, 1)
        east = (end[1] - start[1]) / max(gaps, 1)
        for k in range(gaps + 1):
            points.append((number, (start[0] + north * k, start[1] + east * k)))
    return points


__all__ = ["MAX_LINES", "MAX_PHOTOS", "Line", "SurveySpec", "survey_photo_points"]
