"""The portal as a person uses it, for the browser tests: the running demo with Chromium
(:class:`World`, :func:`demo_world`), signing in, the devices people hold, and what a
person does on a session page (request the car or the drone, drive, hold a key, end),
with the scripts the tests put in pages to watch them.

The fixtures built on these are in the packages' conftest.py (``world`` in
tests/integration, ``portal`` in kinds/rescue_at_sea/tests).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
import re
from collections.abc import AsyncIterator, Callable, Iterable
from pathlib import Path
from typing import Any

import pytest
from playwright.async_api import Browser, Page, expect
from playwright.async_api import TimeoutError as PlaywrightTimeout

from agents.config import AgentConfig
from agents.runtime import Agent
from fleet.models import AgentMessage
from services.demo import demo_seed
from services.models import Service, Session
from services.sessions.ending import session_end_by_user
from services.sessions.states import FINAL, SessionStateError
from tests.browser import chromium_browser, needs_chromium
from tests.demo import PASSWORD, agents_online, demo_agent_config, demo_running
from tests.servers import db, platform_process, until


@dataclasses.dataclass
class World:
    """The portal at ``base``, Chromium, and the demo vehicles' agents by name."""

    base: str
    browser: Browser
    agents: dict[str, Agent]

    async def login(
        self,
        username: str,
        password: str = PASSWORD,
        *,
        init_script: str | None = None,
        **context_options: Any,
    ) -> Page:
        """A new browser context (Playwright's ``new_context`` options: a viewport, a
        phone's touch...) signed in as ``username``; ``init_script`` runs in each of its
        pages first. Returns its page, on the catalog."""
        context = await self.browser.new_context(**context_options)
        if init_script:
            await context.add_init_script(init_script)
        page = await context.new_page()
        await sign_in(page, self.base, username, password)
        return page


async def sign_in(page: Page, base: str, username: str, password: str = PASSWORD) -> None:
    """Sign ``page`` in as ``username`` through the login form; it ends on the catalog."""
    await page.goto(f"{base}/accounts/login/")
    await page.fill("#id_username", username)
    await page.fill("#id_password", password)
    await page.click("button[type=submit]")
    await page.wait_for_url(f"{base}/")


#: The services' link-loss fail-safe in a browser world, at least. The demo's 500 ms
#: suits a phone on a real link; Chromium on a saturated test machine misses its
#: keepalives for longer now and then, and the vehicle would stop or go home in the
#: middle of a test about something else. The fail-safe's own timing is tested where a
#: client's silence is the test's to choose (tests/agents, test_scale_out, ...).
WORLD_LINK_LOSS_MS = 3000


def _link_loss_raised(floor_ms: int) -> dict[str, int]:
    """Every service's link-loss timeout raised to at least ``floor_ms``; returns them
    all by slug, as they are now."""
    Service.objects.filter(link_loss_timeout_ms__lt=floor_ms).update(link_loss_timeout_ms=floor_ms)
    return dict(Service.objects.values_list("slug", "link_loss_timeout_ms"))


@contextlib.asynccontextmanager
async def demo_world(
    directory: Path,
    names: Iterable[str] = ("car-1", "quad-1"),
    configure: Callable[[Path, str], AgentConfig] = demo_agent_config,
    *,
    env: dict[str, str] | None = None,
    worker: bool = False,
    within: float = 30,
    positioned: bool = True,
    webrtc_loopback: bool = True,
    link_loss_timeout_ms: int = WORLD_LINK_LOSS_MS,
) -> AsyncIterator[World]:
    """The seeded demo on the platform, the agents of ``names`` online (by default
    car-1's and quad-1's, idle with a position; their configs in ``directory``), and
    Chromium (``webrtc_loopback``: able to take their video). Every service's link-loss
    timeout is at least ``link_loss_timeout_ms`` (:data:`WORLD_LINK_LOSS_MS`). The other
    options are tests.demo.demo_running's."""
    running = demo_running(
        directory, names, configure, env=env, worker=worker, within=within, positioned=positioned
    )
    # The agents stop (cancelled, then their simulators) after the browser.
    async with running as demo, chromium_browser(webrtc_loopback=webrtc_loopback) as browser:
        await db(_link_loss_raised, link_loss_timeout_ms)
        yield World(demo.base, browser, demo.agents)


