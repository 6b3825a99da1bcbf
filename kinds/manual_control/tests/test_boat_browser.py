"""The boat, driven from the browser: the demo's "Manual control of a boat" with the
platform under its server and the boat's real agent on its ArduRover-like simulator."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from playwright.async_api import expect

from agents.geo import distance_m
from agents.geography import is_water
from fleet.models import Vehicle
from services.models import Session
from tests.browser import needs_chromium
from tests.portal import (
    World,
    assert_nothing_refused,
    demo_world,
    end_session,
    wait_for,
)
from tests.servers import db, until

pytestmark = [pytest.mark.django_db(transaction=True), needs_chromium]


@pytest.fixture
async def world(tmp_path: Path) -> AsyncIterator[World]:
    """The seeded demo on the platform, boat-1's agent online with a position, and
    Chromium."""
    async with demo_world(tmp_path, ("boat-1",)) as running:
        yield running


async def test_client_steers_the_boat_from_the_browser(world: World) -> None:
    page = await world.login("client")
    await page.click("[data-service=drive-boat] a.button")
    await page.select_option("#id_station", label="Costa Nova station")
    await page.click("#request-button")
    await page.wait_for_url("**/sessions/*/")
    session_id = page.url.rstrip("/").rsplit("/", 1)[-1]
    await wait_for(page, "c.role === 'controller' && c.stats.framesDecoded > 3")
    boat = world.agents["boat-1"].adapter
    # A boat's page: no take-off, no altitude; the arrows steer it.
    assert await page.locator("[data-command=take_off]").count() == 0
    assert await page.locator("[data-command=release_payload]").count() == 0
    assert await page.locator("[data-topic=altitude]").count() == 0

    await page.click("[data-command=arm]")
    for _ in range(100):
        if boat.state().armed:
            break
        await asyncio.sleep(0.1)
    assert boat.state().armed

    start = boat.state().position
    heading = boat.state().heading_deg
    await page.keyboard.down("ArrowUp")
    # Held: it gets under way ahead of it.
    for _ in range(100):
        if (boat.state().speed_mps or 0) > 1.0:
            break
        await asyncio.sleep(0.1)
    await page.keyboard.down("ArrowLeft")  # and curves to port while both are held
    await asyncio.sleep(1.5)
    await page.keyboard.up("ArrowLeft")
    await page.keyboard.up("ArrowUp")
    moved = boat.state().position
    assert start is not None and moved is not None
    assert distance_m(start, moved) > 2.0
    turned = ((boat.state().heading_deg or 0) - (heading or 0) + 540) % 360 - 180
    assert turned < -5, turned  # left: the heading went down
    # Released: "stop" went out and the boat comes to rest where it is, on the water.
    for _ in range(80):
        if (boat.state().speed_mps or 0) < 0.3:
            break
        await asyncio.sleep(0.1)
    assert (boat.state().speed_mps or 0) < 0.3
    here = boat.state().position
    assert here is not None and is_water(*here)
    await expect(page.locator("[data-topic=speed] .value")).not_to_have_text("\u2013")
    await assert_nothing_refused(page)

    asked = await end_session(page)
    assert asked == "End the session? boat-1 will go back to its home point and hold there."
    session = await db(Session.objects.get, pk=session_id)
    assert session.state == Session.State.ENDED

    async def free() -> bool:
        v = await db(Vehicle.objects.get, name="boat-1")
        return v.status == Vehicle.Status.IDLE

    # Free again once its agent confirmed the end and it is back, at rest.
    await until(free, within=60, what="the boat to be free again")


#: The mean colour (r, g, b) of the lower middle of the picture (below the horizon,
#: above the digits): what the boat's camera sees of the world ahead.
PICTURE_BELOW_HORIZON = """() => {
  const video = document.querySelector("video");
  const canvas = document.createElement("canvas");
  canvas.width = video.videoWidth;
  canvas.height = video.videoHeight;
  const ctx = canvas.getContext("2d");
  ctx.drawImage(video, 0, 0);
  const top = Math.round(canvas.height * 0.58), rows = Math.round(canvas.height * 0.2);
  const data = ctx.getImageData(0, top, canvas.width, rows).data;
  const sum = [0, 0, 0];
  for (let i = 0; i < data.length; i += 4) {
    for (let c = 0; c < 3; c++) sum[c] += data[i + c];
  }
  const n = data.length / 4;
  return sum.map((v) => v / n);
}"""


async def test_the_boat_says_to_arm_it_first_and_its_camera_sees_the_water(world: World) -> None:
    page = await world.login("client")
    await page.click("[data-service=drive-boat] a.button")
    await page.select_option("#id_station", label="Costa Nova station")
    await page.click("#request-button")
    await page.wait_for_url("**/sessions/*/")
    await wait_for(page, "c.role === 'controller' && c.stats.framesDecoded > 3")
    boat = world.agents["boat-1"].adapter
    assert not boat.state().armed

    # Its motors are off: the page says what to press before the arrows do anything.
    hint = page.locator("[data-ready-hint]")
    await expect(hint).to_have_text(
        "boat-1's motors are off: press Arm first, then the arrow keys steer it."
    )
    await page.keyboard.down("ArrowUp")
    try:
        await expect(page.locator("[data-toast]")).to_have_text(
            "forward: the motors are off. Press Arm first."
        )
    finally:
        await page.keyboard.up("ArrowUp")
    assert not boat.state().armed and (boat.state().speed_mps or 0) < 0.1
    await page.click("[data-command=arm]")
    await expect(hint).to_be_hidden(timeout=10000)
    assert boat.state().armed

    # What its camera shows below the horizon is water: blue, not grass.
    red, green, blue = await page.evaluate(PICTURE_BELOW_HORIZON)
    assert blue > green > red and blue > 1.2 * green, (red, green, blue)
