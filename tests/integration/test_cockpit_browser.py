"""The session page on the devices people use: a phone held in the hand and a laptop.

A phone (390 by 844, touch) gets the picture first with the steering on it: on-screen
sticks in proportion to the push, the vehicle's other commands along the top of the
picture, touch hints rather than keys, and no page wider than the screen. A laptop
(1366 by 768) shows the picture and every control without scrolling.

Same world as ``test_portal`` (the ``world`` fixture): the seeded demo on the platform,
the simulated car and drone's agents, Debian's Chromium.
"""

from __future__ import annotations

import asyncio
import math
import os
from typing import Any

from playwright.async_api import FloatRect, Page

from tests.portal import (
    LAPTOP,
    PHONE,
    PORTAL_MARKS,
    World,
    login,
    no_wider_than_the_screen,
    request_car,
    request_drone,
    wait_for,
)

pytestmark = PORTAL_MARKS


async def rect(page: Page, selector: str) -> FloatRect:
    box = await page.locator(selector).first.bounding_box()
    assert box is not None, f"{selector} is not displayed"
    return box


def inside(inner: FloatRect, outer: FloatRect) -> bool:
    return (
        inner["x"] >= outer["x"] - 0.5
        and inner["y"] >= outer["y"] - 0.5
        and inner["x"] + inner["width"] <= outer["x"] + outer["width"] + 0.5
        and inner["y"] + inner["height"] <= outer["y"] + outer["height"] + 0.5
    )


async def visible_texts(page: Page, selector: str) -> list[str]:
    return [
        (await node.inner_text()).strip()
        for node in await page.locator(selector).all()
        if await node.is_visible()
    ]


def sent(name: str) -> str:
    return f"window.sentCommands.filter(m => m.name === {name!r}).map(m => m.args)"


async def test_on_a_phone_the_picture_comes_first_with_sticks_on_it(world: World) -> None:
    page = await login(world, "client", PHONE)
    await no_wider_than_the_screen(page)  # the catalog
    await request_car(world, page)
    await wait_for(page, "c.stats.framesDecoded > 3 && c.inputMode === 'touch'")
    await no_wider_than_the_screen(page)

    # The picture first, tall, with the steering on it.
    video = await rect(page, "[data-video-pane]")
    assert video["y"] < (await rect(page, ".side"))["y"]
    assert video["height"] >= 0.5 * 844 * 0.9, video
    sticks = page.locator("[data-stick]")
    assert await sticks.count() == 2  # the car: driving (arrows) and its camera (w/a/s/d)
    for i in range(2):
        box = await sticks.nth(i).bounding_box()
        assert box is not None and inside(box, video), (box, video)
    stop = await rect(page, "[data-overlay-actions] [data-command=stop]")
    assert inside(stop, video)
    right = page.locator("[data-stick=right]")
    assert "forward" in (await right.get_attribute("aria-label") or "")
    # No keyboard hints on a touch screen; the touch hint instead.
    assert await visible_texts(page, ".cmd kbd") == []
    hints = await visible_texts(page, ".hint")
    assert len(hints) == 1 and hints[0].startswith("Drag a stick"), hints

    # The right stick pushed about half way up (past the dead zone): "forward" at half
    # the key's speed; to the rim, at the key's own; let go, the car stops.
    adapter: Any = world.agents["car-1"].adapter  # the car's adapter, on mock pins
    car = adapter.sensors  # the simulated world
    ring = await right.bounding_box()
    assert ring is not None
    radius = ring["width"] / 2
    cx, cy = ring["x"] + radius, ring["y"] + radius
    await page.mouse.move(cx, cy)
    await page.mouse.down()
    await page.mouse.move(cx, cy - 0.575 * radius, steps=4)
    await page.wait_for_function(
        f"() => {sent('forward')}.filter(a => Math.abs(a.speed - 0.25) < 0.01).length >= 2"
    )
    if shots := os.environ.get("IOUV_TEST_SHOTS"):
        await page.screenshot(path=f"{shots}/phone-car-stick.png")
    half = await page.evaluate(f"() => {sent('forward')}")
    assert all(args["speed"] < 0.26 for args in half), half  # never more on the way out
    start = car.pose
    await page.mouse.move(cx, cy - 1.5 * radius, steps=4)  # past the rim: full
    await page.wait_for_function(f"() => {sent('forward')}.some(a => !('speed' in a))")
    for _ in range(100):
        if math.hypot(car.pose.north_m - start.north_m, car.pose.east_m - start.east_m) > 0.05:
            break
        await asyncio.sleep(0.05)
    assert math.hypot(car.pose.north_m - start.north_m, car.pose.east_m - start.east_m) > 0.05
    await page.mouse.up()
    await page.wait_for_function(f"() => {sent('stop')}.length >= 1")
    assert await page.evaluate("() => window.iouvController.held.size") == 0

    # A key pressed (a keyboard plugged into a tablet): the keys' layout and hints.
    await page.keyboard.press("c")
    await wait_for(page, "c.inputMode === 'keys'")
    assert await page.locator("[data-stick]").count() == 0
    assert await visible_texts(page, "[data-command=forward] kbd") == ["↑"]
    hints = await visible_texts(page, ".hint")
    assert len(hints) == 1 and "key" in hints[0], hints

    # The pages around it fit the phone too.
    for path in ("/",):
        await page.goto(f"{world.base}{path}")
        await no_wider_than_the_screen(page)


