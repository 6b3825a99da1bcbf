"""Every page has an icon: no browser asks for a /favicon.ico that is not there."""

from __future__ import annotations

from pathlib import Path

import pytest
from django.contrib.staticfiles import finders
from django.test import Client

pytestmark = pytest.mark.django_db


def test_pages_name_their_icon_and_it_is_served(client: Client) -> None:
    page = client.get("/accounts/login/")
    assert b'rel="icon" href="/static/img/favicon.svg"' in page.content
    # Served with the other static files (the ASGI application's static handler).
    found = finders.find("img/favicon.svg")
    assert isinstance(found, str) and Path(found).read_text().startswith("<svg")


def test_the_conventional_address_leads_to_the_icon(client: Client) -> None:
    # The admin's pages name no icon: browsers then ask for /favicon.ico.
    answer = client.get("/favicon.ico")
    assert answer.status_code == 301
    assert answer["Location"] == "/static/img/favicon.svg"
