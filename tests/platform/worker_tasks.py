"""Tasks a test's Celery worker runs besides the platform's own
(``celery worker --include tests.platform.worker_tasks``)."""

from __future__ import annotations

from celery import shared_task
from django.db import connection


@shared_task(name="tests.record_backend_pid")
def record_backend_pid(path: str) -> None:
    """Append the PostgreSQL backend pid of the connection this task ran on to ``path``,
    one line each: the same pid twice is one connection used twice."""
    with connection.cursor() as cursor:
        cursor.execute("SELECT pg_backend_pid()")
        row = cursor.fetchone()
    assert row is not None
    with open(path, "a") as out:
        out.write(f"{row[0]}\n")