#: The marks of a browser module whose tests share a world started once for the module
#: (tests/integration's ``world`` on its :class:`Portal`, or a module's own): the test
#: database, not ``transaction=True``, which would empty it after each test while the
#: world lives on (the root conftest's ``module_database``), and the module's event
#: loop, which the world lives in.
PORTAL_MARKS = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db,
    needs_chromium,
    pytest.mark.asyncio(loop_scope="module"),
]


@dataclasses.dataclass
class Portal:
    """The seeded demo on the platform at ``base``, and Chromium: what a module's
    browser tests share, each with a fleet of its own (:func:`fleet_world`). The
    agents' configs are in ``directory``; ``link_loss_ms`` is each service's link-loss
    timeout (by slug) as every test starts with it."""

    directory: Path
    base: str
    browser: Browser
    link_loss_ms: dict[str, int]


@contextlib.asynccontextmanager
async def portal_running(
    directory: Path, *, link_loss_timeout_ms: int = WORLD_LINK_LOSS_MS
) -> AsyncIterator[Portal]:
    """The seeded demo (its agents' configs in ``directory``) on the platform, with
    Chromium able to take the vehicles' video, and every service's link-loss timeout
    at least ``link_loss_timeout_ms``. For a module's tests together: starting the
    platform and Chromium, seeding and emptying the database cost a world about 3 s
    of CPU, more than most of its tests. Needs the module's database (the root
    conftest's ``module_database``): a transactional test's teardown would empty it."""
    await db(demo_seed, password=PASSWORD, credentials_dir=directory)
    link_loss = await db(_link_loss_raised, link_loss_timeout_ms)
    with platform_process() as base:
        async with chromium_browser(webrtc_loopback=True) as browser:
            yield Portal(directory, base, browser, link_loss)


def _link_loss_set(timeouts: dict[str, int]) -> None:
    for slug, ms in timeouts.items():
        Service.objects.filter(slug=slug).exclude(link_loss_timeout_ms=ms).update(
            link_loss_timeout_ms=ms
        )


def _sessions_left_end() -> None:
    """End every session a test left open, as its user would (one still waiting is
    withdrawn): its vehicles get ``end_task``."""
    for session in Session.objects.exclude(state__in=FINAL):
        with contextlib.suppress(SessionStateError):  # it ended meanwhile
            session_end_by_user(session=session)


def _owed(names: list[str]) -> int:
    """How many messages the platform still owes the agents of ``names``."""
    return AgentMessage.objects.filter(
        vehicle__name__in=names, state=AgentMessage.State.PENDING
    ).count()


@contextlib.asynccontextmanager
async def fleet_world(
    portal: Portal,
    names: Iterable[str] = ("car-1", "quad-1"),
    *,
    within: float = 30,
) -> AsyncIterator[World]:
    """The agents of ``names`` (by default car-1's and quad-1's) online against
    ``portal``'s platform on fresh simulators, idle with a position, for one test: what
    it changes in an agent or a simulator goes with them. It starts with the portal's
    link-loss timeouts, whatever an earlier test set. On exit the browser contexts it
    opened close, the sessions it left open end, and the agents stop once they have
    acknowledged those ends, so the next test finds every vehicle free."""
    await db(_link_loss_set, portal.link_loss_ms)
    configs = {
        name: demo_agent_config(portal.directory / f"{name}.json", portal.base) for name in names
    }
    before = set(portal.browser.contexts)
    async with agents_online(configs, within=within) as running:
        try:
            yield World(portal.base, portal.browser, running.agents)
        finally:
            for context in portal.browser.contexts:
                if context not in before:
                    await context.close()
            await db(_sessions_left_end)
            alive = [name for name, task in running.tasks.items() if not task.done()]

            async def acknowledged() -> bool:
                return await db(_owed, alive) == 0

            await until(
                acknowledged, within=30, what="the agents to take the ends of their sessions"
            )


# --- on a session page --------------------------------------------------------------------


async def controller(page: Page, expression: str) -> Any:
    """``expression`` evaluated in the page with ``c``, its controller."""
    return await page.evaluate(f"() => {{ const c = window.iouvController; return {expression}; }}")


