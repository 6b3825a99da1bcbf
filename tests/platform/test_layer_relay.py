"""Embedded mode: a worker process's pushes reach the ASGI process's consumers."""

from __future__ import annotations

import asyncio

import pytest
from channels.layers import get_channel_layer
from django.test import override_settings

from fleet.models import LayerMessage
from iouv import layer

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


@override_settings(CHANNEL_LAYERS=IN_MEMORY)
def test_a_push_while_the_server_stops_is_dropped_instead_of_holding_the_thread() -> None:
    # A server shutting down stops its loop while a closing uplink's database work is
    # still in a thread: its push must give up, or the process waits for ever to exit.
    import threading

    from asgiref.sync import SyncToAsync

    stopped = asyncio.new_event_loop()  # the server's loop, no longer running
    done = threading.Event()

    def consumer_thread() -> None:
        SyncToAsync.threadlocal.main_event_loop = stopped
        SyncToAsync.threadlocal.main_event_loop_pid = __import__("os").getpid()
        layer._push(get_channel_layer(), "feed-x", {"type": "feed.update"})
        done.set()

    thread = threading.Thread(target=consumer_thread, daemon=True)
    thread.start()
    thread.join(timeout=30)
    stopped.close()
    assert done.is_set(), "the push held its thread after the server's loop stopped"


@override_settings(CHANNEL_LAYERS=IN_MEMORY)
@pytest.mark.django_db(transaction=True)  # the consumer's thread reads the connection
def test_a_push_the_busy_server_cannot_take_in_time_is_dropped_with_one_line(
    monkeypatch, caplog
) -> None:
    # Thousands of agents connecting at once kept the server's loop busy past the
    # push's wait: the committed change stands, the push is given up with a warning.
    import threading

    from asgiref.sync import SyncToAsync

    monkeypatch.setattr(layer, "PUSH_TIMEOUT_S", 0.3)
    busy = asyncio.new_event_loop()
    release = threading.Event()
    server = threading.Thread(target=busy.run_forever, daemon=True)
    server.start()
    busy.call_soon_threadsafe(release.wait, 30)  # the loop is stuck in a long callback
    errors: list[BaseException] = []

    def consumer_thread() -> None:
        SyncToAsync.threadlocal.main_event_loop = busy
        SyncToAsync.threadlocal.main_event_loop_pid = __import__("os").getpid()
        try:
            # Outside a transaction: sent at once, in this (the consumer's) thread.
            layer.group_send_after_commit("feed-x", {"type": "feed.update"})
        except BaseException as exc:  # reported below
            errors.append(exc)

    try:
        with caplog.at_level("WARNING", logger="iouv.layer"):
            thread = threading.Thread(target=consumer_thread, daemon=True)
            thread.start()
            thread.join(timeout=30)
    finally:
        release.set()
        busy.call_soon_threadsafe(busy.stop)
        server.join(timeout=10)
        busy.close()
    assert not thread.is_alive() and not errors, errors
    (record,) = [r for r in caplog.records if r.name == "iouv.layer"]
    assert record.levelname == "WARNING" and "feed-x" in record.getMessage()
    assert record.exc_info is None
