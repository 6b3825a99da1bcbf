"""Group memberships held for as long as their consumer lives (fleet.memberships), on
a private redis-server that the tests restart: the shared one must stay up for everyone
else."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
import redis
from channels.layers import get_channel_layer

from fleet.memberships import Memberships
from tests.servers import redis_server_process

pytestmark = pytest.mark.redis


@pytest.fixture
def private_redis(settings: Any) -> Any:
    """A redis-server of this test's own, as the platform's Redis (channel layer
    included: channels resets its layers when the setting changes)."""
    with redis_server_process() as server:
        settings.REDIS_URL = server.url
        settings.CHANNEL_LAYERS = {
            "default": {
                "BACKEND": "channels_redis.core.RedisChannelLayer",
                "CONFIG": {"hosts": [server.url], "group_expiry": 180},
            }
        }
        yield server


async def group_send(layer: Any, group: str, message: dict[str, Any]) -> None:
    """``layer.group_send``, again while it finds pooled connections that a Redis
    restart closed (channels_redis raises once for each, then reconnects)."""
    for _ in range(5):
        try:
            await layer.group_send(group, message)
            return
        except redis.exceptions.ConnectionError:
            continue
    await layer.group_send(group, message)


async def checked_until_answered(memberships: Memberships) -> None:
    """Check as a process does every CHECK_S, until Redis answers and every membership
    was added again (the first check or add after a restart may find its pooled
    connection closed, as the layer's sends do: the next one reconnects)."""
    for _ in range(5):
        await memberships.check_once()
        if not memberships.lost and all(due > 0 for due in memberships.held.values()):
            return
    raise AssertionError("the memberships were not added again")


async def delivered(layer: Any, channel: str, within: float = 1.0) -> dict[str, Any] | None:
    """The next message on ``channel``, or None when none comes ``within`` seconds."""
    try:
        return await asyncio.wait_for(layer.receive(channel), within)
    except TimeoutError:
        return None


async def test_a_held_membership_is_back_once_redis_restarted(private_redis: Any) -> None:
    layer = get_channel_layer()
    channel = await layer.new_channel()
    memberships = Memberships()
    await memberships.hold("vehicle-1", channel)
    await memberships.check_once()  # learns which Redis server it talks to
    await group_send(layer, "vehicle-1", {"type": "relay.test", "n": 1})
    assert (await delivered(layer, channel))["n"] == 1

    private_redis.kill()  # it keeps nothing on disk: every group is gone
    await memberships.check_once()  # unreachable: nothing to do but notice
    private_redis.start()
    await group_send(layer, "vehicle-1", {"type": "relay.test", "n": 2})
    assert await delivered(layer, channel, within=0.3) is None  # lost with Redis

    await checked_until_answered(memberships)
    await group_send(layer, "vehicle-1", {"type": "relay.test", "n": 3})
    assert (await delivered(layer, channel))["n"] == 3
    assert memberships.rejoined == 1
    await memberships.close()


async def test_a_released_membership_is_not_joined_again(private_redis: Any) -> None:
    layer = get_channel_layer()
    kept, left = await layer.new_channel(), await layer.new_channel()
    memberships = Memberships()
    await memberships.hold("feed", kept)
    await memberships.hold("feed", left)
    await memberships.check_once()
    await memberships.release("feed", left)
    private_redis.kill()
    private_redis.start()
    await checked_until_answered(memberships)
    await group_send(layer, "feed", {"type": "feed.test"})
    assert await delivered(layer, kept) is not None
    assert await delivered(layer, left, within=0.3) is None
    await memberships.close()


async def test_memberships_are_refreshed_before_the_group_expiry(
    private_redis: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every membership is added again about every REFRESH_S, so channels_redis never
    expires a member whose consumer still lives."""
    layer = get_channel_layer()
    channel = await layer.new_channel()
    memberships = Memberships()
    await memberships.hold("vehicle-2", channel)
    await memberships.check_once()
    assert memberships.rejoined == 0
    # Due now: as if REFRESH_S had passed.
    memberships.held = dict.fromkeys(memberships.held, 0.0)
    await memberships.check_once()
    assert memberships.rejoined == 1
    assert all(due > 0 for due in memberships.held.values())
    await memberships.close()
