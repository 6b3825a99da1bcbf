"""The platform processes that serve agent uplinks, and what their absence excuses.

A vehicle is judged by its silence: offline after ``IOUV_OFFLINE_AFTER_S`` without a
word, lost to its session after ``IOUV_VEHICLE_LOST_S`` more. But an agent can only
speak to a platform process that is there. When the process holding its uplink is
killed, stopped for a deploy or cut off, every vehicle it served goes silent at once,
and the supervisor's timers (Celery beat, in another process that stays up) would end
sessions that go on perfectly well point-to-point. The platform's own absence is never
read as a vehicle's:

* every process that serves uplinks is an :class:`~fleet.models.UplinkServer` row that it
  writes ``alive_at`` to every ``IOUV_UPLINK_SERVER_BEAT_S`` while it runs
  (:func:`uplink_server_ensure`, called by each uplink as it connects), and each
  vehicle's row names the process that holds its uplink (``Vehicle.uplink_server``);
* a process vouches for a vehicle's silence only while it beats: once it stops, the
  silence counts no further than its last beat (plus one period);
* after it stopped, the vehicle is given ``IOUV_AGENT_RECONNECT_S`` (the agents'
  longest reconnect backoff) to come back through a process that is there, counted
  from when some process was there again: the platform may have been away entirely.

:func:`vehicles_silence` applies both to a set of vehicles; the offline sweep
(fleet.status) and the lost-vehicle rule (services.supervision.reports) judge by it.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import uuid
import weakref
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from channels.db import database_sync_to_async
from django.conf import settings
from django.utils import timezone

from fleet.models import UplinkServer

log = logging.getLogger(__name__)

#: Rows of processes gone longer than this are deleted by the beat of a live one.
FORGET_AFTER = timedelta(days=1)


@dataclass
class _Process:
    """This process's identity as an uplink server (a fork gets a new one)."""

    pid: int
    id: uuid.UUID
    started_at: datetime


_process: _Process | None = None


def uplink_server_id() -> uuid.UUID:
    """The id of this process as an uplink server (made on first use, anew after a
    fork: a Celery or server worker forked from a parent is a process of its own)."""
    global _process
    if _process is None or _process.pid != os.getpid():
        _process = _Process(os.getpid(), uuid.uuid4(), timezone.now())
    return _process.id


def _register(now: datetime | None = None) -> None:
    """Write this process's row (alive now), and forget processes gone for a day."""
    server_id = uplink_server_id()
    assert _process is not None
    now = now or timezone.now()
    if not UplinkServer.objects.filter(pk=server_id).update(alive_at=now):
        UplinkServer.objects.create(
            pk=server_id,
            started_at=_process.started_at,
            alive_at=now,
            name=f"{socket.gethostname()}:{os.getpid()}"[:120],
        )
        UplinkServer.objects.filter(alive_at__lt=now - FORGET_AFTER).delete()


def _beat() -> bool:
    """Say this process is alive; False when its row is gone (deleted by someone: the
    process then stops beating, and registers again with its next uplink)."""
    return bool(UplinkServer.objects.filter(pk=uplink_server_id()).update(alive_at=timezone.now()))


async def _beat_forever() -> None:
    period = float(settings.IOUV_UPLINK_SERVER_BEAT_S)
    beat = database_sync_to_async(_beat)
    while True:
        await asyncio.sleep(period)
        try:
            if not await beat():
                log.warning("uplink server %s: its row is gone; beating stops", uplink_server_id())
                return
        except Exception as exc:  # the database away: the process then looks gone
            log.warning("uplink server beat failed: %s", exc)


_beats: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, asyncio.Task[None]] = (
    weakref.WeakKeyDictionary()
)


async def uplink_server_ensure() -> uuid.UUID:
    """Make sure this process beats as an uplink server (the first call writes its row
    before it returns, so a vehicle is never held by a process the table lacks);
    returns its id."""
    loop = asyncio.get_running_loop()
    task = _beats.get(loop)
    if task is None or task.done():
        await database_sync_to_async(_register)()
        _beats[loop] = loop.create_task(_beat_forever(), name="uplink-server-beat")
    return uplink_server_id()


