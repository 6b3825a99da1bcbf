"""Maps that show the world, in Chromium at a desktop's and a phone's size.

With no tile server (the demo, the tests: no Internet) the maps draw the packaged land
mask: a person tells the sea from the land by its colour, with OpenStreetMap's credit
shown. Labels (vehicles, stations, the person found, the grid's coordinates) never
cover one another nor the map's controls. The monitor sees the whole fleet on a map,
live; the mission page has no empty box under its map.

The platform runs (iouv.serve) with the demo seeded and simulated agents, as in
``tests/integration/test_portal.py`` and ``kinds/rescue_at_sea/tests/test_integration.py``
(their worlds: tests/portal.py and kinds/rescue_at_sea/tests/sea.py).
"""

from __future__ import annotations

import contextlib
import struct
import zlib
from collections import Counter
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from playwright.async_api import Browser, Page, expect
from playwright.async_api import TimeoutError as PlaywrightTimeout

from agents.geo import distance_m
from agents.geography import land_at
from agents.runtime import Agent
from agents.vehicles.car.kinematics import Pose
from fleet.models import Vehicle
from kinds.rescue_at_sea.tests.sea import client_requests_rescue, sea, search_area
from services.demo import CASTAWAY
from tests.browser import chromium_browser, needs_chromium
from tests.portal import demo_world, sign_in
from tests.servers import db, until

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    needs_chromium,
]

#: Playwright context options of the two screens the portal must work on.
VIEWPORTS: dict[str, dict[str, Any]] = {
    "desktop": {"viewport": {"width": 1366, "height": 768}},
    "phone": {
        "viewport": {"width": 390, "height": 844},
        "is_mobile": True,
        "has_touch": True,
        "device_scale_factor": 3,
    },
}
#: Sea off Costa Nova, and land south-east of the campus, both inside the mask's region
#: and a few hundred metres at least from its coarse coastline.
SEA = CASTAWAY
LAND = (40.615, -8.63)


async def login(browser: Browser, base: str, username: str, screen: str) -> tuple[Page, list[str]]:
    """A new browser context of ``screen``'s size, logged in as ``username``; returns its
    page and the list its uncaught script errors are added to."""
    context = await browser.new_context(**VIEWPORTS[screen])
    page = await context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    await sign_in(page, base, username)
    return page, errors


# --- what the page shows, measured in the page -------------------------------------------
# (Functions, not strings: the Content-Security-Policy forbids evaluating strings.)

#: Visible label boxes of the map ``sel`` that intersect, and how many labels are visible.
OVERLAPS = """(sel) => {
  const node = document.querySelector(sel);
  const boxes = [...node.querySelectorAll(".map-label, .grid-label, .leaflet-tooltip")]
    .filter((e) => e.checkVisibility({ visibilityProperty: true, opacityProperty: true }))
    .map((e) => ({ text: e.textContent, r: e.getBoundingClientRect() }))
    .filter((b) => b.r.width > 0 && b.r.height > 0);
  const bad = [];
  for (let i = 0; i < boxes.length; i++) {
    for (let j = i + 1; j < boxes.length; j++) {
      const a = boxes[i].r, b = boxes[j].r;
      if (a.left < b.right && b.left < a.right && a.top < b.bottom && b.top < a.bottom) {
        bad.push([boxes[i].text, boxes[j].text]);
      }
    }
  }
  return { shown: boxes.map((b) => b.text), bad };
}"""

#: Grid labels under the zoom control while the map is panned down 150 px, 10 px at a
#: time (a grid line crosses the control's height on the way, whatever the zoom).
UNDER_ZOOM = """async (sel) => {
  const node = document.querySelector(sel);
  const map = window.iouvMap.map;
  const zoom = node.querySelector(".leaflet-control-zoom").getBoundingClientRect();
  const hidden = [];
  let seen = 0;
  for (let i = 0; i < 15; i++) {
    map.panBy([0, -10], { animate: false });
    await new Promise((resolve) => requestAnimationFrame(() => resolve()));
    for (const e of node.querySelectorAll(".grid-label")) {
      if (!e.checkVisibility({ visibilityProperty: true, opacityProperty: true })) continue;
      seen += 1;
      const r = e.getBoundingClientRect();
      if (r.left < zoom.right && zoom.left < r.right
          && r.top < zoom.bottom && zoom.top < r.bottom) {
        hidden.push(e.textContent);
      }
    }
  }
  map.panBy([0, 150], { animate: false });
  return { seen, hidden };
}"""

