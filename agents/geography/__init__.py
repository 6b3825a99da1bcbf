"""Land or water at a point: a land mask over packaged OpenStreetMap land polygons.

Pure Python and no Django, for the agent (the boat's simulator keeps the boat on water)
and the platform alike (which deliveries a boat can make)::

    from agents.geography import is_land, land_at
    land_at(40.6441, -8.7561)   # False: sea, off Costa Nova
    land_at(48.85, 2.35)        # None: outside the packaged regions

The mask (``data/land.geo.json``) is a GeoJSON FeatureCollection with one feature per
region: the land polygons of the region's box, clipped to it (:mod:`.extract` builds
and extends it from the full OpenStreetMap land polygons; ``python -m agents.geography
--help``). Inside a region a point is land when it is inside an odd number of the
region's rings (outer rings and holes alike); outside every region the mask cannot
tell. The data is © OpenStreetMap contributors, under the ODbL (``data/README.md``).
"""

from __future__ import annotations

import functools
import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agents.geography.polygons import Box, EvenOdd

#: The mask this package ships.
MASK_PATH = Path(__file__).resolve().parent / "data" / "land.geo.json"


@dataclass(frozen=True)
class Region:
    """One region of a mask: its box and its land rings (clipped to the box)."""

    name: str
    box: Box
    land: EvenOdd

    def land_at(self, lat: float, lon: float) -> bool:
        return self.land.inside(lat, lon)


class LandMask:
    """Land and water over a few regions (see the module docstring)."""

    def __init__(self, regions: Iterable[Region]) -> None:
        self.regions = list(regions)

    @classmethod
    def from_geojson(cls, data: Mapping[str, Any]) -> LandMask:
        """A mask from a FeatureCollection of regions (``properties.region`` and
        ``properties.bbox`` [south, west, north, east], a Polygon or MultiPolygon
        geometry). Raises ValueError naming what is wrong."""
        if data.get("type") != "FeatureCollection":
            raise ValueError("a land mask is a GeoJSON FeatureCollection")
        regions = []
        for i, feature in enumerate(data.get("features") or []):
            try:
                props = feature["properties"]
                box = Box(*(float(v) for v in props["bbox"]))
                rings = list(_rings(feature["geometry"]))
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"land mask feature {i}: {exc}") from None
            regions.append(Region(str(props.get("region", i)), box, EvenOdd(rings, box)))
        return cls(regions)

    @classmethod
    def load(cls, path: str | Path) -> LandMask:
        """Read a mask file (see :meth:`from_geojson`)."""
        return cls.from_geojson(json.loads(Path(path).read_text()))

    def region_of(self, lat: float, lon: float) -> Region | None:
        """The first region whose box holds the point, or None."""
        for region in self.regions:
            if region.box.contains(lat, lon):
                return region
        return None

    def land_at(self, lat: float, lon: float) -> bool | None:
        """True on land, False on water, None outside every region (unknown)."""
        region = self.region_of(lat, lon)
        return None if region is None else region.land_at(lat, lon)


def _rings(geometry: Mapping[str, Any]) -> Iterable[Sequence[Sequence[float]]]:
    kind = geometry["type"]
    if kind == "Polygon":
        polygons = [geometry["coordinates"]]
    elif kind == "MultiPolygon":
        polygons = geometry["coordinates"]
    else:
        raise ValueError(f"a region's geometry is a Polygon or MultiPolygon, not {kind}")
    for polygon in polygons:
        yield from polygon


@functools.cache
def land_mask() -> LandMask:
    """The packaged mask (read once)."""
    return LandMask.load(MASK_PATH)


def land_at(lat: float, lon: float) -> bool | None:
    """Land (True), water (False) or unknown (None: outside the packaged regions)."""
    return land_mask().land_at(lat, lon)


def is_land(lat: float, lon: float) -> bool:
    """Whether the point is not known to be water: land, or outside the packaged
    regions. The cautious answer for "may a boat go there?": ``not is_land(...)``."""
    return land_at(lat, lon) is not False


def is_water(lat: float, lon: float) -> bool:
    """Whether the point is known to be water (inside a packaged region, not land)."""
    return land_at(lat, lon) is False
