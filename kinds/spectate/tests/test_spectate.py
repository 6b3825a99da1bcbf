"""Spectating: the page to watch a session's vehicle, view-only."""

from __future__ import annotations

import pytest
from django.test import Client
from django.urls import reverse

from services.assignment import session_request
from services.models import Session
from tests import factories as f
from tests.services.test_deployment import TARGET, _registered_vehicle, _service
from tests.services.test_grant_pages import _page_grant, _uncacheable

pytestmark = pytest.mark.django_db


@pytest.fixture
def watched(client: Client) -> tuple[Session, str]:
    """alice's live session, and its vehicle's id; vera, a client, is logged in."""
    vehicle = _registered_vehicle()
    session = session_request(user=f.user(username="alice"), service=_service(), target=TARGET)
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
    _uncacheable(page)
    assert _page_grant(page.content.decode(), vehicle_id).role == "viewer"


def test_spectating_is_not_requested_as_a_session(client, watched) -> None:
    response = client.get(reverse("service_request", args=["spectate"]))
    assert response.status_code == 302 and response["Location"] == reverse("spectate")
