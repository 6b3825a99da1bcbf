"""The rescue's pages: request with a drawn area, the mission page and its JSON."""

from __future__ import annotations

import html
import json

import pytest
from django.test import Client
from django.urls import reverse

from accounts.tokens import token_issue
from fleet.models import Vehicle
from kinds.rescue_at_sea.models import Mission
from kinds.rescue_at_sea.request import rescue_request
from kinds.rescue_at_sea.tests.sea import area, search_area
from kinds.rescue_at_sea.workflow import mission_advance
from services.models import Session
from tests import factories as f
from tests.deployment import uncacheable

pytestmark = pytest.mark.django_db


@pytest.fixture
def skipper(client, world):
    """skipper, a client, logged in; the sea fleet online (``world``)."""
    user = f.user(username="skipper")
    client.force_login(user)
    return user


def test_request_page_shows_the_map_and_the_stations(client, skipper) -> None:
    page = client.get(reverse("service_request", args=["rescue-at-sea"]))
    assert page.status_code == 200
    html = page.content.decode()
    assert 'id="area-map"' in html and "vendor/leaflet/leaflet.js" in html
    config = page.context["map"]
    assert {"name": "Costa Nova station", "lat": 40.6443, "lon": -8.7455} in config["stations"]
    assert config["tiles"] == ""  # no tile server unless configured


def test_drawn_area_starts_the_mission_and_opens_its_page(client, skipper) -> None:
    url = reverse("service_request", args=["rescue-at-sea"])
    response = client.post(url, {"area": json.dumps(area()), "altitude_m": "35"})
    session = Session.objects.get()
    assert response.status_code == 302 and response.url == reverse("session", args=[session.pk])
    mission = Mission.objects.get(pk=session.pk)
    assert mission.altitude_m == 35 and mission.state == Mission.State.WAITING_SEARCH
    page = client.get(response.url)
    assert page.status_code == 200
    assert 'id="mission-map"' in page.content.decode()
    data = client.get(reverse("session_mission", args=[session.pk])).json()
    assert data["state"] == "waiting_search" and len(data["area"]) == 4 and data["path"]


@pytest.mark.parametrize(
    ("area_field", "message"),
    [
        ("", "Draw the search area"),
        ("[[40.6, -8.7]", "not valid JSON"),
        (json.dumps([[40.6, -8.7], [40.61, -8.7]]), "at least 3"),
    ],
)
def test_bad_areas_are_explained_and_nothing_starts(client, skipper, area_field, message) -> None:
    url = reverse("service_request", args=["rescue-at-sea"])
    page = client.post(url, {"area": area_field})
    assert page.status_code == 200 and message in page.content.decode()
    assert not Session.objects.exists()


def test_the_mission_is_private_to_its_user_and_the_monitors(client, skipper) -> None:
    url = reverse("service_request", args=["rescue-at-sea"])
    client.post(url, {"area": json.dumps(area())})
    session = Session.objects.get()
    mission_url = reverse("session_mission", args=[session.pk])
    client.force_login(f.user(username="stranger"))
    assert client.get(mission_url).status_code == 404
    assert client.get(reverse("session", args=[session.pk])).status_code == 404
    client.force_login(f.user(username="watch", roles=("monitor",)))
    assert client.get(mission_url).status_code == 200


def test_the_rescue_mission_page_is_not_stored(client, world, skipper) -> None:
    # The same view as the controller's: once a search vehicle flies, it carries the
    # user's viewer grant.
    session = rescue_request(user=skipper, service=world, area=area())
    page = client.get(reverse("session", args=[session.pk]))
    uncacheable(page)
    assert 'id="mission-map"' in page.content.decode()


WITHDRAWN = "withdrawn by the user while it waited for a vehicle; no vehicle was sent"


def test_a_rescue_waiting_for_its_drone_is_called_off_and_may_be_asked_again(
    client, skipper
) -> None:
    # The search drone is out on another job: the rescue waits for it.
    Vehicle.objects.filter(name="search-1").update(status=Vehicle.Status.IN_SERVICE)
    url = reverse("service_request", args=["rescue-at-sea"])
    opened = client.post(url, {"area": json.dumps(area())})
    session = Session.objects.get()
    mission_advance(session.pk)
    assert Mission.objects.get(pk=session.pk).state == Mission.State.WAITING_SEARCH
    assert "Call off the search" in client.get(opened.url).content.decode()

    called_off = client.post(reverse("session_end", args=[session.pk]), follow=True)
    assert called_off.status_code == 200
    assert called_off.redirect_chain[-1][0] == reverse("catalog")
    words = called_off.content.decode()
    assert "your request was withdrawn while it waited for a vehicle" in words
    session.refresh_from_db()
    assert session.state == Session.State.ENDED and session.reason == WITHDRAWN
    mission_advance(session.pk)
    assert Mission.objects.get(pk=session.pk).state == Mission.State.ABORTED
    # It no longer counts against the one-session limit.
    again = client.post(url, {"area": json.dumps(area())})
    assert again.status_code == 302 and Session.objects.count() == 2


