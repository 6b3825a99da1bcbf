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
import contextlib
import logging
import time
from typing import Any

from channels.exceptions import ChannelFull
from channels_redis.core import RedisChannelLayer
from redis.asyncio import BlockingConnectionPool
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import ResponseError
from redis.exceptions import TimeoutError as RedisTimeoutError

log = logging.getLogger(__name__)

# channels_redis's send, to one channel or to each member of a group once the group's
# members are read, as one script: KEYS the channels' keys; ARGV each key's message,
# then each key's capacity, then the expiry cut-off, the score (now) and the keys'
# expiry in seconds. Returns how many channels were full (their message not stored).
_SEND_LUA = """
local n = #KEYS
local full = 0
for i = 1, n do
    redis.call('ZREMRANGEBYSCORE', KEYS[i], 0, ARGV[2 * n + 1])
    if redis.call('ZCOUNT', KEYS[i], '-inf', '+inf') < tonumber(ARGV[n + i]) then
        redis.call('ZADD', KEYS[i], ARGV[2 * n + 2], ARGV[i])
        redis.call('EXPIRE', KEYS[i], ARGV[2 * n + 3])
    else
        full = full + 1
    end
end
return full
"""

#: How long a receiver waits before trying a Redis that did not answer again.
RECEIVE_RETRY_S = 0.5
#: The most messages the pump takes from Redis in one round trip.
PUMP_BATCH = 100


