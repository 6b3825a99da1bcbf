"""What every consumer shares (operations.consumers.DirectDispatch): a send to a socket whose
client has gone does not end the consumer before its disconnect runs."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from channels.generic.websocket import AsyncWebsocketConsumer
from uvicorn.protocols.utils import ClientDisconnected

from operations.consumers import DirectDispatch

# Channels' disconnect closes the database connections it finds stale on its executor's
# thread (close_old_connections); a connection an earlier test left there is checked,
# which is database access.
pytestmark = pytest.mark.django_db


class _Answering(AsyncWebsocketConsumer):
    """Answers every frame twice; records what its disconnect saw."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.disconnected: list[int] = []
        self.answered = 0

    async def receive(self, text_data: str | None = None, bytes_data: bytes | None = None) -> None:
        await self.send(text_data="first")
        await self.send(text_data="second")
        self.answered += 1

    async def disconnect(self, code: int) -> None:
        self.disconnected.append(code)


class _Platforms(DirectDispatch, _Answering):
    pass


@pytest.fixture(autouse=True)
def _in_memory_layer(settings: Any) -> None:
    # The consumers only need a channel name; Redis would keep each test 5 s longer.
    settings.CHANNEL_LAYERS = {"default": {"BACKEND": "channels.layers.InMemoryChannelLayer"}}


async def _serve_a_client_who_leaves(consumer: Any) -> list[str]:
    """Run ``consumer`` as uvicorn would for a client that sends one frame and is gone
    before the answer: the server has queued the disconnect, and each send raises
    ClientDisconnected. Returns the types the consumer sent before the first answer."""
    incoming: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
    for message in (
        {"type": "websocket.connect"},
        {"type": "websocket.receive", "text": "hello"},
        {"type": "websocket.disconnect", "code": 1006},
    ):
        incoming.put_nowait(message)
    sent: list[str] = []

    async def send(message: dict[str, Any]) -> None:
        if message["type"] == "websocket.send":
            raise ClientDisconnected()
        sent.append(message["type"])

    scope = {"type": "websocket", "path": "/ws/x/", "headers": [], "subprotocols": []}
    await asyncio.wait_for(consumer(scope, incoming.get, send), 10)
    return sent


async def test_a_send_to_a_client_who_left_is_dropped_and_the_disconnect_runs() -> None:
    consumer = _Platforms()
    assert await _serve_a_client_who_leaves(consumer) == ["websocket.accept"]
    # The handler went on past the sends, and the disconnect ran with the server's code.
    assert consumer.answered == 1
    assert consumer.disconnected == [1006]


async def test_without_it_the_consumer_ends_before_its_disconnect() -> None:
    # Channels' own consumer under uvicorn: what DirectDispatch guards against.
    consumer = _Answering()
    with pytest.raises(ClientDisconnected):
        await _serve_a_client_who_leaves(consumer)
    assert consumer.disconnected == []
