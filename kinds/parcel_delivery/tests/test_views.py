"""The parcel's pages as a person uses them, on the demo world: the request page and
its map, a request that cannot be served, withdrawing a request, the session page."""

from __future__ import annotations

import json
from typing import Any

import pytest
from django.test import Client
from django.urls import reverse

from fleet.models import Vehicle
from kinds.parcel_delivery.models import Delivery
from kinds.parcel_delivery.workflow import delivery_advance
from services.models import Service, Session

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
    assert "Cancel the delivery" in client.get(opened.url).content.decode()

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
