"""Person rescue at sea, end to end: the platform (iouv.serve), a real Celery worker
(with beat) on Redis, Postgres, and the demo's sea fleet as real agents on their
MAVLink simulators, with the search drone's thermal camera looking at a simulated sea
that holds a person. Nothing is played by the test except the user's request (and, in
one test, a crash of the worker or of a drone's agent).

Flight runs at 10x in the simulators, at 15 m/s so a search takes seconds, not minutes
(the fleet and the areas: kinds/rescue_at_sea/tests/sea.py).
"""

from __future__ import annotations

import asyncio
import http.server
import json
import re
import threading
from pathlib import Path
from typing import Any

import pytest
from playwright.async_api import expect

from agents.geo import distance_m
from agents.geography import is_water
from fleet.models import Vehicle
from kinds.rescue_at_sea.models import Mission, RescueTeam
from kinds.rescue_at_sea.tests.sea import CENTER, client_requests_rescue, sea, search_area
from services.demo import CASTAWAY
from services.models import Assignment, Notice, Session
from tests.browser import chromium_browser, needs_chromium
from tests.portal import sign_in
from tests.servers import db, until

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    pytest.mark.cost(60),  # a rescue flown end to end: about a minute each
]


def _mission(session_id: Any) -> Mission:
    return Mission.objects.get(pk=session_id)


def _kinds(session_id: Any) -> list[str]:
    """The session log's kinds, a notice about the person found named
    ``team_notified`` (other notices, such as the dashboard's warnings, stay
    ``notice_sent``)."""
    session = Session.objects.get(pk=session_id)
    return [
        "team_notified"
        if kind == "notice_sent" and data.get("topic") == "person_in_water"
        else kind
        for kind, data in session.events.order_by("seq").values_list("kind", "data")
    ]


async def mission_reaches(session_id: Any, state: str, *, within: float) -> Mission:
    async def reached() -> Mission | None:
        mission = await db(_mission, session_id)
        return mission if mission.state == state else None

    try:
        return await until(reached, within=within, what=f"mission {state}")
    except AssertionError:
        mission = await db(_mission, session_id)
        kinds = await db(_kinds, session_id)
        raise AssertionError(
            f"mission stuck in {mission.state} ({mission.status_text}); log: {kinds}"
        ) from None


async def _assert_rescued_and_home(session_id: Any, *, delivery: str = "lifeguard-1") -> None:
    """The person was found where they are, the life jacket went to them, both
    vehicles flew home and are free, and the session log keeps the timeline."""
    done = await db(_mission, session_id)
    found = (done.detection["lat"], done.detection["lon"])
    assert distance_m(found, CASTAWAY) < 10, found
    assert done.detection["confidence"] >= 0.6
    kinds = await db(_kinds, session_id)
    order = ["mission_planned", "assigned", "task_accepted", "person_detected"]
    order += ["team_notified", "payload_released"]
    positions = [kinds.index(k) for k in order]
    positions.append(len(kinds) - 1 - kinds[::-1].index("mission_state"))  # completed
    assert positions == sorted(positions), kinds
    roles = await db(
        lambda: sorted(
            Assignment.objects.filter(session_id=session_id).values_list("role", "vehicle__name")
        )
    )
    assert roles == [("delivery", delivery), ("search", "search-1")]
    homes: dict[str, tuple[str, float]] = {}

    async def both_home_and_free() -> bool:
        # Free once each agent has confirmed the end it was sent (releasing until then).
        homes.update(
            await db(
                lambda: {
                    v.name: (v.status, distance_m(v.position, (v.station.lat, v.station.lon)))
                    for v in Vehicle.objects.select_related("station").filter(
                        name__in=["search-1", delivery]
                    )
                }
            )
        )
        return all(s == Vehicle.Status.IDLE and d < 30 for s, d in homes.values())

    try:
        await until(both_home_and_free, within=30, what="both vehicles home and free")
    except AssertionError:
        raise AssertionError(f"not home and free: {homes}") from None
    final = await db(
        lambda: (
            Session.objects.get(pk=session_id)
            .events.filter(kind="mission_state")
            .order_by("-seq")
            .first()
            .data
        )
    )
    assert final["to"] == "completed"
    assert {"requested", "person_detected", "payload_released", "completed"} <= set(
        final["timeline"]
    )
    session = await db(Session.objects.get, pk=session_id)
    assert session.state == Session.State.ENDED


class _SlowHook(http.server.BaseHTTPRequestHandler):
    """The rescue team's webhook: the first call hangs until released."""

    seen: list[str] = []
    first_arrived = threading.Event()
    release = threading.Event()

    def do_POST(self) -> None:
        self.rfile.read(int(self.headers["Content-Length"]))
        type(self).seen.append(self.headers["Idempotency-Key"])
        if len(type(self).seen) == 1:
            type(self).first_arrived.set()
            type(self).release.wait(30)
        self.send_response(200)
        self.end_headers()

    def log_message(self, *args: Any) -> None:
        pass


