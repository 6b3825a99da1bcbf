"""The rescue's part of the demo world: its service's roles and the lifeguards."""

from __future__ import annotations

from typing import Any

import pytest

from fleet.models import Vehicle
from kinds.rescue_at_sea.models import RescueTeam
from services.demo import demo_seed
from services.models import Service

pytestmark = pytest.mark.django_db


@pytest.fixture(autouse=True)
def _fast_hasher(settings: Any) -> None:
    settings.PASSWORD_HASHERS = ["django.contrib.auth.hashers.MD5PasswordHasher"]


def test_rescue_roles() -> None:
    demo_seed(password="pw")
    roles = {r.name: r for r in Service.objects.get(slug="rescue-at-sea").roles.all()}
    assert set(roles) == {"search", "delivery"}
    assert roles["search"].required and not roles["delivery"].required
    assert roles["delivery"].min_attributes == {"max_payload_kg": 1.0}
    assert roles["delivery"].features == ["payload_release"]
    # Only the coastal quadcopter has the thermal camera the search needs.
    thermal = [v.name for v in Vehicle.objects.all() if "thermal" in v.cameras]
    assert thermal == ["search-1"]


def test_the_coastal_station_has_its_lifeguards_once() -> None:
    demo_seed(password="pw")
    demo_seed(password="pw")
    team = RescueTeam.objects.get()
    assert team.station.name == "Costa Nova station"
    assert team.email.endswith(".example")  # never a real team
    assert not team.webhook
