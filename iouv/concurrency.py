"""How many HTTP requests a platform process handles at once.

Django runs each request's view on a thread of its own. Those threads and the event
loop, which carries every WebSocket (the agents' uplinks, the relay, the live feeds),
share one interpreter lock. With eight busy API clients the loop got an eighth of it:
a process holding a thousand agents fell behind their heartbeats, and a relayed
command waited 1.8 s for its answer (median). With at most four requests at a time
and the rest waiting their turn on the loop, where waiting costs nothing, the same
load gave as many sessions per second and relayed commands 0.18 s. (Both measured by
``python -m benchmarks.scale``, run with ``IOUV_HTTP_CONCURRENCY=0`` and with 4.)
"""

from __future__ import annotations

import asyncio
from typing import Any

from asgiref.typing import ASGIReceiveCallable, ASGISendCallable

ASGIApp = Any  # an ASGI 3 application: await app(scope, receive, send)


class HttpConcurrencyLimit:
    """ASGI middleware: at most ``limit`` HTTP requests inside ``app`` at once.

    Requests beyond the limit wait in arrival order; nothing is refused. Other scopes
    (WebSocket, lifespan) pass straight through. ``limit`` 0 means no limit.
    """

    def __init__(self, app: ASGIApp, *, limit: int) -> None:
        if limit < 0:
            raise ValueError(f"limit must be 0 (none) or more, not {limit}")
        self.app = app
        self.limit = limit
        # Made on first use: a semaphore belongs to the loop it is first awaited in.
        self._slots: asyncio.Semaphore | None = None

    async def __call__(
        self, scope: dict[str, Any], receive: ASGIReceiveCallable, send: ASGISendCallable
    ) -> None:
        if scope["type"] != "http" or not self.limit:
            await self.app(scope, receive, send)
            return
        if self._slots is None:
            self._slots = asyncio.Semaphore(self.limit)
        async with self._slots:
            await self.app(scope, receive, send)
