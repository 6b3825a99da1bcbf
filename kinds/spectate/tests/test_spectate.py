"""Spectating: the page to watch a session's vehicle, view-only."""

from __future__ import annotations

import html
from datetime import timedelta

import pytest
from django.conf import settings
from django.test import Client
from django.urls import reverse

from services.models import Session
from services.sessions.log import event_append
from tests import factories as f
from tests.deployment import alices_session, page_grant, uncacheable

pytestmark = pytest.mark.django_db


@pytest.fixture
def watched(client: Client) -> tuple[Session, str]:
    """alice's live session, and its vehicle's id; vera, a client, is logged in."""
    session, vehicle = alices_session()
    f.service("spectate", kind="spectate")
    client.force_login(f.user(username="vera"))
    return session, str(vehicle.pk)


def test_the_list_shows_sessions_whose_vehicle_streams(client, watched) -> None:
    session, _ = watched
    page = client.get(reverse("spectate"))
    assert page.status_code == 200
    assert f'data-spectate="{session.pk}"' in page.content.decode()


def test_the_spectators_page_carries_a_viewer_grant_and_is_not_stored(client, watched) -> None:
    session, vehicle_id = watched
    page = client.get(reverse("spectate_session", args=[session.pk]))
    uncacheable(page)
    assert page_grant(page.content.decode(), vehicle_id).role == "viewer"


def test_spectating_is_not_requested_as_a_session(client, watched) -> None:
    response = client.get(reverse("service_request", args=["spectate"]))
    assert response.status_code == 302 and response["Location"] == reverse("spectate")


def test_the_list_says_when_nobody_controls_the_vehicle_and_when_the_session_ends(
    client, watched
) -> None:
    session, _ = watched
    card = _card(client.get(reverse("spectate")).content.decode(), session)
    assert ">live<" in card and "Waiting for the driver to connect." in card
    Session.objects.filter(pk=session.pk).update(state=Session.State.ACTIVE)
    event_append(session=session, kind="user_connected", data={"role": "controller"})
    card = _card(client.get(reverse("spectate")).content.decode(), session)
    assert ">live<" in card and "alice is in control." in card

    # The driver's link dropped and the car stopped on its own: still an "active"
    # session, but nobody drives it, and it ends after the grace unless they return.
    gone = event_append(
        session=session, kind="unintentional_end", data={"cause": "link_lost", "action": "stop"}
    )
    card = _card(client.get(reverse("spectate")).content.decode(), session)
    assert ">live<" not in card and "nobody in control" in card
    assert (
        "Nobody is in control: the driver's link to the vehicle was lost, so it performed "
        "its fail-safe (stop)."
    ) in html.unescape(card)
    ends = gone.created_at + timedelta(seconds=settings.IOUV_RECONNECT_GRACE_S)
    assert f'datetime="{ends.isoformat()}"' in card

    event_append(session=session, kind="link_recovered", data={})
    card = _card(client.get(reverse("spectate")).content.decode(), session)
    assert ">live<" in card and "nobody in control" not in card


@pytest.mark.parametrize("failsafe_first", [True, False])
def test_a_closed_tab_reads_as_what_the_vehicle_did_whichever_report_came_first(
    client, watched, failsafe_first: bool
) -> None:
    """The driver closes the tab: the agent reports the link lost (with the car's
    fail-safe) and the driver's socket gone, in either order. The list says what the car
    did, not that the driver left; after a release of control, that the driver did."""
    session, _ = watched
    Session.objects.filter(pk=session.pk).update(state=Session.State.ACTIVE)
    event_append(session=session, kind="user_connected", data={"role": "controller"})
    reports = [
        ("unintentional_end", {"cause": "link_lost", "action": "stop"}),
        ("user_disconnected", {"role": "controller"}),
    ]
    for kind, data in reports if failsafe_first else reversed(reports):
        event_append(session=session, kind=kind, data=data)
    card = html.unescape(_card(client.get(reverse("spectate")).content.decode(), session))
    assert "Nobody is in control: the driver's link to the vehicle was lost" in card
    assert "The driver left." not in card

    # Back, then gone without a fail-safe: the words are the driver's leaving again.
    event_append(session=session, kind="user_connected", data={"role": "controller"})
    event_append(session=session, kind="user_disconnected", data={"role": "controller"})
    card = html.unescape(_card(client.get(reverse("spectate")).content.decode(), session))
    assert "The driver left." in card and "link to the vehicle was lost" not in card


def test_the_list_follows_the_server_without_a_reload(client, watched) -> None:
    page = client.get(reverse("spectate")).content.decode()
    assert 'id="spectatable" data-refresh-s=' in page and "js/refresh.js" in page


def _card(page: str, session: Session) -> str:
    start = page.index(f'data-spectate="{session.pk}"')
    return page[start : page.index("</article>", start)]
