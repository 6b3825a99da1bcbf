"""The Redis channel layer, with a connection pool that waits when it is full.

channels_redis builds a plain ``redis.asyncio.ConnectionPool``, which raises
``MaxConnectionsError`` the moment every connection is in use. A burst larger than the
pool (a thousand agents reconnecting at once after a proxy restart: each leaves its
group, joins it again and is welcomed, and the platform pushes what it saved for them)
then fails frames at random and the agents must reconnect again. Here the pool is
redis-py's ``BlockingConnectionPool``: a caller waits for a free connection, up to the
host's ``timeout`` seconds (set in settings; redis-py's default is 20), and the burst
is served in turn.
"""

from __future__ import annotations

from typing import Any

from channels_redis.core import RedisChannelLayer
from redis.asyncio import BlockingConnectionPool


class WaitingRedisChannelLayer(RedisChannelLayer):  # type: ignore[misc]
    """``RedisChannelLayer`` whose pools wait for a connection instead of raising.

    Only hosts given as ``{"address": url, ...}`` change; the other keys of the host
    (``max_connections``, ``socket_timeout``, ``timeout`` for the wait) go to the pool.
    """

    def create_pool(self, index: int) -> Any:
        host = dict(self.hosts[index])
        if "address" not in host:
            return super().create_pool(index)
        address = host.pop("address")
        return BlockingConnectionPool.from_url(address, **host)
