"""Portal answers that carry a signed user grant are never kept by a cache.

The JSON API's answers are covered in test_api.py and the admin's fresh credentials in
tests/test_admin.py; here the portal's pages and its reconnect endpoint.
"""

from __future__ import annotations

from datetime import timedelta

import pytest
from django.urls import reverse
from django.utils import timezone

from agents.protocol import UserGrant
from fleet.models import Vehicle
from services.models import Session
from services.sessions.selectors import service_vehicles_matching
from services.sessions.signing import platform_public_key
from tests import factories as f
from tests.deployment import page_grant, uncacheable

pytestmark = pytest.mark.django_db


def test_the_controller_page_is_not_stored(client, live_session) -> None:
    session, vehicle_id = live_session
    page = client.get(reverse("session", args=[session.pk]))
    uncacheable(page)
    assert page_grant(page.content.decode(), vehicle_id).role == "controller"


def test_a_fresh_grant_to_reconnect_is_not_stored(client, live_session) -> None:
    session, vehicle_id = live_session
    answer = client.post(reverse("session_grant", args=[session.pk]))
    uncacheable(answer)
    UserGrant.verify(answer.json()["grant"], platform_public_key(), vehicle_id=vehicle_id)


def test_a_session_still_waiting_for_its_vehicle_says_so_and_then_the_session_over(
    client, live_session
) -> None:
    # An autonomous kind's page asks for its grant until a vehicle is assigned: it must
    # tell "not yet" (ask again) from "over" (stop asking).
    session, _ = live_session
    Session.objects.filter(pk=session.pk).update(state=Session.State.REQUESTED)
    answer = client.post(reverse("session_grant", args=[session.pk]))
    assert answer.status_code == 409
    assert answer.json()["error"]["code"] == "no_vehicle_yet"
    Session.objects.filter(pk=session.pk).update(state=Session.State.ENDED, reason="done")
    answer = client.post(reverse("session_grant", args=[session.pk]))
    assert answer.status_code == 409
    assert answer.json()["error"]["code"] == "session_over"


def test_ending_asks_with_what_the_vehicle_will_do_in_its_own_words(client, live_session) -> None:
    # The service's fail-safe is "land": the page says what that means for this vehicle,
    # in the words its agent declared, else by the action's name.
    session, vehicle_id = live_session
    vehicle = Vehicle.objects.get(pk=vehicle_id)
    html = client.get(reverse("session", args=[session.pk])).content.decode()
    assert 'data-confirm="End the session?"' in html
    assert f'data-consequence="{vehicle.name} will land."' in html

    profile = {**vehicle.profile, "safe_actions": {"land": "hover and land where it is"}}
    Vehicle.objects.filter(pk=vehicle_id).update(profile=profile)
    html = client.get(reverse("session", args=[session.pk])).content.decode()
    assert f'data-consequence="{vehicle.name} will hover and land where it is."' in html


def test_the_request_form_offers_only_vehicles_heard_from_lately() -> None:
    """A vehicle that went quiet since the last offline sweep still reads idle, but it is
    not offered: the request would fail on it (assignment checks the same)."""
    station = f.station()
    vtype = f.vehicle_type()
    heard = f.vehicle(station=station, vtype=vtype, name="heard")
    quiet = f.vehicle(station=station, vtype=vtype, name="quiet")
    Vehicle.objects.filter(pk=quiet.pk).update(last_seen=timezone.now() - timedelta(minutes=5))
    service = f.service()
    assert [v.name for v in service_vehicles_matching(service)] == ["heard"]
    assert heard.status == quiet.status == Vehicle.Status.IDLE
