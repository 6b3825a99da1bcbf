"""A rescue's page from the search to the vehicles home, in Chromium against the real
platform, a worker, and the demo's sea fleet on its simulators at 10x with the search
drone's thermal video (kinds/rescue_at_sea/tests/sea.py):

* the banner and "Now" agree while the drone searches;
* "connected" is said once the picture is there, not over a black box;
* the session stays open while the vehicles fly home: the video goes on, and the list
  says they fly home (not "idle" kilometres out);
* at the end one banner says it, and each alert of the timeline says what it was about.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from playwright.async_api import expect

from kinds.rescue_at_sea.tests.sea import client_requests_rescue, sea, search_area
from tests.browser import chromium_browser, needs_chromium
from tests.portal import sign_in
from tests.servers import db

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    needs_chromium,
    pytest.mark.cost(45),  # a rescue watched to its end
]

FRAMES = "() => (window.iouvController ? window.iouvController.stats.framesDecoded : 0)"


async def test_the_rescue_page_from_the_search_to_the_vehicles_home(tmp_path: Path) -> None:
    async with (
        sea(tmp_path, ("search-1", "lifeguard-1"), video=True) as world,
        chromium_browser(webrtc_loopback=True) as browser,
    ):
        session: Any = await db(client_requests_rescue, search_area())
        page = await (await browser.new_context()).new_page()
        await sign_in(page, world.base, "client")
        await page.goto(f"{world.base}/sessions/{session.pk}/")

        # "connected" only once the picture moves.
        await page.wait_for_function(
            "() => document.querySelector('[data-conn-state]').textContent === 'connected'",
            timeout=60000,
        )
        assert await page.evaluate(FRAMES) > 0
        # While it searches, the banner says what "Now" says.
        await page.wait_for_function(
            """() => {
              const now = document.querySelector("[data-mission-progress]").textContent;
              const banner = document.querySelector("[data-mission-status]").textContent;
              return now.startsWith("Searching") && banner === "search-1 is searching";
            }""",
            timeout=90000,
        )

        # The life jacket out, the vehicles fly home with the session still open: the
        # video goes on and the list says where they are.
        live = page.locator("#mission-map")
        await expect(live).to_have_attribute("data-mission-state", "returning", timeout=120000)
        await expect(page.locator("[data-session-state]")).to_have_text("active")
        frames = await page.evaluate(FRAMES)
        await page.wait_for_function(
            f"""() => {FRAMES}() > {frames} + 10
              && document.querySelector("#mission-map").dataset.missionState === "returning"
            """,
            timeout=30000,
        )
        vehicles = page.locator("[data-mission-vehicles] li")
        await expect(vehicles.filter(has_text="flying home, ")).not_to_have_count(0)
        for line in await vehicles.all_inner_texts():
            assert "· idle" not in line, line

        # Home: the mission completes and the session ends, said once.
        await expect(live).to_have_attribute("data-mission-state", "completed", timeout=120000)
        await expect(page.locator("[data-mission-status]")).to_contain_text("mission completed")
        await expect(page.locator("[data-banner]")).to_be_hidden()
        alerts = await page.locator(
            "[data-mission-timeline] li[data-kind=notice_sent]"
        ).all_inner_texts()
        texts = [line.split(" ", 1)[1] for line in alerts]
        assert alerts and len(set(texts)) == len(texts), texts
