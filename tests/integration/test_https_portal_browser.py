"""The portal over HTTPS, as production runs it: TLS at nginx, the platform behind it.

The platform runs (iouv.serve) with production's security settings (``BEHIND_PROXY``,
``SECURE_SSL_REDIRECT``, secure cookies, HSTS at its production default) behind
Debian's nginx (``benchmarks.nginx_proxy``), which terminates TLS with a certificate
from a CA the test makes (``tests.tls``) and redirects plain http to https. The car's
agent dials its uplink as ``wss://`` through nginx, trusting that CA; Chromium trusts
the server's key alone (``--ignore-certificate-errors-spki-list``), not every
certificate. A user signs in over https, requests the car and drives it: the
controller page must reach the vehicle with no ``ws://`` anywhere (which an https page
may not open: mixed content), authenticate on the platform's ``wss://`` relay, signal
WebRTC there and drive on the data channels, the vehicle accepting no inbound
connection. docs/operations.md, "The portal over HTTPS", describes the set-up.
"""

from __future__ import annotations

import asyncio
import dataclasses
import http.client
import math
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from playwright.async_api import Browser, ConsoleMessage, Request, WebSocket

from agents.config import AgentConfig
from benchmarks.nginx_proxy import Backend, NginxProxy, NginxUnavailable, Routes, Tls, nginx_binary
from services.demo import demo_seed
from services.models import Service, Session
from tests.browser import chromium_browser
from tests.demo import PASSWORD, agents_online
from tests.portal import (
    PORTAL_MARKS,
    WORLD_LINK_LOSS_MS,
    World,
    assert_nothing_refused,
    controller,
    request_car,
    sign_in,
    wait_for,
)
from tests.servers import db, platform_process, until
from tests.tls import Certificates, certificates_make

pytestmark = PORTAL_MARKS

#: The platform's environment in production behind a TLS proxy (the test process's own
#: environment turns the redirect and secure cookies off: these override it).
#: SECURE_HSTS_SECONDS is left to its production default, a year; Chromium keeps no
#: HSTS for an IP address, and its profile is thrown away with it.
PRODUCTION_ENV = {
    "BEHIND_PROXY": "1",
    "SECURE_SSL_REDIRECT": "1",
    "SECURE_COOKIES": "1",
}
#: Generous bounds: the suite runs on loaded 2-core machines.
PAGE_TIMEOUT_MS = 60_000
WEBRTC_TIMEOUT_MS = 45_000
DRIVE_TIMEOUT_S = 20.0

#: Records each command the page sends and what carried it: the socket (relay) or a
#: WebRTC data channel (its label).
RECORD_COMMANDS = """
window.sentCommands = [];
const carriers = [["socket", WebSocket.prototype], ["datachannel", RTCDataChannel.prototype]];
for (const [via, proto] of carriers) {
  const send = proto.send;
  proto.send = function (data) {
    try {
      const msg = JSON.parse(data);
      if (msg.type === "command") {
        window.sentCommands.push({ via, label: this.label || null, name: msg.name });
      }
    } catch (e) { /* not JSON: not ours */ }
    return send.call(this, data);
  };
}
"""


@dataclasses.dataclass
class HttpsPortal:
    world: World  # base: the proxy's https URL
    proxy: NginxProxy
    platform: str  # http://127.0.0.1:N: the platform process itself, behind the proxy
    certs: Certificates

    @property
    def base(self) -> str:
        return self.world.base

    @property
    def browser(self) -> Browser:
        return self.world.browser


