"""Liveness: when each vehicle's agent was last heard from, and what it last said of its
battery and position, kept apart from the vehicle's row.

A heartbeat says "still here" and little else. Written to the database, each one was a
row update and a commit, about 1.2 ms of a platform process's CPU: a thousand agents
heartbeating every two seconds took more than half a core. With Redis (``REDIS_URL``,
production) a heartbeat is one entry in a batch of Redis writes instead: every vehicle's
last-heard time in a sorted set and its latest battery and position in a hash. The
vehicle's row changes only on a state change (online or offline, a new status, a
battery or position step, see ``fleet.uplink``), and its ``last_seen`` is the time of
that change; the sweep (``fleet.status.vehicles_mark_stale_offline``) reads the sorted
set to find silent vehicles, and the monitor's live view reads the hash.

Without Redis (the embedded demo: SQLite, a handful of vehicles, a Celery worker in
another process) the database is the only store every process shares: heartbeats are
written to the rows as before, and the reads below read the rows.

Reads take the row's value for a vehicle Redis does not know (never heard since Redis
started, or a test that set the row by hand), and for all of them while Redis cannot
be reached: the uplinks then write every heartbeat to the rows.
"""

from __future__ import annotations

import asyncio
import logging
import weakref
from collections.abc import Callable, Iterable, Sequence
from datetime import UTC, datetime, timedelta
from typing import Any

import msgspec
import redis
import redis.asyncio as aioredis
from django.conf import settings
from django.utils import timezone

from fleet.models import Vehicle

log = logging.getLogger(__name__)


class Live(msgspec.Struct, array_like=True, frozen=True):
    """What the platform last heard from one vehicle's agent. ``None``: not known
    (no battery reading, no position fix)."""

    seen: float  # Unix time, seconds
    battery: float | None = None
    lat: float | None = None
    lon: float | None = None
    alt: float | None = None

    @property
    def seen_at(self) -> datetime:
        return datetime.fromtimestamp(self.seen, tz=UTC)

    @property
    def position(self) -> tuple[float, float] | None:
        if self.lat is None or self.lon is None:
            return None
        return (self.lat, self.lon)

    @classmethod
    def of_vehicle(cls, vehicle: Vehicle) -> Live | None:
        """What ``vehicle``'s row says (None if it was never heard from)."""
        if vehicle.last_seen is None:
            return None
        return cls(
            vehicle.last_seen.timestamp(), vehicle.battery, vehicle.lat, vehicle.lon, vehicle.alt
        )


_encode = msgspec.json.Encoder().encode
_decode = msgspec.json.Decoder(Live).decode


def in_redis() -> bool:
    """True when liveness lives in Redis (``REDIS_URL`` set), else in the rows."""
    return bool(settings.REDIS_URL)


def _keys() -> tuple[str, str]:
    """The sorted set of last-heard times and the hash of latest reports."""
    prefix = settings.IOUV_LIVENESS_PREFIX
    return f"{prefix}:seen", f"{prefix}:state"


def online_cutoff(now: datetime | None = None) -> datetime:
    """Vehicles last heard from before this instant count as offline."""
    return (now or timezone.now()) - timedelta(seconds=settings.IOUV_OFFLINE_AFTER_S)


# -- reads (synchronous: Django views, Celery tasks, database_sync_to_async) ------------

_sync_clients: dict[str, redis.Redis] = {}


def _client() -> redis.Redis:
    url = str(settings.REDIS_URL)
    client = _sync_clients.get(url)
    if client is None:
        client = _sync_clients[url] = redis.Redis.from_url(
            url, socket_timeout=5, socket_connect_timeout=5
        )
    return client


def _from_redis(read: Callable[[redis.Redis], list[Any]], count: int) -> list[Any]:
    """``read``'s answer (one entry per id), or ``None`` for each while Redis cannot be
    reached: the uplinks then write their heartbeats to the rows (fleet.uplink), so the
    rows are what is known."""
    if not in_redis():
        return [None] * count
    try:
        return read(_client())
    except redis.RedisError as exc:
        log.warning("liveness: Redis unreachable (%s); reading the rows", exc)
        return [None] * count


def vehicles_live(ids: Iterable[Any]) -> dict[str, Live]:
    """The latest report of each of ``ids`` (vehicles never heard from are left out)."""
    keys = [str(pk) for pk in ids]
    if not keys:
        return {}
    _, state = _keys()
    reports = _from_redis(lambda client: client.hmget(state, keys), len(keys))
    found = {pk: _decode(raw) for pk, raw in zip(keys, reports, strict=True) if raw is not None}
    missing = [pk for pk in keys if pk not in found]
    if missing:
        for vehicle in Vehicle.objects.filter(pk__in=missing, last_seen__isnull=False).only(
            "id", "last_seen", "battery", "lat", "lon", "alt"
        ):
            live = Live.of_vehicle(vehicle)
            if live is not None:
                found[str(vehicle.pk)] = live
    return found


