"""Fixtures of the integration tests: the portal's world, the database for a world a
module's tests share, and the network lab."""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
from django.core.management import call_command
from django.test import override_settings

from tests.netlab import NetLab, leftovers
from tests.portal import World, demo_world


@pytest.fixture
async def world(tmp_path: Path) -> AsyncIterator[World]:
    """The seeded demo on the platform, car-1's and quad-1's agents online with a
    position, and Chromium able to take their video (tests.portal.demo_world)."""
    async with demo_world(tmp_path) as running:
        yield running


@pytest.fixture(scope="module")
def module_database(django_db_setup: Any, django_db_blocker: Any) -> Iterator[None]:
    """The test database, open to the module for its whole run, for a world its tests
    share (started once: the slow part). What the module writes is committed, as
    ``transaction=True`` would (the servers it starts share it), and the database is
    emptied after the module, as a transactional test's teardown does, once the world
    (which depends on this) has stopped.

    The module's tests are marked ``django_db``, not ``transaction=True``: that would
    empty the database after each test, under the world's feet."""
    with django_db_blocker.unblock():
        # The demo users' passwords hashed the fast way (the platform the tests start
        # accepts it), as the root conftest's per-test fixture does.
        with override_settings(PASSWORD_HASHERS=["django.contrib.auth.hashers.MD5PasswordHasher"]):
            yield
        call_command("flush", interactive=False, verbosity=0)


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