class WaitingRedisChannelLayer(RedisChannelLayer):  # type: ignore[misc]
    """``RedisChannelLayer`` whose pools wait for a connection instead of raising, and
    whose receivers wait through a Redis outage instead of failing.

    Only hosts given as ``{"address": url, ...}`` change; the other keys of the host
    (``max_connections``, ``socket_timeout``, ``timeout`` for the wait) go to the pool.
    """

    _outage_since = 0.0

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        #: This process's channels with a consumer receiving on them, and its loop.
        self._receivers: dict[str, asyncio.AbstractEventLoop] = {}
        self._pump: asyncio.Task[None] | None = None

    async def receive(self, channel: str) -> Any:
        """The next message of ``channel``.

        Process-local channels (a consumer's own) are served by one task per process,
        the pump, which pops the process's messages from Redis in batches and hands
        each to its channel's buffer; a consumer only waits on its buffer. channels_redis
        has every waiting consumer take turns at one blocking pop and costs four Redis
        commands per message (a clean-up script, the pop, a backup copy and its
        removal); the backup only protects a pop cancelled halfway, which the pump is
        not. And since the buffers are in this process, :meth:`send` fills the buffer
        of a consumer that lives here directly, without Redis.

        The channel is known to have a consumer here until that consumer ends, which it
        does by cancelling its pending receive. The pump lives as long as its loop.
        """
        if "!" not in channel:
            return await super().receive(channel)
        assert self.require_valid_channel_name(channel)
        loop = asyncio.get_running_loop()
        self._receivers[channel] = loop
        self._pump_ensure(loop)
        try:
            return await self.receive_buffer[channel].get()
        except asyncio.CancelledError:
            self._receivers.pop(channel, None)
            self.receive_buffer.pop(channel, None)
            raise

    async def close_pools(self) -> None:
        """Stop the pump, then close the connections (channels_redis's)."""
        pump, self._pump = self._pump, None
        if pump is not None and not pump.done():
            pump.cancel()
            if pump.get_loop() is asyncio.get_running_loop():
                with contextlib.suppress(asyncio.CancelledError):
                    await pump
        await super().close_pools()

    def _pump_ensure(self, loop: asyncio.AbstractEventLoop) -> None:
        pump = self._pump
        if pump is not None and not pump.done():
            other = pump.get_loop()
            if other is loop:
                return
            if other.is_running():
                raise RuntimeError("Two event loops are trying to receive() on one channel layer")
        # The first receive, or the pump's loop has ended (a server restarted in the
        # same process, one loop per test): what was registered on it is gone with it.
        for channel, registered in list(self._receivers.items()):
            if registered is not loop:
                del self._receivers[channel]
                self.receive_buffer.pop(channel, None)
        self._pump = loop.create_task(self._pump_run(), name="channel-layer-pump")

    async def _pump_run(self) -> None:
        """Hand every message of this process's channels to its channel's buffer."""
        local = self.non_local_name(await self.new_channel())
        key, index = self.prefix + local, self.consistent_hash(local)
        batch_max, timeout = PUMP_BATCH, self.brpop_timeout
        task = asyncio.current_task()
        assert task is not None
        while True:
            try:
                members = await self._pop_batch(index, key, batch_max, timeout)
            except (RedisConnectionError, RedisTimeoutError, OSError) as exc:
                if task.cancelling():
                    # redis-py reports a read cut short by the cancellation as a lost
                    # connection: the pump is being stopped, not facing an outage.
                    raise asyncio.CancelledError from exc
                now = time.monotonic()
                if not self._outage_since:
                    log.warning("channel layer: Redis unreachable (%s); receivers wait", exc)
                    self._outage_since = now
                await asyncio.sleep(RECEIVE_RETRY_S)
                continue
            if self._outage_since:
                log.warning(
                    "channel layer: Redis back after %.1f s",
                    time.monotonic() - self._outage_since,
                )
                self._outage_since = 0.0
            for member in members:
                try:
                    message = self.deserialize(member)
                    channel = message.pop("__asgi_channel__", None)
                except Exception as exc:  # not a message of ours: dropped, the rest go on
                    log.error("channel layer: dropping an unreadable message: %s", exc)
                    continue
                for name in channel if isinstance(channel, list) else [channel]:
                    if name in self._receivers:  # else its consumer is gone: dropped
                        self.receive_buffer[name].put_nowait(dict(message))
            if task.cancelling():
                # A cancellation redis-py absorbed (it may, in a blocking read): the
                # pump is being stopped all the same, once what it took is handed on.
                raise asyncio.CancelledError

    _bzmpop = True  # Redis 7's BZMPOP; older servers: BZPOPMIN, then ZPOPMIN

    async def _pop_batch(self, index: int, key: str, count: int, wait_s: float) -> list[bytes]:
        """Up to ``count`` messages of ``key``, waiting up to ``wait_s`` for the first
        (then an empty list): one round trip."""
        connection = self.connection(index)
        if self._bzmpop:
            try:
                result = await connection.bzmpop(wait_s, 1, [key], min=True, count=count)
            except ResponseError:
                type(self)._bzmpop = False
            else:
                return [] if result is None else [member for member, _score in result[1]]
        popped = await connection.bzpopmin(key, timeout=wait_s)
        if popped is None:
            return []
        rest = await connection.zpopmin(key, count - 1)
        return [popped[1], *(member for member, _score in rest)]

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
        """Send ``message`` to one channel: straight to its consumer when that runs in
        this process, else in one round trip to Redis.

        channels_redis makes four (drop expired messages, count, add, set the expiry),
        one after the other, so a send to a known channel cost as much as a group send.
        The relay sends every relayed command and answer to a known channel; here the
        same four steps run as one script, with the same capacity rule (ChannelFull).
        """
        assert isinstance(message, dict), "message is not a dict"
        assert self.require_valid_channel_name(channel), "Channel name not valid"
        assert "__asgi_channel__" not in message
        if self._receivers.get(channel) is asyncio.get_running_loop():
            # Its consumer runs in this process, on this loop: Redis has nothing to add
            # but two round trips and two (de)serialisations (a relayed command and its
            # answer when the browser and the agent reach the same process). A copy, as
            # serialisation would give; full is full, as in Redis.
            buffer = self.receive_buffer[channel]
            if buffer.qsize() >= self.get_capacity(channel):
                raise ChannelFull(channel)
            buffer.put_nowait(dict(message))
            return
        name = channel
        if "!" in channel:  # process-local: the full name travels in the message
            message = {**message, "__asgi_channel__": channel}
            name = self.non_local_name(channel)
            index = self.consistent_hash(name)  # where the process reads: by its name
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

    async def group_send(self, group: str, message: dict[str, Any]) -> None:
        """Send ``message`` to every channel in ``group``: one round trip to Redis when
        the group has no member, two when it has.

        channels_redis makes two to read the members (drop the expired ones, then list
        them) and two more to send (drop expired messages, then a script), one after
        the other. The platform pushes a dozen times or more per session to feeds that
        often have nobody listening (monitors, the session's page), so the empty case
        is most of them. The same rules hold: expired members and messages are dropped,
        a full channel is skipped and counted in the log line, never raised.
        """
        assert self.require_valid_group_name(group), "Group name not valid"
        key = self._group_key(group)
        connection = self.connection(self.consistent_hash(group))
        async with connection.pipeline(transaction=False) as pipe:
            pipe.zremrangebyscore(key, min=0, max=int(time.time()) - self.group_expiry)
            pipe.zrange(key, 0, -1)
            _, members = await pipe.execute()
        if not members:
            return
        channel_names = [member.decode("utf8") for member in members]
        by_connection, messages, capacities = self._map_channel_keys_to_connection(
            channel_names, message
        )
        for index, keys in by_connection.items():
            now = time.time()
            full = await self.connection(index).eval(
                _SEND_LUA,
                len(keys),
                *keys,
                *(messages[k] for k in keys),
                *(capacities[k] for k in keys),
                int(now) - int(self.expiry),
                now,
                int(self.expiry),
            )
            if full:
                log.info(
                    "channel layer: %s of %s channels full in group %s",
                    full,
                    len(channel_names),
                    group,
                )

    def create_pool(self, index: int) -> Any:
        host = dict(self.hosts[index])
        if "address" not in host:
            return super().create_pool(index)
        address = host.pop("address")
        return BlockingConnectionPool.from_url(address, **host)
