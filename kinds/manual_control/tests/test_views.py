"""The manual-control request page as a person uses it, on the demo world: asking for a
car with a camera arm."""

from __future__ import annotations

from typing import Any

import pytest
from django.contrib.auth import get_user_model
from django.test import Client
from django.urls import reverse
from django.utils import timezone

from fleet.models import Station, Vehicle
from services.demo import demo_seed
from services.models import Assignment, Session

pytestmark = pytest.mark.django_db


@pytest.fixture
def cars(client: Client) -> None:
    """The demo seeded, car-1 (the one with a camera arm) and car-2 online at the campus
    station, car-2 the fuller (so matching prefers it); the demo's client logged in."""
    demo_seed(password="pw")
    campus = Station.objects.get(name="Campus station")
    for name, battery in (("car-1", 80.0), ("car-2", 99.0)):
        Vehicle.objects.filter(name=name).update(
            status=Vehicle.Status.IDLE,
            last_seen=timezone.now(),
            lat=campus.lat,
            lon=campus.lon,
            battery=battery,
        )
    client.force_login(get_user_model().objects.get(username="client"))


def _requested(client: Client, **wishes: Any) -> str:
    url = reverse("service_request", args=["drive-car"])
    station = Station.objects.get(name="Campus station").pk
    answer = client.post(url, {"station": station, **wishes})
    assert answer.status_code == 302, answer.content.decode()
    session = Session.objects.order_by("-created_at").first()
    assert session is not None
    return str(Assignment.objects.get(session=session).vehicle.name)


def test_a_car_with_a_camera_arm_can_be_asked_for(client: Client, cars: None) -> None:
    page = client.get(reverse("service_request", args=["drive-car"])).content.decode()
    assert "a camera arm (pan and tilt)" in page
    assert _requested(client, features=["camera_arm"]) == "car-1"


def test_without_the_wish_the_fullest_car_goes(client: Client, cars: None) -> None:
    assert _requested(client) == "car-2"


def test_a_wish_no_car_meets_is_refused_saying_which(client: Client, cars: None) -> None:
    url = reverse("service_request", args=["drive-car"])
    page = client.post(url, {"features": ["payload_release"]}, follow=True)
    assert "no idle vehicle has features payload_release" in page.content.decode()
