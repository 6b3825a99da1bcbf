"""The Redis channel layer as the settings configure it (channels_redis's own layer): a
consumer waiting on it outlives a Redis restart, and a reconnect storm larger than
redis-py's default pool loses nothing. On a private redis-server that the tests
restart: the shared one must stay up for everyone else."""

from __future__ import annotations

import asyncio
import copy
import uuid
from collections.abc import AsyncIterator, Iterator
from typing import Any

import pytest
from channels_redis.core import RedisChannelLayer
from django.conf import settings

from tests.servers import RedisServer, redis_server_process

pytestmark = pytest.mark.redis

#: More consumers than redis-py's pool allows by default (100 connections).
AGENTS = 300


@pytest.fixture
def private_redis() -> Iterator[RedisServer]:
    with redis_server_process() as server:
        yield server


@pytest.fixture
async def layer(private_redis: RedisServer) -> AsyncIterator[RedisChannelLayer]:
    """A layer configured as settings.CHANNEL_LAYERS configures one for Redis, on the
    private server, with a prefix of its own."""
    config = copy.deepcopy(_redis_layer_config())
    config["hosts"][0]["address"] = private_redis.url
    config["prefix"] = f"test-{uuid.uuid4().hex[:8]}"
    layer = RedisChannelLayer(**config)
    try:
        yield layer
    finally:
        await layer.flush()


def _redis_layer_config() -> dict[str, Any]:
    """The CONFIG of the Redis layer in settings (the tests run with REDIS_URL set)."""
    default = settings.CHANNEL_LAYERS["default"]
    if default["BACKEND"] != "channels_redis.core.RedisChannelLayer":
        pytest.skip("needs the platform's Redis channel layer (REDIS_URL)")
    config: dict[str, Any] = default["CONFIG"]
    return config


async def test_a_waiting_consumer_receives_what_is_sent_after_redis_restarted(
    layer: RedisChannelLayer, private_redis: RedisServer
) -> None:
    channel = await layer.new_channel()
    await layer.send(channel, {"type": "relay.test", "n": 1})
    assert (await asyncio.wait_for(layer.receive(channel), 5))["n"] == 1

    waiting = asyncio.ensure_future(layer.receive(channel))
    await asyncio.sleep(0.2)  # in its blocking pop on Redis
    private_redis.kill()
    await asyncio.sleep(1.0)
    assert not waiting.done(), "the receive failed with Redis: its consumer would have ended"
    private_redis.start()
    await layer.send(channel, {"type": "relay.test", "n": 2})
    assert (await asyncio.wait_for(waiting, 5))["n"] == 2


async def test_a_reconnect_storm_beyond_redis_pys_default_pool_loses_nothing(
    layer: RedisChannelLayer,
) -> None:
    """Many consumers join their groups at once, each is sent a message on its group,
    and each gets it."""
    channels = [await layer.new_channel() for _ in range(AGENTS)]
    await asyncio.gather(
        *(layer.group_add(f"vehicle-{i}", name) for i, name in enumerate(channels))
    )
    await asyncio.gather(
        *(layer.group_send(f"vehicle-{i}", {"type": "welcome", "n": i}) for i in range(AGENTS))
    )
    got = await asyncio.wait_for(
        asyncio.gather(*(layer.receive(name) for name in channels)), timeout=30
    )
    assert sorted(m["n"] for m in got) == list(range(AGENTS))
