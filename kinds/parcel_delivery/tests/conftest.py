"""Fixtures of the parcel tests: the demo world with its carriers online (as rows)."""

from __future__ import annotations

from typing import Any

import pytest
from django.utils import timezone

from fleet.models import Vehicle
from services.demo import demo_seed
from services.models import Service


def carriers_online(*names: str) -> None:
    """The demo vehicles ``names`` online, idle at their station with a full battery, as
    their agents would report them."""
    for vehicle in Vehicle.objects.filter(name__in=names).select_related("station"):
        vehicle.status = Vehicle.Status.IDLE
        vehicle.last_seen = timezone.now()
        vehicle.lat, vehicle.lon, vehicle.alt = vehicle.station.lat, vehicle.station.lon, 0.0
        vehicle.battery = 99.0
        vehicle.save()


@pytest.fixture
def demo(client: Any) -> Service:
    """The seeded demo with lifeguard-1 and boat-1 (the carriers, at Costa Nova) online,
    the demo's client logged in; the parcel service."""
    demo_seed(password="pw")
    carriers_online("lifeguard-1", "boat-1")
    from django.contrib.auth import get_user_model

    client.force_login(get_user_model().objects.get(username="client"))
    return Service.objects.get(slug="parcel-delivery")