async def test_on_a_laptop_the_drone_cockpit_fits_the_screen(world: World) -> None:
    page = await login(world, "client", LAPTOP)
    await request_drone(world, page)
    await wait_for(page, "c.inputMode === 'keys'")
    screen = FloatRect(x=0.0, y=0.0, width=1366.0, height=768.0)
    assert await page.evaluate("() => window.scrollY") == 0
    assert inside(await rect(page, "[data-video-pane]"), screen)
    assert inside(await rect(page, ".side"), screen) or (await rect(page, ".side"))["y"] < 768
    if shots := os.environ.get("IOUV_TEST_SHOTS"):
        await page.screenshot(path=f"{shots}/laptop-drone.png")
    buttons = page.locator("[data-controls] .cmd")
    assert await buttons.count() >= 10

    async def every_button_on_the_screen() -> None:
        for i in range(await buttons.count()):
            box = await buttons.nth(i).bounding_box()
            assert box is not None and inside(box, screen), (
                await buttons.nth(i).get_attribute("data-command"),
                box,
            )

    await every_button_on_the_screen()
    # A banner (the frozen picture's, as a loaded link shows it) and the hint above the
    # controls take their room from the picture: the buttons stay on the screen.
    await page.evaluate(
        "() => { const c = window.iouvController; c.showBanner('The video is frozen: driving"
        " is paused until the picture moves again. Stop, land and return home still work.',"
        " 'warn'); const h = document.querySelector('[data-ready-hint]');"
        " h.textContent = 'Take off first: the drone is on the ground.'; h.hidden = false; }"
    )
    await every_button_on_the_screen()
    # Keys on the buttons, no sticks, and the keyboard's hint.
    assert await page.locator("[data-stick]").count() == 0
    if shots := os.environ.get("IOUV_TEST_SHOTS"):
        await page.screenshot(path=f"{shots}/laptop-drone.png")
    assert "T" in [t.upper() for t in await visible_texts(page, "[data-command=take_off] kbd")]
    hints = await visible_texts(page, ".hint")
    assert len(hints) == 1 and "Each button shows its key" in hints[0], hints

    # The same page on a narrow screen (a phone held upright, a keyboard attached):
    # nothing wider than the screen, the waypoint's fields included.
    await page.set_viewport_size({"width": 390, "height": 844})
    await no_wider_than_the_screen(page)
    fields = page.locator("[data-command=go_to_waypoint] ~ input")
    assert [await f.get_attribute("placeholder") for f in await fields.all()] == [
        "latitude (deg)",
        "longitude (deg)",
        "altitude (m)",
    ]


async def test_the_spectate_list_follows_a_session_whose_driver_is_gone(world: World) -> None:
    driver = await login(world, "client", LAPTOP)
    session_id = await request_car(world, driver)
    watcher = await login(world, "client2", PHONE)
    await watcher.goto(f"{world.base}/spectate/")
    card = watcher.locator(f'[data-spectate="{session_id}"]')
    await card.wait_for()
    # The list follows the session live: on a saturated machine the driver's page may
    # connect (or lose and recover its link once) a moment after the list is drawn.
    await watcher.wait_for_function(
        f"""() => {{
          const card = document.querySelector('[data-spectate="{session_id}"]');
          return card && card.dataset.live === "true"
            && card.innerText.includes("client is in control.");
        }}""",
        timeout=30000,
    )
    await no_wider_than_the_screen(watcher)

    # The driver closes the tab: the car stops on its own, and the open list says so
    # (and when the session ends) without a reload, rather than a bare "active".
    await driver.close()
    await watcher.wait_for_function(
        f"""() => {{
          const card = document.querySelector('[data-spectate="{session_id}"]');
          return card && card.dataset.live === "false";
        }}""",
        timeout=30000,
    )
    text = await watcher.locator(f'[data-spectate="{session_id}"]').inner_text()
    # In words, not codes: why nobody is, and what the car did, in its own words.
    assert (
        "Nobody is in control: the driver's link to the vehicle was lost, so car-1 will "
        "stop where it is." in text
    )
    assert "if nobody takes control" in text
