"""The session page's paths to the vehicle, in Chromium: WebRTC signalled through the
platform, the relay when WebRTC cannot be had (and another relay socket when one goes
silent), and driving paused while the video is frozen.

Same world as ``test_portal`` (the ``world`` fixture): the seeded demo on the platform,
the simulated car and drone's agents (in this process, so a test can switch a vehicle's
WebRTC off or freeze its camera), Debian's Chromium.
"""

from __future__ import annotations

import asyncio
import dataclasses
from typing import Any
from urllib.parse import urlsplit

from services.models import Session
from tests.freezing_proxy import FreezingProxy
from tests.portal import (
    FAKE_GAMEPAD,
    PORTAL_MARKS,
    RECORD_COMMANDS,
    World,
    drive_forward,
    request_car,
    wait_for,
)
from tests.servers import db, until

pytestmark = PORTAL_MARKS


#: The sign between a picture's width and height on the page (a multiplication sign).
TIMES = "\u00d7"


def _sent(name: str) -> str:
    return f"window.sentCommands.filter(m => m.name === {name!r}).length"


async def test_the_page_drives_over_webrtc_and_says_which_path(world: World) -> None:
    page = await world.login("client", init_script=RECORD_COMMANDS)
    session_id = await request_car(world, page)
    await wait_for(page, "c.path === 'webrtc_direct' && c.channels !== null")
    assert await page.locator("[data-path]").inner_text() == "WebRTC, direct"
    assert await drive_forward(world, page) > 0.05
    # The commands went on the data channels, not on the platform's socket.
    on_channels = await page.evaluate(
        "() => window.iouvController.channels.input.readyState === 'open'"
    )
    assert on_channels

    async def recorded() -> bool:
        session = await db(Session.objects.get, pk=session_id)
        return session.control_path == "webrtc_direct"

    await until(recorded, what="the session to record the WebRTC path")


async def test_the_pilot_sees_what_the_camera_sends_and_what_arrives(world: World) -> None:
    page = await world.login("client")
    await request_car(world, page)
    await wait_for(page, "c.videoStatus !== null && c.videoReceived && c.videoReceived.fps > 0")
    encoder = world.agents["car-1"].video.encoder
    assert encoder.rate.governing_role() == "pilot"

    def words(status: Any) -> str:
        rate = (
            f"{status.bitrate / 1e6:.1f} Mbit/s"
            if status.bitrate >= 1e6
            else f"{round(status.bitrate / 1e3)} kbit/s"
        )
        return f"{status.width}{TIMES}{status.height}, {status.fps} fps, {rate}"

    async def agree() -> bool:
        # The agent's encoder and the page say the same (a new status may be on its way).
        shown = await page.locator("[data-video-stats]").inner_text()
        return shown == words(encoder.status)

    await until(agree, within=10, what="the page to show what the encoder sends")
    status = encoder.status
    received = await page.evaluate("window.iouvController.videoReceived")
    assert (received["width"], received["height"]) == (status.width, status.height)
    title = await page.locator("[data-video-stats]").get_attribute("title")
    assert title is not None and title.startswith(f"Received: {status.width}{TIMES}{status.height}")


async def test_without_webrtc_the_page_stays_on_the_relay_and_says_so(world: World) -> None:
    hub: Any = world.agents["car-1"].hub
    hub.webrtc_options = {"enabled": False}  # as an agent configured without it
    page = await world.login("client")
    await request_car(world, page)
    await wait_for(page, "c.path === 'relay' && c.pc === null")
    assert await page.locator("[data-path]").inner_text() == "relay through the platform"
    toast = page.locator("[data-toast]")
    assert "No direct connection" in await toast.inner_text()
    assert await drive_forward(world, page) > 0.05


async def test_a_relay_socket_gone_silent_is_given_up_and_driving_resumes(world: World) -> None:
    """The platform process holding the page's relay socket drops off the network while
    the proxy in front stays up: the socket neither answers nor closes. The page gives
    it up after 5 s of silence, says so, and drives on over a new relay socket (through
    the same proxy, to a platform that answers) without the user doing anything."""
    hub: Any = world.agents["car-1"].hub
    hub.webrtc_options = {"enabled": False}  # control on the relay socket all along
    target = urlsplit(world.base)
    async with FreezingProxy(target_port=target.port or 80) as proxy:
        proxied = dataclasses.replace(world, base=f"http://127.0.0.1:{proxy.port}")
        page = await proxied.login("client")
        await request_car(proxied, page)
        await wait_for(page, "c.path === 'relay' && c.pc === null")
        assert await drive_forward(world, page) > 0.05
        assert proxy.freeze(lambda first_line: "/ws/relay/" in first_line) == 1
        said = "Connection to the vehicle lost (no answer for 5 s)"
        banner = "document.querySelector('[data-banner]').innerText"
        await wait_for(page, f"{banner}.includes({said!r})")
        await wait_for(page, "c.role === 'controller' && c.path === 'relay'", 30000)
        # A second relay socket, on a connection the proxy still passes.
        assert sum("/ws/relay/" in c.first_line for c in proxy.connections) == 2
        assert await drive_forward(world, page) > 0.05