def car_agent_config(path: Path, platform_url: str) -> AgentConfig:
    """The demo car's agent, dialling ``platform_url``; WebRTC on loopback only."""
    loopback = ["127.0.0.1"]
    return dataclasses.replace(
        AgentConfig.load(path),
        platform_url=platform_url,
        video={"source": "synthetic", "ice_host_addresses": loopback},
        webrtc={"ice_host_addresses": loopback},
        reconnect_min_s=0.2,
    )


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def portal(
    module_database: None, tmp_path_factory: pytest.TempPathFactory
) -> AsyncIterator[HttpsPortal]:
    """The seeded demo on the platform with production's settings, nginx terminating TLS
    in front, car-1's agent online through it, and Chromium trusting the server key: one
    for the module (one test drives the car, the other only asks for pages)."""
    try:
        await asyncio.to_thread(nginx_binary)  # Debian's, installed if missing
    except NginxUnavailable as exc:
        pytest.skip(f"needs nginx: {exc}")
    tmp_path = tmp_path_factory.mktemp("https")
    certs = certificates_make(tmp_path / "tls")
    await db(demo_seed, password=PASSWORD, credentials_dir=tmp_path / "agents")
    # As in every browser world (tests.portal.WORLD_LINK_LOSS_MS): no fail-safe from a
    # saturated machine holding up Chromium's keepalives.
    await db(lambda: Service.objects.update(link_loss_timeout_ms=WORLD_LINK_LOSS_MS))
    with (
        platform_process(extra_env=PRODUCTION_ENV) as platform,
        pytest.MonkeyPatch.context() as monkeypatch,
    ):
        routes = Routes(default=Backend.parse(platform.removeprefix("http://")))
        tls = Tls(certs.chain, certs.key)
        async with NginxProxy(routes, prefix=tmp_path / "nginx", tls=tls, redirect_port=0) as proxy:
            # The agent's uplink makes its TLS context as any program does (the
            # system's trust store); here that store is the test's CA.
            monkeypatch.setenv("SSL_CERT_FILE", str(certs.ca))
            config = car_agent_config(
                tmp_path / "agents" / "car-1.json", f"wss://127.0.0.1:{proxy.port}"
            )
            online = agents_online(
                {"car-1": config}, within=60, what="car-1 online over wss with a position"
            )
            async with (
                online as running,
                chromium_browser(webrtc_loopback=True, extra_args=certs.chromium_args()) as browser,
            ):
                world = World(proxy.url, browser, running.agents)
                yield HttpsPortal(world, proxy, platform, certs)


def _get(
    url_host: str, port: int, path: str, *, https: Certificates | None = None, **headers: str
) -> http.client.HTTPResponse:
    """One GET, redirects not followed; the response, its body read."""
    connection: http.client.HTTPConnection
    if https is not None:
        connection = http.client.HTTPSConnection(
            url_host, port, timeout=15, context=https.client_context()
        )
    else:
        connection = http.client.HTTPConnection(url_host, port, timeout=15)
    try:
        connection.request("GET", path, headers=headers)
        response = connection.getresponse()
        response.read()
        return response
    finally:
        connection.close()


async def test_plain_http_is_sent_to_https_by_nginx_and_by_the_platform(
    portal: HttpsPortal,
) -> None:
    proxy, base = portal.proxy, portal.base
    # nginx's port "80": every request to the same path on https.
    assert proxy.redirect_port is not None
    response = await asyncio.to_thread(
        _get, "127.0.0.1", proxy.redirect_port, "/accounts/login/?next=/"
    )
    assert response.status == 301
    assert response.getheader("Location") == f"{base}/accounts/login/?next=/"
    # A browser that types the http:// address ends on the https page.
    context = await portal.browser.new_context()
    context.set_default_timeout(PAGE_TIMEOUT_MS)
    page = await context.new_page()
    landed = await page.goto(f"{proxy.redirect_url}/accounts/login/")
    assert page.url == f"{base}/accounts/login/"
    assert landed is not None and landed.status == 200
    first = landed.request.redirected_from  # nginx's answer, not a browser upgrade
    assert first is not None and first.url == f"{proxy.redirect_url}/accounts/login/"
    first_response = await first.response()
    assert first_response is not None and first_response.status == 301
    await context.close()

    # Through the proxy a request is secure, whatever the client claims: nginx
    # overwrites X-Forwarded-Proto. Django sends HSTS on secure requests only.
    response = await asyncio.to_thread(
        _get,
        "127.0.0.1",
        proxy.port,
        "/accounts/login/",
        https=portal.certs,
        **{"X-Forwarded-Proto": "http"},
    )
    assert response.status == 200
    assert "max-age=31536000" in (response.getheader("Strict-Transport-Security") or "")

    # The platform process itself, reached without the proxy (or a proxy that forgot
    # the header): Django's SECURE_SSL_REDIRECT. Health checks stay on plain http.
    platform_port = int(portal.platform.rsplit(":", 1)[1])
    response = await asyncio.to_thread(_get, "127.0.0.1", platform_port, "/accounts/login/")
    assert response.status == 301
    assert response.getheader("Location") == f"https://127.0.0.1:{platform_port}/accounts/login/"
    assert (await asyncio.to_thread(_get, "127.0.0.1", platform_port, "/healthz")).status == 200


