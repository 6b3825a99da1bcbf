"""A Celery worker keeps its PostgreSQL connections from task to task, and replaces
the ones PostgreSQL dropped without being restarted.

Celery's Django fixup closes a task's database connections when it ends; with Django's
pool that hands the connection back to the pool (a thread-pool worker: settings'
``CELERY_WORKER_POOL``), so the next task borrows it again instead of starting a
PostgreSQL backend of its own. A real worker (tests/servers.py) runs tasks that each
write down the backend pid their connection has (tests/platform/worker_tasks.py).

When PostgreSQL ends the pooled connections (a restart), the pool finds each dead one as
it lends it and throws it away. The task that meets them first may fail, after the
pool's wait (DB_POOL_TIMEOUT_S), as a request would be answered 503; its next tick runs
it again. The tasks after it run on new connections.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from iouv.celery import app
from tests.servers import celery_worker_process, postgres_terminate

pytestmark = [pytest.mark.postgres, pytest.mark.redis, pytest.mark.django_db(transaction=True)]

#: Tasks per batch: far more than the connections a worker should open for them.
TASKS = 30
#: The worker's concurrency (tests/servers.py): each task it runs at once holds one
#: connection; psycopg's pool may open one more while it grows to meet them, and after
#: PostgreSQL dropped its connections one more again, refilling while a task waits (a
#: run saw 4 after the drop). Far below one per task either way.
MOST_CONNECTIONS = 2 + 2


def _pids(path: Path) -> list[int]:
    return [int(line) for line in path.read_text().split()] if path.exists() else []


def _pids_once(path: Path, count: int, *, within: float) -> list[int] | None:
    """The pids in ``path`` once it has ``count`` of them; None after ``within`` s."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        if len(pids := _pids(path)) >= count:
            return pids
        time.sleep(0.1)
    return None


def _run_batch(path: Path) -> list[int]:
    """Queue :data:`TASKS` tasks recording into ``path``; their backend pids, once all ran."""
    path.unlink(missing_ok=True)
    for _ in range(TASKS):
        app.send_task("tests.record_backend_pid", args=[str(path)])
    pids = _pids_once(path, TASKS, within=60)
    assert pids is not None, f"the worker did not run {TASKS} tasks within 60 s"
    return pids


def _until_a_task_runs(path: Path, *, tries: int = 5) -> None:
    """Queue one task at a time until one runs (the first may meet the dead connections
    and fail): the worker is working again."""
    path.unlink(missing_ok=True)
    for _ in range(tries):
        app.send_task("tests.record_backend_pid", args=[str(path)])
        # A task waits at most the pool's 1 s for a connection, then runs or fails.
        if _pids_once(path, 1, within=3.0):
            return
    raise AssertionError(f"the worker ran none of {tries} tasks")


def _terminate(pids: set[int]) -> int:
    """End these backends from outside, as a PostgreSQL restart or an idle timeout would."""
    return postgres_terminate("pid = ANY(%s)", [list(pids)])


def test_a_worker_running_many_tasks_opens_few_connections_and_replaces_dropped_ones(
    tmp_path: Path,
) -> None:
    pids = tmp_path / "pids"
    with celery_worker_process(extra_args=["--include", "tests.platform.worker_tasks"]) as worker:
        first = _run_batch(pids)
        assert len(set(first)) <= MOST_CONNECTIONS, (
            f"{TASKS} tasks used {len(set(first))} connections",
            worker.output(),
        )

        assert _terminate(set(first)) >= 1
        _until_a_task_runs(pids)
        second = _run_batch(pids)
        assert not set(second) & set(first)
        assert len(set(second)) <= MOST_CONNECTIONS, worker.output()
