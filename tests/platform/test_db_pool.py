"""The platform's pool of database connections outlives the connections it holds.

PostgreSQL restarting, a failover, or a firewall dropping idle connections leave a
process's pooled connections dead. Django's pool checks each connection as it lends it
(``CONN_HEALTH_CHECKS``: psycopg_pool's check), throws a dead one away and lends another,
so the platform is ready again within seconds without a restart. A request that meets
two dead connections in a row may be answered 503 with Retry-After (psycopg_pool waits
before trying a third, past the pool's 1 s), never 500. The platform runs as the project
runs it (iouv.serve, its pool as settings configure it, tests/servers.py) and its
connections are killed from outside.
"""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.request
import uuid

import pytest
from django.conf import settings

from tests.servers import _test_database_url, platform_process, postgres_terminate

pytestmark = [pytest.mark.postgres, pytest.mark.django_db(transaction=True)]

#: How soon the platform is ready again after its connections were killed.
READY_AGAIN_WITHIN_S = 3.0


def _kill(application_name: str) -> int:
    """Terminate the test database's connections opened under ``application_name``."""
    return postgres_terminate(
        "datname = %s AND application_name = %s",
        [settings.DATABASES["default"]["NAME"], application_name],
    )


def _ready(base: str) -> bool:
    """``/readyz``: True when its database check ran a statement (200), False when it
    answered 503 with Retry-After; anything else fails the test."""
    try:
        with urllib.request.urlopen(f"{base}/readyz", timeout=10) as response:
            return bool(json.load(response)["checks"]["database"]["ok"])
    except urllib.error.HTTPError as answer:
        assert answer.code == 503, answer.read()
        assert answer.headers["Retry-After"], "a 503 without Retry-After"
        return False


def test_requests_after_the_database_dropped_every_connection_are_answered() -> None:
    name = f"iouv-pool-{uuid.uuid4().hex[:8]}"
    url = f"{_test_database_url()}?application_name={name}"
    with platform_process(extra_env={"DATABASE_URL": url}) as base:
        for _ in range(4):  # the pool holds connections now (its minimum, at least)
            assert _ready(base)
        assert _kill(name) >= 1, "the platform held no connection to kill"

        killed_at = time.monotonic()
        while not _ready(base):
            assert time.monotonic() - killed_at < READY_AGAIN_WITHIN_S, "not ready again"
            time.sleep(0.1)
        # The dead connections were thrown away: every check after reads the database.
        assert [_ready(base) for _ in range(6)] == [True] * 6
        assert _kill(name) >= 1  # it is connected again
