"""Group messages on the channel layer, sent after the current transaction commits.

Everything the platform pushes (tasks to agents, session and fleet feeds) goes through
:func:`group_send_after_commit`. With Redis every process reaches every consumer. In
embedded mode the in-memory layer only reaches consumers of its own process, so a Celery
worker (another process) would push into the void: there, messages are written to the
database instead (in the sender's transaction) and the ASGI process relays them to its
consumers (:func:`relay_run`). Nothing else changes between the two modes.

The table is an app's (``fleet.LayerMessage``): that app registers it here when it is
ready (:func:`relay_store_set`), so this project-level helper depends on no app's model.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
import weakref
from contextvars import ContextVar
from typing import Any, Protocol

from asgiref.sync import async_to_sync
from channels.db import database_sync_to_async
from channels.layers import get_channel_layer
from django.conf import settings
from django.db import transaction

log = logging.getLogger(__name__)

#: Set in processes that are not the ASGI server (the Celery worker and beat) when the
#: layer is in-memory: their group messages go through the database.
CROSS_PROCESS = False

#: How often the ASGI process looks for relayed messages (embedded mode only).
RELAY_POLL_S = 0.25
#: How many pushes from worker threads may wait for the ASGI server's loop.
PUSH_QUEUE_MAX = 10_000

_relay_task: asyncio.Task[None] | None = None


class RelayStore(Protocol):
    """Where a worker's group messages wait for the ASGI process (embedded mode)."""

    def put(self, group: str, message: dict[str, Any]) -> None:
        """Store one message, in the caller's transaction."""

    def take(self, limit: int) -> list[tuple[str, dict[str, Any]]]:
        """Remove and return up to ``limit`` stored messages, oldest first."""


_relay_store: RelayStore | None = None


def relay_store_set(store: RelayStore) -> None:
    """Use ``store`` for relayed messages (called by the app that owns the table)."""
    global _relay_store
    _relay_store = store


def _store() -> RelayStore:
    if _relay_store is None:
        raise RuntimeError("operations.layer: no relay store (is the fleet app installed?)")
    return _relay_store


def in_memory() -> bool:
    """True when the channel layer only reaches this process's consumers."""
    backend = str(settings.CHANNEL_LAYERS.get("default", {}).get("BACKEND", ""))
    return backend.endswith("InMemoryChannelLayer")


def group_send_after_commit(group: str, message: dict[str, Any]) -> None:
    """Send ``message`` to ``group`` once the current transaction commits (at once
    outside one); in a worker process of an embedded platform, relay it through the
    database instead, written in the same transaction."""
    if CROSS_PROCESS and in_memory():
        _store().put(group, message)
        return

    def send() -> None:
        layer = get_channel_layer()
        if layer is not None:
            _push(layer, group, message)

    # Robust: a push that fails (Redis away, its connections all in use) is logged and
    # lost like any best-effort push; it must not turn the committed change into an
    # error for the caller, nor stop the callbacks after it.
    transaction.on_commit(send, robust=True)


#: The event loop of the ASGI server handling the current connection, set by
#: :class:`ServerLoop` in the connection's context. asgiref's ``sync_to_async`` runs
#: synchronous code (a view, a consumer's database work) in a thread with a copy of
#: the caller's context, so that code sees it too; a Celery worker or a command never
#: does.
_server_loop_var: ContextVar[asyncio.AbstractEventLoop | None] = ContextVar(
    "iouv_server_loop", default=None
)


class ServerLoop:
    """ASGI middleware: marks each connection's context with the server's event loop,
    so that pushes from its worker threads are handed to that loop (:func:`_push`)."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: Any, receive: Any, send: Any) -> Any:
        # Each connection runs in a task of its own, with a context of its own: the
        # mark stays with this connection.
        _server_loop_var.set(asyncio.get_running_loop())
        return await self.app(scope, receive, send)


def _server_loop() -> asyncio.AbstractEventLoop | None:
    """The ASGI server's event loop when this code runs for one of its connections."""
    return _server_loop_var.get()


