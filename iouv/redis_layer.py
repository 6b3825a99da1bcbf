"""The Redis channel layer, with a connection pool that waits when it is full.

channels_redis builds a plain ``redis.asyncio.ConnectionPool``, which raises
``MaxConnectionsError`` the moment every connection is in use. A burst larger than the
pool (a thousand agents reconnecting at once after a proxy restart: each leaves its
group, joins it again and is welcomed, and the platform pushes what it saved for them)
then fails frames at random and the agents must reconnect again. Here the pool is
redis-py's ``BlockingConnectionPool``: a caller waits for a free connection, up to the
host's ``timeout`` seconds (set in settings; redis-py's default is 20), and the burst
is served in turn.

And a consumer waiting for its next message outlives a Redis outage: channels_redis
raises the lost connection out of ``receive``, which ends the consumer and closes its
WebSocket, so every agent uplink and browser socket of the process dropped with Redis,
and agents reconnecting during the outage were refused. Here the wait goes on (and
simply receives nothing) until Redis is back. What the platform owes the agents does
not wait for Redis at all (fleet.outbox).
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

from channels.exceptions import ChannelFull
from channels_redis.core import RedisChannelLayer
from redis.asyncio import BlockingConnectionPool
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import TimeoutError as RedisTimeoutError

log = logging.getLogger(__name__)

# channels_redis's send as one script: KEYS[1] the channel's key; ARGV the message,
# the capacity, the expiry cut-off, the score (now) and the key's expiry in seconds.
_SEND_LUA = """
redis.call('ZREMRANGEBYSCORE', KEYS[1], 0, ARGV[3])
if redis.call('ZCOUNT', KEYS[1], '-inf', '+inf') >= tonumber(ARGV[2]) then
    return 1
end
redis.call('ZADD', KEYS[1], ARGV[4], ARGV[1])
redis.call('EXPIRE', KEYS[1], ARGV[5])
return 0
"""

#: How long a receiver waits before trying a Redis that did not answer again.
RECEIVE_RETRY_S = 0.5


class WaitingRedisChannelLayer(RedisChannelLayer):  # type: ignore[misc]
    """``RedisChannelLayer`` whose pools wait for a connection instead of raising, and
    whose receivers wait through a Redis outage instead of failing.

    Only hosts given as ``{"address": url, ...}`` change; the other keys of the host
    (``max_connections``, ``socket_timeout``, ``timeout`` for the wait) go to the pool.
    """

    _outage_since = 0.0

    async def _brpop_with_clean(
        self,
        index: int,
        channel: str,
        timeout: int,  # noqa: ASYNC109 - the parent's signature
    ) -> Any:
        # channels_redis's receive_single calls this in a loop until it returns a
        # message; None means "nothing yet", so an unreachable Redis becomes a wait.
        try:
            result = await super()._brpop_with_clean(index, channel, timeout)
        except (RedisConnectionError, RedisTimeoutError, OSError) as exc:
            now = time.monotonic()
            if not self._outage_since:
                log.warning("channel layer: Redis unreachable (%s); receivers wait", exc)
                self._outage_since = now
            await asyncio.sleep(RECEIVE_RETRY_S)
            return None
        if self._outage_since:
            log.warning(
                "channel layer: Redis back after %.1f s", time.monotonic() - self._outage_since
            )
            self._outage_since = 0.0
        return result

    async def send(self, channel: str, message: dict[str, Any]) -> None:
        """Send ``message`` to one channel in one round trip to Redis.

        channels_redis makes four (drop expired messages, count, add, set the expiry),
        one after the other, so a send to a known channel cost as much as a group send.
        The relay sends every relayed command and answer to a known channel; here the
        same four steps run as one script, with the same capacity rule (ChannelFull).
        """
        assert isinstance(message, dict), "message is not a dict"
        assert self.require_valid_channel_name(channel), "Channel name not valid"
        assert "__asgi_channel__" not in message
        name = channel
        if "!" in channel:  # process-local: the full name travels in the message
            message = {**message, "__asgi_channel__": channel}
            name = self.non_local_name(channel)
            index = self.consistent_hash(channel)
        else:
            index = next(self._send_index_generator)
        now = time.time()
        full = await self.connection(index).eval(
            _SEND_LUA,
            1,
            self.prefix + name,
            self.serialize(message),
            self.get_capacity(channel),
            int(now) - int(self.expiry),
            now,
            int(self.expiry),
        )
        if full:
            raise ChannelFull(channel)

    def create_pool(self, index: int) -> Any:
        host = dict(self.hosts[index])
        if "address" not in host:
            return super().create_pool(index)
        address = host.pop("address")
        return BlockingConnectionPool.from_url(address, **host)