def _stopped() -> None:
    """Mark this process gone now: its last beat a period back."""
    beat = timedelta(seconds=float(settings.IOUV_UPLINK_SERVER_BEAT_S))
    UplinkServer.objects.filter(pk=uplink_server_id()).update(
        alive_at=timezone.now() - beat - timedelta(milliseconds=1)
    )


async def uplink_server_stopping() -> None:
    """This process is shutting down (its server closes the uplinks with 1012): it
    stops vouching for its vehicles at once, so their silence is the platform's while
    they reconnect to another process, however long the shutdown takes. Idempotent."""
    task = _beats.pop(asyncio.get_running_loop(), None)
    if task is None:
        return
    task.cancel()
    try:
        await database_sync_to_async(_stopped)()
    except Exception as exc:
        log.warning("uplink server %s: could not record its stop: %s", uplink_server_id(), exc)


# --------------------------------------------------------------------------------------
# Judging silence
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Availability:
    """The uplink servers as the platform's timers see them at ``now``."""

    now: datetime
    #: Each known server's last beat.
    alive_at: dict[uuid.UUID, datetime]
    #: Since when some server has been there without a break: ``now`` when none is, None
    #: when no server ever beat (the registry unused: silence is judged as it is).
    since: datetime | None
    #: ``since``, when a server had been there before it (the platform came back from
    #: an outage then); None when the platform has been there since its first server.
    back_at: datetime | None = None

    def silence(self, heard: datetime | None, server: uuid.UUID | None) -> float | None:
        """How long a vehicle last heard at ``heard``, whose uplink ``server`` held,
        has been silent by its own doing, in seconds (None: never heard from)."""
        if heard is None:
            return None
        beat = timedelta(seconds=float(settings.IOUV_UPLINK_SERVER_BEAT_S))
        grace = timedelta(seconds=float(settings.IOUV_AGENT_RECONNECT_S))
        last_beat = self.alive_at.get(server) if server is not None else None
        if last_beat is not None and last_beat + beat < self.now:
            # Its server is gone: the silence it witnessed, then what follows the
            # agent's grace to reconnect, from when a server was there again.
            gone = last_beat + beat
            witnessed = max(timedelta(0), gone - heard)
            back = max(self.since or self.now, gone) + grace
            return (witnessed + max(timedelta(0), self.now - back)).total_seconds()
        start = heard
        if self.back_at is not None and self.back_at > heard:
            # Heard before the platform was last away entirely (its server unknown):
            # counted from the end of the grace after the platform came back.
            start = self.back_at + grace
        return max(0.0, (self.now - start).total_seconds())


def availability(now: datetime | None = None) -> Availability:
    """Read the uplink servers' beats (one query)."""
    now = now or timezone.now()
    beat = timedelta(seconds=float(settings.IOUV_UPLINK_SERVER_BEAT_S))
    rows = list(
        UplinkServer.objects.filter(alive_at__gte=now - FORGET_AFTER).values_list(
            "pk", "started_at", "alive_at"
        )
    )
    if not rows:
        return Availability(now=now, alive_at={}, since=None)
    # The servers' spans, [start, last beat + one period], merged back from now.
    spans = sorted(((started, alive + beat) for _pk, started, alive in rows), reverse=True)
    since = now
    for start, end in spans:
        if end >= since and start < since:
            since = start
    back_at = since if any(end < since for _start, end in spans) else None
    return Availability(
        now=now, alive_at={pk: alive for pk, _s, alive in rows}, since=since, back_at=back_at
    )


def vehicles_silence(
    rows: Iterable[tuple[Any, datetime | None, uuid.UUID | None]], now: datetime | None = None
) -> dict[Any, float | None]:
    """For each ``(vehicle id, last heard, uplink server)``, how long the vehicle has
    been silent by its own doing (seconds; None: never heard), see the module
    docstring."""
    found = availability(now)
    return {pk: found.silence(heard, server) for pk, heard, server in rows}
