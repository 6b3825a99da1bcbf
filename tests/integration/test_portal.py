"""The portal as a person uses it: real Chromium, real platform, real agents.

The demo world is seeded, the platform runs under its server (Postgres, Redis), the
simulated car's agent runs here, and Playwright drives Debian's Chromium: the ``world``
fixture (tests/integration/conftest.py, on tests.portal).
"""

from __future__ import annotations

import asyncio
import re
from datetime import datetime
from typing import Any

from playwright.async_api import Page, expect

from accounts.roles import CLIENT
from agents.geo import distance_m
from fleet.models import Vehicle
from services.models import Service, Session
from tests import factories as f
from tests.demo import TEST_CAMERA
from tests.portal import (
    FAKE_GAMEPAD,
    PORTAL_MARKS,
    World,
    assert_nothing_refused,
    controller,
    drive_forward,
    end_session,
    hold_until,
    request_car,
    request_drone,
    wait_for,
)
from tests.servers import db, until

pytestmark = PORTAL_MARKS


async def hold(page: Page, key: str, seconds: float) -> None:
    await page.keyboard.down(key)
    await asyncio.sleep(seconds)
    await page.keyboard.up(key)


def _altitude_above(drone: Any, floor: float) -> Any:
    async def above() -> bool:
        return bool(drone.telemetry()["altitude"] > floor)

    return above


async def test_client_flies_the_drone_from_the_browser(world: World):
    page = await world.login("client")
    drone = await request_drone(world, page)
    await expect(page.locator("[data-topic=altitude] .value")).not_to_have_text("\u2013")

    before = drone.telemetry()["altitude"]
    # Climbs while held.
    await hold_until(page, "w", _altitude_above(drone, before + 0.5), what="the drone to climb")

    # The on-screen buttons work from the keyboard too: the "up" button, focused, climbs
    # while Enter is held, and says its key to a screen reader.
    up = page.locator("[data-command=up]")
    await expect(up).to_have_accessible_name("up w")
    assert await up.get_attribute("aria-keyshortcuts") == "w"
    await up.focus()
    before = drone.telemetry()["altitude"]
    await hold_until(page, "Enter", _altitude_above(drone, before + 0.5), what="the drone to climb")
    await up.blur()

    start = drone.state().position

    async def gone_forward() -> bool:  # forward while held
        moved = drone.state().position
        return start is not None and moved is not None and distance_m(start, moved) > 0.05

    await hold_until(page, "ArrowUp", gone_forward, what="the drone to move forward")
    # Released: "stop" went out and the drone brakes to a hover.
    for _ in range(60):
        if (drone.telemetry().get("speed") or 0) < 0.3:
            break
        await asyncio.sleep(0.1)
    assert drone.telemetry()["speed"] < 0.3
    await expect(page.locator("[data-rtt]")).to_have_text(re.compile(r"\d+\.\d ms"))
    await assert_nothing_refused(page)

    asked = await end_session(page)
    assert asked == (
        "End the session? quad-1 will climb to its return altitude, fly back to its home "
        "point and land."
    ), asked
    # No longer reserved: "releasing" until its agent confirms the end, then it flies
    # home on its own and shows "returning" until it has landed, when its agent reports
    # it idle again.
    quad = await db(Vehicle.objects.get, name="quad-1")
    assert quad.status in (
        Vehicle.Status.RELEASING,
        Vehicle.Status.IDLE,
        Vehicle.Status.RETURNING,
    )
    assert not await db(lambda: quad.assignments.filter(active=True).exists())

    async def returning() -> bool:
        v = await db(Vehicle.objects.get, name="quad-1")
        return v.status == Vehicle.Status.RETURNING

    await until(returning, within=8, what="the drone to report it is flying home")


async def test_client_requests_drives_sees_video_and_ends(world: World):
    page = await world.login("client")
    session_id = await request_car(world, page)

    await wait_for(page, "c.stats.framesDecoded > 5")
    # The picture is the camera's, at its size.
    assert await page.locator("video").evaluate("v => v.videoWidth") == TEST_CAMERA["width"]

    assert await drive_forward(world, page) > 0.1
    agent = world.agents["car-1"]
    # Releasing the key stops the car ("stop" is sent on release).

    async def stopped() -> bool:
        return bool(agent.adapter.telemetry()["motors"] == {"left": 0.0, "right": 0.0})

    await until(stopped, within=10, what="the car's motors to stop")

    await expect(page.locator("[data-rtt]")).to_have_text(re.compile(r"\d+\.\d ms"))
    await expect(page.locator("[data-topic=battery_level] .value")).not_to_have_text("\u2013")
    # Telemetry in words, with units and sensible rounding (the agent describes its topics).
    battery = page.locator("[data-topic=battery_level]")
    await expect(battery.locator(".topic")).to_have_text("Battery")
    await expect(battery.locator(".value")).to_have_text(re.compile(r"^\d+ %$"))
    await expect(page.locator("[data-topic=distance_ahead] .topic")).to_have_text("Obstacle ahead")
    await expect(page.locator("[data-topic=heading] .value")).to_have_text(re.compile(r"^\d+°$"))
    await expect(page.locator("[data-topic=location] .value")).to_have_text(
        re.compile(r"^\d+\.\d{5}° N, \d+\.\d{5}° W$")
    )
    await assert_nothing_refused(page)
    # The session log: one time format (24-hour, local), in order, the newest last,
    # whether the line came with the page or live from the feed.
    await expect(page.locator("[data-log] li")).not_to_have_count(0)
    times = await page.locator("[data-log] li time").evaluate_all(
        "nodes => nodes.map(n => [n.textContent, n.getAttribute('datetime')])"
    )
    assert all(re.fullmatch(r"\d\d:\d\d:\d\d", text) for text, _ in times), times
    stamps = [iso for _, iso in times]
    assert stamps == sorted(stamps, key=lambda iso: datetime.fromisoformat(iso)), stamps

    # Asked first, with what the car will do; Cancel leaves the session as it was.
    asked = await end_session(page, first_dismiss=True)
    assert asked == "End the session? car-1 will stop where it is.", asked
    session = await db(Session.objects.get, pk=session_id)
    assert session.state == Session.State.ENDED

    async def car_free() -> bool:
        car = await db(Vehicle.objects.get, name="car-1")
        return car.status == Vehicle.Status.IDLE

    # Free once its agent has confirmed the end, a moment later.
    await until(car_free, what="the car to be free again")