#: The page's pixel position of each [lat, lon] (null when outside the map).
PIXELS = """([sel, points]) => {
  const map = window.iouvMap.map;
  const box = document.querySelector(sel).getBoundingClientRect();
  const size = map.getSize();
  return points.map((p) => {
    const c = map.latLngToContainerPoint(p);
    if (c.x < 8 || c.y < 8 || c.x > size.x - 8 || c.y > size.y - 8) return null;
    return { x: box.left + c.x, y: box.top + c.y };
  });
}"""

#: Hide (or show again) what is drawn over the ground: markers, labels, overlays, controls.
GROUND_ONLY = """([sel, only]) => {
  const node = document.querySelector(sel);
  for (const el of node.querySelectorAll(
    ".leaflet-marker-pane, .leaflet-overlay-pane, .leaflet-tooltip-pane, .leaflet-control-container"
  )) el.style.visibility = only ? "hidden" : "";
}"""


def png_pixels(data: bytes) -> list[tuple[int, int, int]]:
    """The RGB pixels of an 8-bit, non-interlaced RGB or RGBA PNG (Chromium's
    screenshots), row by row."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, chunks, head = 8, [], b""
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        if kind == b"IHDR":
            head = body
        elif kind == b"IDAT":
            chunks.append(body)
        pos += 12 + length
    width, height, depth, color = struct.unpack(">IIBB", head[:10])
    assert depth == 8 and color in (2, 6), (depth, color)
    bpp = 3 if color == 2 else 4
    raw = zlib.decompress(b"".join(chunks))
    stride = width * bpp
    rows: list[bytearray] = []
    prior = bytearray(stride)
    for y in range(height):
        kind, line = (
            raw[y * (stride + 1)],
            bytearray(raw[y * (stride + 1) + 1 : (y + 1) * (stride + 1)]),
        )
        for i in range(stride):
            a = line[i - bpp] if i >= bpp else 0
            b = prior[i]
            c = prior[i - bpp] if i >= bpp else 0
            if kind == 1:
                line[i] = (line[i] + a) & 255
            elif kind == 2:
                line[i] = (line[i] + b) & 255
            elif kind == 3:
                line[i] = (line[i] + (a + b) // 2) & 255
            elif kind == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append(line)
        prior = line
    return [
        (row[x * bpp], row[x * bpp + 1], row[x * bpp + 2]) for row in rows for x in range(width)
    ]


async def ground_colour(page: Page, x: float, y: float) -> tuple[int, int, int]:
    """The colour most of a 5 x 5 px square around (x, y) has (a grid line may cross it)."""
    shot = await page.screenshot(clip={"x": x - 2, "y": y - 2, "width": 5, "height": 5})
    return Counter(png_pixels(shot)).most_common(1)[0][0]


async def assert_sea_and_land_differ(page: Page, sel: str) -> None:
    """Framed on the sea point and the land point, with nothing over the ground, the two
    show clearly different colours, and OpenStreetMap's credit is on the map."""
    assert land_at(*SEA) is False and land_at(*LAND) is True
    await page.wait_for_function(
        "(sel) => document.querySelector(sel).dataset.land === 'ready'", arg=sel
    )
    await page.evaluate(
        "(points) => window.iouvMap.map.fitBounds(points, { padding: [40, 40], animate: false })",
        [list(SEA), list(LAND)],
    )
    await expect(page.locator(f"{sel} .leaflet-control-attribution")).to_contain_text(
        "OpenStreetMap contributors"
    )
    await page.locator(sel).scroll_into_view_if_needed()
    sea_at, land_at_px = await page.evaluate(PIXELS, [sel, [list(SEA), list(LAND)]])
    assert sea_at and land_at_px, "both points in view"
    await page.evaluate(GROUND_ONLY, [sel, True])
    try:
        sea = await ground_colour(page, sea_at["x"], sea_at["y"])
        land = await ground_colour(page, land_at_px["x"], land_at_px["y"])
    finally:
        await page.evaluate(GROUND_ONLY, [sel, False])
    assert sum((a - b) ** 2 for a, b in zip(sea, land, strict=True)) ** 0.5 > 60, (sea, land)
    # The sea is drawn as sea (bluer than it is red), and neither is the map's empty
    # ground, which stands for "unknown" outside the mask's regions.
    assert sea[2] > sea[0] + 40, sea
    background = await page.evaluate(
        "(sel) => getComputedStyle(document.querySelector(sel)).backgroundColor", sel
    )
    assert f"rgb({sea[0]}, {sea[1]}, {sea[2]})" != background
    assert f"rgb({land[0]}, {land[1]}, {land[2]})" != background


