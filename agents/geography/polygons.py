"""Plane geometry on (lon, lat) rings: clipping to a box and point-in-polygon.

Degrees are treated as plane coordinates: for a region of a few tens of kilometres the
error of that is far below what a land mask at metre resolution can tell. Rings follow
GeoJSON (``[lon, lat]`` pairs, first point repeated last or not); which side is inside
comes from the even-odd rule over all the rings of a region (an island in a lake in an
island needs nothing special).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

#: A point as GeoJSON writes it: (lon, lat).
Point = tuple[float, float]
Ring = list[Point]


@dataclass(frozen=True)
class Box:
    """A latitude/longitude box: south, west, north, east (degrees)."""

    south: float
    west: float
    north: float
    east: float

    def __post_init__(self) -> None:
        if not (-90 <= self.south < self.north <= 90 and -180 <= self.west < self.east <= 180):
            raise ValueError(f"not a box (south < north, west < east): {self}")

    def contains(self, lat: float, lon: float) -> bool:
        return self.south <= lat <= self.north and self.west <= lon <= self.east

    def overlaps(self, ring: Sequence[Sequence[float]]) -> bool:
        """Whether ``ring``'s bounding box meets this box."""
        lons = [p[0] for p in ring]
        lats = [p[1] for p in ring]
        return not (
            max(lons) < self.west
            or min(lons) > self.east
            or max(lats) < self.south
            or min(lats) > self.north
        )

    def as_list(self) -> list[float]:
        return [self.south, self.west, self.north, self.east]


def ring_clip(ring: Sequence[Sequence[float]], box: Box) -> Ring:
    """``ring`` clipped to ``box`` (Sutherland-Hodgman; the box is convex, the ring need
    not be). Where the ring leaves the box and comes back the result runs along the
    box's edge, which the even-odd test inside the box is not misled by. Returns [] when
    nothing of the ring's area is in the box (fewer than three points left)."""
    points: Ring = [(float(p[0]), float(p[1])) for p in ring]
    if len(points) > 1 and points[0] == points[-1]:
        points.pop()
    # (axis, bound, keep the side where the coordinate is >= bound?)
    for axis, bound, keep_above in (
        (0, box.west, True),
        (0, box.east, False),
        (1, box.south, True),
        (1, box.north, False),
    ):
        if not points:
            return []

        def inside(
            p: Point, axis: int = axis, bound: float = bound, above: bool = keep_above
        ) -> bool:
            return p[axis] >= bound if above else p[axis] <= bound

        def crossing(a: Point, b: Point, axis: int = axis, bound: float = bound) -> Point:
            t = (bound - a[axis]) / (b[axis] - a[axis])
            other = 1 - axis
            value = a[other] + t * (b[other] - a[other])
            return (bound, value) if axis == 0 else (value, bound)

        out: Ring = []
        previous = points[-1]
        for current in points:
            if inside(current):
                if not inside(previous):
                    out.append(crossing(previous, current))
                out.append(current)
            elif inside(previous):
                out.append(crossing(previous, current))
            previous = current
        points = out
    distinct = {(round(x, 9), round(y, 9)) for x, y in points}
    return points if len(distinct) >= 3 else []


class EvenOdd:
    """Point-in-polygon by the even-odd rule over a set of rings, with the edges
    bucketed by latitude band so a test looks at a few edges, not all of them."""

    def __init__(
        self, rings: Iterable[Sequence[Sequence[float]]], box: Box, bands: int = 64
    ) -> None:
        self.box = box
        self.bands = max(1, bands)
        self._height = (box.north - box.south) / self.bands
        self._edges: list[list[tuple[float, float, float, float]]] = [[] for _ in range(self.bands)]
        for ring in rings:
            n = len(ring)
            for i in range(n):
                x1, y1 = float(ring[i][0]), float(ring[i][1])
                x2, y2 = float(ring[(i + 1) % n][0]), float(ring[(i + 1) % n][1])
                if y1 == y2:
                    continue  # a horizontal edge is never crossed by a horizontal ray
                for band in range(self._band(min(y1, y2)), self._band(max(y1, y2)) + 1):
                    self._edges[band].append((x1, y1, x2, y2))

    def _band(self, lat: float) -> int:
        index = int((lat - self.box.south) / self._height) if self._height > 0 else 0
        return min(self.bands - 1, max(0, index))

    def inside(self, lat: float, lon: float) -> bool:
        """Whether (lat, lon) is inside an odd number of rings (a ray to the east
        crosses an odd number of edges)."""
        crossings = 0
        for x1, y1, x2, y2 in self._edges[self._band(lat)]:
            if (y1 > lat) != (y2 > lat):
                x = x1 + (lat - y1) * (x2 - x1) / (y2 - y1)
                if x > lon:
                    crossings += 1
        return crossings % 2 == 1
