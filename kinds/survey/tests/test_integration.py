"""The aerial survey end to end, in Chromium: the platform (iouv.serve), a real Celery
worker on Redis, Postgres, and quad-1 as a real agent on its MAVLink simulator, its
photo camera the simulated nadir one of its demo config. The user draws the area on the
map and picks the resolution; the autopilot flies the lines; the photos reach the
platform and cover the area on the page as they come; the mosaic is laid over the map
and downloads as a KMZ. Nothing is played by the test but the user.

Flight runs in real time in the simulator: photos are taken on the wall clock, a few
metres apart, a place about every second at ArduCopter's speed, as on a real drone. At
2x a saturated machine's photographer fell behind the autopilot (6 photos of 22 taken,
the rest reported missed). A survey takes a minute or two.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import io
import itertools
import re
import statistics
import zipfile
from pathlib import Path
from typing import Any

import pytest
from playwright.async_api import TimeoutError as PlaywrightTimeout
from playwright.async_api import expect

from agents.config import AgentConfig
from agents.geo import distance_m, offset
from agents.missions.survey.spec import survey_photo_points
from kinds.survey.geometry import coverage
from kinds.survey.models import Survey
from kinds.survey.planning import plan_lines
from kinds.survey.workflow import footprints, photos
from services.models import Session
from tests.browser import chromium_browser, needs_chromium
from tests.demo import Demo, missions_running
from tests.portal import sign_in
from tests.servers import db, until

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    pytest.mark.cost(60),  # a survey flown end to end
]

CAMPUS = (40.6306, -8.6588)
#: A 70 x 55 m field 80 m north-east of the campus station: at 4 cm a pixel quad-1 flies
#: two lines of 11 photos, 27 m up.
CORNERS = [offset(CAMPUS, n, e) for n, e in ((80, 60), (80, 130), (135, 130), (135, 60))]
#: quad-1's simulator: ArduCopter's own speeds, in real time.
SURVEY_SIM: dict[str, Any] = {"speedup": 1, "params": {"RTL_ALT": 3000}}


def survey_agent_config(path: Path, base: str) -> AgentConfig:
    """quad-1's demo config (with its nadir photo camera) against the platform at
    ``base``, on its simulator in real time, without video."""
    config = AgentConfig.load(path)
    assert config.photo is not None and config.photo["source"] == "nadir"
    return dataclasses.replace(
        config,
        platform_url=base.replace("http://", "ws://"),
        adapter_options={**config.adapter_options, "simulator": SURVEY_SIM},
        video=None,
        reconnect_min_s=0.2,
    )


def fleet(
    directory: Path, names: tuple[str, ...] = ("quad-1",)
) -> contextlib.AbstractAsyncContextManager[Demo]:
    """The survey drones ``names`` running for real on the seeded demo, with the
    platform and a worker; quad-2, if named, a second drone like quad-1 at the campus.
    The mosaic waits 20 s for photos a drone switched off will never send."""
    return missions_running(
        directory,
        names,
        survey_agent_config,
        env={"IOUV_SURVEY_PHOTOS_WAIT_S": "20"},
        spares={"quad-2": "quad-1"} if "quad-2" in names else None,
        what="the survey drones online",
    )


def _where(session_id: Any) -> str:
    """A stuck survey in words: its state and its session's log."""
    survey = _survey(session_id)
    log = list(survey.session.events.order_by("seq").values_list("kind", flat=True))
    return f"survey {survey.state}, session log {log}"


def _survey(session_id: Any) -> Survey:
    return Survey.objects.select_related("session").get(pk=session_id)


