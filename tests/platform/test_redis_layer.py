"""The Redis channel layer serves a burst larger than its connection pool."""

from __future__ import annotations

import asyncio
import os
import uuid

import pytest
from channels.exceptions import ChannelFull
from channels_redis.core import RedisChannelLayer
from redis.exceptions import MaxConnectionsError

from iouv.redis_layer import WaitingRedisChannelLayer

REDIS_URL = os.environ.get("REDIS_URL", "")
pytestmark = pytest.mark.skipif(not REDIS_URL, reason="needs the machine's Redis (REDIS_URL)")

AGENTS = 60


async def _reconnect_storm(layer: RedisChannelLayer) -> list[dict]:
    """Many consumers join their groups at once, then each is sent a message."""
    channels = [await layer.new_channel() for _ in range(AGENTS)]
    await asyncio.gather(
        *(layer.group_add(f"vehicle-{i}", name) for i, name in enumerate(channels))
    )
    await asyncio.gather(
        *(layer.group_send(f"vehicle-{i}", {"type": "welcome", "n": i}) for i in range(AGENTS))
    )
    got = await asyncio.wait_for(
        asyncio.gather(*(layer.receive(name) for name in channels)), timeout=20
    )
    await asyncio.gather(
        *(layer.group_discard(f"vehicle-{i}", name) for i, name in enumerate(channels))
    )
    return got


def _layer(cls: type[RedisChannelLayer], prefix: str) -> RedisChannelLayer:
    host = {"address": REDIS_URL, "max_connections": 3, "timeout": 10}
    return cls(hosts=[host], prefix=prefix)


@pytest.mark.asyncio
async def test_a_burst_beyond_the_pool_waits_for_connections_and_loses_nothing() -> None:
    layer = _layer(WaitingRedisChannelLayer, f"test-{uuid.uuid4().hex[:8]}")
    try:
        got = await _reconnect_storm(layer)
    finally:
        await layer.flush()
        await layer.close_pools()
    assert sorted(m["n"] for m in got) == list(range(AGENTS))


@pytest.mark.asyncio
async def test_channels_redis_own_pool_fails_the_same_burst() -> None:
    """The reason for the layer above: the stock pool raises when it is full."""
    prefix = f"test-{uuid.uuid4().hex[:8]}"
    layer = _layer(RedisChannelLayer, prefix)
    layer.hosts[0].pop("timeout")  # the stock pool has no wait
    try:
        with pytest.raises(MaxConnectionsError):
            await _reconnect_storm(layer)
    finally:
        await layer.close_pools()
        # The failed burst's other calls may still hold the stock pool: clean up apart.
        cleaner = _layer(WaitingRedisChannelLayer, prefix)
        await cleaner.flush()
        await cleaner.close_pools()


@pytest.mark.asyncio
async def test_a_send_to_a_channel_is_one_round_trip_and_keeps_the_layers_rules() -> None:
    """Sends to process-local and general channels arrive in order; a full channel
    refuses (ChannelFull) without storing; expired messages are dropped."""
    prefix = f"test-{uuid.uuid4().hex[:8]}"
    layer = WaitingRedisChannelLayer(
        hosts=[{"address": REDIS_URL}], prefix=prefix, capacity=3, expiry=60
    )
    calls: list[str] = []
    try:
        local = await layer.new_channel()
        connection = layer.connection(layer.consistent_hash(local))
        real_execute = connection.execute_command

        async def counted(*args: object, **options: object) -> object:
            calls.append(str(args[0]))
            return await real_execute(*args, **options)

        connection.execute_command = counted
        for n in range(3):
            await layer.send(local, {"type": "relay.from_agent", "n": n})
        assert calls == ["EVAL"] * 3  # one command each, not four
        with pytest.raises(ChannelFull):
            await layer.send(local, {"type": "relay.from_agent", "n": 3})
        got = [await asyncio.wait_for(layer.receive(local), 5) for _ in range(3)]
        assert [m["n"] for m in got] == [0, 1, 2]
        assert all(m["type"] == "relay.from_agent" for m in got)

        await layer.send("general", {"type": "x", "n": 9})
        assert (await asyncio.wait_for(layer.receive("general"), 5))["n"] == 9

        # A message older than the expiry is dropped by the next send to its channel.
        key = prefix + "general"
        await connection.zadd(key, {b"stale": 1.0})
        await layer.send("general", {"type": "y", "n": 10})
        assert await connection.zcount(key, "-inf", "+inf") == 1
    finally:
        await layer.flush()
        await layer.close_pools()