async def assert_labels_apart(page: Page, sel: str, *, expected: set[str]) -> None:
    """No two visible labels of the map intersect, each of ``expected`` is shown (alone
    or counted on a neighbour's "+N"), and no grid label hides under the zoom control."""
    shown = (
        "(sel) => [...document.querySelectorAll(`${sel} .map-label`)].map((e) =>"
        " e.checkVisibility({ visibilityProperty: true }) ? `${e.textContent} ${e.title}` : '')"
        ".join(' | ')"
    )
    # Placed after the last change (the placement runs once the page's script is done),
    # no zoom under way (the map frames the vehicles with an animated zoom when they
    # show, which hides the labels until they are placed again at its end), and the
    # expected labels shown: a placement made before the map framed the vehicles (a pan,
    # which hides nothing while it moves) found them off the map and hid them, until
    # the next one.
    try:
        await page.wait_for_function(
            f"""([sel, expected]) => {{
              const node = document.querySelector(sel);
              const shown = ({shown})(sel);
              return Number(node.dataset.labelsPlaced || 0) > 0
                && !node.classList.contains("labels-zooming")
                && expected.every((text) => shown.includes(text));
            }}""",
            arg=[sel, sorted(expected)],
            timeout=15000,
        )
    except PlaywrightTimeout:
        named = await page.evaluate(shown, sel)
        raise AssertionError(f"{sorted(expected)} not all shown within 15 s: {named!r}") from None
    found = await page.evaluate(OVERLAPS, sel)
    assert not found["bad"], found
    named = await page.evaluate(shown, sel)
    for text in expected:
        assert text in named, (text, named)
    under = await page.evaluate(UNDER_ZOOM, sel)
    assert under["seen"] > 0 and not under["hidden"], under
    found = await page.evaluate(OVERLAPS, sel)
    assert not found["bad"], found


# --- the monitor's fleet map ---------------------------------------------------------------


@contextlib.asynccontextmanager
async def campus(tmp_path: Path) -> AsyncIterator[tuple[str, dict[str, Agent], Browser]]:
    """The demo world with car-1 and quad-1 online at the campus station (one spot: three
    labels that a naive map piles on one another)."""
    async with demo_world(tmp_path, webrtc_loopback=False) as world:
        yield world.base, world.agents, world.browser


def _position(name: str) -> tuple[float, float]:
    """Where the platform has vehicle ``name`` (it has reported a position)."""
    v = Vehicle.objects.get(name=name)
    assert v.lat is not None and v.lon is not None, name
    return (v.lat, v.lon)