def _push(layer: Any, group: str, message: dict[str, Any]) -> None:
    """``layer.group_send`` from synchronous code.

    In a worker thread of the ASGI server (an HTTP request's view, a consumer's
    database work) the push is handed to the server's loop and the thread goes on at
    once: the loop sends its pushes one after the other, in the order they came
    (:class:`_Pushes`). The thread used to wait for each send, a hop to the loop and
    back and two Redis round trips, three to four times per request, behind a loop
    busy with a thousand agents' frames. A push to a loop that has stopped (a
    server shutting down, while a closing uplink's database work is still in a
    thread) is dropped with a line. Elsewhere (a Celery worker, a command)
    ``async_to_sync`` runs the send on a loop of its own and returns when it is done.
    """
    loop = _server_loop()
    if loop is None:
        async_to_sync(layer.group_send)(group, message)
        return
    if not loop.is_running():
        log.info("layer: push to %s dropped, the server is stopping", group)
        return
    try:
        loop.call_soon_threadsafe(_Pushes.of(loop).put, layer, group, message)
    except RuntimeError:  # the loop closed since the check above
        log.info("layer: push to %s dropped, the server is stopping", group)


class _Pushes:
    """The pushes a server's worker threads handed to its loop, sent in order by one
    task. Bounded: when the loop cannot keep up for long (thousands of agents
    connecting at once), the pushes over :data:`PUSH_QUEUE_MAX` are dropped, one
    warning line per second at most; each is best effort, as every push is."""

    _by_loop: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, _Pushes] = (
        weakref.WeakKeyDictionary()
    )

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.waiting: collections.deque[tuple[Any, str, dict[str, Any]]] = collections.deque()
        self.sender: asyncio.Task[None] | None = None
        self.dropped = 0
        self.warned_at = 0.0

    @classmethod
    def of(cls, loop: asyncio.AbstractEventLoop) -> _Pushes:
        """The queue of ``loop`` (made on first use; a thread may race to make it, and
        the loser's queue is simply not kept)."""
        found = cls._by_loop.get(loop)
        if found is None:
            found = cls._by_loop.setdefault(loop, cls(loop))
        return found

    def put(self, layer: Any, group: str, message: dict[str, Any]) -> None:
        """On the loop: queue one push and make sure the sender runs."""
        if len(self.waiting) >= PUSH_QUEUE_MAX:
            self.dropped += 1
            now = time.monotonic()
            if now - self.warned_at >= 1.0:
                log.warning(
                    "layer: push to %s dropped, %d pushes already wait for the server "
                    "(%d dropped since the last line)",
                    group,
                    len(self.waiting),
                    self.dropped,
                )
                self.warned_at, self.dropped = now, 0
            return
        self.waiting.append((layer, group, message))
        if self.sender is None or self.sender.done():
            self.sender = self.loop.create_task(self._send_all())

    async def _send_all(self) -> None:
        while self.waiting:
            layer, group, message = self.waiting.popleft()
            try:
                await layer.group_send(group, message)
            except Exception:  # Redis away: this push is lost, the next ones are tried
                log.warning("layer: push to %s failed", group, exc_info=True)


def _take_relayed(limit: int = 200) -> list[tuple[str, dict[str, Any]]]:
    return _store().take(limit)


async def relay_run() -> None:
    """Deliver relayed messages to this process's consumers, forever."""
    layer = get_channel_layer()
    if layer is None:  # no channel layer configured: nobody to deliver to
        return
    take = database_sync_to_async(_take_relayed)
    while True:
        try:
            for group, message in await take():
                await layer.group_send(group, message)
        except asyncio.CancelledError:
            raise
        except Exception:  # a database hiccup must not end the relay
            log.exception("layer relay: delivery failed, retrying")
        await asyncio.sleep(RELAY_POLL_S)


def relay_ensure() -> None:
    """Start the relay in this (ASGI) process if the platform needs one; idempotent.

    Called when consumers connect: the first browser or agent starts it.
    """
    global _relay_task
    if not (settings.IOUV_LAYER_RELAY and in_memory()):
        return
    if _relay_task is not None and not _relay_task.done():
        return
    _relay_task = asyncio.get_running_loop().create_task(relay_run(), name="layer-relay")
