"""benchmarks.http_handler, small: both handlers serve the platform's API under daphne
and the table compares them. Nothing about timing is asserted (the machine may be busy).
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import psycopg
import pytest
from django.conf import settings
from psycopg import sql

from benchmarks import http_handler


@pytest.fixture
def database_url() -> Iterator[str]:
    """A database of its own beside the test database: the benchmark drops and
    migrates it from nothing."""
    db = settings.DATABASES["default"]
    name = f"{db['NAME']}_http_handler"
    host, port, user = db.get("HOST") or "127.0.0.1", db.get("PORT") or 5432, db.get("USER")
    yield f"postgres://{user or ''}@{host}:{port}/{name}"
    with psycopg.connect(host=host, port=port, user=user, dbname="postgres", autocommit=True) as c:
        c.execute(sql.SQL("DROP DATABASE IF EXISTS {} WITH (FORCE)").format(sql.Identifier(name)))


@pytest.mark.postgres
def test_both_handlers_answer_the_api_and_are_measured(database_url, capsys):
    http_handler.main(
        ["--requests", "30", "--rounds", "1", "--json", "--database-url", database_url]
    )
    runs = json.loads(capsys.readouterr().out)
    assert [r["handler"] for r in runs] == list(http_handler.APPS)
    for run in runs:
        assert run["cpu_ms"] >= 0 and run["wall_ms"] > 0
    # The table a person reads.
    table = http_handler.table([http_handler.Run(**r) for r in runs])
    assert table.count("\n") == 3 and "| Django's |" in table
