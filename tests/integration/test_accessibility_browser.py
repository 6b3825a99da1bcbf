"""The portal's pages pass axe-core's accessibility checks, on a laptop and on a phone.

The catalog, a car's controller session (video playing, telemetry in), the fleet
monitor and a rescue mission under way (its map drawn) are opened in Chromium at
1366x768 and at a phone's 390x844 (touch, mobile), each in its real state (see
tests/tour.py), and the vendored axe-core (tests/accessibility.py) must find no
serious or critical violation of WCAG 2.x A/AA or axe's best practices.

The world (demo seed, platform, worker, agents, browser) starts once for the module,
not per test: it is the slow part, and these tests only read pages.
"""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest
import pytest_asyncio

from tests.accessibility import axe_violations, violations_report
from tests.portal import PORTAL_MARKS
from tests.tour import VIEWPORTS, Tour, open_page, tour_world

pytestmark = PORTAL_MARKS


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def tour(
    module_database: None, tmp_path_factory: pytest.TempPathFactory
) -> AsyncIterator[Tour]:
    # No thermal video from the search drone: encoding it is the costliest part of the
    # world on a small machine, and the mission page around the video is the same.
    async with tour_world(tmp_path_factory.mktemp("accessibility"), video=False) as world:
        yield world


async def check(tour: Tour, name: str) -> None:
    """Page ``name`` of the tour at each viewport: no serious or critical violation."""
    reports = []
    for viewport in VIEWPORTS:
        page = await open_page(tour, name, viewport)
        try:
            found = await axe_violations(page)
        finally:
            await page.context.close()
        if found:
            reports.append(violations_report(found, where=f"{name} at {viewport}"))
    assert not reports, "\n\n".join(reports)


async def test_the_catalog_is_accessible(tour: Tour) -> None:
    await check(tour, "catalog")


async def test_a_controller_session_is_accessible(tour: Tour) -> None:
    await check(tour, "car-controller")


async def test_a_rescue_mission_under_way_is_accessible(tour: Tour) -> None:
    await check(tour, "rescue-mission")


async def test_the_monitor_is_accessible(tour: Tour) -> None:
    # After the sessions above: the monitor lists them.
    await check(tour, "monitor")
