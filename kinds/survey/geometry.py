"""The survey's geometry: the area checked, the photo grid planned from a camera, and
what the photos cover.

Everything is worked in a flat local frame, metres north and east of the area's first
vertex (:func:`agents.geo.local_offset_m`, good to centimetres over the few hundred
metres of a survey), and turned back into latitude and longitude at the end.

The grid (:func:`grid_plan`): the altitude at which one pixel of the camera covers the
asked ground resolution; lines along the area's longest edge, the picture's top along
the line (a copter faces where it flies), ``side`` overlap between lines and ``front``
overlap between photos of a line; each line spans the area within its picture's band,
so the pictures at its ends reach the edge.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from agents.geo import distance_m, local_offset_m, offset
from services.kit import CameraOptics

Point = tuple[float, float]  # (lat, lon) or, in the local frame, (north, east)


def to_local(origin: Point, points: Iterable[Point]) -> list[Point]:
    """``points`` (lat, lon) as (north, east) metres from ``origin``."""
    return [local_offset_m(origin, p) for p in points]


def to_global(origin: Point, points: Iterable[Point]) -> list[Point]:
    """(north, east) metres from ``origin`` as (lat, lon)."""
    return [offset(origin, n, e) for n, e in points]


def area_m2(local: Sequence[Point]) -> float:
    """The polygon's area (shoelace; any orientation)."""
    total = 0.0
    for (n1, e1), (n2, e2) in zip(local, [*local[1:], local[0]], strict=True):
        total += e1 * n2 - e2 * n1
    return abs(total) / 2


def _cross(o: Point, a: Point, b: Point) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _segments_cross(a: Point, b: Point, c: Point, d: Point) -> bool:
    """Segments ab and cd touch or cross (collinear overlaps included)."""
    d1, d2 = _cross(c, d, a), _cross(c, d, b)
    d3, d4 = _cross(a, b, c), _cross(a, b, d)
    if ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and 0 not in (d1, d2, d3, d4):
        return True

    def on(p: Point, q: Point, r: Point) -> bool:
        return min(p[0], q[0]) <= r[0] <= max(p[0], q[0]) and min(p[1], q[1]) <= r[1] <= max(
            p[1], q[1]
        )

    return (
        (d1 == 0 and on(c, d, a))
        or (d2 == 0 and on(c, d, b))
        or (d3 == 0 and on(a, b, c))
        or (d4 == 0 and on(a, b, d))
    )


