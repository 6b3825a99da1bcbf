"""The HTTP concurrency limit: requests beyond it wait their turn; sockets never do."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from iouv.asgi import application
from iouv.concurrency import HttpConcurrencyLimit


class SlowApp:
    """An ASGI app whose requests take ``hold`` seconds; counts how many run at once."""

    def __init__(self, hold: float = 0.05) -> None:
        self.hold = hold
        self.running = 0
        self.most = 0
        self.started: list[int] = []

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        self.running += 1
        self.most = max(self.most, self.running)
        self.started.append(scope["n"])
        try:
            await asyncio.sleep(self.hold)
            await send({"type": "done", "n": scope["n"]})
        finally:
            self.running -= 1


async def _call(app: Any, n: int, kind: str, sent: list[int]) -> None:
    async def send(message: dict[str, Any]) -> None:
        sent.append(message["n"])

    await app({"type": kind, "n": n}, None, send)


async def test_at_most_the_limit_run_at_once_and_every_request_is_answered_in_turn():
    inner = SlowApp()
    app = HttpConcurrencyLimit(inner, limit=3)
    sent: list[int] = []
    await asyncio.gather(*(_call(app, n, "http", sent) for n in range(10)))
    assert inner.most == 3
    assert sorted(sent) == list(range(10))  # nobody refused
    assert inner.started == list(range(10))  # waiting requests go in arrival order


async def test_websockets_and_an_unlimited_process_are_not_held():
    for app_limit, kind in ((2, "websocket"), (0, "http")):
        inner = SlowApp()
        sent: list[int] = []
        app = HttpConcurrencyLimit(inner, limit=app_limit)
        await asyncio.gather(*(_call(app, n, kind, sent) for n in range(6)))
        assert inner.most == 6, (app_limit, kind)


def test_a_negative_limit_is_refused():
    with pytest.raises(ValueError, match="limit"):
        HttpConcurrencyLimit(SlowApp(), limit=-1)


def test_the_platform_serves_http_through_the_limit(settings):
    # The ASGI application routes HTTP through the limit set by IOUV_HTTP_CONCURRENCY.
    http = application.application_mapping["http"]
    while not isinstance(http, HttpConcurrencyLimit):
        http = http.application  # the static files handler, when the platform serves /static/
    assert http.limit == settings.IOUV_HTTP_CONCURRENCY > 0
