"""Flying the drone on a phone, in Chromium at a phone's size (touch) against the real
platform and quad-1's agent: while the sticks steer it, its altitude and battery ride
on the picture, in view, not in the telemetry panel below the fold."""

from __future__ import annotations

import re

from playwright.async_api import expect

from tests.portal import PHONE, PORTAL_MARKS, World, login, wait_for
from tests.servers import until

pytestmark = PORTAL_MARKS


async def test_on_a_phone_altitude_and_battery_are_on_the_picture(world: World) -> None:
    # The world's link-loss timeout (tests.portal.WORLD_LINK_LOSS_MS) keeps the drone
    # from going home when a saturated machine holds up Chromium's keepalives.
    page = await login(world, "client", PHONE)
    await page.click("[data-service=fly-drone] a.button")
    await page.select_option("#id_station", label="Campus station")
    await page.click("#request-button")
    await page.wait_for_url("**/sessions/*/")
    await wait_for(page, "c.role === 'controller' && c.inputMode === 'touch'")
    await page.tap("[data-overlay-actions] [data-command=take_off]")
    drone = world.agents["quad-1"].adapter

    async def flying() -> bool:
        return bool((drone.telemetry().get("altitude") or 0) > 2.0)

    await until(flying, within=30, what="the drone to take off")
    hud = page.locator("[data-hud]")
    await expect(hud.locator("[data-hud-topic=altitude]")).to_have_text(
        re.compile(r"^Altitude \d+(\.\d+)? m$")
    )
    await expect(hud.locator("[data-hud-topic=battery_level]")).to_contain_text("%")
    # On the picture, and on the screen without scrolling, with the sticks.
    box = await hud.bounding_box()
    pane = await page.locator("[data-video-pane]").bounding_box()
    assert box is not None and pane is not None
    assert pane["y"] <= box["y"] and box["y"] + box["height"] <= pane["y"] + pane["height"]
    assert box["y"] + box["height"] <= 844, box
    assert await page.locator("[data-stick]").count() == 2
