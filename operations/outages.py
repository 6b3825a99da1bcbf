"""What a client is told while PostgreSQL cannot be reached: 503 with ``Retry-After``.

A request whose view cannot get a database connection fails within the pool's wait
(``DB_POOL_TIMEOUT_S``, a second: settings) with Django's ``OperationalError`` (Django's
backend re-raises psycopg_pool's ``PoolTimeout``, a psycopg ``OperationalError``, as its
own); ``InterfaceError`` is a connection that broke under it. Either is an outage of the
database, not a fault of the request: the client gets 503 and ``Retry-After:
IOUV_RETRY_AFTER_S``, JSON under ``/api/`` (the API's error envelope, code
``database_unavailable``) and a short page elsewhere, and the log gets one line, not a
traceback per request. Nothing has to restart when PostgreSQL is back: the pool connects
again by itself (settings: ``reconnect_timeout``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from django.conf import settings
from django.db import InterfaceError, OperationalError
from django.http import HttpRequest, HttpResponse, JsonResponse
from django.utils.cache import add_never_cache_headers

log = logging.getLogger(__name__)

#: The exceptions that mean "the database is away", not "this request is wrong".
DATABASE_UNAVAILABLE = (OperationalError, InterfaceError)

MESSAGE = "the platform's database cannot be reached right now; try again shortly"


def database_unavailable_response(request: HttpRequest) -> HttpResponse:
    """503 with ``Retry-After``, never cached: the API's JSON envelope under ``/api/``,
    plain text elsewhere (no template: rendering one may itself need the database)."""
    response: HttpResponse
    if request.path.startswith("/api/"):
        response = JsonResponse(
            {"error": {"code": "database_unavailable", "message": MESSAGE}}, status=503
        )
    else:
        response = HttpResponse(
            f"Service unavailable: {MESSAGE}.\n", status=503, content_type="text/plain"
        )
    response["Retry-After"] = str(settings.IOUV_RETRY_AFTER_S)
    add_never_cache_headers(response)
    return response


class DatabaseUnavailableLogFilter(logging.Filter):
    """A log record of an error that is the database being away keeps its line and the
    error's words, not its traceback (``LOGGING``'s console handler): during an outage
    every request, report and timer meets the same error, and a traceback each would
    bury the log; the traceback says nothing the words do not."""

    def filter(self, record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        if isinstance(error, DATABASE_UNAVAILABLE):
            record.msg = f"{record.getMessage()} [{type(error).__name__}: {error}]"
            record.args = None
            record.exc_info = None
            record.exc_text = None
        return True


class DatabaseUnavailableMiddleware:
    """Answers a view that raised one of :data:`DATABASE_UNAVAILABLE` with
    :func:`database_unavailable_response` (the API answers its own views the same way,
    services.web.api_kit)."""

    def __init__(self, get_response: Callable[[HttpRequest], HttpResponse]) -> None:
        self.get_response = get_response

    def __call__(self, request: HttpRequest) -> HttpResponse:
        return self.get_response(request)

    def process_exception(self, request: HttpRequest, exception: Exception) -> HttpResponse | None:
        if not isinstance(exception, DATABASE_UNAVAILABLE):
            return None
        log.warning("database unavailable: %s %s: %s", request.method, request.path, exception)
        return database_unavailable_response(request)
