"""What every WebSocket consumer of the platform shares."""

from __future__ import annotations

import logging
from typing import Any

from asgiref.typing import ASGIReceiveCallable, ASGISendCallable, ASGISendEvent
from channels.consumer import AsyncConsumer, get_handler_name

log = logging.getLogger(__name__)


class DirectDispatch(AsyncConsumer):
    """Dispatch each message straight to its handler, and drop a send to a socket that
    is gone.

    Channels (4.2 and later) first runs ``close_old_connections`` on the process's one
    thread for synchronous database work, for every message of every consumer: a
    heartbeat, a relayed command, its answer. All of them then queue behind whatever
    that thread is doing for anyone else (a session's supervision, a hello, a slow
    lock), and a relayed command waited seconds for its answer under load. Our
    consumers touch the database only through ``database_sync_to_async``, which closes
    stale connections around each call itself, so the extra hop buys nothing here.

    A send to a socket whose client has just gone raises under uvicorn
    (``ClientDisconnected``, an ``OSError``) where daphne drops it. Raised in a
    handler, it would end the consumer there, before the server's disconnect message
    is handled: ``disconnect`` would never run, and what it does would never happen
    (the relay telling the agent its controller left, an uplink marked closed, a feed
    leaving its groups). The send is dropped instead, as daphne does; the disconnect
    that the server has already queued comes next.

    Put it first among the bases: ``class C(DirectDispatch, AsyncWebsocketConsumer)``.
    """

    async def __call__(
        self, scope: Any, receive: ASGIReceiveCallable, send: ASGISendCallable
    ) -> None:
        async def send_while_connected(message: ASGISendEvent) -> None:
            try:
                await send(message)
            except OSError as exc:
                log.debug("dropped %s to a socket that is gone: %r", message["type"], exc)

        await super().__call__(scope, receive, send_while_connected)

    async def dispatch(self, message: dict[str, Any]) -> None:
        handler = getattr(self, get_handler_name(message), None)
        if handler is None:
            raise ValueError(f"No handler for message type {message['type']}")
        await handler(message)