def vehicles_seen(ids: Iterable[Any]) -> dict[str, datetime]:
    """When each of ``ids`` was last heard from (vehicles never heard from are left out)."""
    keys = [str(pk) for pk in ids]
    if not keys:
        return {}
    seen, _ = _keys()
    scores = _from_redis(lambda client: client.zmscore(seen, keys), len(keys))
    found = {
        pk: datetime.fromtimestamp(score, tz=UTC)
        for pk, score in zip(keys, scores, strict=True)
        if score is not None
    }
    missing = [pk for pk in keys if pk not in found]
    if missing:
        rows = Vehicle.objects.filter(pk__in=missing, last_seen__isnull=False)
        for vehicle_id, at in rows.values_list("pk", "last_seen"):
            if at is not None:
                found[str(vehicle_id)] = at
    return found


def vehicles_fresh(ids: Iterable[Any], now: datetime | None = None) -> set[str]:
    """Those of ``ids`` heard from within ``IOUV_OFFLINE_AFTER_S`` of ``now``."""
    cutoff = online_cutoff(now)
    return {pk for pk, seen in vehicles_seen(ids).items() if seen >= cutoff}


# -- writes (the uplinks' event loop) ---------------------------------------------------


class LivenessWriter:
    """Writes the heartbeats of every uplink of this process to Redis, many per round trip.

    :meth:`put` only notes the report (the latest per vehicle wins) and returns: an
    uplink never waits for Redis. One task writes what was noted: what arrives while a
    write is in flight goes with the next one, so a lone heartbeat is written at once
    and under load each write carries more (a batch is two commands in one pipeline,
    whatever its size). If Redis refuses a batch, each of its reports' ``lost``
    callback is called: the uplinks then write their next heartbeat to the row.
    """

    #: The most vehicles in one pipeline.
    BATCH_MAX = 2000

    def __init__(self) -> None:
        self._pending: dict[str, tuple[Live, Callable[[], None] | None]] = {}
        self._flusher: asyncio.Task[None] | None = None
        self._redis: aioredis.Redis | None = None

    def _connection(self) -> aioredis.Redis:
        if self._redis is None:
            self._redis = aioredis.Redis.from_url(
                str(settings.REDIS_URL), socket_timeout=5, socket_connect_timeout=5
            )
        return self._redis

    def put(self, vehicle_id: str, live: Live, lost: Callable[[], None] | None = None) -> None:
        """Note ``live`` for writing; ``lost`` is called if Redis does not take it."""
        self._pending[vehicle_id] = (live, lost)
        if self._flusher is None or self._flusher.done():
            self._flusher = asyncio.get_running_loop().create_task(
                self._flush(), name="liveness-writer"
            )

    async def drain(self) -> None:
        """Return once everything noted so far has been written (or refused)."""
        while self._flusher is not None and not self._flusher.done():
            await asyncio.shield(self._flusher)

    async def _flush(self) -> None:
        while self._pending:
            ids = list(self._pending)[: self.BATCH_MAX]
            batch = [(pk, *self._pending.pop(pk)) for pk in ids]
            try:
                await self._store([(pk, live) for pk, live, _ in batch])
            except Exception as exc:
                log.warning("liveness: writing %d heartbeats failed: %s", len(batch), exc)
                for _pk, _live, lost in batch:
                    if lost is not None:
                        lost()

    async def _store(self, batch: Sequence[tuple[str, Live]]) -> None:
        seen, state = _keys()
        pipe = self._connection().pipeline(transaction=False)
        pipe.zadd(seen, {pk: live.seen for pk, live in batch})
        pipe.hset(state, mapping={pk: _encode(live) for pk, live in batch})
        await pipe.execute()

    async def close(self) -> None:
        """Write what is noted, then close the connection."""
        await self.drain()
        if self._redis is not None:
            await self._redis.aclose()
            self._redis = None


_writers: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, LivenessWriter] = (
    weakref.WeakKeyDictionary()
)


def liveness_writer() -> LivenessWriter:
    """This event loop's writer (a server process runs one loop; tests run many)."""
    loop = asyncio.get_running_loop()
    writer = _writers.get(loop)
    if writer is None:
        writer = _writers[loop] = LivenessWriter()
    return writer
