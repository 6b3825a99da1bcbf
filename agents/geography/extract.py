"""Building the land mask: a region's land polygons, clipped from the full OpenStreetMap
land polygons, into the mask file.

The source is any GeoJSON of land polygons (a Geometry, a GeometryCollection, a Feature
or a FeatureCollection of Polygons and MultiPolygons), e.g. the npm package
``@geo-maps/earth-lands-10m`` (``npm pack @geo-maps/earth-lands-10m``: its
``map.geo.json``, 134 MB, OpenStreetMap land polygons, ODbL). Reading it whole takes
about 10 s and 2 GB of memory; the extract of a region is a few kilobytes.

Every ring (outer or hole) whose bounding box meets the region's box is clipped to the
box (:func:`~agents.geography.polygons.ring_clip`) and its coordinates rounded to
``digits`` decimals (5: about a metre, the source's own precision).
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from agents.geography.polygons import Box, ring_clip

ATTRIBUTION = "© OpenStreetMap contributors"
LICENSE = "ODbL-1.0 (https://opendatacommons.org/licenses/odbl/1-0/)"


def _polygons(node: Mapping[str, Any]) -> Iterator[list[Any]]:
    """Every polygon (a list of rings) in a GeoJSON object."""
    kind = node.get("type")
    if kind == "FeatureCollection":
        for feature in node.get("features") or []:
            yield from _polygons(feature)
    elif kind == "Feature":
        if node.get("geometry"):
            yield from _polygons(node["geometry"])
    elif kind == "GeometryCollection":
        for geometry in node.get("geometries") or []:
            yield from _polygons(geometry)
    elif kind == "Polygon":
        yield node["coordinates"]
    elif kind == "MultiPolygon":
        yield from node["coordinates"]


def region_extract(
    source: Mapping[str, Any], *, name: str, box: Box, digits: int = 5
) -> dict[str, Any]:
    """The mask feature of region ``name``: ``source``'s land within ``box``."""
    polygons = []
    for polygon in _polygons(source):
        if not polygon or not box.overlaps(polygon[0]):
            # Holes lie within their outer ring: nothing of this polygon is here.
            continue
        rings = []
        for ring in polygon:
            if not box.overlaps(ring):
                continue
            clipped = ring_clip(ring, box)
            if clipped:
                points = [[round(x, digits), round(y, digits)] for x, y in clipped]
                rings.append([*points, points[0]])  # GeoJSON closes its rings
        if rings:
            polygons.append(rings)
    return {
        "type": "Feature",
        "properties": {"region": name, "bbox": box.as_list()},
        "geometry": {"type": "MultiPolygon", "coordinates": polygons},
    }


def mask_update(
    mask: dict[str, Any] | None, feature: Mapping[str, Any], *, source: str
) -> dict[str, Any]:
    """``mask`` (a FeatureCollection, or None for a new one) with ``feature`` added, or
    replacing the region of the same name."""
    out = mask or {"type": "FeatureCollection", "features": []}
    out["attribution"] = ATTRIBUTION
    out["license"] = LICENSE
    name = feature["properties"]["region"]
    features = [f for f in out.get("features", []) if f["properties"].get("region") != name]
    features.append(dict(feature))
    out["features"] = features
    sources = dict(out.get("sources", {}))
    sources[name] = source
    out["sources"] = sources
    return out


def mask_write(path: Path, mask: Mapping[str, Any]) -> None:
    """Write ``mask`` compactly, a feature a line (small diffs when a region changes)."""
    head = {k: v for k, v in mask.items() if k != "features"}
    lines = [json.dumps(f, separators=(",", ":")) for f in mask["features"]]
    text = json.dumps(head, ensure_ascii=False, indent=1)[:-2]
    text += ',\n "features": [\n' + ",\n".join(lines) + "\n ]\n}\n"
    path.write_text(text)