def self_crossing(local: Sequence[Point]) -> tuple[int, int] | None:
    """The first two edges (by their first vertex's index) that cross or touch, other
    than neighbours at their shared vertex; None for a simple polygon."""
    n = len(local)
    edges = [(local[i], local[(i + 1) % n]) for i in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue
            if _segments_cross(*edges[i], *edges[j]):
                return (i, j)
    return None


@dataclass(frozen=True)
class Grid:
    """A planned photo grid: ``lines`` ((lat, lon) start and end, in flight order), the
    photos' ``spacing_m`` along them, the ``altitude_m``, each picture's ground
    ``footprint_m`` (across the line, along it) and the lines' spacing."""

    lines: list[tuple[Point, Point]]
    spacing_m: float
    altitude_m: float
    footprint_m: tuple[float, float]
    line_spacing_m: float

    def length_m(self) -> float:
        """The lines' length and the legs between them."""
        total = 0.0
        previous: Point | None = None
        for start, end in self.lines:
            if previous is not None:
                total += distance_m(previous, start)
            total += distance_m(start, end)
            previous = end
        return total


def _clip_band(local: Sequence[Point], low: float, high: float) -> list[Point]:
    """The polygon (in (along, across) coordinates) clipped to ``low <= across <=
    high`` (Sutherland-Hodgman, one half-plane at a time)."""

    def clip(points: list[Point], keep: float, sign: float) -> list[Point]:
        out: list[Point] = []
        for k, current in enumerate(points):
            previous = points[k - 1]
            inside_now = sign * (current[1] - keep) >= 0
            inside_before = sign * (previous[1] - keep) >= 0
            if inside_now != inside_before:
                t = (keep - previous[1]) / (current[1] - previous[1])
                out.append((previous[0] + t * (current[0] - previous[0]), keep))
            if inside_now:
                out.append(current)
        return out

    points = clip(list(local), low, 1.0)
    return clip(points, high, -1.0) if points else []


def grid_plan(
    polygon: Sequence[Point],
    *,
    optics: CameraOptics,
    gsd_m: float,
    front: float,
    side: float,
) -> Grid:
    """The photo grid over ``polygon`` (lat, lon) for a camera of ``optics`` at ground
    resolution ``gsd_m``, ``front`` and ``side`` overlaps (fractions); see the module
    docstring."""
    origin = polygon[0]
    local = to_local(origin, polygon)
    altitude = optics.altitude_for_m(gsd_m)
    across_m, along_m = optics.footprint_m(altitude)
    spacing = along_m * (1 - front)
    line_spacing = across_m * (1 - side)
    # Lines along the longest edge: the fewest turns for a long narrow area.
    longest = max(
        range(len(local)),
        key=lambda i: math.dist(local[i], local[(i + 1) % len(local)]),
    )
    (n1, e1), (n2, e2) = local[longest], local[(longest + 1) % len(local)]
    angle = math.atan2(n2 - n1, e2 - e1)  # of the lines, from east, counter-clockwise
    c, s = math.cos(angle), math.sin(angle)
    # (along, across) of each vertex.
    turned = [(e * c + n * s, -e * s + n * c) for n, e in local]
    low = min(y for _, y in turned)
    high = max(y for _, y in turned)
    count = max(1, math.ceil(max(0.0, (high - low) - across_m) / line_spacing - 1e-9) + 1)
    first = (low + high) / 2 - (count - 1) * line_spacing / 2
    lines: list[tuple[Point, Point]] = []
    for k in range(count):
        y = first + k * line_spacing
        band = _clip_band(turned, y - across_m / 2, y + across_m / 2)
        if not band:
            continue
        xs = [x for x, _ in band]
        ends = [(min(xs), y), (max(xs), y)]
        if len(lines) % 2:
            ends.reverse()  # back and forth
        # Back from (along, across) to (north, east), then to (lat, lon).
        as_local = [(x * s + y_ * c, x * c - y_ * s) for x, y_ in ends]
        start, end = to_global(origin, as_local)
        lines.append((start, end))
    return Grid(
        lines=lines,
        spacing_m=spacing,
        altitude_m=altitude,
        footprint_m=(across_m, along_m),
        line_spacing_m=line_spacing,
    )


# --- what the photos cover ---------------------------------------------------------------


@dataclass(frozen=True)
class Footprint:
    """The ground a nadir picture covers: its corners (lat, lon), clockwise from the
    top left (the top towards ``heading_deg``)."""

    corners: list[Point]
    center: Point
    heading_deg: float
    size_m: tuple[float, float]  # across, along

    @classmethod
    def of(
        cls,
        *,
        lat: float,
        lon: float,
        alt: float,
        heading_deg: float,
        hfov_deg: float,
        width: int,
        height: int,
    ) -> Footprint:
        across = 2 * max(alt, 0.5) * math.tan(math.radians(hfov_deg) / 2)
        along = across * height / width
        h = math.radians(heading_deg)
        corners = []
        for right, ahead in (
            (-across / 2, along / 2),
            (across / 2, along / 2),
            (across / 2, -along / 2),
            (-across / 2, -along / 2),
        ):
            east = right * math.cos(h) + ahead * math.sin(h)
            north = -right * math.sin(h) + ahead * math.cos(h)
            corners.append(offset((lat, lon), north, east))
        return cls(corners, (lat, lon), heading_deg, (across, along))


def _inside(
    polygon: Sequence[Point], north: npt.NDArray[np.float64], east: npt.NDArray[np.float64]
) -> npt.NDArray[np.bool_]:
    """Which of the points (north, east arrays) are inside ``polygon`` (local; even-odd
    rule)."""
    inside = np.zeros(north.shape, dtype=bool)
    count = len(polygon)
    for k in range(count):
        (n1, e1), (n2, e2) = polygon[k], polygon[(k - 1) % count]
        crosses = (n1 > north) != (n2 > north)
        with np.errstate(divide="ignore", invalid="ignore"):
            at = (e2 - e1) * (north - n1) / (n2 - n1) + e1
        inside ^= crosses & (east < at)
    return inside


def coverage(
    polygon: Sequence[Point], footprints: Iterable[Footprint], *, cells: int = 300
) -> float:
    """The fraction of ``polygon`` (lat, lon) that at least one of ``footprints``
    covers, measured on a grid of about ``cells`` x ``cells`` points over it."""
    origin = polygon[0]
    local = to_local(origin, polygon)
    norths = [n for n, _ in local]
    easts = [e for _, e in local]
    step = max(max(norths) - min(norths), max(easts) - min(easts)) / cells
    north, east = np.meshgrid(
        np.arange(min(norths) + step / 2, max(norths), step),
        np.arange(min(easts) + step / 2, max(easts), step),
        indexing="ij",
    )
    area = _inside(local, north, east)
    if not area.any():
        return 0.0
    covered = np.zeros_like(area)
    for footprint in footprints:
        covered |= _inside(to_local(origin, footprint.corners), north, east)
    return int(np.count_nonzero(covered & area)) / int(np.count_nonzero(area))
