"""The parcel's pages as a person uses them, on the demo world: the request page and
its map, a request that cannot be served, withdrawing a request, the session page."""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
from django.core import mail
from django.test import Client
from django.urls import reverse

from fleet.models import Vehicle
from kinds.parcel_delivery.models import Delivery
from kinds.parcel_delivery.notifications import parcel_notices
from kinds.parcel_delivery.workflow import delivery_advance
from services.models import Service, Session
from services.sessions.notices import notices_send

pytestmark = pytest.mark.django_db

#: On land north-west of Costa Nova station (about 700 m and 1 km from it), 480 m
#: apart: a drone's parcel.
PICKUP = (40.6485, -8.7520)
DROPOFF = (40.6510, -8.7480)
WITHDRAWN = "withdrawn by the user while it waited for a vehicle; no vehicle was sent"


def form(pickup: tuple[float, float], dropoff: tuple[float, float], **extra: Any) -> dict[str, Any]:
    """The request form as the page posts it once both points are picked."""
    return {
        "pickup": json.dumps(list(pickup)),
        "dropoff": json.dumps(list(dropoff)),
        "weight_kg": "1",
        "recipient_name": "Rita",
        "recipient_email": "rita@example.org",
        **extra,
    }


URL = reverse("service_request", args=["parcel-delivery"])


def test_a_parcel_waiting_for_its_carrier_is_cancelled_and_may_be_sent_again(
    client: Client, demo: Service
) -> None:
    # Both carriers are out on other jobs: the parcel waits.
    Vehicle.objects.filter(name__in=["lifeguard-1", "boat-1"]).update(
        status=Vehicle.Status.IN_SERVICE
    )
    opened = client.post(URL, form(PICKUP, DROPOFF))
    assert opened.status_code == 302, opened.content.decode()
    session = Session.objects.get()
    delivery_advance(session.pk)
    assert Delivery.objects.get(pk=session.pk).state == Delivery.State.WAITING_CARRIER
    assert "Cancel the delivery" in client.get(opened["Location"]).content.decode()

    cancelled = client.post(reverse("session_end", args=[session.pk]), follow=True)
    assert cancelled.status_code == 200
    assert cancelled.redirect_chain[-1][0] == reverse("catalog")
    assert "your request was withdrawn while it waited for a vehicle" in (
        cancelled.content.decode()
    )
    session.refresh_from_db()
    assert session.state == Session.State.ENDED and session.reason == WITHDRAWN
    delivery_advance(session.pk)
    assert Delivery.objects.get(pk=session.pk).state == Delivery.State.CANCELLED
    again = client.post(URL, form(PICKUP, DROPOFF))
    assert again.status_code == 302 and Session.objects.count() == 2


# --- what can never be served -------------------------------------------------------------

#: On the campus, far from the coast: the first place a newcomer clicks used to be here.
CAMPUS_PICKUP = (40.6290, -8.6600)
CAMPUS_DROPOFF = (40.6330, -8.6560)
#: West of the beach, at sea; and a point on land north-west of the station.
SEA = (40.6440, -8.7600)


def test_the_request_map_opens_on_the_carriers_station_with_where_they_reach(
    client: Client, demo: Service
) -> None:
    page = client.get(URL)
    config = page.context["map"]
    # Costa Nova, not the campus (first by name), where no vehicle carries a parcel.
    assert [s["name"] for s in config["stations"]] == ["Costa Nova station"]
    reach = {r["vehicle"]: r for r in config["reach"]}
    assert set(reach) == {"lifeguard-1", "boat-1"}
    assert reach["lifeguard-1"]["radius_m"] == 2980  # 6 km there and back, a 20 m trip
    html = page.content.decode()
    assert "by air: pickups within 3.0 km of Costa Nova station (lifeguard-1)" in html
    assert "on the water: pickups within 7.5 km of Costa Nova station (boat-1)" in html
    # lifeguard-1 is idle: it is listed as available (the carrier role is not required:
    # the workflow assigns it, so "the first required role" found none).
    assert "lifeguard-1" in [v.name for v in page.context["available"]]


def test_a_parcel_on_the_campus_is_refused_at_once_saying_where_parcels_go(
    client: Client, demo: Service
) -> None:
    page = client.post(URL, form(CAMPUS_PICKUP, CAMPUS_DROPOFF))
    assert page.status_code == 200
    html = page.content.decode()
    assert (
        "parcels on a 560 m trip can be picked up within 2.4 km of Costa Nova station "
        "(lifeguard-1 on a full charge); this pickup is 7.4 km from it"
    ) in html
    assert not Session.objects.exists()
    # Near the station it goes.
    assert client.post(URL, form(PICKUP, DROPOFF)).status_code == 302


def test_a_pickup_on_the_water_for_a_drop_off_on_land_is_refused(
    client: Client, demo: Service
) -> None:
    page = client.post(URL, form(SEA, PICKUP))
    assert page.status_code == 200
    assert "the pickup is on the water and the other point on land" in page.content.decode()
    page = client.post(URL, form(PICKUP, SEA))
    assert "the drop-off is on the water and the other point on land" in page.content.decode()
    assert not Session.objects.exists()


def test_a_parcel_waiting_for_a_busy_carrier_says_so_with_its_place_in_the_queue(
    client: Client, demo: Service
) -> None:
    Vehicle.objects.filter(name="lifeguard-1").update(status=Vehicle.Status.IN_SERVICE)
    opened = client.post(URL, form(PICKUP, DROPOFF))
    session = Session.objects.get()
    delivery_advance(session.pk)
    status = Delivery.objects.get(pk=session.pk).status_text
    assert status == (
        "waiting for a vehicle: lifeguard-1 is busy with another session: this request is "
        "next in line"
    )
    assert (
        "lifeguard-1 is busy with another session"
        in client.get(opened["Location"]).content.decode()
    )


# --- the recipient's link ------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[3]


def test_the_demo_on_another_port_e_mails_links_to_that_port(
    client: Client, demo: Service, settings: Any
) -> None:
    # What bin/demo gives its servers when started as PORT=8210 bin/demo.
    shown = subprocess.run(
        ["bin/demo", "--print-env"],
        cwd=ROOT,
        env={**os.environ, "PORT": "8210"},
        capture_output=True,
        text=True,
        check=True,
        timeout=30,
    ).stdout
    given = dict(line.split("=", 1) for line in shown.splitlines())
    settings.IOUV_PUBLIC_URL = given["IOUV_PUBLIC_URL"]
    client.post(URL, form(PICKUP, DROPOFF))
    delivery = Delivery.objects.get()
    parcel_notices(delivery, moment="dispatched")  # as the carrier loads it
    notices_send(delivery.pk)
    (sent,) = mail.outbox
    link = re.search(r"https?://\S+", str(sent.body))
    assert link is not None, sent.body
    url = urlsplit(link.group(0))
    assert (url.scheme, url.netloc) == ("http", "127.0.0.1:8210"), link.group(0)
    # The path opens the recipient's page, with no account.
    page = Client().get(url.path)
    assert page.status_code == 200 and 'id="parcel-map"' in page.content.decode()
