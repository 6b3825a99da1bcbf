"""Parcel delivery, end to end: the platform (iouv.serve), a real Celery worker (with
beat) on Redis, Postgres, and the demo's payload drones as real agents on their
MAVLink simulators. Nothing is played by the test but the user (in a browser, or
through the request path the API shares) and, in one test, a carrier switched off
with the parcel on board.

Flight runs at 10x in the simulators, at 15 m/s, and the parcel is loaded in 2 s, so
a delivery takes seconds.
"""

from __future__ import annotations

import contextlib
import re
from pathlib import Path
from typing import Any

import pytest
from playwright.async_api import expect

from agents.geo import distance_m
from agents.geography import is_water
from fleet.models import Vehicle
from kinds.parcel_delivery.models import Delivery
from services.kinds import Opened, Request
from services.models import Assignment, Service, Session
from services.sessions.request import service_request
from tests.browser import chromium_browser, needs_chromium
from tests.demo import Demo, mission_agent_config, missions_running
from tests.portal import sign_in
from tests.servers import db, until

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    pytest.mark.cost(30),  # a delivery flown end to end
]
#: On land north-west of the coastal station (about 700 m and 1 km from it), 480 m
#: apart: a drone's parcel, not a boat's.
PICKUP = (40.6485, -8.7520)
DROPOFF = (40.6510, -8.7480)
RECIPIENT = "rita@example.org"


def fleet(directory: Path, names: tuple[str, ...]) -> contextlib.AbstractAsyncContextManager[Demo]:
    """The carriers ``names`` running for real on the seeded demo, with the platform and
    a worker (tests.demo.missions_running), a parcel loaded in 2 s; lifeguard-2, if
    named, a second payload drone at the coastal station beside lifeguard-1."""
    return missions_running(
        directory,
        names,
        mission_agent_config,
        env={"IOUV_PARCEL_LOAD_S": "2"},
        spares={"lifeguard-2": "lifeguard-1"} if "lifeguard-2" in names else None,
        what="the carriers online",
    )


def _delivery(session_id: Any) -> Delivery:
    return Delivery.objects.get(pk=session_id)


def _log(session_id: Any) -> list[tuple[str, dict[str, Any]]]:
    session = Session.objects.get(pk=session_id)
    return list(session.events.order_by("seq").values_list("kind", "data"))


async def delivery_reaches(session_id: Any, state: str, *, within: float) -> Delivery:
    async def reached() -> Delivery | None:
        delivery = await db(_delivery, session_id)
        return delivery if delivery.state == state else None

    try:
        return await until(reached, within=within, what=f"delivery {state}")
    except AssertionError:
        delivery = await db(_delivery, session_id)
        kinds = [kind for kind, _ in await db(_log, session_id)]
        raise AssertionError(
            f"delivery stuck in {delivery.state} ({delivery.status_text}); log: {kinds}"
        ) from None


async def carriers_home(names: tuple[str, ...]) -> dict[str, tuple[str, float]]:
    """Each carrier's status and distance from its station, once all are idle there."""

    async def home() -> dict[str, tuple[str, float]] | None:
        where = await db(
            lambda: {
                v.name: (v.status, distance_m(v.position, (v.station.lat, v.station.lon)))
                for v in Vehicle.objects.select_related("station").filter(name__in=names)
            }
        )
        done = all(s == Vehicle.Status.IDLE and d < 30 for s, d in where.values())
        return where if done else None

    return await until(home, within=90, what=f"{', '.join(names)} home and idle")


def test_the_test_points_are_a_drones_parcel() -> None:
    # Both on land: the boat may not take it, a drone must.
    assert not is_water(*PICKUP) and not is_water(*DROPOFF)


