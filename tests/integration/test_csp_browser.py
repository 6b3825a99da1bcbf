"""The portal works under its Content-Security-Policy in a real browser.

The platform runs (iouv.serve) with map tiles from a tile server on another origin; the
simulated car's agent serves its control socket and WebRTC video on a port of its own.
Chromium (Playwright) opens the catalog, the rescue request map, a controller session,
the monitor dashboard and the admin, and every ``securitypolicyviolation`` event and
CSP console error fails the test.
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import http.server
import re
import threading
from collections.abc import AsyncIterator, Iterator
from typing import Any

import pytest
import pytest_asyncio
from django.contrib.auth import get_user_model
from playwright.async_api import Browser, Page, Response, expect

from fleet.models import Station
from services.models import Service, Session
from tests.deployment import session_requested
from tests.portal import LISTEN_FOR_VIOLATIONS, PORTAL_MARKS, World, demo_world, sign_in, wait_for
from tests.servers import db

pytestmark = PORTAL_MARKS

#: A 1x1 PNG: every tile the map asks for.
TILE = base64.b64decode(
    "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mNkYPhfDwAChwGA60e6kgAAAABJRU5ErkJggg=="
)


@dataclasses.dataclass
class TileServer:
    base: str
    served: list[str]


@contextlib.contextmanager
def tile_server() -> Iterator[TileServer]:
    """A map tile server on its own loopback port, so on an origin of its own."""
    served: list[str] = []

    class Tiles(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            served.append(self.path)
            self.send_response(200)
            self.send_header("Content-Type", "image/png")
            self.send_header("Content-Length", str(len(TILE)))
            self.end_headers()
            self.wfile.write(TILE)

        def log_message(self, format: str, *args: Any) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Tiles)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield TileServer(f"http://127.0.0.1:{server.server_address[1]}", served)
    finally:
        server.shutdown()
        server.server_close()


@dataclasses.dataclass
class Portal:
    base: str
    browser: Browser
    tiles: TileServer
    console: list[str] = dataclasses.field(default_factory=list)

    async def login(self, username: str) -> Page:
        """A fresh browser context logged in as ``username``, on the catalog, its CSP
        violations recorded (see :func:`assert_no_violations`)."""
        context = await self.browser.new_context()
        await context.add_init_script(script=LISTEN_FOR_VIOLATIONS)
        page = await context.new_page()
        page.on("console", self._console)
        await sign_in(page, self.base, username)
        return page

    def _console(self, message: Any) -> None:
        if "Content Security Policy" in message.text:
            self.console.append(f"{message.type}: {message.text}")

    async def open(self, page: Page, path: str) -> Response:
        response = await page.goto(f"{self.base}{path}")
        assert response is not None and response.ok, path
        policy = await response.header_value("content-security-policy")
        assert policy and "script-src 'self'" in policy, f"{path}: policy {policy!r}"
        return response

    async def assert_no_violations(self, page: Page, what: str) -> None:
        seen = await page.evaluate("window.__cspViolations")
        assert seen == [], f"{what}: {seen}"
        assert self.console == [], f"{what}: {self.console}"


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def csp_world(
    module_database: None, tmp_path_factory: pytest.TempPathFactory
) -> AsyncIterator[tuple[World, TileServer]]:
    """The seeded demo on the platform, with map tiles from the tile server, car-1's
    agent online and idle, and Chromium: one for the module (its tests only open pages,
    and one of them a session of its own on the car)."""
    with tile_server() as tiles:
        tiles_url = {"IOUV_MAP_TILES_URL": f"{tiles.base}/{{z}}/{{x}}/{{y}}.png"}
        async with demo_world(
            tmp_path_factory.mktemp("csp"), ("car-1",), env=tiles_url, within=15, positioned=False
        ) as world:
            yield world, tiles


@pytest.fixture
def portal(csp_world: tuple[World, TileServer]) -> Portal:
    """The module's world as a test sees it: with its own record of what the console
    said, and of the tiles served from now on."""
    world, tiles = csp_world
    tiles.served.clear()
    return Portal(world.base, world.browser, tiles)


def _drive_car_for(username: str) -> Session:
    """A deployed drive-car session of ``username`` near the campus station."""
    station = Station.objects.get(name="Campus station")
    session = session_requested(
        user=get_user_model().objects.get(username=username),
        service=Service.objects.get(slug="drive-car"),
        target=(station.lat, station.lon),
    ).session
    return session


async def test_the_policy_blocks_inline_script_and_the_test_sees_it(portal: Portal) -> None:
    """The detector itself: an injected inline script is blocked and reported."""
    page = await portal.login("client")
    await portal.open(page, "/")
    ran = await page.evaluate(
        """() => {
             const script = document.createElement("script");
             script.textContent = "window.__inlineRan = true";
             document.body.append(script);
             return window.__inlineRan === true;
           }"""
    )
    assert ran is False
    await page.wait_for_function("window.__cspViolations.length > 0")
    assert "script-src" in (await page.evaluate("window.__cspViolations"))[0]


async def test_portal_pages_work_under_the_policy_without_violations(portal: Portal) -> None:
    client = await portal.login("client")

    await portal.open(client, "/")
    await expect(client.locator("[data-service=drive-car]")).to_be_visible()
    await portal.assert_no_violations(client, "the catalog")

    # The rescue request's map, with tiles from the tile server's origin.
    await portal.open(client, "/services/rescue-at-sea/")
    await client.wait_for_function("document.querySelectorAll('img.leaflet-tile-loaded').length")
    assert portal.tiles.served
    await client.click("#area-map", position={"x": 200, "y": 150})
    await expect(client.locator("[data-area-info]")).to_contain_text("1 point")
    await portal.assert_no_violations(client, "the rescue request page")

    # A controller session: a socket straight to the car's agent on its own port,
    # WebRTC video decoding, the session feed from the platform. (Requested as the
    # portal's form does; the form itself is tested in test_portal.py.)
    session = await db(_drive_car_for, "client")
    await portal.open(client, f"/sessions/{session.pk}/")
    await wait_for(client, "c.role === 'controller' && c.stats.framesDecoded > 3")
    control_url = await client.evaluate("window.iouvController.task.control_url")
    assert control_url.startswith("ws://") and not control_url.startswith(
        portal.base.replace("http", "ws")
    )
    await expect(client.locator("[data-rtt]")).to_have_text(re.compile(r"\d+\.\d ms"))
    await portal.assert_no_violations(client, "the controller session page")

    monitor = await portal.login("monitor")
    await portal.open(monitor, "/monitor/")
    await expect(monitor.locator("[data-conn-state]")).to_have_text("live")
    await expect(monitor.locator("[data-vehicle=car-1]")).to_contain_text("in service")
    await portal.assert_no_violations(monitor, "the monitor dashboard")

    admin = await portal.login("admin")
    for path in ("/admin/", "/admin/fleet/vehicle/", "/admin/fleet/vehicle/add/"):
        await portal.open(admin, path)
        await expect(admin.locator("#site-name")).to_be_visible()
        await portal.assert_no_violations(admin, path)
