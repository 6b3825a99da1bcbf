"""Fixtures of the integration tests."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from tests.portal import World, demo_world


@pytest.fixture
async def world(tmp_path: Path) -> AsyncIterator[World]:
    """The seeded demo on the platform, car-1's and quad-1's agents online with a
    position, and Chromium able to take their video (tests.portal.demo_world)."""
    async with demo_world(tmp_path) as running:
        yield running
