"""Turning the car from the browser, in Chromium against the real platform and car-1's
agent on its simulated car: a held arrow turns it on the spot slowly enough to aim
(about 45° a second), not several turns a second."""

from __future__ import annotations

import time
from typing import Any

from tests.portal import PORTAL_MARKS, World, request_car, wait_for
from tests.servers import until

pytestmark = PORTAL_MARKS


async def test_a_held_arrow_turns_the_car_slowly_enough_to_aim(world: World) -> None:
    page = await world.login("client")
    await request_car(world, page)
    await wait_for(page, "c.stats.framesDecoded > 3")
    adapter: Any = world.agents["car-1"].adapter
    car = adapter.sensors  # the simulated world
    start = car.pose.heading_deg

    def turned() -> float:
        return abs((car.pose.heading_deg - start + 540) % 360 - 180)

    marks: dict[str, float] = {}

    async def past(degrees: float) -> bool:
        if turned() >= degrees:
            marks.setdefault(str(degrees), time.monotonic())
            return True
        return False

    await page.keyboard.down("ArrowLeft")
    try:
        await until(lambda: past(5.0), within=20, what="the car to start turning")
        await until(lambda: past(35.0), within=20, what="the car to turn 30° more")
    finally:
        await page.keyboard.up("ArrowLeft")
    # Polled every 0.1 s: a turn faster than that counts as taking one poll.
    rate = 30.0 / max(0.1, marks["35.0"] - marks["5.0"])
    # About 45°/s as declared; a busy machine only runs the simulator slower.
    assert rate < 70, f"{rate:.0f}°/s"