async def wait_for(page: Page, expression: str, timeout_ms: int = 45000) -> None:
    """Wait until the page has a controller ``c`` and ``expression`` holds.

    45 s by default: with the suite's other workers on a saturated machine, WebRTC's
    first frames have taken over 15 s; a state is waited on, never timed. On time out,
    the failure says where the page's controller stood (:data:`PAGE_STATE`)."""
    try:
        await page.wait_for_function(
            f"() => {{ const c = window.iouvController; return c && ({expression}); }}",
            timeout=timeout_ms,
        )
    except PlaywrightTimeout:
        state = await page.evaluate(PAGE_STATE)
        raise AssertionError(f"{expression!r} not within {timeout_ms} ms; {state}") from None


#: What a page's controller was doing, for a failure to say: its role, path, sockets and
#: round trip, its WebRTC connection's states, the video's frozen flag, its counters,
#: the commands awaiting an answer (how long each has waited, ms), its last banner.
PAGE_STATE = """() => {
  const c = window.iouvController;
  if (!c) return "no controller on " + location.pathname;
  const pc = c.pc;
  const banner = document.querySelector("[data-banner]");
  return JSON.stringify({
    role: c.role, path: c.path, ws: c.ws ? c.ws.readyState : null,
    rttMs: c.rtt === null ? null : Math.round(c.rtt), intervalMs: Math.round(c.interval()),
    pc: pc ? [pc.connectionState, pc.iceConnectionState, pc.signalingState] : null,
    videoFrozen: c.videoFrozen, stats: c.stats,
    awaiting: [...c.pending.values()].map(
      (p) => [p.name, Math.round(performance.now() - p.sentAt)]),
    banner: banner && !banner.hidden ? banner.innerText : null,
  });
}"""


async def assert_nothing_refused(page: Page) -> None:
    """No command of the page was refused, but what a saturated machine makes the agent
    refuse by design: one that arrived after its moment (``stale``), that a stop
    overtook (``superseded``), or a movement sent while the round trip was over the
    service's limit (``latency``: 400 ms for the manual services, which a saturated
    machine's WebSocket can take)."""
    refused = await controller(page, "c.stats.refusedBy")
    assert set(refused) <= {"stale", "superseded", "latency"}, refused


async def request_car(
    world: World, page: Page, *, relay: bool = False, timeout_ms: int = 15000
) -> str:
    """Request drive-car from the catalog (through the relay, if ``relay``); returns the
    session's id once the page controls the car (within ``timeout_ms``)."""
    await page.click("[data-service=drive-car] a.button")
    await page.select_option("#id_station", label="Campus station")
    if relay:
        await page.check("#id_relay")
    await page.click("#request-button")
    await page.wait_for_url("**/sessions/*/")
    await wait_for(page, "c.role === 'controller'", timeout_ms)
    return page.url.rstrip("/").rsplit("/", 1)[-1]


async def request_drone(world: World, page: Page) -> Any:
    """Request fly-drone from the catalog and take off; returns the drone's adapter."""
    await page.click("[data-service=fly-drone] a.button")
    await page.select_option("#id_station", label="Campus station")
    await page.click("#request-button")
    await page.wait_for_url("**/sessions/*/")
    await wait_for(page, "c.role === 'controller' && c.stats.framesDecoded > 3")
    drone = world.agents["quad-1"].adapter
    await page.keyboard.press("t")  # take off to the default 5 m
    for _ in range(300):  # 30 s: a loaded machine's simulator climbs slower
        if (drone.telemetry().get("altitude") or 0) > 4.5:
            break
        await asyncio.sleep(0.1)
    assert drone.telemetry()["altitude"] > 4.5
    return drone


async def hold_until(
    page: Page, key: str, reached: Any, *, within: float = 20.0, what: str = ""
) -> None:
    """Hold ``key`` until ``reached`` (a coroutine function) says so, then let go: the
    simulators run as fast as the machine lets them, so a fixed hold proves nothing on
    a busy one."""
    await page.keyboard.down(key)
    try:
        await until(reached, within=within, what=what)
    except AssertionError as exc:
        # What the page saw of its commands (sent, answered, refused, awaited) and of
        # its connection says whether they were lost, refused or carried out without
        # effect.
        state = await page.evaluate(PAGE_STATE)
        raise AssertionError(f"{exc}; the page: {state}") from None
    finally:
        await page.keyboard.up(key)


