"""The rescue request on a phone: the map to draw the area on is as wide as the screen."""

from __future__ import annotations

import pytest

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
