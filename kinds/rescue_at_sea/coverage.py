"""Coverage paths for area searches: a lawnmower (boustrophedon) pattern over a polygon.

The search camera looks straight down, so it sees a strip ``2·h·tan(hfov/2)`` wide at
altitude ``h``. Lines are laid that far apart, less an overlap that leaves no gap when
the drone drifts or banks, parallel to the polygon's longest edge (fewest turns for the
usual long strip of coast or sea), and joined end to end, alternating direction. Each
line is clipped to the polygon, so concave areas are covered without flying far
outside them; a line the polygon cuts in two becomes two passes.

Everything works in a local flat frame (metres north/east of the polygon's first
vertex), exact to centimetres over the few kilometres of a search.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

from agents.geo import distance_m, local_offset_m, offset

#: Default horizontal field of view of a search drone's thermal camera (FLIR Lepton 3.5).
DEFAULT_HFOV_DEG = 57.0
#: Side overlap between neighbouring strips.
OVERLAP = 0.2
MAX_VERTICES = 64
#: Largest area one mission may search (a drone's battery covers far less at useful
#: altitudes: the range check refuses what cannot be flown).
MAX_AREA_M2 = 25_000_000.0
MIN_AREA_M2 = 100.0

LatLon = tuple[float, float]
XY = tuple[float, float]  # (east, north) metres


class AreaError(ValueError):
    """The search area is not a usable polygon; the message says why."""


@dataclass(frozen=True)
class CoveragePlan:
    """A search path: waypoints in flying order and the figures behind them."""

    waypoints: list[LatLon]
    spacing_m: float
    footprint_m: float
    length_m: float
    area_m2: float
    lines: int


def footprint_width_m(altitude_m: float, hfov_deg: float = DEFAULT_HFOV_DEG) -> float:
    """Width of ground a nadir camera sees from ``altitude_m``."""
    return 2.0 * altitude_m * math.tan(math.radians(hfov_deg) / 2.0)


def line_spacing_m(altitude_m: float, hfov_deg: float = DEFAULT_HFOV_DEG) -> float:
    """Distance between neighbouring search lines: the footprint less the overlap."""
    return footprint_width_m(altitude_m, hfov_deg) * (1.0 - OVERLAP)


def area_clean(raw: object) -> list[LatLon]:
    """Validate a polygon given as [[lat, lon], ...] (closing vertex optional).

    Returns the vertices as tuples. Raises AreaError naming the problem: not a list,
    fewer than 3 or more than MAX_VERTICES vertices, a coordinate out of range,
    crossing edges, or an area too small or too large.
    """
    if not isinstance(raw, list | tuple):
        raise AreaError("the area must be a list of [lat, lon] points")
    points: list[LatLon] = []
    for i, p in enumerate(raw):
        if (
            not isinstance(p, list | tuple)
            or len(p) != 2
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in p)
        ):
            raise AreaError(f"point {i} must be [lat, lon] numbers")
        lat, lon = float(p[0]), float(p[1])
        if not (math.isfinite(lat) and math.isfinite(lon)) or abs(lat) > 85 or abs(lon) > 180:
            raise AreaError(f"point {i} is not a valid latitude/longitude")
        points.append((lat, lon))
    if len(points) > 1 and points[0] == points[-1]:
        points.pop()
    if len(points) < 3:
        raise AreaError("the area needs at least 3 points")
    if len(points) > MAX_VERTICES:
        raise AreaError(f"the area may have at most {MAX_VERTICES} points")
    xy = _to_local(points)
    if _self_intersects(xy):
        raise AreaError("the area's edges cross each other; draw a simple polygon")
    area = abs(_signed_area(xy))
    if area < MIN_AREA_M2:
        raise AreaError(f"the area is too small ({area:.0f} m², at least {MIN_AREA_M2:.0f})")
    if area > MAX_AREA_M2:
        raise AreaError(f"the area is too large ({area / 1e6:.1f} km², at most 25 km²)")
    return points


def coverage_plan(
    area: Sequence[LatLon],
    *,
    altitude_m: float,
    hfov_deg: float = DEFAULT_HFOV_DEG,
    start_near: LatLon | None = None,
) -> CoveragePlan:
    """The lawnmower path over ``area`` (validated by :func:`area_clean`) at
    ``altitude_m``. ``start_near``: the path starts at whichever end is closer to it
    (where the vehicle comes from)."""
    origin = area[0]
    xy = _to_local(area)
    spacing = line_spacing_m(altitude_m, hfov_deg)
    angle = _longest_edge_angle(xy)
    # Rotate so the sweep lines are horizontal (constant y) in the working frame.
    rotated = [_rotate(p, -angle) for p in xy]
    ys = [p[1] for p in rotated]
    y_min, y_max = min(ys), max(ys)
    count = max(1, math.ceil((y_max - y_min) / spacing))
    # Centre the lines in the polygon's extent: half a margin at each side.
    first = y_min + ((y_max - y_min) - (count - 1) * spacing) / 2.0
    path: list[XY] = []
    lines = 0
    for i in range(count):
        y = first + i * spacing
        segments = _clip(rotated, y)
        if not segments:
            continue
        if lines % 2 == 1:
            segments = [(b, a) for a, b in reversed(segments)]
        for a, b in segments:
            path.append((a, y))
            path.append((b, y))
        lines += 1
    local = [_rotate(p, angle) for p in path]
    waypoints = [offset(origin, north, east) for east, north in local]
    if (
        start_near is not None
        and waypoints
        and distance_m(start_near, waypoints[-1]) < distance_m(start_near, waypoints[0])
    ):
        waypoints.reverse()
    length = sum(distance_m(a, b) for a, b in itertools.pairwise(waypoints))
    return CoveragePlan(
        waypoints=[(round(lat, 7), round(lon, 7)) for lat, lon in waypoints],
        spacing_m=spacing,
        footprint_m=footprint_width_m(altitude_m, hfov_deg),
        length_m=length,
        area_m2=abs(_signed_area(xy)),
        lines=lines,
    )


def area_centroid(area: Sequence[LatLon]) -> LatLon:
    """The polygon's centroid (area-weighted)."""
    xy = _to_local(area)
    a = _signed_area(xy)
    cx = cy = 0.0
    for (x0, y0), (x1, y1) in zip(xy, [*xy[1:], xy[0]], strict=True):
        cross = x0 * y1 - x1 * y0
        cx += (x0 + x1) * cross
        cy += (y0 + y1) * cross
    east, north = cx / (6 * a), cy / (6 * a)
    return offset(area[0], north, east)