async def drive_forward(world: World, page: Page, *, at_least_m: float = 0.15) -> float:
    """Hold ArrowUp until the simulated car has moved ``at_least_m`` (however slowly a
    busy machine runs it; fails after 20 s); returns how far it moved (metres)."""
    adapter: Any = world.agents["car-1"].adapter  # the car's adapter, on mock pins
    car = adapter.sensors  # the simulated world
    start = car.pose

    def moved() -> float:
        return math.hypot(car.pose.north_m - start.north_m, car.pose.east_m - start.east_m)

    async def far_enough() -> bool:
        return moved() >= at_least_m

    try:
        await hold_until(page, "ArrowUp", far_enough, what=f"the car to move {at_least_m} m")
    except AssertionError as exc:
        raise AssertionError(f"{exc}; it moved {moved():.3f} m") from None
    return moved()


async def end_session(page: Page, *, first_dismiss: bool = False) -> str:
    """Press End session and confirm (after saying Cancel once, if ``first_dismiss``);
    returns what the confirmation asked."""
    asked: list[str] = []

    async def answer(dialog: Any) -> None:
        asked.append(dialog.message)
        if first_dismiss and len(asked) == 1:
            await dialog.dismiss()
        else:
            await dialog.accept()

    page.on("dialog", answer)
    try:
        if first_dismiss:
            await page.click("[data-end-session]")
            await expect(page.locator("[data-end-session]")).to_be_visible()
        await page.click("[data-end-session]")
        await page.wait_for_url(re.compile(r"^https?://[^/]+/$"))  # the catalog
    finally:
        page.remove_listener("dialog", answer)
    return asked[-1]


# --- the devices people use ---------------------------------------------------------------

#: A phone held in the hand (Playwright context options).
PHONE: dict[str, Any] = {
    "viewport": {"width": 390, "height": 844},
    "device_scale_factor": 2,
    "is_mobile": True,
    "has_touch": True,
}
#: A laptop's screen.
LAPTOP: dict[str, Any] = {"viewport": {"width": 1366, "height": 768}}


async def login(world: World, username: str, device: dict[str, Any]) -> Page:
    """A page on ``device`` (:data:`PHONE`, :data:`LAPTOP`) signed in as ``username``,
    recording the commands it sends (:data:`RECORD_COMMANDS`)."""
    return await world.login(username, init_script=RECORD_COMMANDS, **device)


async def no_wider_than_the_screen(page: Page) -> None:
    widths = await page.evaluate("() => [document.documentElement.scrollWidth, window.innerWidth]")
    assert widths[0] <= widths[1], f"{page.url}: the page is {widths[0]} px wide on {widths[1]}"


# --- scripts the tests put in pages --------------------------------------------------------

#: Records every command the page sends to the vehicle (window.sentCommands), on its
#: socket or its WebRTC data channels.
RECORD_COMMANDS = """
window.sentCommands = [];
for (const proto of [WebSocket.prototype, RTCDataChannel.prototype]) {
  const send = proto.send;
  proto.send = function (data) {
    const msg = JSON.parse(data);
    if (msg.type === "command") window.sentCommands.push(msg);
    return send.call(this, data);
  };
}
"""

#: A gamepad in the Standard Gamepad layout that the test moves (navigator.getGamepads).
FAKE_GAMEPAD = (
    """
window.testPad = {
  id: "test pad", index: 0, connected: true, mapping: "standard",
  axes: [0, 0, 0, 0],
  buttons: Array.from({ length: 17 }, () => ({ pressed: false, value: 0 })),
};
navigator.getGamepads = () => [window.testPad];
"""
    + RECORD_COMMANDS
)


#: Records the page's Content-Security-Policy violations (window.__cspViolations) before
#: any of its own scripts runs.
LISTEN_FOR_VIOLATIONS = """
window.__cspViolations = [];
document.addEventListener("securitypolicyviolation", (e) => {
  window.__cspViolations.push(
    `${e.effectiveDirective} blocked ${e.blockedURI || "inline"} (${e.sourceFile}:${e.lineNumber})`
  );
});
"""
