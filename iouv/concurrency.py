"""How many HTTP requests a platform process handles at once.

Each request's view runs on a thread (one per request at a time; iouv.handler keeps
them for the next requests). Those threads and the event loop, which carries every
WebSocket (the agents' uplinks, the relay, the live feeds), share one interpreter lock.
With eight busy API clients the loop got an eighth of it: a process holding a thousand
agents fell behind their heartbeats, and a relayed command waited 1.8 s for its answer
(median).

Since a request's middleware and view run in one go on its thread (iouv.handler), a
request thread gives the interpreter back only when it waits (for the database, say)
or when the loop has waited for it a switch interval (IOUV_SWITCH_INTERVAL_MS). Every
further request thread is one more the loop waits behind, and adds no processor: the
lock lets one thread run at a time. ``python -m benchmarks.scale --phases one`` (1,000
agents, eight API clients, a relayed command every 100 ms) measured, on one 2-core
machine, the relayed round trip p50 / p95 and the sessions per second:

=========================  ======================  ==============
requests at once           relayed round trip      sessions per s
=========================  ======================  ==============
4 (switch interval 5 ms)   64 / 122, 84 / 156 ms   9.7, 7.9
2 (5 ms)                   26 / 56 ms              9.9
1 (5 ms)                   10 / 27 ms              8.8
1 (1 ms)                   8.4 / 20 ms             10.3
=========================  ======================  ==============

The sessions per second are the same within this machine's spread (runs of one setting
differ by a fifth); the relay is not. Hence one request at a time and a 1 ms interval
by default. A deployment whose views wait on slow services would raise the limit.

Those runs were under daphne. Under uvicorn (iouv.serve), with the clients paced at 30
sessions per second (``--api-rate 30``), one request at a time kept 27.2 sessions/s with
the process at 87 % of its core, waiting on the database between a request's
statements; two kept the pace, 30.0, and the relayed round trip went from 4.2 / 8.6 to
7.8 / 17 ms (docs/benchmarks/scale/report.md, "The server"). The default stays one:
the relay's margin is the platform's promise, a session more per second is not. Most of
that wait was the process standing still for a full garbage collection: since those are
out of the way and a request takes one trip to a kept thread (iouv.collector,
iouv.handler), one request at a time keeps 30 sessions/s, request p50 / p95 11.6 / 25 ms,
relayed round trip 2.3 / 6.1 ms, the process at 74 % of its core (the same report, "Full
collections out of the way").
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
