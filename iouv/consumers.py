"""What every WebSocket consumer of the platform shares."""

from __future__ import annotations

from typing import Any

from channels.consumer import get_handler_name


class DirectDispatch:
    """Dispatch each message straight to its handler.

    Channels (4.2 and later) first runs ``close_old_connections`` on the process's one
    thread for synchronous database work, for every message of every consumer: a
    heartbeat, a relayed command, its answer. All of them then queue behind whatever
    that thread is doing for anyone else (a session's supervision, a hello, a slow
    lock), and a relayed command waited seconds for its answer under load. Our
    consumers touch the database only through ``database_sync_to_async``, which closes
    stale connections around each call itself, so the extra hop buys nothing here.

    Put it first among the bases: ``class C(DirectDispatch, AsyncWebsocketConsumer)``.
    """

    async def dispatch(self, message: dict[str, Any]) -> None:
        handler = getattr(self, get_handler_name(message), None)
        if handler is None:
            raise ValueError(f"No handler for message type {message['type']}")
        await handler(message)