def _measured(session_id: Any) -> dict[str, Any]:
    """What the photos that reached the platform cover, and how much neighbours on a
    line and neighbouring lines overlap, from where each says it was taken."""
    survey = _survey(session_id)
    stored = photos(survey)
    plan = survey.plan or {}
    across, along = plan["footprint_m"]
    polygon = [(p[0], p[1]) for p in survey.polygon]
    line_of = [line for line, _ in survey_photo_points(plan_lines(plan), plan["spacing_m"])]
    taken = {int(a.name[6:10]): (a.meta["lat"], a.meta["lon"]) for a in stored}
    # Along a line: each photo and the next one on the same line.
    front = [
        1 - distance_m(taken[i], taken[j]) / along
        for i, j in itertools.pairwise(sorted(taken))
        if j == i + 1 and line_of[i] == line_of[j]
    ]
    return {
        "count": len(stored),
        "expected": survey.photo_count,
        # Places the drone's photographer reported missed (it came too late for them).
        "missed": survey.session.events.filter(kind="photo_missed").count(),
        "coverage": coverage(polygon, footprints(survey, stored)),
        "front": min(front),
        "front_median": statistics.median(front),
        "front_planned": 1 - plan["spacing_m"] / along,
        "side": 1 - plan["line_spacing_m"] / across,
        "session": survey.session.state,
    }


@needs_chromium
async def test_the_user_draws_an_area_and_gets_a_mosaic_of_it(tmp_path: Path) -> None:
    async with fleet(tmp_path) as world, chromium_browser() as browser:
        page = await (await browser.new_context()).new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(f"{exc} {exc.stack}"))
        await sign_in(page, world.base, "client")
        await page.click("a[href='/services/aerial-survey/']")
        await page.wait_for_url("**/services/aerial-survey/")
        await page.wait_for_function("() => window.iouvMap && window.iouvMap.map")
        middle = offset(CAMPUS, 107, 95)
        await page.evaluate(
            "([lat, lon]) => window.iouvMap.map.setView([lat, lon], 18)", list(middle)
        )
        box = await page.locator("#survey-map").bounding_box()
        assert box is not None
        for lat, lon in CORNERS:
            point = await page.evaluate(
                "([lat, lon]) => window.iouvMap.map.latLngToContainerPoint([lat, lon])",
                [lat, lon],
            )
            await page.mouse.click(box["x"] + point["x"], box["y"] + point["y"])
        await expect(page.locator("[data-pick-info]")).to_contain_text("4 corners")
        await expect(page.locator("#survey-map path.survey-area")).to_have_count(1)
        drawn = await page.evaluate("() => window.iouvMap.points()")
        for (lat, lon), corner in zip(drawn, CORNERS, strict=True):
            assert distance_m((lat, lon), corner) < 1
        await page.fill("#id_gsd_cm", "4")
        await page.click("#request-button")
        await page.wait_for_url("**/sessions/*/")
        session_id = page.url.rstrip("/").rsplit("/", 1)[-1]

        # Live: the planned lines, the drone, and the photos' footprints growing while
        # it flies.
        survey_map = page.locator("#survey-map")
        await expect(page.locator("#survey-map path.survey-line")).to_have_count(2, timeout=30000)
        await expect(page.locator("path.vehicle-marker")).to_have_count(1, timeout=30000)
        try:
            await page.wait_for_function(
                "() => { const n = document.querySelector('#survey-map');"
                " return n.dataset.surveyState === 'flying' && Number(n.dataset.photos) >= 3; }",
                timeout=180000,
            )
        except PlaywrightTimeout:
            # Where it stopped, from the platform's side and the drone's.
            drone = world.agents["quad-1"].adapter.state()
            raise AssertionError(f"{await db(_where, session_id)}; quad-1 {drone}") from None
        # The autopilot flies the lines itself (the agent uploaded them as a mission).
        assert world.agents["quad-1"].adapter.state().mode == "AUTO"
        # The mosaic, laid over the map, and its KMZ.
        await expect(survey_map).to_have_attribute("data-survey-state", "done", timeout=240000)
        mosaic = page.locator("#survey-map img.survey-mosaic")
        await expect(mosaic).to_have_count(1)
        await page.wait_for_function(
            "() => { const i = document.querySelector('img.survey-mosaic');"
            " return i && i.complete && i.naturalWidth > 0; }",
            timeout=30000,
        )
        footprints_shown = await page.locator("#survey-map path.photo-footprint").count()
        await expect(page.locator("[data-coverage]")).to_contain_text("%")
        async with page.expect_download() as download_info:
            await page.click("a[data-kmz]")
        download = await download_info.value
        body = await asyncio.to_thread(Path(await download.path()).read_bytes)
        kmz = zipfile.ZipFile(io.BytesIO(body))
        assert kmz.namelist() == ["doc.kml", "files/mosaic.png"]
        assert not errors, errors

        measured = await until(
            lambda: db(_measured, session_id), within=5, what="the survey measured"
        )
        # Every place is photographed, or reported missed: a photographer that falls
        # behind on a busy machine (1 to 5 places in 22 seen with the suite's workers on
        # two slow cores) says so rather than leaving a hole nobody hears of. The mosaic
        # shows what was taken; the coverage the issue asks for is checked below.
        assert measured["count"] == footprints_shown
        assert measured["count"] + measured["missed"] == measured["expected"], measured
        # The photos' footprints cover the area, with the asked overlaps (75 % front,
        # 65 % side): the plan spaces them so, and most photos are taken where planned.
        # A photo taken late is taken further along its line (agents.missions.survey.
        # route: LATE), tagged where it was, so its overlap with the one before shrinks:
        # the photographer polls the position, and a busy machine has left one 1.5
        # spacings late (front 37 %) in an idle full run, 61 % and more in others. Two
        # neighbours on a line still overlap; the coverage says the area is whole.
        assert measured["coverage"] >= 0.95, measured["coverage"]
        assert measured["front_planned"] >= 0.75 - 1e-6, measured["front_planned"]
        assert measured["front_median"] >= 0.7, measured["front_median"]
        assert measured["front"] > 0, measured["front"]
        assert measured["side"] >= 0.65 - 1e-6
        assert measured["session"] == Session.State.ENDED


