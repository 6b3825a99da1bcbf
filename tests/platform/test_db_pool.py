"""The platform's pool of database connections outlives the connections it holds.

PostgreSQL restarting, a failover, or a firewall dropping idle connections leave a
process's pooled connections dead. Each one must be replaced as it is lent, not fail
the request that gets it. The platform runs as the project runs it (iouv.serve, its pool
as settings configure it, tests/servers.py) and its connections are killed from outside.
"""

from __future__ import annotations

import urllib.request
import uuid

import psycopg
import pytest
from django.conf import settings

from tests.servers import _test_database_url, platform_process

pytestmark = pytest.mark.postgres


def _kill(application_name: str) -> int:
    """Terminate the test database's connections opened under ``application_name``."""
    db = settings.DATABASES["default"]
    with psycopg.connect(
        host=db.get("HOST") or "127.0.0.1",
        port=db.get("PORT") or 5432,
        user=db.get("USER") or None,
        password=db.get("PASSWORD") or None,
        dbname="postgres",
        autocommit=True,
    ) as admin:
        rows = admin.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
            "WHERE datname = %s AND application_name = %s",
            [db["NAME"], application_name],
        ).fetchall()
    return len(rows)


def _health(base: str) -> int:
    with urllib.request.urlopen(f"{base}/healthz", timeout=10) as response:
        return int(response.status)


def test_requests_after_the_database_dropped_every_connection_are_answered(
    django_db_setup: None,
) -> None:
    name = f"iouv-pool-{uuid.uuid4().hex[:8]}"
    url = f"{_test_database_url()}?application_name={name}"
    with platform_process(extra_env={"DATABASE_URL": url}) as base:
        for _ in range(4):  # the pool holds connections now (its minimum, at least)
            assert _health(base) == 200
        assert _kill(name) >= 1, "the platform held no connection to kill"
        # Every request after it is answered: each dead connection is found and
        # replaced as the pool lends it (healthz reads the database).
        assert [_health(base) for _ in range(6)] == [200] * 6
        assert _kill(name) >= 1  # it is connected again
