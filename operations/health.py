"""Health checks for load balancers, orchestrators and operators, answered within a second.

* ``/healthz`` (liveness): 200 as long as the process answers at all, whatever is down
  around it. Restarting a platform process cures nothing while PostgreSQL or Redis is
  away, so a liveness probe must not fail for that.
* ``/readyz`` (readiness): 200 when the process can serve (its database and, with
  ``REDIS_URL``, Redis answer), else 503: a proxy or orchestrator sends it no traffic.

Both say what they found, the same way: ``{"ok", "live", "ready", "checks": {"database":
{"ok", "ms" | "error"}, "redis": {...}}}``. Each check has :data:`CHECK_WITHIN_S` to
answer, run beside the request on a thread of its own, so a database that does not
answer (the pool waits ``DB_POOL_TIMEOUT_S`` for a connection) makes the check say
"no answer", not the request wait; a check still waiting from an earlier request is not
started again, and its last error is what is said meanwhile.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Any

import redis
from django.conf import settings
from django.db import connection
from django.http import HttpRequest, JsonResponse
from django.utils.cache import add_never_cache_headers

#: How long each check may take before it counts as down.
CHECK_WITHIN_S = 0.5


def _database() -> None:
    try:
        with connection.cursor() as cursor:
            cursor.execute("SELECT 1")
    finally:
        connection.close()  # back to the pool (or closed): the thread keeps nothing


_redis_client: redis.Redis | None = None


def _redis() -> None:
    global _redis_client
    if _redis_client is None:
        _redis_client = redis.Redis.from_url(
            settings.REDIS_URL,
            socket_timeout=CHECK_WITHIN_S,
            socket_connect_timeout=CHECK_WITHIN_S,
        )
    _redis_client.ping()


class _Check:
    """One dependency's check, run on a thread of its own with a deadline."""

    def __init__(self, name: str, probe: Callable[[], None]) -> None:
        self.name = name
        self.probe = probe
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"iouv-health-{name}")
        self._running: Future[None] | None = None
        self._last_error = ""
        self._lock = threading.Lock()

    def run(self) -> dict[str, Any]:
        started = time.monotonic()
        with self._lock:
            if self._running is None or self._running.done():
                self._running = self._thread.submit(self.probe)
            running = self._running
        try:
            running.result(timeout=CHECK_WITHIN_S)
        except FutureTimeout:
            waited = f"no answer within {CHECK_WITHIN_S:g} s"
            return {
                "ok": False,
                "error": f"{waited} ({self._last_error})" if self._last_error else waited,
            }
        except Exception as exc:  # what the server said, for the operator
            self._last_error = f"{type(exc).__name__}: {exc}".strip()[:300]
            return {"ok": False, "error": self._last_error}
        self._last_error = ""
        return {"ok": True, "ms": round((time.monotonic() - started) * 1000, 1)}


_checks: dict[str, _Check] = {}


def _checks_run() -> dict[str, dict[str, Any]]:
    wanted = {"database": _database, **({"redis": _redis} if settings.REDIS_URL else {})}
    for name, probe in wanted.items():
        _checks.setdefault(name, _Check(name, probe))
    return {name: _checks[name].run() for name in wanted}


def _answer(*, readiness: bool) -> JsonResponse:
    checks = _checks_run()
    ready = all(check["ok"] for check in checks.values())
    status = 503 if readiness and not ready else 200
    response = JsonResponse(
        {"ok": ready if readiness else True, "live": True, "ready": ready, "checks": checks},
        status=status,
    )
    if status == 503:
        response["Retry-After"] = str(settings.IOUV_RETRY_AFTER_S)
    add_never_cache_headers(response)
    return response


def healthz(request: HttpRequest) -> JsonResponse:
    """Liveness: 200 while the process answers; ``checks`` say what is down."""
    return _answer(readiness=False)


def readyz(request: HttpRequest) -> JsonResponse:
    """Readiness: 200 when every check passed, else 503 naming what failed."""
    return _answer(readiness=True)
