"""Ending a drone's session while it lands, in Chromium against the real platform and
quad-1's agent on its ArduCopter-like simulator: the confirmation says what will
happen as the drone is now (it goes on landing), and it does (no climb back to its
return altitude from the last metres)."""

from __future__ import annotations

import pytest

from tests.browser import needs_chromium
from tests.portal import World, end_session, request_drone
from tests.servers import until

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    needs_chromium,
]


async def test_ending_the_session_while_the_drone_lands_lets_it_land(world: World) -> None:
    page = await world.login("client")
    drone = await request_drone(world, page)
    await page.keyboard.press("l")  # land where it is

    async def landing_low() -> bool:
        t = drone.telemetry()
        return t["flight_mode"] == "LAND" and 0.8 < (t["altitude"] or 0) < 3.5

    await until(landing_low, within=30, what="the drone to be landing, below 3.5 m")
    await page.wait_for_function(
        "() => document.querySelector('form[data-confirm]').dataset.consequence"
        " === 'quad-1 will go on landing where it is.'"
    )
    low = drone.telemetry()["altitude"]
    asked = await end_session(page)
    assert asked == "End the session? quad-1 will go on landing where it is.", asked

    # It does: down to the ground, never climbing back up.
    highest = [low]

    async def landed() -> bool:
        t = drone.telemetry()
        highest.append(t["altitude"] or 0)
        assert t["flight_mode"] != "RTL", t
        return t["in_air"] is False

    await until(landed, within=40, what="the drone to land")
    assert max(highest) < low + 0.5, (low, max(highest))
