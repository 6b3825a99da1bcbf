"""Where along the survey's path the vehicle is, and so which photo is due.

The photographer cannot count on seeing the vehicle at each place: the autopilot flies
the lines at its own pace, and a picture that takes long (a slow camera, a busy
companion computer) lets the vehicle fly past the next place, round the end of a line
and on. So each place is judged by where the vehicle is on the *path*: the photo
places from the first of this flight on, joined in flight order (along each line, then
across to the next). A place is

- ``NOW`` when the vehicle is within the photo radius of it;
- ``LATE`` when the vehicle is past it on the path but still on its line, or has left
  the line but is still within ``late_m`` of it (the picture, tagged where it was
  taken, still covers the line the place is on: the mosaic puts it where it was taken);
- ``MISSED`` when the vehicle has left the place's line and is further than that (a
  picture now would be of another line: the place is reported missed, and the survey's
  coverage shows the gap);
- ``WAIT`` otherwise: the vehicle has not reached it, or is off the path (on its way
  to the area, or home).

Before the first photo of the flight the vehicle may be coming from anywhere, across
the lines: it joins the path only at the first place or just past it, along its line.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from typing import Final

from agents.geo import local_offset_m
from agents.missions.spec import LatLon

#: Off the path by less than this (or half the photo spacing, if more), the vehicle is
#: on it: ArduPilot tracks a line to a metre or two, and cuts corners by its
#: waypoint radius (WPNAV_RADIUS, 2 m by default).
TRACK_M: Final = 3.0


class Due(enum.Enum):
    """What to do about the next place (module docstring)."""

    WAIT = "wait"
    NOW = "now"
    LATE = "late"
    MISSED = "missed"


class PhotoRoute:
    """The survey's photo places ``points`` (``(line, place)`` in flight order) from
    ``start`` on, as a path (module docstring). ``radius_m``: near enough to be at a
    place; ``late_m``: how far past its place a photo is still worth taking."""

    def __init__(
        self,
        points: Sequence[tuple[int, LatLon]],
        *,
        start: int,
        radius_m: float,
        late_m: float,
        track_m: float,
    ) -> None:
        #: The local frame's origin: the flight's first place (``xy[start]`` is 0, 0).
        self.origin = points[start][1]
        self.start = start
        self.lines = [line for line, _ in points]
        self.xy = [local_offset_m(self.origin, place) for _, place in points]
        self.radius_m = radius_m
        self.late_m = max(late_m, radius_m)
        self.track_m = track_m

    def due(self, here: LatLon, index: int, *, joined: bool, over: bool = False) -> Due:
        """Place ``index``, the vehicle at ``here``: ``joined`` once it has been on the
        path (a photo of this flight taken); ``over`` once the flight is over (the
        return home has begun: every place left is behind the vehicle)."""
        p = local_offset_m(self.origin, here)
        gap = _length(p, self.xy[index])
        if gap <= self.radius_m:
            return Due.NOW
        past = True if over else self._past(p, index, joined=joined)
        if past is None:
            return Due.WAIT
        if past == "line" or gap <= self.late_m:
            return Due.LATE
        return Due.MISSED

    def _past(self, p: tuple[float, float], index: int, *, joined: bool) -> str | None:
        """Where the vehicle at ``p`` is beyond place ``index`` on the path: ``"line"``,
        further along the place's own line; ``"beyond"``, past its line; None, not past
        it (or off the path)."""
        last = len(self.xy) - 1
        if index >= last:
            return None  # nothing beyond the last place but the way home (``over``)
        if not joined:
            # Only along the first place's own segment, past the place.
            along, off = _on_segment(p, self.xy[index], self.xy[index + 1])
            if off > self.track_m or along <= self.radius_m:
                return None
            return self._along(index, index)
        # The nearest segment from the one before the place to the end of the next
        # line: the path there, never a later line the vehicle may fly near.
        end = index
        while end < last and self.lines[end + 1] <= self.lines[index] + 1:
            end += 1
        best: tuple[float, int, float] | None = None
        for k in range(max(index - 1, self.start), min(end, last)):
            along, off = _on_segment(p, self.xy[k], self.xy[k + 1])
            if best is None or off < best[0]:
                best = (off, k, along)
        if best is None or best[0] > self.track_m:
            return None
        _, k, along = best
        if k < index or (k == index and along <= self.radius_m):
            return None
        return self._along(index, k)

    def _along(self, index: int, k: int) -> str:
        """Segment ``k`` (place ``k`` to the next) against place ``index``'s line."""
        line = self.lines[index]
        return "line" if self.lines[k] == line and self.lines[k + 1] == line else "beyond"


def _length(a: tuple[float, float], b: tuple[float, float]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def _on_segment(
    p: tuple[float, float], a: tuple[float, float], b: tuple[float, float]
) -> tuple[float, float]:
    """``p`` against segment ``a``→``b``: how far along it from ``a`` its nearest point
    is (metres, 0 to the segment's length), and how far off it ``p`` is."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    length = math.hypot(dx, dy)
    if length < 1e-9:
        return 0.0, _length(p, a)
    t = max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / (length * length)))
    nearest = (a[0] + t * dx, a[1] + t * dy)
    return t * length, _length(p, nearest)


__all__ = ["TRACK_M", "Due", "PhotoRoute"]