def point_in_area(point: LatLon, area: Sequence[LatLon], *, margin_m: float = 0.0) -> bool:
    """True if ``point`` lies inside ``area`` or within ``margin_m`` of its edge."""
    xy = _to_local(area)
    north, east = local_offset_m(area[0], point)
    x, y = east, north
    inside = False
    for (x0, y0), (x1, y1) in zip(xy, [*xy[1:], xy[0]], strict=True):
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    if inside or margin_m <= 0:
        return inside
    return any(
        _segment_distance((x, y), a, b) <= margin_m
        for a, b in zip(xy, [*xy[1:], xy[0]], strict=True)
    )


# --- geometry in the local frame ---------------------------------------------------------
def _to_local(points: Sequence[LatLon]) -> list[XY]:
    origin = points[0]
    out = []
    for p in points:
        north, east = local_offset_m(origin, p)
        out.append((east, north))
    return out


def _signed_area(xy: Sequence[XY]) -> float:
    return 0.5 * sum(
        x0 * y1 - x1 * y0 for (x0, y0), (x1, y1) in zip(xy, [*xy[1:], xy[0]], strict=True)
    )


def _rotate(p: XY, angle: float) -> XY:
    c, s = math.cos(angle), math.sin(angle)
    return (p[0] * c - p[1] * s, p[0] * s + p[1] * c)


def _longest_edge_angle(xy: Sequence[XY]) -> float:
    edges = list(zip(xy, [*xy[1:], xy[0]], strict=True))
    (x0, y0), (x1, y1) = max(edges, key=lambda e: math.dist(e[0], e[1]))
    return math.atan2(y1 - y0, x1 - x0)


def _clip(polygon: Sequence[XY], y: float) -> list[tuple[float, float]]:
    """The x intervals where the horizontal line at ``y`` is inside ``polygon``."""
    xs = []
    for (x0, y0), (x1, y1) in zip(polygon, [*polygon[1:], polygon[0]], strict=True):
        # Half-open rule: a vertex exactly on the line is counted once.
        if (y0 > y) != (y1 > y):
            xs.append(x0 + (y - y0) * (x1 - x0) / (y1 - y0))
    xs.sort()
    return [(xs[i], xs[i + 1]) for i in range(0, len(xs) - 1, 2) if xs[i + 1] - xs[i] > 0.5]


def _segment_distance(p: XY, a: XY, b: XY) -> float:
    ax, ay = a
    dx, dy = b[0] - ax, b[1] - ay
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((p[0] - ax) * dx + (p[1] - ay) * dy) / length2))
    return math.dist(p, (ax + t * dx, ay + t * dy))


def _orientation(a: XY, b: XY, c: XY) -> float:
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


def _segments_cross(a: XY, b: XY, c: XY, d: XY) -> bool:
    d1, d2 = _orientation(c, d, a), _orientation(c, d, b)
    d3, d4 = _orientation(a, b, c), _orientation(a, b, d)
    return (d1 > 0) != (d2 > 0) and (d3 > 0) != (d4 > 0) and 0 not in (d1, d2, d3, d4)


def _self_intersects(xy: Sequence[XY]) -> bool:
    edges = list(zip(xy, [*xy[1:], xy[0]], strict=True))
    n = len(edges)
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue  # neighbours through the closing vertex
            if _segments_cross(*edges[i], *edges[j]):
                return True
    return False
