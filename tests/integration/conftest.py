"""Fixtures of the integration tests: the portal's world and the network lab (the
database a module's tests share is the root conftest's ``module_database``)."""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
import pytest_asyncio

from tests.netlab import NetLab, leftovers
from tests.portal import Portal, World, fleet_world, portal_running


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def module_portal(
    module_database: None, tmp_path_factory: pytest.TempPathFactory
) -> AsyncIterator[Portal]:
    """The seeded demo on the platform, and Chromium, for the module's tests
    (tests.portal.portal_running)."""
    async with portal_running(tmp_path_factory.mktemp("portal")) as portal:
        yield portal


@pytest_asyncio.fixture(loop_scope="module")
async def world(module_portal: Portal) -> AsyncIterator[World]:
    """The module's portal with car-1's and quad-1's agents online with a position, on
    fresh simulators, for one test (tests.portal.fleet_world). A module using it marks
    its tests ``django_db`` (not ``transaction=True``, which would empty the shared
    database after each) and ``asyncio(loop_scope="module")``, the portal's loop."""
    async with fleet_world(module_portal) as running:
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