async def test_a_frozen_picture_pauses_driving_until_it_moves_again(world: World) -> None:
    """While the picture is frozen nothing moves the car. A key held through the freeze
    and a stick pushed meanwhile wait, and drive once the picture moves again, still
    held (the browser repeats no press for a held key, the stick none either); a key
    pressed and let go meanwhile is forgotten. Stop goes all along."""
    page = await world.login("client", init_script=FAKE_GAMEPAD)
    await request_car(world, page)
    await wait_for(page, "c.channels !== null && c.stats.framesDecoded > 5", 30000)
    source: Any = world.agents["car-1"].video.encoder.source
    frame, thawed = source.frame, asyncio.Event()

    async def frozen() -> Any:
        await thawed.wait()  # the camera hangs: no new frame reaches the page
        return await frame()

    async def sent(name: str) -> int:
        return int(await page.evaluate(f"() => {_sent(name)}"))

    source.frame = frozen
    try:
        await wait_for(page, "c.videoFrozen === true", 15000)
        banner = page.locator("[data-banner]")
        assert "video is frozen" in await banner.inner_text()
        before = {name: await sent(name) for name in ("forward", "back", "right")}
        # Back: pressed and let go while frozen, forgotten.
        await page.keyboard.down("ArrowDown")
        await page.wait_for_function("() => !document.querySelector('[data-toast]').hidden")
        await page.keyboard.up("ArrowDown")
        await page.keyboard.down("ArrowUp")  # forward: held through the freeze
        await wait_for(page, "c.keyPaused.has('forward') && !c.keyPaused.has('back')")
        # The safe commands still go.
        stops = await sent("stop")
        await page.click("[data-command=stop]")
        await page.wait_for_function(f"() => {_sent('stop')} > {stops}")
        # The right stick pushed right all the way: it waits too.
        await page.evaluate("() => { window.testPad.axes[2] = 1; }")
        await wait_for(page, "c.stickPaused.has('right')")
        assert {name: await sent(name) for name in before} == before
    finally:
        source.frame = frame
        thawed.set()
    await wait_for(page, "c.videoFrozen === false", 15000)
    # The picture moves: the key and the stick, never let go, drive; back does not.
    await page.wait_for_function(
        f"() => {_sent('forward')} > {before['forward']} && {_sent('right')} > {before['right']}"
    )
    assert await sent("back") == before["back"]
    await page.keyboard.up("ArrowUp")
    await page.evaluate("() => { window.testPad.axes[2] = 0; }")
    await page.wait_for_function(f"() => {_sent('stop')} > {stops + 1}")
    assert await drive_forward(world, page) > 0.05


#: The platform's relay socket cannot be opened (as when the platform is out of reach of
#: the user's network but the vehicle is on the same LAN): every relay URL is swapped
#: for a port nobody listens on.
RELAY_UNREACHABLE = """
const RealWebSocket = window.WebSocket;
window.WebSocket = function (url, protocols) {
  if (String(url).includes("/ws/relay/")) url = "ws://127.0.0.1:9/";
  return new RealWebSocket(url, protocols);
};
window.WebSocket.prototype = RealWebSocket.prototype;
Object.assign(window.WebSocket, { OPEN: 1, CLOSED: 3, CONNECTING: 0, CLOSING: 2 });
"""


async def test_when_the_relay_cannot_be_opened_the_page_uses_the_vehicles_own_socket(
    world: World,
) -> None:
    page = await world.login("client", init_script=RELAY_UNREACHABLE)
    await request_car(world, page)
    await wait_for(page, "c.path === 'websocket' && c.direct === true")
    assert await page.locator("[data-path]").inner_text() == "the vehicle's own socket"
    assert await drive_forward(world, page) > 0.05