async def test_worker_killed_mid_step_completes_without_duplicates(tmp_path: Path) -> None:
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _SlowHook)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    _SlowHook.seen = []
    _SlowHook.first_arrived.clear()
    _SlowHook.release.clear()
    try:
        async with sea(tmp_path, ("search-1", "lifeguard-1")) as world:
            hook = f"http://127.0.0.1:{server.server_port}/alerts"
            await db(
                lambda: RescueTeam.objects.filter(station__name="Costa Nova station").update(
                    webhook=hook
                )
            )
            session = await db(client_requests_rescue, search_area())
            # The worker is inside the step that alerts the team: kill it there.
            arrived = await asyncio.to_thread(_SlowHook.first_arrived.wait, 120)
            assert arrived, await db(_kinds, session.pk)
            world.worker.kill()
            _SlowHook.release.set()
            world.worker.start()
            await mission_reaches(session.pk, Mission.State.COMPLETED, within=150)

            # The notice the killed worker was sending goes again once its claim lapses
            # (two webhook timeouts and 5 s) at the next periodic retry (10 s): the
            # mission may well have ended before that.
            def notices() -> list[tuple[str, Any]]:
                return list(
                    Notice.objects.filter(topic="person_in_water").values_list("channel", "sent_at")
                )

            async def all_sent() -> bool:
                return all(sent for _, sent in await db(notices))

            await until(all_sent, within=60, what="every notice sent")
            assert sorted(c for c, _ in await db(notices)) == ["dashboard", "email", "webhook"]
            # The webhook was re-sent after the crash, with the same key: one alert.
            assert len(set(_SlowHook.seen)) == 1 and len(_SlowHook.seen) >= 1
            # E-mail too is at least once: a worker killed between handing the message
            # to the mail server and recording it sends it again after the restart,
            # with the same Message-ID, by which mail systems drop the repeat.
            emails = world.emails()
            ids = {re.search(r"^Message-ID:\s*(\S+)", e, re.M).group(1) for e in emails}
            assert len(emails) >= 1 and ids == {f"<iouv-person_in_water-{session.pk}-email@iouv>"}
            kinds = await db(_kinds, session.pk)
            assert kinds.count("payload_released") == 1
            assert kinds.count("team_notified") == 3
            deliveries = await db(
                Assignment.objects.filter(session_id=session.pk, role="delivery").count
            )
            assert deliveries == 1
            await _assert_rescued_and_home(session.pk)
            lifeguard: Any = world.agents["lifeguard-1"].adapter  # a MAVLink adapter
            released = sum(1 for *_, text in lifeguard.texts if text == "Gripper load released")
            assert released == 1
    finally:
        _SlowHook.release.set()
        server.shutdown()


async def test_search_drone_offline_hands_its_remaining_lines_to_another(
    tmp_path: Path,
) -> None:
    async with sea(tmp_path, ("search-1", "search-2", "lifeguard-1"), spare=True) as world:
        # A wider area, so the first drone is still searching when it is lost.
        session = await db(client_requests_rescue, search_area(260, 160))

        async def first_waypoints() -> Any:
            mission = await db(_mission, session.pk)
            return mission if mission.progress >= 1 and mission.detection is None else None

        mission = await until(first_waypoints, within=60, what="the search under way")
        first = await db(
            lambda: Assignment.objects.get(session_id=session.pk, role="search").vehicle.name
        )
        await world.switch_off(first)

        async def handed_over() -> Any:
            return await db(
                lambda: (
                    Assignment.objects.filter(session_id=session.pk, role="search", active=True)
                    .exclude(vehicle__name=first)
                    .first()
                )
            )

        second = await until(handed_over, within=30, what="a second search drone")
        leg = await db(
            lambda: (
                Session.objects.get(pk=session.pk)
                .events.filter(kind="search_leg")
                .order_by("-seq")
                .first()
                .data
            )
        )
        assert leg["start_index"] >= mission.progress >= 1
        released = await db(
            lambda: Session.objects.get(pk=session.pk).events.get(kind="vehicle_released").data
        )
        assert released["vehicle_name"] == first and "offline" in released["reason"]
        done = await mission_reaches(session.pk, Mission.State.DELIVERING, within=120)
        assert done.detection["vehicle"] == str(second.vehicle_id)


