"""``python -m agents.geography``: build, extend and query the land mask.

    python -m agents.geography extract SOURCE --region NAME --bbox S,W,N,E [--mask FILE]
    python -m agents.geography at LAT,LON [--mask FILE]

``extract`` clips a region's land from SOURCE (a GeoJSON of land polygons, e.g.
``map.geo.json`` of the npm package ``@geo-maps/earth-lands-10m``) and adds it to the
mask, or replaces the region of that name (the packaged mask by default). ``at`` says
land, water or unknown for a point.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from agents.geography import MASK_PATH, LandMask
from agents.geography.extract import mask_update, mask_write, region_extract
from agents.geography.polygons import Box


def _floats(text: str, count: int) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {count} numbers separated by commas") from None
    if len(values) != count:
        raise argparse.ArgumentTypeError(f"expected {count} numbers separated by commas")
    return values


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m agents.geography",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    commands = parser.add_subparsers(dest="command", required=True)
    extract = commands.add_parser("extract", help="add or replace a region of the mask")
    extract.add_argument("source", type=Path, help="GeoJSON land polygons")
    extract.add_argument("--region", required=True, help="the region's name")
    extract.add_argument("--bbox", required=True, type=lambda t: _floats(t, 4), help="S,W,N,E")
    extract.add_argument("--mask", type=Path, default=MASK_PATH)
    extract.add_argument("--digits", type=int, default=5, help="decimals kept (5: ~1 m)")
    at = commands.add_parser("at", help="land, water or unknown at a point")
    at.add_argument("point", type=lambda t: _floats(t, 2), help="LAT,LON")
    at.add_argument("--mask", type=Path, default=MASK_PATH)
    args = parser.parse_args(argv)

    if args.command == "at":
        lat, lon = args.point
        answer = LandMask.load(args.mask).land_at(lat, lon)
        print({True: "land", False: "water", None: "unknown"}[answer])
        return 0
    try:
        box = Box(*args.bbox)
    except ValueError as exc:
        parser.error(str(exc))
    print(f"reading {args.source} ...", file=sys.stderr)
    source = json.loads(args.source.read_text())
    feature = region_extract(source, name=args.region, box=box, digits=args.digits)
    mask = json.loads(args.mask.read_text()) if args.mask.exists() else None
    label = f"{args.source.name} (OpenStreetMap land polygons), clipped to {box.as_list()}"
    mask_write(args.mask, mask_update(mask, feature, source=label))
    rings = sum(len(p) for p in feature["geometry"]["coordinates"])
    points = sum(len(r) for p in feature["geometry"]["coordinates"] for r in p)
    print(f"{args.mask}: region {args.region}: {rings} rings, {points} points", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