def _request() -> Any:
    from django.contrib.auth import get_user_model

    from services.kinds import Request
    from services.models import Service
    from services.sessions.request import service_request

    params = {"polygon": [list(c) for c in CORNERS], "gsd_cm": 4}
    return service_request(
        user=get_user_model().objects.get(username="client"),
        service=Service.objects.get(slug="aerial-survey"),
        request=Request(params=params),
    ).session


def _surveyors(session_id: Any) -> list[str]:
    from services.models import Assignment

    return list(
        Assignment.objects.filter(session_id=session_id)
        .order_by("created_at")
        .values_list("vehicle__name", flat=True)
    )


async def test_a_drone_switched_off_mid_survey_is_replaced_from_the_last_photo(
    tmp_path: Path,
) -> None:
    async with fleet(tmp_path, ("quad-1", "quad-2")) as world:
        session = await db(_request)

        async def photographed(count: int) -> Survey | None:
            survey = await db(_survey, session.pk)
            return survey if survey.next_photo >= count else None

        await until(lambda: photographed(6), within=180, what="six photos taken")
        first = (await db(_surveyors, session.pk))[0]
        await world.switch_off(first)

        async def done() -> Survey | None:
            survey = await db(_survey, session.pk)
            return survey if survey.state == Survey.State.DONE else None

        survey = await until(done, within=300, what="the survey done by another drone")
        second = "quad-2" if first == "quad-1" else "quad-1"
        assert await db(_surveyors, session.pk) == [first, second]
        log = await db(lambda: list(survey.session.events.values_list("kind", "data")))
        released = [data for kind, data in log if kind == "vehicle_released"]
        assert released and released[0]["vehicle_name"] == first
        # The second drone began at the first photo the first had not taken, and took
        # every one from there.
        resumed = [
            re.search(r"from photo (\d+)", data.get("text", ""))
            for kind, data in log
            if kind == "survey_state"
        ]
        start = int(next(m for m in resumed if m is not None).group(1)) - 1
        assert start >= 6
        taken_by = await db(
            lambda: {int(a.name[6:10]): a.vehicle.name for a in photos(_survey(session.pk))}
        )
        assert {taken_by[i] for i in taken_by if i >= start} == {second}
        # Every place from there is photographed, or reported missed by the second
        # drone's photographer (it falls behind on a saturated machine, as in the
        # end-to-end test above).
        missed = {data.get("index") for kind, data in log if kind == "photo_missed"}
        assert set(range(start, survey.photo_count)) <= set(taken_by) | missed, missed
        assert {taken_by[i] for i in taken_by if i < start} == {first}
        measured = await db(_measured, session.pk)
        assert measured["coverage"] >= 0.95, measured