def test_a_waiting_rescue_is_withdrawn_through_the_api_with_the_same_words(client, skipper) -> None:
    Vehicle.objects.filter(name="search-1").update(status=Vehicle.Status.OFFLINE)
    client.post(reverse("service_request", args=["rescue-at-sea"]), {"area": json.dumps(area())})
    session = Session.objects.get()
    token = token_issue(user=skipper, name="tests")
    answer = Client().post(
        f"/api/v1/sessions/{session.pk}/end",
        content_type="application/json",
        HTTP_AUTHORIZATION=f"Bearer {token}",
    )
    assert answer.status_code == 200, answer.content
    assert answer.json()["state"] == "ended" and answer.json()["reason"] == WITHDRAWN
    again = Client().post(
        f"/api/v1/sessions/{session.pk}/end",
        content_type="application/json",
        HTTP_AUTHORIZATION=f"Bearer {token}",
    )
    assert again.status_code == 409


# --- what can never be served, and what waits ---------------------------------------------


def test_the_request_map_opens_on_the_search_drones_station_with_their_reach(
    client, skipper
) -> None:
    page = client.get(reverse("service_request", args=["rescue-at-sea"]))
    config = page.context["map"]
    assert config["stations"][0]["name"] == "Costa Nova station"
    (reach,) = config["reach"]
    # search-1 flies 8 km on a full battery: 4 km out and back.
    assert reach["vehicle"] == "search-1" and reach["radius_m"] == 4000
    assert "search-1 reaches 4.0 km from Costa Nova station" in page.content.decode()


def test_an_area_no_drone_can_search_is_refused_at_once_saying_what_would_work(
    client, skipper
) -> None:
    # 0.37 km² around the castaway, 900 m off the beach: search-1, idle with a full
    # battery, flies 8 km, of which the way there and back leaves about 6.8 km of
    # pattern, its lines 35 m apart at 40 m.
    url = reverse("service_request", args=["rescue-at-sea"])
    page = client.post(url, {"area": json.dumps(search_area(760, 490))})
    assert page.status_code == 200
    words = page.content.decode()
    assert "this area (0.37 km²) is larger than any search drone can cover there" in words
    assert "the largest area search-1 from Costa Nova station can search is about 0.2 km²" in (
        words
    )
    assert "(about 0.7 km² from 120 m up). Draw a smaller area or search from higher up." in (words)
    assert not Session.objects.exists()
    # The same area from 120 m up fits.
    page = client.post(url, {"area": json.dumps(search_area(760, 490)), "altitude_m": "120"})
    assert page.status_code == 302 and Session.objects.count() == 1


def test_a_rescue_waiting_for_its_busy_drone_says_so_with_its_place_in_the_queue(
    client, skipper
) -> None:
    Vehicle.objects.filter(name="search-1").update(status=Vehicle.Status.IN_SERVICE)
    url = reverse("service_request", args=["rescue-at-sea"])
    client.post(url, {"area": json.dumps(area())})
    first = Session.objects.get()
    other = Client()
    other.force_login(f.user(username="second"))
    other.post(url, {"area": json.dumps(area())})
    second = Session.objects.exclude(pk=first.pk).get()
    for session in (first, second):
        mission_advance(session.pk)
    assert Mission.objects.get(pk=first.pk).status_text == (
        "waiting for a search vehicle: search-1 is busy with another session: this request "
        "is next in line"
    )
    assert Mission.objects.get(pk=second.pk).status_text.endswith("this request is 2nd in line")
    page = client.get(reverse("session", args=[first.pk]))
    assert "search-1 is busy with another session" in page.content.decode()


def test_the_spectate_list_says_a_rescue_runs_by_itself(client, skipper) -> None:
    client.post(reverse("service_request", args=["rescue-at-sea"]), {"area": json.dumps(area())})
    session = Session.objects.get()
    mission_advance(session.pk)  # search-1 goes
    Vehicle.objects.filter(name="search-1").update(profile={"video": True})
    page = html.unescape(client.get(reverse("spectate")).content.decode())
    card = page[page.index(f'data-spectate="{session.pk}"') :]
    card = card[: card.index("</article>")]
    assert "Runs by itself, nobody drives it: search-1 " in card
    assert "in control" not in card