@needs_chromium
async def test_user_sends_a_parcel_from_the_map_and_both_follow_it(tmp_path: Path) -> None:
    async with (
        fleet(tmp_path, ("lifeguard-1",)) as world,
        chromium_browser() as browser,
    ):
        page = await (await browser.new_context()).new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(f"{exc} {exc.stack}"))
        await sign_in(page, world.base, "client")
        # The catalog offers it; its button opens the request page.
        await page.click("a[href='/services/parcel-delivery/']")
        await page.wait_for_url("**/services/parcel-delivery/")
        await page.wait_for_function("() => window.iouvMap && window.iouvMap.map")
        middle = [(PICKUP[0] + DROPOFF[0]) / 2, (PICKUP[1] + DROPOFF[1]) / 2]
        await page.evaluate("([lat, lon]) => window.iouvMap.map.setView([lat, lon], 16)", middle)
        box = await page.locator("#parcel-map").bounding_box()
        assert box is not None
        for lat, lon in (PICKUP, DROPOFF):
            point = await page.evaluate(
                "([lat, lon]) => window.iouvMap.map.latLngToContainerPoint([lat, lon])",
                [lat, lon],
            )
            await page.mouse.click(box["x"] + point["x"], box["y"] + point["y"])
        await expect(page.locator("[data-pick-info]")).to_contain_text("km from pickup")
        picked = await page.evaluate("() => window.iouvMap.points()")
        assert distance_m(tuple(picked[0]), PICKUP) < 5
        assert distance_m(tuple(picked[1]), DROPOFF) < 5
        await page.fill("#id_weight_kg", "1.2")
        await page.fill("#id_recipient_name", "Rita")
        await page.fill("#id_recipient_email", RECIPIENT)
        await page.click("#request-button")
        await page.wait_for_url("**/sessions/*/")
        session_id = page.url.rstrip("/").rsplit("/", 1)[-1]

        # Live: the carrier on the map, moving, with an arrival time.
        marker = page.locator("path.carrier-marker")
        await expect(marker).to_have_count(1, timeout=30000)
        await expect(page.locator("[data-eta]")).not_to_have_text("–", timeout=30000)  # noqa: RUF001
        eta = await page.locator("[data-eta]").inner_text()
        assert re.search(r"\d", eta), eta
        before = await page.evaluate("() => window.iouvMap.state().vehicles?.[0]?.lat ?? null")
        await page.wait_for_function(
            "(before) => { const v = window.iouvMap.state().vehicles?.[0];"
            " return v && v.lat !== null && v.lat !== before; }",
            arg=before,
            timeout=30000,
        )
        await expect(page.locator("#parcel-map")).to_have_attribute(
            "data-delivery-state", "delivered", timeout=120000
        )
        await expect(page.locator("span[data-delivery-state]")).to_have_text("Delivered")
        assert not errors, errors

        done = await db(_delivery, session_id)
        assert done.released_at is not None
        log = await db(_log, session_id)
        kinds = [kind for kind, _ in log]
        for earlier, later in (
            ("assigned", "task_accepted"),
            ("task_accepted", "parcel_loaded"),
            ("parcel_loaded", "payload_released"),
        ):
            assert kinds.index(earlier) < kinds.index(later), kinds
        released = next(data for kind, data in log if kind == "payload_released")
        assert distance_m((released["lat"], released["lon"]), DROPOFF) < 15, released
        session = await db(Session.objects.get, pk=session_id)
        assert session.state == Session.State.ENDED

        # The recipient was told twice (on its way, delivered), with a link that
        # needs no account.
        async def told() -> list[str] | None:
            mails = [m for m in world.emails() if RECIPIENT in m]
            return mails if len(mails) >= 2 else None

        mails = await until(told, within=30, what="the recipient's two e-mails")
        assert any("on its way" in m for m in mails) and any("delivered" in m for m in mails)
        link = re.search(r"https?://\S+/track/\S+/", mails[0])
        assert link is not None, mails[0]
        path = link.group(0).split("/track/", 1)[1]
        stranger = await (await browser.new_context()).new_page()
        await stranger.goto(f"{world.base}/track/{path}")
        await expect(stranger.locator("#parcel-map")).to_have_attribute(
            "data-delivery-state", "delivered"
        )
        await expect(stranger.locator("dd[data-delivery-state]")).to_have_text("Delivered")
        # The carrier flew home by itself and is free again.
        await carriers_home(("lifeguard-1",))


async def test_a_carrier_lost_with_the_parcel_hands_it_over_where_it_is(tmp_path: Path) -> None:
    async with fleet(tmp_path, ("lifeguard-1", "lifeguard-2")) as world:

        def request() -> Opened:
            from django.contrib.auth import get_user_model

            client = get_user_model().objects.get(username="client")
            params = {
                "pickup": {"lat": PICKUP[0], "lon": PICKUP[1]},
                "dropoff": {"lat": DROPOFF[0], "lon": DROPOFF[1]},
                "weight_kg": 1.0,
                "recipient": {"name": "Rita", "email": RECIPIENT},
            }
            service = Service.objects.get(slug="parcel-delivery")
            return service_request(user=client, service=service, request=Request(params=params))

        session = (await db(request)).session
        loaded = await delivery_reaches(session.pk, Delivery.State.TO_DROPOFF, within=90)
        first = await db(lambda: Assignment.objects.get(session=session, active=True).vehicle.name)

        # Switched off a little way towards the drop-off, the parcel on board.
        async def under_way() -> bool:
            v = await db(Vehicle.objects.get, name=first)
            return v.position is not None and distance_m(v.position, PICKUP) > 40

        await until(under_way, within=60, what=f"{first} under way with the parcel")
        await world.switch_off(first)
        lost_at = (await db(Vehicle.objects.get, name=first)).position
        assert lost_at is not None and loaded.loaded_at is not None

        await delivery_reaches(session.pk, Delivery.State.DELIVERED, within=180)
        # The other carrier collected it where the first was lost, and delivered it.
        log = await db(_log, session.pk)
        loads = [data for kind, data in log if kind == "parcel_loaded"]
        assert len(loads) == 2, loads
        assert distance_m((loads[1]["lat"], loads[1]["lon"]), lost_at) < 20, (loads, lost_at)
        released = [data for kind, data in log if kind == "vehicle_released"]
        assert released and released[0]["vehicle_name"] == first
        assert "offline" in released[0]["reason"] or "lost" in released[0]["reason"]
        carriers = await db(
            lambda: list(
                Assignment.objects.filter(session=session)
                .order_by("created_at")
                .values_list("vehicle__name", flat=True)
            )
        )
        second = "lifeguard-2" if first == "lifeguard-1" else "lifeguard-1"
        assert carriers == [first, second]
        assert loads[1]["vehicle"] != loads[0]["vehicle"]
        drop = [data for kind, data in log if kind == "payload_released"]
        assert len(drop) == 1 and distance_m((drop[0]["lat"], drop[0]["lon"]), DROPOFF) < 15
        await carriers_home((second,))