async def test_over_https_the_controller_drives_on_webrtc_with_no_mixed_content(
    portal: HttpsPortal,
) -> None:
    base = portal.base
    assert base.startswith("https://")
    # The vehicle dialled out over wss://, through the proxy, like the browser does.
    uplink = portal.world.agents["car-1"].uplink
    assert uplink is not None and uplink.connected.is_set()
    assert uplink.url.startswith(f"wss://127.0.0.1:{portal.proxy.port}/"), uplink.url
    context = await portal.browser.new_context()
    context.set_default_timeout(PAGE_TIMEOUT_MS)
    await context.add_init_script(RECORD_COMMANDS)
    console: list[tuple[str, str, str]] = []  # (type, text, page url)
    page_errors: list[str] = []
    sockets: list[str] = []
    requests: list[str] = []
    failed: list[str] = []
    context.on("request", lambda request: requests.append(request.url))

    def request_failed(request: Request) -> None:
        failed.append(f"{request.url}: {request.failure}")

    context.on("requestfailed", request_failed)
    page = await context.new_page()

    def on_console(message: ConsoleMessage) -> None:
        console.append((message.type, message.text, page.url))

    def on_socket(socket: WebSocket) -> None:
        sockets.append(socket.url)

    page.on("console", on_console)
    page.on("pageerror", lambda error: page_errors.append(str(error)))
    page.on("websocket", on_socket)

    # Signed in over https: the form's POST passes CSRF (Origin and Referer are the
    # proxy's https origin, the Host nginx passes on is the same), and both cookies
    # are Secure.
    await sign_in(page, base, "client")
    cookies = {c["name"]: c for c in await context.cookies(base)}
    assert cookies["sessionid"]["secure"] and cookies["csrftoken"]["secure"], cookies

    session_id = await request_car(portal.world, page, timeout_ms=PAGE_TIMEOUT_MS)
    assert page.url == f"{base}/sessions/{session_id}/"
    assert await page.evaluate("() => window.isSecureContext") is True
    # Every socket the page opens is wss:// on the portal's own origin: the relay
    # (signalling, and control until WebRTC is up) and the session feed.
    wss = f"wss://127.0.0.1:{portal.proxy.port}/"
    relay_url = await controller(page, "c.task.relay_url")
    assert relay_url.startswith(f"{wss}ws/relay/"), relay_url
    feed_url = await page.get_attribute("#controller", "data-feed-url")
    assert feed_url is not None and feed_url.startswith(f"{wss}ws/sessions/"), feed_url

    # The agent moves the user from the relay to WebRTC, directly (loopback here).
    await wait_for(page, "c.path === 'webrtc_direct' && !!c.channels", WEBRTC_TIMEOUT_MS)
    assert await page.get_attribute("[data-path]", "data-path") == "webrtc_direct"
    assert await controller(page, "c.channels.control.readyState") == "open"

    # Driving: hold the key until the simulated car has moved (bounded), then let go.
    car: Any = portal.world.agents["car-1"].adapter
    acks_before = await controller(page, "c.stats.acks")
    start = car.sensors.pose

    def moved_m() -> float:
        pose = car.sensors.pose
        return math.hypot(pose.north_m - start.north_m, pose.east_m - start.east_m)

    await page.keyboard.down("ArrowUp")
    try:

        async def moving() -> bool:
            return moved_m() > 0.1

        await until(moving, within=DRIVE_TIMEOUT_S, what="the car to move while ArrowUp is held")
    finally:
        await page.keyboard.up("ArrowUp")

    async def stopped() -> bool:
        return bool(car.telemetry()["motors"] == {"left": 0.0, "right": 0.0})

    await until(stopped, within=DRIVE_TIMEOUT_S, what="the car to stop once the key is up")
    await wait_for(page, f"c.stats.acks > {acks_before}", 30_000)
    await assert_nothing_refused(page)
    sent = await page.evaluate("() => window.sentCommands")
    assert any(s["name"] == "forward" for s in sent), sent
    # All of it on the data channels: held motions on "input", the stop on "urgent".
    assert all(s["via"] == "datachannel" for s in sent), sent
    assert {s["label"] for s in sent if s["name"] == "forward"} == {"input"}, sent
    await wait_for(page, "window.sentCommands.some(s => s.name === 'stop')", 15_000)
    stops = await page.evaluate("() => window.sentCommands.filter(s => s.name === 'stop')")
    assert {s["label"] for s in stops} == {"urgent"}, stops

    # The platform records the path, from the agent's report.
    async def recorded() -> bool:
        session = await db(Session.objects.get, pk=session_id)
        return session.control_path == "webrtc_direct"

    await until(recorded, within=30, what="the session to record the WebRTC path")

    # Nothing insecure was attempted, nothing failed, and the console is clean.
    assert sockets and all(url.startswith(wss) for url in sockets), sockets
    insecure = [url for url in requests if not url.startswith((f"{base}/", "data:", "blob:"))]
    assert insecure == [], insecure
    assert failed == [], failed
    assert page_errors == [], page_errors
    problems = [
        entry
        for entry in console
        if entry[0] == "error"
        or any(word in entry[1] for word in ("Mixed Content", "insecure", "Content Security"))
    ]
    assert problems == [], problems
