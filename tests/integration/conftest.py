"""Fixtures of the integration tests: the portal's world and the network lab (the
database a module's tests share is the root conftest's ``module_database``)."""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest

from tests.netlab import NetLab, leftovers
from tests.portal import World, demo_world


@pytest.fixture
async def world(tmp_path: Path) -> AsyncIterator[World]:
    """The seeded demo on the platform, car-1's and quad-1's agents online with a
    position, and Chromium able to take their video (tests.portal.demo_world)."""
    async with demo_world(tmp_path) as running:
        yield running


@pytest.fixture
def lab(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[NetLab]:
    """A network lab with the sites of the test's ``tests.netlab.nat`` (logs in
    tmp_path). Teardown asserts that nothing of it is left: close() raises on leftovers,
    and they are looked for again here, after what the test's other fixtures started in
    it (peers, coturn, the platform: torn down first) is gone."""
    lab = NetLab(nat=request.param, workdir=tmp_path / "lab")
    lab.open()
    yield lab
    try:
        lab.close()
    finally:
        assert not leftovers(lab.tag)