@needs_chromium
async def test_user_draws_the_area_and_watches_the_mission_on_the_map(tmp_path: Path) -> None:
    async with (
        sea(tmp_path, ("search-1", "lifeguard-1"), video=True) as world,
        chromium_browser(webrtc_loopback=True) as browser,
    ):
        page = await (await browser.new_context()).new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(f"{exc} {exc.stack}"))
        await sign_in(page, world.base, "client")
        await page.goto(f"{world.base}/services/rescue-at-sea/")
        await page.wait_for_function("() => window.iouvMap && window.iouvMap.map")
        # Click the area's corners on the map, where those coordinates are drawn.
        await page.evaluate(
            "([lat, lon]) => window.iouvMap.map.setView([lat, lon], 17)", list(CENTER)
        )
        box = await page.locator("#area-map").bounding_box()
        for lat, lon in search_area():
            point = await page.evaluate(
                "([lat, lon]) => window.iouvMap.map.latLngToContainerPoint([lat, lon])",
                [lat, lon],
            )
            await page.mouse.click(box["x"] + point["x"], box["y"] + point["y"])
        await expect(page.locator("[data-area-info]")).to_contain_text("4 points")
        drawn = json.loads(await page.input_value("input[name=area]"))
        assert len(drawn) == 4
        assert all(
            distance_m((p[0], p[1]), (q[0], q[1])) < 3
            for p, q in zip(drawn, search_area(), strict=True)
        )
        await page.fill("#id_altitude_m", "30")
        await page.click("#request-button")
        await page.wait_for_url("**/sessions/*/")

        # The map shows the planned path, the search drone moving, then the person.
        await page.wait_for_load_state()
        assert not errors, errors
        await expect(page.locator("path.mission-path")).to_have_count(1)
        marker = page.locator("path.vehicle-search")
        await expect(marker).to_have_count(1, timeout=20000)
        before = await marker.get_attribute("data-latlon")
        await page.wait_for_function(
            "(before) => { const m = document.querySelector('path.vehicle-search');"
            " return m && m.getAttribute('data-latlon') !== before; }",
            arg=before,
            timeout=20000,
        )
        # The search drone's thermal video plays in the page while it searches (waited
        # for: the first frame may come after the marker's first move).
        await page.wait_for_function(
            "() => { const v = document.querySelector('video'); return v && v.videoWidth > 0; }",
            timeout=30000,
        )
        # What is happening, in words, with the time left, not "0 of 12 waypoints".
        # (Read together: at 10x the phases follow each other quickly.)
        await page.wait_for_function(
            """() => {
              const now = document.querySelector("[data-mission-progress]").textContent;
              const left = document.querySelector("[data-mission-eta]").textContent;
              return /^(On the way to the search area|Searching|Bringing the life jacket) — /
                .test(now) && /^about \\d+ (s|min) \\(\\d\\d:\\d\\d\\)$/.test(left);
            }""",
            timeout=20000,
        )
        await expect(page.locator("path.detection-marker")).to_have_count(1, timeout=90000)
        await expect(page.locator("[data-mission-detection]")).to_contain_text("confidence")
        await expect(page.locator("path.vehicle-delivery")).to_have_count(1, timeout=30000)
        await expect(
            page.locator("[data-mission-timeline] li[data-kind=person_detected]")
        ).to_have_count(1)
        await expect(page.locator("#mission-map")).to_have_attribute(
            "data-mission-state", "completed", timeout=120000
        )
        session_id = page.url.rstrip("/").rsplit("/", 1)[-1]
        await _assert_rescued_and_home(session_id)
        emails = world.emails()
        assert len(emails) == 1 and "Person in the water" in emails[0]


async def test_the_boat_brings_the_life_jacket_when_it_is_the_nearest_capable(
    tmp_path: Path,
) -> None:
    """No payload drone is out: the boat moored off the beach is the vehicle that can
    carry the life jacket, so it sails to the person, releases it there (no climb or
    descent on the surface) and sails home, on the water all the way."""
    async with sea(tmp_path, ("search-1", "boat-1")) as world:
        track: list[tuple[float, float]] = []

        adapter: Any = world.agents["boat-1"].adapter  # a MAVLink adapter

        async def watch_boat() -> None:
            # Where the boat's autopilot says it is, five times a second.
            while True:
                state = adapter.state()
                if state.lat is not None and state.lon is not None:
                    track.append((state.lat, state.lon))
                await asyncio.sleep(0.2)

        watcher = asyncio.create_task(watch_boat())
        try:
            session = await db(client_requests_rescue, search_area())
            await mission_reaches(session.pk, Mission.State.COMPLETED, within=240)
        finally:
            watcher.cancel()
        await _assert_rescued_and_home(session.pk, delivery="boat-1")
        released = await db(
            lambda: Session.objects.get(pk=session.pk).events.get(kind="payload_released").data
        )
        assert distance_m((released["lat"], released["lon"]), CASTAWAY) < 15, released
        # It went out to the person and never onto the land.
        assert max(distance_m(p, CASTAWAY) for p in track) > 500
        assert min(distance_m(p, CASTAWAY) for p in track) < 15
        assert all(is_water(*p) for p in track), [p for p in track if not is_water(*p)]
        assert "Gripper load released" in {text for *_, text in adapter.texts}
