"""Small geodesy helpers shared by the platform and the agent (no Django here)."""

from __future__ import annotations

import math

EARTH_RADIUS_M = 6_371_008.8  # mean radius (IUGG)


def distance_m(a: tuple[float, float], b: tuple[float, float]) -> float:
    """Great-circle distance in metres between two (lat, lon) points in degrees."""
    lat1, lon1 = map(math.radians, a)
    lat2, lon2 = map(math.radians, b)
    h = (
        math.sin((lat2 - lat1) / 2) ** 2
        + math.cos(lat1) * math.cos(lat2) * math.sin((lon2 - lon1) / 2) ** 2
    )
    return 2 * EARTH_RADIUS_M * math.asin(min(1.0, math.sqrt(h)))


def offset(origin: tuple[float, float], north_m: float, east_m: float) -> tuple[float, float]:
    """The (lat, lon) reached by moving ``north_m`` and ``east_m`` from ``origin``.

    Flat-earth approximation: good to centimetres over the few kilometres a vehicle
    covers in one session.
    """
    lat, lon = origin
    dlat = north_m / EARTH_RADIUS_M
    dlon = east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat)))
    return (lat + math.degrees(dlat), lon + math.degrees(dlon))


def local_offset_m(origin: tuple[float, float], point: tuple[float, float]) -> tuple[float, float]:
    """(north, east) metres from ``origin`` to ``point``; inverse of :func:`offset`."""
    north = math.radians(point[0] - origin[0]) * EARTH_RADIUS_M
    east = math.radians(point[1] - origin[1]) * EARTH_RADIUS_M * math.cos(math.radians(origin[0]))
    return (north, east)
