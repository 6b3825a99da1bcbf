"""The recipient's tracking page and the sender's delivery page, in Chromium against the
real platform: the map is drawn (it used to be wiped out by the page's own state
label), the state follows the delivery to its end, and the arrival time is in the
portal's 24-hour format.

The carrier is played by its reports, through the platform's own handlers, as the
workflow's tests do: what is under test is what the pages show of a delivery.
"""

from __future__ import annotations

import json
import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from django.contrib.auth import get_user_model
from django.utils import timezone
from playwright.async_api import expect

from agents.protocol import parse_message
from fleet.models import Vehicle
from fleet.vehicle_events import vehicle_events
from kinds.parcel_delivery.models import Delivery
from kinds.parcel_delivery.workflow import delivery_advance
from services.kinds import Request
from services.models import Assignment, Service
from services.sessions.request import service_request
from tests.browser import needs_chromium
from tests.portal import World, demo_world, sign_in
from tests.servers import db

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    needs_chromium,
]

#: On land north-west of Costa Nova station, 480 m apart: lifeguard-1's parcel.
PICKUP = (40.6485, -8.7520)
DROPOFF = (40.6510, -8.7480)


@pytest.fixture
async def portal(tmp_path: Path) -> AsyncIterator[World]:
    """The seeded demo on the platform and Chromium; no agent runs (the carrier is
    played by its reports)."""
    async with demo_world(tmp_path, names=()) as world:
        yield world


def _requested() -> Delivery:
    """lifeguard-1 online at its station; the client sends a parcel; the workflow
    sends lifeguard-1 to the pickup."""
    Vehicle.objects.filter(name="lifeguard-1").update(
        status=Vehicle.Status.IDLE, last_seen=timezone.now(), lat=40.6443, lon=-8.7455, battery=99
    )
    params = {
        "pickup": {"lat": PICKUP[0], "lon": PICKUP[1]},
        "dropoff": {"lat": DROPOFF[0], "lon": DROPOFF[1]},
        "weight_kg": 1.0,
        "recipient": {"name": "Rita", "email": "rita@example.org"},
    }
    session = service_request(
        user=get_user_model().objects.get(username="client"),
        service=Service.objects.get(slug="parcel-delivery"),
        request=Request(params=params),
    ).session
    delivery_advance(session.pk)
    return Delivery.objects.get(pk=session.pk)


def _carrier_reports(delivery: Delivery, *events: str) -> str:
    """The carrier reports ``events`` (through the uplink's handlers), each followed by
    the workflow's step; returns the delivery's state."""
    carrier = Assignment.objects.get(session_id=delivery.pk, active=True)
    for name in events:
        message = parse_message(
            json.dumps(
                {"type": "event", "session_id": str(delivery.pk), "event": name, "data": {}}
            ),
            channel="uplink_to_platform",
        )
        vehicle_events().agent_message(vehicle_id=str(carrier.vehicle_id), message=message)
        delivery_advance(delivery.pk)
    return str(Delivery.objects.get(pk=delivery.pk).state)


async def test_the_recipient_sees_the_map_and_the_state_to_the_end(portal: World) -> None:
    delivery: Any = await db(_requested)
    page = await (await portal.browser.new_context()).new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    await page.goto(f"{portal.base}/track/{delivery.tracking_token}/")
    # The map is there: its pickup, its drop-off and the carrier, over land and sea.
    await expect(page.locator("#parcel-map path.pickup-marker")).to_have_count(1)
    await expect(page.locator("#parcel-map path.dropoff-marker")).to_have_count(1)
    await expect(page.locator("#parcel-map path.carrier-marker")).to_have_count(1)
    state = page.locator("dd[data-delivery-state]")
    await expect(state).to_have_text("on its way to the pickup")
    await page.wait_for_timeout(1500)  # a poll or two later: still drawn
    await expect(page.locator("#parcel-map path.pickup-marker")).to_have_count(1)

    assert await db(_carrier_reports, delivery, "parcel_loaded", "payload_released") == (
        "delivered"
    )
    # The banner and the state agree, and the map stays.
    await expect(page.locator("[data-delivery-status]")).to_contain_text("delivered")
    await expect(state).to_have_text("Delivered")
    await expect(page.locator("dd[data-eta]")).to_have_text("delivered")
    await expect(page.locator("#parcel-map")).to_have_attribute("data-delivery-state", "delivered")
    await expect(page.locator("#parcel-map path.dropoff-marker")).to_have_count(1)
    assert not errors, errors


async def test_the_arrival_time_is_in_the_portals_24_hour_format(portal: World) -> None:
    delivery: Any = await db(_requested)
    # A browser whose locale writes times with AM/PM by default.
    page = await (await portal.browser.new_context(locale="en-US")).new_page()
    await sign_in(page, portal.base, "client")
    await page.goto(f"{portal.base}/sessions/{delivery.pk}/")
    eta = page.locator("[data-eta]")
    await expect(eta).to_have_text(re.compile(r"^in about \d+ min \(\d\d:\d\d\)$"))
    assert not re.search(r"AM|PM", await eta.inner_text())