async def test_a_gamepad_flies_the_drone_in_proportion_and_its_buttons_act(world: World):
    page = await world.login("client")
    await page.context.add_init_script(FAKE_GAMEPAD)
    drone = await request_drone(world, page)  # the pages it opens have the pad
    sent = "(() => window.sentCommands.filter(m => m.name === {!r}).map(m => m.args))()"

    # The right stick pushed about half way forward (past the dead zone): "front" at
    # half the key's speed; all the way, at the key's own.
    await page.evaluate("() => { window.testPad.axes[3] = -0.575; }")
    await page.wait_for_function(f"() => {sent.format('front')}.length >= 3")
    half = await page.evaluate(f"() => {sent.format('front')}")
    assert all(abs(args["speed_mps"] - 0.5) < 0.01 for args in half), half
    start = drone.state().position
    await page.evaluate("() => { window.testPad.axes[3] = -1; }")
    await page.wait_for_function(
        f"() => {sent.format('front')}.some(a => Object.keys(a).length === 0)"
    )

    # Held: the drone moves forward (as fast as the simulator runs on a busy machine).
    async def moved_forward() -> bool:
        moved = drone.state().position
        return start is not None and moved is not None and distance_m(start, moved) > 0.05

    await until(moved_forward, within=20, what="the drone to move forward")
    await page.evaluate("() => { window.testPad.axes[3] = 0; }")  # let go: the drone stops
    await page.wait_for_function(f"() => {sent.format('stop')}.length >= 1")
    await assert_nothing_refused(page)

    # A stick inside the dead zone sends nothing.
    count = await page.evaluate("() => window.sentCommands.length")
    await page.evaluate("() => { window.testPad.axes[1] = 0.1; }")
    await page.wait_for_timeout(300)
    assert await page.evaluate("() => window.sentCommands.length") == count

    # B: return home, once however long it is held.
    await page.evaluate("() => { window.testPad.buttons[1].pressed = true; }")
    await page.wait_for_function(f"() => {sent.format('return_to_home')}.length === 1")
    # Everything held is let go while B is down (the window loses focus; a frozen
    # picture or a fail-safe does the same): B is still not sent again.
    await page.evaluate("() => window.dispatchEvent(new Event('blur'))")
    await page.wait_for_timeout(300)
    await page.evaluate("() => { window.testPad.buttons[1].pressed = false; }")
    assert len(await page.evaluate(f"() => {sent.format('return_to_home')}")) == 1

    async def flying_home() -> bool:
        return drone.telemetry().get("flight_mode") == "RTL"

    await until(flying_home, within=10, what="the drone to fly home (RTL)")


async def test_second_user_spectates_the_drone_but_cannot_steer(world: World):
    driver = await world.login("client")
    drone = await request_drone(world, driver)
    await db(f.user, "viewer-vera", roles=(CLIENT,))
    vera = await world.login("viewer-vera", "pw-for-tests")
    await vera.goto(f"{world.base}/spectate/")
    await expect(vera.locator("[data-spectate]")).to_contain_text("quad-1")
    await vera.click("[data-spectate] a.button")
    await wait_for(vera, "c.role === 'viewer' && c.stats.framesDecoded > 3")
    await expect(vera.locator("[data-topic=altitude] .value")).not_to_have_text("\u2013")
    assert await vera.locator("[data-controls]").count() == 0

    altitude = drone.telemetry()["altitude"]
    await hold(vera, "w", 1.0)  # the viewer tries to climb: nothing happens
    assert abs(drone.telemetry()["altitude"] - altitude) < 0.3
    # The driver still flies.
    await hold_until(driver, "w", _altitude_above(drone, altitude + 0.5), what="the drone to climb")


