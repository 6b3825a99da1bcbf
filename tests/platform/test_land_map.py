"""The land mask the maps draw offline: served as packaged, to anyone, cached long."""

from __future__ import annotations

import json

import pytest
from django.test import Client
from django.urls import reverse

from agents.geography import MASK_PATH, LandMask

pytestmark = pytest.mark.django_db


def test_the_packaged_mask_is_served_as_geojson_to_anyone(client: Client) -> None:
    # Anonymous: the recipient's tracking page, which needs no account, shows it too.
    answer = client.get("/map/land.geo.json")
    assert answer.status_code == 200
    assert reverse("land_map") == "/map/land.geo.json"
    assert answer["Content-Type"] == "application/geo+json"
    assert answer.content == MASK_PATH.read_bytes()
    data = json.loads(answer.content)
    # What the maps read: a region's box, its land rings, and the credit they must show.
    mask = LandMask.from_geojson(data)
    assert mask.land_at(40.6441, -8.7561) is False  # sea, off Costa Nova
    assert mask.land_at(40.6306, -8.6588) is True  # the campus
    assert data["features"][0]["properties"]["bbox"] == [40.55, -8.85, 40.75, -8.55]
    assert "OpenStreetMap contributors" in data["attribution"]


def test_browsers_and_proxies_may_keep_it(client: Client) -> None:
    answer = client.get("/map/land.geo.json")
    directives = {d.strip() for d in answer["Cache-Control"].split(",")}
    assert "public" in directives
    max_age = next(int(d.split("=")[1]) for d in directives if d.startswith("max-age="))
    assert max_age >= 24 * 3600


def test_only_read(client: Client) -> None:
    assert client.post("/map/land.geo.json").status_code == 405
