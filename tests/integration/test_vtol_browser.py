"""The VTOL's page in Chromium against the real platform and vtol-1's agent on its
simulated Spektrum receiver line: its receiver channels read as what they are (servo
positions, 1024 the centre), not as implausible pulse widths ("throttle 342 µs")."""

from __future__ import annotations

import re
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from playwright.async_api import expect

from tests.browser import needs_chromium
from tests.portal import World, demo_world, wait_for

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    needs_chromium,
]


@pytest.fixture
async def world(tmp_path: Path) -> AsyncIterator[World]:
    """The seeded demo on the platform, vtol-1's agent online with a position, and
    Chromium."""
    async with demo_world(tmp_path, ("vtol-1",)) as running:
        yield running


async def test_the_receiver_channels_read_as_positions(world: World) -> None:
    page = await world.login("client")
    await page.click("[data-service=fly-vtol] a.button")
    await page.select_option("#id_station", label="Campus station")
    await page.click("#request-button")
    await page.wait_for_url("**/sessions/*/")
    await wait_for(page, "c.role === 'controller' && c.stats.telemetry > 2")
    row = page.locator("[data-topic=channels]")
    await expect(row.locator(".topic")).to_have_text("Receiver channels (position, 1024 = centre)")
    value = row.locator(".value")
    await expect(value).to_have_text(re.compile(r"^throttle \d+ · aileron 1024 · "))
    assert "µs" not in await value.inner_text()