async def test_monitor_stops_a_running_session(world: World):
    client = await world.login("client")
    session_id = await request_car(world, client)
    await client.keyboard.down("ArrowUp")

    monitor = await world.login("monitor")
    await monitor.goto(f"{world.base}/monitor/")
    row = monitor.locator(f"[data-session='{session_id}']")
    await expect(row).to_be_visible(timeout=10000)
    await expect(monitor.locator("[data-vehicle=car-1]")).to_contain_text("in service")
    asked: list[str] = []

    async def confirm(dialog: Any) -> None:
        asked.append(dialog.message)
        await dialog.accept()

    monitor.once("dialog", confirm)
    await row.locator("[data-stop]").click()

    await expect(client.locator("[data-banner]")).to_contain_text(
        "Session over: stopped by a monitor (monitor).", timeout=10000
    )
    await client.keyboard.up("ArrowUp")
    # The driver's page no longer offers what does not apply: nothing to end or steer,
    # no live picture, the telemetry marked as the last values received.
    await expect(client.locator("[data-end-session]")).to_have_count(0)
    await expect(client.locator("[data-controls]")).to_be_hidden()
    await expect(client.locator("[data-video-note]")).to_have_text(
        "The session is over: no live video."
    )
    await expect(client.locator("[data-telemetry]")).to_have_attribute("data-stale", "true")
    await expect(client.locator("[data-session-state]")).to_have_text("aborted")
    assert world.agents["car-1"].adapter.telemetry()["motors"] == {"left": 0.0, "right": 0.0}
    session = await db(Session.objects.get, pk=session_id)
    assert session.state == Session.State.ABORTED and "monitor" in session.reason
    await expect(row).to_have_count(0, timeout=10000)
    # The monitor was told what the car would do, and sees that the stop reached it.
    assert asked == [
        "Stop client's session? car-1 will stop where it is. The user loses control."
    ], asked
    delivered = monitor.locator(f"[data-ended-session='{session_id}'] [data-delivery]")
    await expect(delivered).to_contain_text("The stop reached car-1", timeout=10000)
    await expect(delivered).to_have_attribute("data-delivery", "delivered")


async def test_closing_the_tab_triggers_failsafe_and_is_recorded(world: World):
    # The fail-safe is under test here: the demo's own timeout, not the world's.
    await db(lambda: Service.objects.filter(slug="drive-car").update(link_loss_timeout_ms=500))
    page = await world.login("client")
    session_id = await request_car(world, page)
    await page.keyboard.down("ArrowUp")
    await asyncio.sleep(0.3)
    await page.close()  # the user closes the tab mid-drive

    agent = world.agents["car-1"]
    for _ in range(50):
        if agent.adapter.telemetry()["motors"] == {"left": 0.0, "right": 0.0}:
            break
        await asyncio.sleep(0.02)
    assert agent.adapter.telemetry()["motors"] == {"left": 0.0, "right": 0.0}

    async def recorded() -> bool:
        return await db(
            lambda: (
                Session.objects.get(pk=session_id).events.filter(kind="unintentional_end").exists()
            )
        )

    for _ in range(100):
        if await recorded():
            break
        await asyncio.sleep(0.1)
    assert await recorded()


async def test_the_same_drive_works_through_the_relay(world: World):
    page = await world.login("client")
    await request_car(world, page, relay=True)
    assert "/ws/relay/" in await controller(page, "c.task.control_url")
    await wait_for(page, "c.stats.framesDecoded > 3")
    assert await drive_forward(world, page) > 0.1
    await expect(page.locator("[data-rtt]")).to_contain_text("ms")


async def test_clients_cannot_reach_what_is_not_theirs(world: World):
    owner = await world.login("client")
    session_id = await request_car(world, owner)
    await db(f.user, "other-olga", roles=(CLIENT,))
    olga = await world.login("other-olga", "pw-for-tests")
    response = await olga.goto(f"{world.base}/sessions/{session_id}/")
    assert response.status == 404
    response = await olga.goto(f"{world.base}/admin/")
    assert "/admin/login/" in olga.url
    response = await olga.goto(f"{world.base}/monitor/")
    assert response.status == 403
    # A service without a grant for her: the fly-drone grant goes to clients, so make one.
    hidden = await db(f.service, "secret-service", grant_clients=False)
    response = await olga.goto(f"{world.base}/services/{hidden.slug}/")
    assert response.status == 404
    # The relay only carries messages: without a grant for this vehicle, the agent
    # refuses her and the relay closes her socket.
    outcome = await olga.evaluate(
        """(url) => new Promise((resolve) => {
             const ws = new WebSocket(url);
             const seen = [];
             ws.onopen = () => ws.send(JSON.stringify({type: "auth", grant: "forged.grant"}));
             ws.onmessage = (e) => seen.push(JSON.parse(e.data));
             ws.onclose = (e) => resolve({code: e.code, seen});
             setTimeout(() => resolve({code: "still open", seen}), 8000);
           })""",
        f"{world.base.replace('http', 'ws')}/ws/relay/{session_id}/",
    )
    assert outcome["code"] == 4401
    assert outcome["seen"][0]["type"] == "error"
