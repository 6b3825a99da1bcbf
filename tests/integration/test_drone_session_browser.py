"""A drone's session page in Chromium against the real platform and quad-1's agent on
its ArduCopter-like simulator, at a laptop's size:

* ending the session while the drone lands: the confirmation says what will happen as
  the drone is now (it goes on landing), and it does (no climb back to its return
  altitude from the last metres);
* pushed past its ceiling and brought back: the breach's banner goes once it is back
  inside (a note, not a banner for the rest of the session that pushes the controls
  below the fold), and the session log says each event in words."""

from __future__ import annotations

from playwright.async_api import expect

from agents.geo import offset
from tests.portal import LAPTOP, PORTAL_MARKS, RECORD_COMMANDS, World, end_session, request_drone
from tests.servers import until

pytestmark = PORTAL_MARKS


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


async def test_back_inside_the_ceiling_the_banner_goes_and_the_log_says_it_in_words(
    world: World,
) -> None:
    page = await world.login("client", init_script=RECORD_COMMANDS, **LAPTOP)
    drone = await request_drone(world, page)
    # Something other than the user's keys (another ground station, a gust) takes it
    # above the service's 30 m ceiling: the agent's envelope catches it.
    here = drone.state()
    assert here.lat is not None and here.lon is not None
    lat, lon = offset((here.lat, here.lon), 0.0, 0.0)
    await drone._reposition(lat, lon, 40.0)
    banner = page.locator("[data-banner]")
    await expect(banner).to_contain_text("Safety limit: altitude", timeout=60000)
    await expect(page.locator("[data-toast]")).to_have_text(
        "Back inside the altitude limit.", timeout=60000
    )
    await expect(banner).to_be_hidden()
    # Every control, the mission's row included, is on the screen without scrolling.
    await page.evaluate("() => window.scrollTo(0, 0)")
    mission = await page.locator("[data-group=mission]").bounding_box()
    assert mission is not None and mission["y"] + mission["height"] <= 768, mission
    # The session log tells the story in words, the breach and its end among them.
    log = page.locator("[data-log] li")
    await expect(log.filter(has_text="back inside the altitude limit")).to_have_count(1)
    lines = await log.all_inner_texts()
    assert not [line for line in lines if line.split(" ", 1)[-1] in ("agent event", "state")]
    assert any("quad-1 reserved as vehicle" in line for line in lines), lines
