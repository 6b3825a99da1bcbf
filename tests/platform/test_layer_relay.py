"""Embedded mode: a worker process's pushes reach the ASGI process's consumers."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from channels.layers import get_channel_layer
from django.test import override_settings

from fleet.models import LayerMessage
from operations import layer

IN_MEMORY = {"default": {"BACKEND": "channels.layers.InMemoryChannelLayer"}}


@pytest.fixture
def worker_process(monkeypatch):
    monkeypatch.setattr(layer, "CROSS_PROCESS", True)


@override_settings(CHANNEL_LAYERS=IN_MEMORY, IOUV_LAYER_RELAY=True)
@pytest.mark.django_db(transaction=True)
async def test_a_worker_message_reaches_a_consumer_of_the_server(worker_process) -> None:
    from channels.db import database_sync_to_async

    channel_layer = get_channel_layer()
    channel = await channel_layer.new_channel()
    await channel_layer.group_add("vehicle-x", channel)
    # The worker side: the message is stored, not lost in the worker's own memory.
    await database_sync_to_async(layer.group_send_after_commit)(
        "vehicle-x", {"type": "agent.send", "text": '{"type":"end_task"}'}
    )
    assert await database_sync_to_async(LayerMessage.objects.count)() == 1
    # The server side: the relay delivers it once and forgets it.
    layer.CROSS_PROCESS = False
    relay = asyncio.create_task(layer.relay_run())
    try:
        received = await asyncio.wait_for(channel_layer.receive(channel), 5)
    finally:
        relay.cancel()
    assert received["text"] == '{"type":"end_task"}'
    assert await database_sync_to_async(LayerMessage.objects.count)() == 0


@override_settings(CHANNEL_LAYERS=IN_MEMORY)
@pytest.mark.django_db
def test_the_server_itself_sends_directly(django_capture_on_commit_callbacks) -> None:
    with django_capture_on_commit_callbacks(execute=False) as callbacks:
        layer.group_send_after_commit("fleet", {"type": "fleet.changed", "ids": []})
    assert len(callbacks) == 1 and not LayerMessage.objects.exists()


@override_settings(CHANNEL_LAYERS=IN_MEMORY)
async def test_a_push_from_a_server_thread_reaches_a_consumer() -> None:
    from asgiref.sync import sync_to_async

    channel_layer = get_channel_layer()
    channel = await channel_layer.new_channel()
    await channel_layer.group_add("feed-x", channel)
    # A consumer's synchronous work (in a thread) pushes to the server's loop.
    await sync_to_async(layer._push)(channel_layer, "feed-x", {"type": "feed.update"})
    assert (await asyncio.wait_for(channel_layer.receive(channel), 5))["type"] == "feed.update"


async def test_a_connections_worker_threads_know_its_server_loop_and_nobody_else_does() -> None:
    from asgiref.sync import sync_to_async

    seen: list[Any] = []

    async def app(scope: Any, receive: Any, send: Any) -> None:
        # A view or a consumer's database work, in a thread of the server.
        seen.append(await sync_to_async(layer._server_loop)())

    # The server runs each connection in a task of its own.
    await asyncio.create_task(layer.ServerLoop(app)({"type": "http"}, None, None))
    assert seen == [asyncio.get_running_loop()]
    # Code outside a connection (a Celery task, a command) sends on a loop of its own.
    assert await sync_to_async(layer._server_loop)() is None


@override_settings(CHANNEL_LAYERS=IN_MEMORY)
def test_a_push_while_the_server_stops_is_dropped_instead_of_holding_the_thread() -> None:
    # A server shutting down stops its loop while a closing uplink's database work is
    # still in a thread: its push must give up, or the process waits for ever to exit.
    import threading

    stopped = asyncio.new_event_loop()  # the server's loop, no longer running
    done = threading.Event()

    def consumer_thread() -> None:
        layer._server_loop_var.set(stopped)  # as layer.ServerLoop marks a connection
        layer._push(get_channel_layer(), "feed-x", {"type": "feed.update"})
        done.set()

    thread = threading.Thread(target=consumer_thread, daemon=True)
    thread.start()
    thread.join(timeout=30)
    stopped.close()
    assert done.is_set(), "the push held its thread after the server's loop stopped"


class _BusyServer:
    """A server's loop, running in a thread of its own, that can be kept stuck in a
    long callback (as thousands of agents connecting at once keep it), and a channel
    in a group of the in-memory layer, on that loop."""

    def __init__(self) -> None:
        import threading

        self.loop = asyncio.new_event_loop()
        self.release = threading.Event()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.layer = get_channel_layer()
        self.channel = self.run(self.layer.new_channel())
        self.run(self.layer.group_add("feed-x", self.channel))

    def run(self, coroutine: Any, timeout: float = 10) -> Any:
        return asyncio.run_coroutine_threadsafe(coroutine, self.loop).result(timeout)

    def stick(self) -> None:
        self.loop.call_soon_threadsafe(self.release.wait, 30)

    def push_from_a_thread(self, count: int) -> None:
        """``count`` pushes from a worker thread of this server, which must finish."""
        import threading

        finished: list[bool] = []

        def consumer_thread() -> None:
            layer._server_loop_var.set(self.loop)  # as layer.ServerLoop marks a connection
            for i in range(count):
                # Outside a transaction: pushed at once, from this (the consumer's) thread.
                layer.group_send_after_commit("feed-x", {"type": "feed.update", "i": i})
            finished.append(True)

        thread = threading.Thread(target=consumer_thread, daemon=True)
        thread.start()
        thread.join(timeout=30)
        assert finished, "the pushing thread did not finish"

    def received(self) -> list[int]:
        out: list[int] = []
        while True:
            try:
                message = self.run(asyncio.wait_for(self.layer.receive(self.channel), 0.5))
            except TimeoutError:
                return out
            out.append(message["i"])

    def close(self) -> None:
        self.release.set()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=10)
        self.loop.close()


@override_settings(CHANNEL_LAYERS=IN_MEMORY)
@pytest.mark.django_db(transaction=True)  # the consumer's thread reads the connection
def test_a_push_to_a_busy_server_does_not_hold_its_thread_and_arrives_in_order() -> None:
    # The server's loop is stuck for as long as the test likes: the pushing thread
    # (an HTTP request's, holding the process's one request slot) goes on at once,
    # and its pushes arrive, in order, when the loop is free again.
    server = _BusyServer()
    try:
        server.stick()
        server.push_from_a_thread(5)  # returns although the loop cannot take them yet
        assert not server.release.is_set()
        server.release.set()
        assert server.received() == [0, 1, 2, 3, 4]
    finally:
        server.close()


@override_settings(CHANNEL_LAYERS=IN_MEMORY)
@pytest.mark.django_db(transaction=True)
def test_pushes_past_what_may_wait_for_the_server_are_dropped_with_one_line(
    monkeypatch, caplog
) -> None:
    monkeypatch.setattr(layer, "PUSH_QUEUE_MAX", 3)
    server = _BusyServer()
    try:
        server.stick()
        with caplog.at_level("WARNING", logger="operations.layer"):
            server.push_from_a_thread(6)
            server.release.set()
            assert server.received() == [0, 1, 2]  # the first ones, in order
    finally:
        server.close()
    (record,) = [r for r in caplog.records if r.name == "operations.layer"]
    assert record.levelname == "WARNING" and "feed-x" in record.getMessage()
    assert record.exc_info is None