@pytest.mark.asyncio
async def test_a_send_to_a_consumer_of_this_process_skips_redis() -> None:
    """While a consumer receives on its channel here, a send reaches it without a
    Redis command, as a copy, in order, and a full channel still refuses; once the
    consumer is gone (its receive cancelled) sends go through Redis again."""
    prefix = f"test-{uuid.uuid4().hex[:8]}"
    layer = WaitingRedisChannelLayer(
        hosts=[{"address": REDIS_URL}], prefix=prefix, capacity=2, expiry=60
    )
    calls: list[str] = []
    try:
        channel = await layer.new_channel()
        connection = layer.connection(layer.consistent_hash(channel))
        real_execute = connection.execute_command

        async def counted(*args: object, **options: object) -> object:
            calls.append(str(args[0]))
            return await real_execute(*args, **options)

        connection.execute_command = counted
        waiting = asyncio.ensure_future(layer.receive(channel))
        await asyncio.sleep(0)  # the consumer is in its receive
        message = {"type": "agent.send", "text": "first"}
        await layer.send(channel, message)
        got = await asyncio.wait_for(waiting, 5)
        assert got == message and got is not message
        assert not [c for c in calls if c in ("EVAL", "ZADD")]  # no send went to Redis

        await layer.send(channel, {"type": "agent.send", "text": "second"})
        await layer.send(channel, {"type": "agent.send", "text": "third"})
        with pytest.raises(ChannelFull):
            await layer.send(channel, {"type": "agent.send", "text": "fourth"})
        assert (await layer.receive(channel))["text"] == "second"
        assert (await layer.receive(channel))["text"] == "third"

        gone = asyncio.ensure_future(layer.receive(channel))
        await asyncio.sleep(0)
        gone.cancel()
        with pytest.raises(asyncio.CancelledError):
            await gone
        await layer.send(channel, {"type": "agent.send", "text": "to redis"})
        assert calls.count("EVAL") == 1
    finally:
        await layer.flush()
        await layer.close_pools()


@pytest.mark.asyncio
async def test_a_group_send_is_one_round_trip_to_nobody_and_two_to_members(caplog) -> None:
    """Every member of a group gets the message once (channels of this process and
    others alike); an expired member is dropped, a full channel is skipped and logged,
    never raised; sending to a group nobody is in costs one round trip."""
    prefix = f"test-{uuid.uuid4().hex[:8]}"
    layer = WaitingRedisChannelLayer(
        hosts=[{"address": REDIS_URL}], prefix=prefix, capacity=2, expiry=60, group_expiry=86400
    )
    try:
        connection = layer.connection(0)
        pool = connection.connection_pool
        borrowed: list[int] = []
        real_get = pool.get_connection

        async def counted(*args: object, **kwargs: object) -> object:
            borrowed.append(1)
            return await real_get(*args, **kwargs)

        pool.get_connection = counted  # each round trip borrows a pooled connection
        await layer.group_send("nobody", {"type": "feed.changed"})
        assert len(borrowed) == 1

        here, there = await layer.new_channel(), await layer.new_channel()
        for channel in (here, there, "elsewhere"):
            await layer.group_add("monitors", channel)
        # Two consumers of this process wait on their channels (one Redis key for both).
        first = [asyncio.ensure_future(layer.receive(c)) for c in (here, there)]
        await asyncio.sleep(0)
        # A member that joined longer ago than group_expiry is gone.
        await connection.zadd(layer._group_key("monitors"), {"stale!abc": 1.0})
        borrowed.clear()
        await layer.group_send("monitors", {"type": "feed.changed", "n": 1})
        assert len(borrowed) == 2
        got = [await asyncio.wait_for(waiting, 5) for waiting in first]
        got.append(await asyncio.wait_for(layer.receive("elsewhere"), 5))
        assert [m["n"] for m in got] == [1, 1, 1]
        assert "stale!abc" not in {
            m.decode() for m in await connection.zrange(layer._group_key("monitors"), 0, -1)
        }

        # "elsewhere" fills up (nobody receives on it): the rest still get theirs.
        for n in (2, 3, 4):
            await layer.group_send("monitors", {"type": "feed.changed", "n": n})
            assert (await asyncio.wait_for(layer.receive(here), 5))["n"] == n
        assert "1 of 3 channels full in group monitors" in caplog.text
        assert await connection.zcount(prefix + "elsewhere", "-inf", "+inf") == 2
    finally:
        await layer.flush()
        await layer.close_pools()
