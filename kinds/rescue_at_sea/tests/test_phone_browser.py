"""The rescue request on a phone: the map to draw the area on is as wide as the screen,
opens with the sea off Costa Nova (the demo's castaway) in view, and its instructions
speak of taps and pinches, not clicks and scrolling."""

from __future__ import annotations

import pytest
from playwright.async_api import expect

from services.demo import CASTAWAY
from tests.browser import needs_chromium
from tests.portal import PHONE, World, login, no_wider_than_the_screen

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    needs_chromium,
]


async def test_on_a_phone_the_area_map_takes_the_screens_width(portal: World) -> None:
    page = await login(portal, "client", PHONE)
    await page.goto(f"{portal.base}/services/rescue-at-sea/")
    box = await page.locator("#area-map").bounding_box()
    assert box is not None and box["width"] >= 0.75 * 390 and box["height"] >= 300, box
    await no_wider_than_the_screen(page)

    # Three taps on the map mark an area.
    for dx, dy in ((-80, -80), (80, -80), (0, 80)):
        await page.mouse.click(box["x"] + box["width"] / 2 + dx, box["y"] + box["height"] / 2 + dy)
    await page.wait_for_function(
        "() => document.querySelector('[data-area-info]').textContent !== 'No area yet.'"
    )


async def test_on_a_phone_the_area_map_opens_on_the_sea_and_speaks_of_taps(
    portal: World,
) -> None:
    page = await login(portal, "client", PHONE)
    await page.goto(f"{portal.base}/services/rescue-at-sea/")
    await page.wait_for_function("() => window.iouvMap && window.iouvMap.map")
    seen = await page.evaluate(
        "([lat, lon]) => window.iouvMap.map.getBounds().contains([lat, lon])", list(CASTAWAY)
    )
    assert seen, "the castaway, 900 m off Costa Nova, is not in view"
    # How far the search drone reaches is drawn.
    await expect(page.locator("path.reach-area")).to_have_count(1)
    help_text = await page.locator("[data-map-help]").inner_text()
    assert help_text.startswith("Tap the map"), help_text
    assert "pinch to zoom" in help_text and "Click" not in help_text and "scroll" not in help_text
