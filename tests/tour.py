"""A tour of the portal's pages, each brought to a real state, at a desktop's and a
phone's viewport: shared by the accessibility test and the screenshot script.

:func:`tour_world` runs what the pages need, as the integration tests do: the seeded
demo, the platform (iouv.serve), a Celery worker (with beat) for the rescue missions,
the simulated agents of the car, the drone, the search drone and the lifeguard drone,
and Chromium. :func:`open_page` then opens one page of :data:`PAGES` as the user who
would see it, in a browser context with the viewport's size, and returns once the page
shows what it is for (video playing, telemetry in, the mission map drawn): no sleeps.

Sessions are started once per tour and shared by both viewports: the phone opens the
desktop's session page again, as a person who picks up their phone would.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

from playwright.async_api import Browser, Page, expect

from agents.config import AgentConfig
from kinds.rescue_at_sea.tests.sea import client_requests_rescue, search_area
from tests.demo import demo_agent_config, mission_agent_config
from tests.portal import World, demo_world, request_car, request_drone, sign_in, wait_for
from tests.servers import db

#: Browser context options per viewport: a laptop, and a phone (touch, mobile layout).
VIEWPORTS: dict[str, dict[str, Any]] = {
    "desktop": {"viewport": {"width": 1366, "height": 768}},
    "phone": {"viewport": {"width": 390, "height": 844}, "is_mobile": True, "has_touch": True},
}

#: The demo vehicles the tour runs: the car and the drone (controllers), the search and
#: the lifeguard drones (the rescue mission).
CONTROLLED = ("car-1", "quad-1")
SEA = ("search-1", "lifeguard-1")

#: The platform's and the worker's settings: the mission's loop ticks every second, so
#: the mission page shows a mission under way soon after the request.
ENV = {"IOUV_MISSION_TICK_S": "1"}


@dataclasses.dataclass
class Tour:
    """The running world: what :func:`open_page` needs."""

    world: World  # the platform's address, the browser and the agents, as test_portal's
    #: Whether the search drone streams its thermal camera (the mission page shows it).
    video: bool = True
    #: The session page of each session the tour started, by page name.
    sessions: dict[str, str] = dataclasses.field(default_factory=dict)
    #: Each user's signed-in browser state (cookies), so a user signs in once a tour.
    logins: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def base(self) -> str:
        return self.world.base

    @property
    def browser(self) -> Browser:
        return self.world.browser


@contextlib.asynccontextmanager
async def tour_world(directory: Path, *, video: bool = True) -> AsyncIterator[Tour]:
    """Seed the demo (agent configs in ``directory``), run the platform, a worker and
    the demo agents, and a browser; yields the :class:`Tour`. ``video``: the search
    drone streams its thermal camera (the car and the drone always stream)."""

    def configure(path: Path, base: str) -> AgentConfig:
        if path.stem in SEA:
            return mission_agent_config(path, base, video=video)
        return demo_agent_config(path, base)

    async with demo_world(
        directory, CONTROLLED + SEA, configure, env=ENV, worker=True, within=60
    ) as world:
        yield Tour(world, video=video)


async def signed_in(tour: Tour, viewport: str, username: str) -> Page:
    """A new browser context at ``viewport``, signed in as ``username``; returns its
    page, on the catalog."""
    if username in tour.logins:
        context = await tour.browser.new_context(
            **VIEWPORTS[viewport], storage_state=tour.logins[username]
        )
        page = await context.new_page()
        await page.goto(f"{tour.base}/")
        return page
    context = await tour.browser.new_context(**VIEWPORTS[viewport])
    page = await context.new_page()
    await sign_in(page, tour.base, username)
    tour.logins[username] = await context.storage_state()
    return page


async def _catalog(tour: Tour, page: Page) -> None:
    await expect(page.locator("[data-service]").first).to_be_visible()


async def _session(tour: Tour, page: Page, name: str, start: Callable[[], Awaitable[Any]]) -> None:
    """Start the tour's session ``name`` from ``page`` (on the catalog), or open the one
    started before."""
    if name in tour.sessions:
        await page.goto(tour.sessions[name])
        # While the session's first page is still open, the vehicle's agent lets this
        # one watch; the user takes control here, as they would on their phone.
        await wait_for(page, "c.role !== 'pending'")
        if await page.evaluate("() => window.iouvController.role") != "controller":
            await page.click("[data-take-control]")
    else:
        await start()
        tour.sessions[name] = page.url


async def _car(tour: Tour, page: Page) -> None:
    await _session(tour, page, "car", lambda: request_car(tour.world, page))
    # Video playing and telemetry in.
    await wait_for(page, "c.role === 'controller' && c.stats.framesDecoded > 5")
    await expect(page.locator("[data-topic=battery_level] .value")).not_to_have_text("\u2013")


async def _drone(tour: Tour, page: Page) -> None:
    await _session(tour, page, "drone", lambda: request_drone(tour.world, page))
    await wait_for(page, "c.role === 'controller' && c.stats.framesDecoded > 3")
    await expect(page.locator("[data-topic=altitude] .value")).not_to_have_text("\u2013")


async def _monitor(tour: Tour, page: Page) -> None:
    await page.goto(f"{tour.base}/monitor/")
    # The live feed's first snapshot in: the fleet and the sessions the tour started.
    # (Two sockets, on a loaded machine: a longer wait than expect's default 5 s.)
    await expect(page.locator("tr[data-vehicle=car-1]")).to_be_visible(timeout=20000)
    if tour.sessions:
        rows = page.locator("[data-sessions] tbody tr")
        await expect(rows.first).to_be_visible(timeout=20000)


async def _rescue_request(tour: Tour, page: Page) -> None:
    await page.goto(f"{tour.base}/services/rescue-at-sea/")
    await page.wait_for_function("() => window.iouvMap && window.iouvMap.map")


async def _rescue_mission(tour: Tour, page: Page) -> None:
    if "rescue" not in tour.sessions:
        # Requested as the request form does (the rescue test draws it with the mouse).
        session = await db(client_requests_rescue, search_area())
        tour.sessions["rescue"] = f"{tour.base}/sessions/{session.pk}/"
    await page.goto(tour.sessions["rescue"])
    # The mission map drawn: the planned path and the search drone on it.
    await expect(page.locator("path.mission-path")).to_have_count(1, timeout=20000)
    await expect(page.locator("path.vehicle-search")).to_have_count(1, timeout=30000)
    await expect(page.locator("[data-mission-progress]")).not_to_have_text("\u2013")
    if tour.video:
        await page.wait_for_function(
            "() => { const v = document.querySelector('video'); return v && v.videoWidth > 0; }",
            timeout=30000,
        )


#: The tour's pages: name -> (the user who sees it, what brings it to its state).
PAGES: dict[str, tuple[str, Callable[[Tour, Page], Awaitable[None]]]] = {
    "catalog": ("client", _catalog),
    "car-controller": ("client", _car),
    "drone-controller": ("client", _drone),
    "monitor": ("monitor", _monitor),
    "rescue-request": ("client", _rescue_request),
    "rescue-mission": ("client", _rescue_mission),
}


async def open_page(tour: Tour, name: str, viewport: str) -> Page:
    """Page ``name`` of :data:`PAGES` at ``viewport``, in its own context, signed in as
    its user and in its real state. Close it with ``await page.context.close()``."""
    username, show = PAGES[name]
    page = await signed_in(tour, viewport, username)
    try:
        await show(tour, page)
    except BaseException:
        await page.context.close()
        raise
    return page
