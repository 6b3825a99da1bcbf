"""Fixtures of the rescue tests: the demo's sea fleet online (as rows), and the portal
running for real."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from kinds.rescue_at_sea.tests.sea import online
from services.demo import demo_seed
from services.models import Service
from tests.portal import World, demo_world


@pytest.fixture
def world() -> Service:
    """The seeded demo with search-1 and lifeguard-1 online at their station; the
    rescue service."""
    demo_seed(password="pw")
    online("search-1", "lifeguard-1")
    return Service.objects.get(slug="rescue-at-sea")


@pytest.fixture
async def portal(tmp_path: Path) -> AsyncIterator[World]:
    """The seeded demo on the platform, car-1's and quad-1's agents online with a
    position, and Chromium (tests.portal.demo_world)."""
    async with demo_world(tmp_path) as running:
        yield running
