"""The platform's pool of database connections outlives the connections it holds.

PostgreSQL restarting, a failover, or a firewall dropping idle connections leave a
process's pooled connections dead. Each one must be replaced as it is lent, not fail
the request that gets it. The platform runs as the project runs it (iouv.serve, its pool
as settings configure it, tests/servers.py) and its connections are killed from outside.
"""

from __future__ import annotations

import select
import urllib.request
import uuid
from typing import Any

import psycopg
import pytest
from django.conf import settings

from iouv.db_pool import pooled_connection_check
from tests.servers import _test_database_url, platform_process

pytestmark = pytest.mark.postgres


def _connect(dbname: str | None = None, **kwargs: Any) -> psycopg.Connection[Any]:
    """A connection of its own to the test database (or to ``dbname``)."""
    db = settings.DATABASES["default"]
    return psycopg.connect(
        host=db.get("HOST") or "127.0.0.1",
        port=db.get("PORT") or 5432,
        user=db.get("USER") or None,
        password=db.get("PASSWORD") or None,
        dbname=dbname or db["NAME"],
        autocommit=True,
        **kwargs,
    )


def _kill(application_name: str) -> int:
    """Terminate the test database's connections opened under ``application_name``."""
    with _connect("postgres") as admin:
        rows = admin.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
            "WHERE datname = %s AND application_name = %s",
            [settings.DATABASES["default"]["NAME"], application_name],
        ).fetchall()
    return len(rows)


def _last_statement(pid: int) -> str:
    """What PostgreSQL last ran for the connection of backend ``pid``."""
    with _connect("postgres") as admin:
        row = admin.execute("SELECT query FROM pg_stat_activity WHERE pid = %s", [pid]).fetchone()
    assert row is not None, f"no backend {pid}"
    return str(row[0])


def test_a_live_idle_connection_is_lent_without_a_round_trip(django_db_setup: None) -> None:
    with _connect() as conn:
        conn.execute("SELECT 'the last statement'")
        for _ in range(3):
            pooled_connection_check(conn)
        # PostgreSQL was sent nothing: psycopg_pool's own check would have run "".
        assert _last_statement(conn.info.backend_pid) == "SELECT 'the last statement'"


def test_a_connection_the_database_ended_is_not_lent(django_db_setup: None) -> None:
    name = f"iouv-check-{uuid.uuid4().hex[:8]}"
    with _connect(application_name=name) as conn:
        pooled_connection_check(conn)
        assert _kill(name) == 1
        _wait_readable(conn)
        with pytest.raises(psycopg.OperationalError):
            pooled_connection_check(conn)
        with pytest.raises(psycopg.OperationalError):  # and stays refused
            pooled_connection_check(conn)


def _wait_readable(conn: psycopg.Connection[Any]) -> None:
    """Until PostgreSQL's goodbye reached the socket (it is sent, not yet arrived,
    when pg_terminate_backend returns)."""
    poller = select.poll()
    poller.register(conn.pgconn.socket, select.POLLIN)
    assert poller.poll(10_000), "PostgreSQL did not close the connection"


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
