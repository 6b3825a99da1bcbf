"""The land mask: known points of the demo region, the clipping and the even-odd rule,
the extract command, and no Django anywhere near it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from agents.geography import MASK_PATH, LandMask, is_land, is_water, land_at
from agents.geography.__main__ import main
from agents.geography.polygons import Box, EvenOdd, ring_clip

ROOT = Path(__file__).resolve().parents[2]

#: The demo's points (services/demo.py): the person in the water and the stations.
CASTAWAY = (40.6441, -8.7561)
COSTA_NOVA_STATION = (40.6443, -8.7455)
CAMPUS = (40.6306, -8.6588)


@pytest.mark.parametrize(
    ("where", "point", "land"),
    [
        ("the castaway, 900 m off the beach", CASTAWAY, False),
        ("the open sea west of Aveiro", (40.64, -8.82), False),
        ("the sea off Mira, south", (40.56, -8.84), False),
        ("the campus", CAMPUS, True),
        ("Costa Nova, on the spit", (40.600, -8.740), True),
        ("the spit north of it", (40.62, -8.735), True),
        ("the land east of the Barra inlet", (40.6443, -8.733), True),
        ("the Ria de Aveiro lagoon, east of the spit", (40.66, -8.70), False),
        ("the lagoon's northern arm", (40.73, -8.63), False),
        # The station's point lies in the Barra inlet (the source's coarse shoreline
        # puts the sea up to -8.735 there): a boat kept there starts afloat.
        ("the demo's Costa Nova station", COSTA_NOVA_STATION, False),
    ],
)
def test_known_points_of_the_demo_region(
    where: str, point: tuple[float, float], land: bool
) -> None:
    assert land_at(*point) is land, where
    assert is_land(*point) is land and is_water(*point) is not land


def test_outside_the_regions_the_mask_cannot_tell() -> None:
    assert land_at(48.85, 2.35) is None
    assert is_land(48.85, 2.35)  # cautious: not known to be water
    assert not is_water(48.85, 2.35)


def test_the_packaged_mask_names_its_source_and_licence() -> None:
    data = json.loads(MASK_PATH.read_text())
    assert data["attribution"] == "© OpenStreetMap contributors"
    assert data["license"].startswith("ODbL")
    assert "OpenStreetMap contributors" in (MASK_PATH.parent / "README.md").read_text()
    assert MASK_PATH.stat().st_size < 100_000


def test_clipping_keeps_what_is_inside_and_runs_along_the_box() -> None:
    box = Box(0.0, 0.0, 1.0, 1.0)
    inside = [(0.2, 0.2), (0.8, 0.2), (0.8, 0.8), (0.2, 0.8), (0.2, 0.2)]
    assert ring_clip(inside, box) == inside[:-1]
    assert ring_clip([(2, 2), (3, 2), (3, 3)], box) == []
    around = ring_clip([(-1, -1), (2, -1), (2, 2), (-1, 2)], box)
    assert sorted(around) == [(0.0, 0.0), (0.0, 1.0), (1.0, 0.0), (1.0, 1.0)]
    half = ring_clip([(-1, -1), (0.5, -1), (0.5, 2), (-1, 2)], box)
    assert sorted(half) == [(0.0, 0.0), (0.0, 1.0), (0.5, 0.0), (0.5, 1.0)]


def test_even_odd_over_an_island_with_a_lake_with_an_islet() -> None:
    box = Box(0.0, 0.0, 10.0, 10.0)
    island = [(1, 1), (9, 1), (9, 9), (1, 9)]
    lake = [(3, 3), (7, 3), (7, 7), (3, 7)]
    islet = [(4.5, 4.5), (5.5, 4.5), (5.5, 5.5), (4.5, 5.5)]
    test = EvenOdd([island, lake, islet], box, bands=4)
    assert test.inside(2, 2) and not test.inside(4, 4) and test.inside(5, 5)
    assert not test.inside(0.5, 5) and not test.inside(9.5, 9.5)


def test_extract_adds_and_replaces_regions(tmp_path: Path) -> None:
    source = tmp_path / "lands.geo.json"
    island = [[[1, 1], [9, 1], [9, 9], [1, 9], [1, 1]], [[3, 3], [7, 3], [7, 7], [3, 7], [3, 3]]]
    source.write_text(json.dumps({"type": "MultiPolygon", "coordinates": [island]}))
    mask = tmp_path / "mask.geo.json"
    assert (
        main(["extract", str(source), "--region", "a", "--bbox", "0,0,5,5", "--mask", str(mask)])
        == 0
    )
    assert (
        main(["extract", str(source), "--region", "b", "--bbox", "5,5,10,10", "--mask", str(mask)])
        == 0
    )
    assert (
        main(["extract", str(source), "--region", "a", "--bbox", "0,0,6,6", "--mask", str(mask)])
        == 0
    )
    loaded = LandMask.load(mask)
    assert [r.name for r in loaded.regions] == ["b", "a"]
    # lat, lon = y, x: land on the island's rim, water in its lake and off it.
    assert loaded.land_at(2, 2) is True and loaded.land_at(4, 4) is False
    assert loaded.land_at(8, 8) is True and loaded.land_at(9.5, 9.5) is False
    assert loaded.land_at(20, 20) is None
    assert json.loads(mask.read_text())["attribution"] == "© OpenStreetMap contributors"


def test_the_land_mask_imports_no_django() -> None:
    code = (
        "import sys, agents.geography as g; g.land_at(40.64, -8.75); "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in "
        "{'django', 'fleet', 'services', 'accounts', 'iouv'}))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]"
