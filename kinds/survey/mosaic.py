"""The survey's mosaic: its photos placed where they were taken, north up, as one
picture over the area's bounds, and the same as a KMZ ground overlay GIS tools open.

Each photo is placed by where it says it was taken (its ``meta``: position, altitude
above the ground, heading, field of view), as the nadir camera saw it
(agents.stills.nadir_lat_lon): every pixel of the mosaic, a point of a regular
latitude/longitude grid, takes the colour of the photo pixel that saw that point; where
photos overlap, the one whose centre is nearest wins (its picture is the least slanted
there). Outside every photo the mosaic is transparent.
"""

from __future__ import annotations

import io
import math
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final
from xml.sax.saxutils import escape

import numpy as np
import numpy.typing as npt
from PIL import Image

from agents.geo import EARTH_RADIUS_M

#: The mosaic's longest side at most, pixels (a phone shows it; a GIS tool zooms it).
MAX_SIDE_PX: Final = 1600
#: Drawn around the photos' footprints.
MARGIN_M: Final = 2.0


@dataclass(frozen=True)
class Placed:
    """A photo to place: its pixels and where it was taken."""

    rgb: npt.NDArray[np.uint8]
    lat: float
    lon: float
    alt: float
    heading_deg: float
    hfov_deg: float

    @classmethod
    def of(cls, jpeg: bytes, meta: dict[str, Any]) -> Placed:
        image = Image.open(io.BytesIO(jpeg)).convert("RGB")
        return cls(
            rgb=np.asarray(image, dtype=np.uint8),
            lat=float(meta["lat"]),
            lon=float(meta["lon"]),
            alt=max(float(meta.get("alt") or 0.0), 0.5),
            heading_deg=float(meta.get("heading_deg") or 0.0),
            hfov_deg=float(meta["hfov_deg"]),
        )

    @property
    def gsd_m(self) -> float:
        return 2 * self.alt * math.tan(math.radians(self.hfov_deg) / 2) / int(self.rgb.shape[1])

    @property
    def radius_m(self) -> float:
        height, width = self.rgb.shape[:2]
        return self.gsd_m * math.hypot(width, height) / 2


@dataclass(frozen=True)
class Mosaic:
    """The picture (PNG with transparency) and its ``[south, west, north, east]``."""

    png: bytes
    bounds: list[float]
    size: tuple[int, int]


def mosaic_build(photos: Sequence[Placed]) -> Mosaic | None:
    """The mosaic of ``photos`` (module docstring); None without any."""
    if not photos:
        return None
    lat0 = sum(p.lat for p in photos) / len(photos)
    m_lat = math.radians(1) * EARTH_RADIUS_M  # metres a degree north
    m_lon = m_lat * math.cos(math.radians(lat0))
    south = min(p.lat - (p.radius_m + MARGIN_M) / m_lat for p in photos)
    north = max(p.lat + (p.radius_m + MARGIN_M) / m_lat for p in photos)
    west = min(p.lon - (p.radius_m + MARGIN_M) / m_lon for p in photos)
    east = max(p.lon + (p.radius_m + MARGIN_M) / m_lon for p in photos)
    height_m, width_m = (north - south) * m_lat, (east - west) * m_lon
    cell = max(min(p.gsd_m for p in photos), max(height_m, width_m) / MAX_SIDE_PX)
    rows, cols = max(1, round(height_m / cell)), max(1, round(width_m / cell))
    # The centre of each mosaic pixel, as latitude and longitude.
    lats = north - (np.arange(rows) + 0.5) * (north - south) / rows
    lons = west + (np.arange(cols) + 0.5) * (east - west) / cols
    out = np.zeros((rows, cols, 4), dtype=np.uint8)
    best = np.full((rows, cols), np.inf)
    for photo in photos:
        _paint(photo, lats, lons, out, best)
    buffer = io.BytesIO()
    Image.fromarray(out, "RGBA").save(buffer, "PNG", optimize=False)
    return Mosaic(png=buffer.getvalue(), bounds=[south, west, north, east], size=(cols, rows))


def _paint(
    photo: Placed,
    lats: npt.NDArray[np.float64],
    lons: npt.NDArray[np.float64],
    out: npt.NDArray[np.uint8],
    best: npt.NDArray[np.float64],
) -> None:
    """Paint the mosaic pixels ``photo`` saw where it is the nearest photo's centre."""
    lat_r = math.radians(photo.lat)
    reach_lat = math.degrees(photo.radius_m / EARTH_RADIUS_M)
    reach_lon = reach_lat / math.cos(lat_r)
    r = np.nonzero(np.abs(lats - photo.lat) <= reach_lat)[0]
    c = np.nonzero(np.abs(lons - photo.lon) <= reach_lon)[0]
    if not len(r) or not len(c):
        return
    grid_lat, grid_lon = np.meshgrid(lats[r], lons[c], indexing="ij")
    # The inverse of agents.stills.nadir_lat_lon: ground offsets, then picture pixels.
    north = np.radians(grid_lat - photo.lat) * EARTH_RADIUS_M
    east = np.radians(grid_lon - photo.lon) * EARTH_RADIUS_M * math.cos(lat_r)
    h = math.radians(photo.heading_deg)
    right = east * math.cos(h) - north * math.sin(h)
    ahead = east * math.sin(h) + north * math.cos(h)
    height, width = photo.rgb.shape[:2]
    gsd = photo.gsd_m
    u = np.floor(right / gsd + width / 2).astype(np.int64)
    v = np.floor(height / 2 - ahead / gsd).astype(np.int64)
    seen = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    distance = np.hypot(right, ahead)
    block = best[np.ix_(r, c)]
    take = seen & (distance < block)
    if not take.any():
        return
    rows, cols = np.nonzero(take)
    out[r[rows], c[cols], :3] = photo.rgb[v[take], u[take]]
    out[r[rows], c[cols], 3] = 255
    block[take] = distance[take]
    best[np.ix_(r, c)] = block


def kmz(mosaic: Mosaic, *, name: str) -> bytes:
    """The mosaic as a KMZ ground overlay: ``doc.kml`` and the picture beside it."""
    south, west, north, east = mosaic.bounds
    kml = f"""<?xml version="1.0" encoding="UTF-8"?>
<kml xmlns="http://www.opengis.net/kml/2.2">
  <Document>
    <name>{escape(name)}</name>
    <GroundOverlay>
      <name>{escape(name)}</name>
      <Icon><href>files/mosaic.png</href></Icon>
      <LatLonBox>
        <north>{north:.8f}</north>
        <south>{south:.8f}</south>
        <east>{east:.8f}</east>
        <west>{west:.8f}</west>
        <rotation>0</rotation>
      </LatLonBox>
    </GroundOverlay>
  </Document>
</kml>
"""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("doc.kml", kml)  # first: what a reader opens
        archive.writestr("files/mosaic.png", mosaic.png)
    return buffer.getvalue()
