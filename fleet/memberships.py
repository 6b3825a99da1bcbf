"""Channel-layer group memberships that last exactly as long as the consumer holding them.

channels_redis keeps a group's members in Redis, each with the time it was added, and
drops members older than its ``group_expiry`` (a day by default); a Redis restart, or a
fail-over to a replica that lacks the data, drops them all at once. Either way a
consumer that is still connected stops receiving what is sent to its groups: an
agent's uplink stops getting relayed commands and WebRTC signalling, a monitor's feed
stops moving. The consumer itself notices nothing.

So a consumer joins its groups through :func:`group_hold` and leaves them through
:func:`group_release`, and each process keeps one :class:`Memberships` per event loop
that adds every held membership again

* when Redis comes back as another server (its ``run_id`` changed: a restart or a
  fail-over), checked every :data:`CHECK_S`, and after Redis could not be reached;
* every :data:`REFRESH_S` in any case, well within the layer's ``group_expiry``
  (settings: three times that), so a member held for days never expires while one left
  behind by a process that died (``kill -9``) ages out in minutes.

Only the public channel-layer API is used (``group_add``); without Redis (the
in-memory layer of the embedded demo) there is nothing to watch and joining is all.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import time
import weakref
from typing import Any

import redis.asyncio as aioredis
from channels.layers import get_channel_layer
from django.conf import settings

log = logging.getLogger(__name__)

#: How often each process asks Redis who it is (one round trip a process).
CHECK_S = 1.0
#: How often every held membership is added again whatever happens (about: each one is
#: spread over ±20 % of this, so a process's refreshes do not come in one burst).
REFRESH_S = 60.0


class Memberships:
    """The memberships the consumers of one event loop hold; see the module docstring."""

    def __init__(self) -> None:
        #: (group, channel) -> when it is due to be added again (monotonic).
        self.held: dict[tuple[str, str], float] = {}
        #: The run_id of the Redis server last answering, and whether it has not
        #: answered since (its memberships must be assumed gone).
        self.server: str | None = None
        self.lost = False
        self.rejoined = 0
        self._task: asyncio.Task[None] | None = None
        self._client: Any = None

    async def hold(self, group: str, channel: str) -> None:
        """Join ``group`` now and keep ``channel`` in it until :meth:`release`. A join
        that fails (Redis away) is not raised: it is made again on the next check."""
        self.held[(group, channel)] = _next_refresh()
        self._ensure_running()
        if not await _add(group, channel) and (group, channel) in self.held:
            self.held[(group, channel)] = 0.0  # due at the next check

    async def release(self, group: str, channel: str) -> None:
        """Leave ``group`` (best effort: a membership left behind ages out)."""
        self.held.pop((group, channel), None)
        layer = get_channel_layer()
        if layer is None:
            return
        try:
            await layer.group_discard(group, channel)
        except Exception as exc:
            log.warning("leaving %s failed: %s", group, exc)

    def _ensure_running(self) -> None:
        if self._task is None and settings.REDIS_URL:
            self._task = asyncio.get_running_loop().create_task(
                self._run(), name="channel-memberships"
            )

    async def _run(self) -> None:
        while True:
            try:
                await self.check_once()
            except Exception:  # the watch must outlive any one failure
                log.exception("channel memberships: check failed")
            await asyncio.sleep(CHECK_S)

    async def check_once(self) -> None:
        """Add every membership again if Redis is another server than last time (or
        was unreachable), else those due for their refresh."""
        if self._client is None:
            self._client = aioredis.Redis.from_url(
                settings.REDIS_URL, socket_timeout=CHECK_S, socket_connect_timeout=CHECK_S
            )
        try:
            info = await self._client.info("server")
            server = str(info.get("run_id"))
        except Exception as exc:
            if not self.lost:
                log.warning("channel memberships: Redis unreachable (%s)", exc)
            self.lost = True
            return
        now = time.monotonic()
        # The first answer only says who Redis is: the memberships were just added.
        changed = self.lost or (self.server is not None and server != self.server)
        self.lost = False
        if self.server is None:
            self.server = server
        if changed:
            if self.held:
                log.warning(
                    "channel memberships: Redis is %s now; joining %d group(s) again",
                    server[:8],
                    len(self.held),
                )
            self.server = server
            due = list(self.held)
        else:
            due = [key for key, at in self.held.items() if at <= now]
        for group, channel in due:
            if (group, channel) not in self.held:
                continue  # released while an earlier add was awaited
            if await _add(group, channel):
                self.held[(group, channel)] = _next_refresh()
                self.rejoined += 1
            else:
                self.held[(group, channel)] = 0.0  # again at the next check

    async def close(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if self._client is not None:
            with contextlib.suppress(Exception):
                await self._client.aclose()


def _next_refresh() -> float:
    return time.monotonic() + REFRESH_S * random.uniform(0.8, 1.2)


async def _add(group: str, channel: str) -> bool:
    """``group_add``, logged and not raised on failure; True when it was added."""
    layer = get_channel_layer()
    if layer is None:
        return False
    try:
        await layer.group_add(group, channel)
    except Exception as exc:
        log.warning("joining %s failed: %s", group, exc)
        return False
    return True


_per_loop: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Memberships] = (
    weakref.WeakKeyDictionary()
)


def memberships() -> Memberships:
    """This event loop's :class:`Memberships` (made on first use)."""
    loop = asyncio.get_running_loop()
    found = _per_loop.get(loop)
    if found is None:
        found = _per_loop[loop] = Memberships()
    return found


async def group_hold(group: str, channel: str) -> None:
    """Join ``group`` with ``channel`` and stay in it, across Redis restarts and past
    the layer's group expiry, until :func:`group_release`."""
    await memberships().hold(group, channel)


async def group_release(group: str, channel: str) -> None:
    """Leave ``group`` for good."""
    await memberships().release(group, channel)