async def test_the_monitor_sees_the_fleet_live_on_a_map(tmp_path: Path) -> None:
    async with campus(tmp_path) as (base, agents, browser):
        for screen in VIEWPORTS:
            page, errors = await login(browser, base, "monitor", screen)
            await page.goto(f"{base}/monitor/")
            sel = "#fleet-map"
            await expect(page.locator(sel)).to_be_visible()
            for name in agents:
                marker = page.locator(f"{sel} path.vehicle-marker[data-map-vehicle='{name}']")
                await expect(marker).to_have_count(1, timeout=15000)
                lat, lon = (
                    float(x) for x in (await marker.get_attribute("data-latlon")).split(",")
                )
                assert distance_m((lat, lon), await db(_position, name)) < 30
                assert await marker.get_attribute("data-status") == "idle"
            await expect(page.locator(f"{sel} path.station-marker")).not_to_have_count(0)
            await assert_labels_apart(
                page, sel, expected={"car-1", "quad-1", "idle", "Campus station"}
            )
            await assert_sea_and_land_differ(page, sel)
            await assert_labels_apart(page, sel, expected={"car-1", "quad-1"})
            assert not errors, errors
            await page.context.close()

        # The car moves (put 400 m north-east by its simulator): the monitor's marker
        # follows, and the labels still keep apart.
        page, errors = await login(browser, base, "monitor", "desktop")
        await page.goto(f"{base}/monitor/")
        marker = page.locator("#fleet-map path.vehicle-marker[data-map-vehicle='car-1']")
        await expect(marker).to_have_count(1, timeout=15000)
        before = await marker.get_attribute("data-latlon")
        car: Any = agents["car-1"].adapter  # the simulated car's adapter
        car.sensors.set_pose(Pose(north_m=300.0, east_m=260.0))
        await page.wait_for_function(
            """(before) => {
              const m = document.querySelector(
                "#fleet-map path.vehicle-marker[data-map-vehicle='car-1']");
              return m && m.dataset.latlon !== before;
            }""",
            arg=before,
            timeout=15000,
        )

        async def moved() -> bool:
            lat, lon = (float(x) for x in (await marker.get_attribute("data-latlon")).split(","))
            return distance_m((lat, lon), car.sensors.position) < 30

        await until(moved, within=15, what="car-1's marker at its new position")
        await expect(page.locator("#monitor [data-fleet] tr[data-vehicle='car-1']")).to_be_visible()
        await assert_labels_apart(page, "#fleet-map", expected={"car-1", "quad-1"})
        assert not errors, errors


async def test_the_request_maps_keep_their_labels_apart(tmp_path: Path) -> None:
    """The maps where a user marks points: the stations' labels and the marked points'
    (a parcel's pickup and drop-off clicked right by a station) never overlap."""
    async with campus(tmp_path) as (base, _, browser):
        for screen in VIEWPORTS:
            page, errors = await login(browser, base, "client", screen)
            await page.goto(f"{base}/services/parcel-delivery/")
            sel = "#parcel-map"
            await page.wait_for_function("() => window.iouvMap && window.iouvMap.map")
            station = await page.evaluate(
                "() => { const c = window.iouvMap.map.getCenter(); return [c.lat, c.lng]; }"
            )
            box = await page.locator(sel).bounding_box()
            assert box is not None
            # The pickup and the drop-off a few pixels from the first station.
            for dx, dy in ((6, 4), (-6, 8)):
                point = await page.evaluate(
                    "(p) => window.iouvMap.map.latLngToContainerPoint(p)", station
                )
                await page.mouse.click(box["x"] + point["x"] + dx, box["y"] + point["y"] + dy)
            await expect(page.locator("[data-pick-info]")).to_contain_text("km from pickup")
            await assert_labels_apart(page, sel, expected={"pickup", "drop-off"})
            await assert_sea_and_land_differ(page, sel)
            await assert_labels_apart(page, sel, expected={"pickup", "drop-off"})

            await page.goto(f"{base}/services/rescue-at-sea/")
            await page.wait_for_function("() => window.iouvMap && window.iouvMap.map")
            await assert_labels_apart(page, "#area-map", expected=set())
            assert not errors, errors
            await page.context.close()


# --- the mission map ----------------------------------------------------------------------


async def test_the_mission_map_shows_sea_land_and_labels_apart(tmp_path: Path) -> None:
    async with (
        sea(tmp_path, ("search-1", "lifeguard-1")) as world,
        chromium_browser() as browser,
    ):
        session = await db(client_requests_rescue, search_area())
        for screen in VIEWPORTS:
            page, errors = await login(browser, world.base, "client", screen)
            await page.goto(f"{world.base}/sessions/{session.pk}/")
            sel = "#mission-map"
            # The vehicles on the map: the drone starts at its station, beside the others.
            await expect(page.locator(f"{sel} path.vehicle-marker")).not_to_have_count(
                0, timeout=30000
            )
            await assert_labels_apart(page, sel, expected={"search-1"})
            if screen == "desktop":
                # No empty box under the map: its card ends with the legend.
                gap = await page.evaluate(
                    """(sel) => {
                      const card = document.querySelector(sel).closest(".card");
                      const legend = card.querySelector(".map-legend");
                      const bottom = (el) => el.getBoundingClientRect().bottom;
                      return bottom(card) - bottom(legend);
                    }""",
                    sel,
                )
                assert gap < 40, gap
            await assert_sea_and_land_differ(page, sel)
            await assert_labels_apart(page, sel, expected={"search-1"})
            assert not errors, errors
            await page.context.close()
