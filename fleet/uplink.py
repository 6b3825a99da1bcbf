"""The agent uplink: the WebSocket every vehicle agent keeps open to the platform.

Wire protocol: docs/protocol.md ("Uplink"). The consumer trusts nothing the agent sends:
every frame goes through ``agents.protocol.parse_message`` first. It records what the
fleet needs itself (profile, heartbeats, online/offline) and hands everything about
sessions to the app that owns them through ``fleet.vehicle_events``, because ``fleet``
never imports ``services``.

Close codes the platform uses on this socket:

=====  ===============================================================
4400   ``hello`` of another protocol version (error ``bad_version``)
4401   bad credential, or anything but a valid ``hello`` first
4408   no ``hello`` within ``IOUV_HELLO_TIMEOUT_S``
4409   replaced: a newer uplink of the same vehicle took over
4401   (also) the vehicle's credential was replaced (error ``credential_revoked``)
4429   flood: too many refused frames in a short time
4500   the platform failed before authentication finished (retry)
4503   the platform is too busy to admit the ``hello`` now (error ``busy``; retry later)
=====  ===============================================================

The codes are in WebSocket's private range (4000-4999): daphne's server (autobahn),
the platform's other server, closes with nothing but 1000 or 3000-4999, so the
standard 1011 and 1013 cannot be sent; 4500 and 4503 say the same as HTTP's 500 and 503.

What the platform tells an agent (tasks, revokes, ends) is owed in the database until
the agent acknowledges it (fleet.sending.vehicle_send, fleet.outbox); relayed control
traffic travels on the channel layer to the group of the vehicle
(fleet.sending.avehicle_send), so any platform process can reach an agent connected to
another.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import time
import uuid
import weakref
from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any, Literal, TypeVar

import msgspec
from channels.db import database_sync_to_async
from channels.generic.websocket import AsyncWebsocketConsumer
from django.conf import settings
from django.db import connection, transaction
from django.utils import timezone
from msgspec import UNSET, UnsetType

from agents.geo import distance_m
from agents.protocol import (
    PROTOCOL_VERSION,
    ProtocolError,
    encode_message,
    error_message,
    parse_message,
)
from agents.protocol.messages import (
    Ack,
    Artifact,
    EndTask,
    Event,
    Hello,
    Message,
    Position,
    Profile,
    Record,
    RelayClose,
    RelayToPlatform,
    Revoke,
    Task,
    TaskAccepted,
    TaskRefused,
    UplinkToPlatform,
    Welcome,
)
from agents.protocol.messages import Heartbeat as HeartbeatMessage
from fleet.artifacts import artifact_keep
from fleet.credentials import vehicle_authenticate
from fleet.feed import fleet_notify
from fleet.liveness import Live, in_redis, liveness_writer
from fleet.memberships import group_hold, group_release
from fleet.models import Vehicle
from fleet.outbox import (
    agent_message_ack,
    outbox,
    vehicle_group,
)
from fleet.records import record_keep
from fleet.sending import relay_group
from fleet.servers import uplink_server_ensure, uplink_server_stopping
from fleet.vehicle_events import (
    agent_acked,
    agent_connected,
    agent_disconnected,
    agent_message,
    agent_welcome,
    vehicles_back,
)
from operations.consumers import DirectDispatch
from operations.layer import relay_ensure
from operations.outages import DATABASE_UNAVAILABLE

log = logging.getLogger(__name__)

T = TypeVar("T")

#: What the server closes every WebSocket with as it shuts down (RFC 6455, "service
#: restart"): received, never sent, by the uplink.
SERVER_SHUTTING_DOWN = 1012
CLOSE_BAD_VERSION = 4400
CLOSE_UNAUTHORIZED = 4401
CLOSE_HELLO_TIMEOUT = 4408
CLOSE_REPLACED = 4409
CLOSE_FLOOD = 4429
CLOSE_INTERNAL = 4500  # a server error (HTTP's 500): the agent reconnects with backoff
CLOSE_TRY_LATER = 4503  # too busy now (HTTP's 503): the agent comes back after its backoff

#: A hello that waited this long for the database is not admitted: its agent waits
#: 10 s for the welcome (agents.uplink.WELCOME_TIMEOUT_S) and has given up, or soon
#: will, so admitting it would be work for nobody (see AgentUplinkConsumer._hello).
ADMIT_WITHIN_S = 8.0

#: What :func:`_admit` says of a hello that waited too long.
BUSY: Literal["busy"] = "busy"

#: This many refused frames within BAD_FRAMES_WINDOW_S closes the uplink (4429).
BAD_FRAMES_MAX = 20
BAD_FRAMES_WINDOW_S = 10.0

# Error texts echo parts of the agent's input; keep the replies small.
_ERROR_TEXT_MAX = 300

#: Relayed browsers one uplink remembers the channel of (beyond this, the oldest are
#: answered through their group again).
RELAYS_MAX = 256

#: Frames of one uplink waiting for its database work (profile, heartbeats, reports);
#: past this the uplink stops reading until they are handled (backpressure).
BACKLOG_MAX = 64

#: While PostgreSQL cannot be reached, a report is tried again after this long, doubling
#: up to the maximum (AgentUplinkConsumer._until_stored).
DATABASE_RETRY_MIN_S = 0.5
DATABASE_RETRY_MAX_S = 4.0

# Statuses the platform owns while a vehicle serves a session or gives one up: what the
# agent says in its profile or heartbeats never overrides them (services and the
# outbox move them on).
_PLATFORM_HELD = frozenset(
    {Vehicle.Status.RESERVED, Vehicle.Status.IN_SERVICE, Vehicle.Status.RELEASING}
)


def _db(func: Callable[..., Any]) -> Callable[..., Awaitable[Any]]:
    """``func`` as a coroutine function for the uplink's database work.

    With a database server, on a pool of threads: a thousand agents reconnecting at
    once (a proxy restart) are a thousand hellos and as many disconnects, and on
    channels' one thread for synchronous calls they queued for longer than the agents
    wait for their welcome, which sent every agent round again. Each uplink still
    does its own work in order (it awaits each call). SQLite takes one writer at a
    time, so there the work stays on that one thread.
    """
    return database_sync_to_async(func, thread_sensitive=connection.vendor == "sqlite")


# --------------------------------------------------------------------------------------
# What the uplink writes
# --------------------------------------------------------------------------------------


def _status_after(
    vehicle: Vehicle,
    *,
    reported: str | None,
    registered: bool,
    new_profile: bool = False,
    running: bool = False,
) -> str:
    """The status a live agent's report leads to.

    Maintenance and the session statuses are the platform's to change. An agent in
    fail-safe is not assignable; one that is heard from again after being offline (or
    that says it is idle again after a fail-safe) is idle, but only once it has sent a
    profile, since without one nobody could control it. ``running``: the agent says
    (in its profile) it still runs a task; unless the platform holds the vehicle for
    that task, it is ``releasing`` until it confirms the end the platform sends it.
    """
    current = vehicle.status
    if vehicle.maintenance or current == Vehicle.Status.MAINTENANCE or current in _PLATFORM_HELD:
        return current
    if reported == "failsafe":
        return Vehicle.Status.FAILSAFE
    if not registered:
        return current
    if running:
        return Vehicle.Status.RELEASING
    # Still flying home or landing after its session: not assignable until it says idle.
    if reported == "returning" and current in (Vehicle.Status.IDLE, Vehicle.Status.OFFLINE):
        return Vehicle.Status.RETURNING
    if reported == "idle" and current == Vehicle.Status.RETURNING:
        return Vehicle.Status.IDLE
    if current == Vehicle.Status.OFFLINE:
        return Vehicle.Status.IDLE
    # A fresh profile means a freshly (re)started agent: its fail-safe is over.
    if current == Vehicle.Status.FAILSAFE and (new_profile or reported == "idle"):
        return Vehicle.Status.IDLE
    return current


def _set_position(vehicle: Vehicle, position: Position | None) -> None:
    if position is None:
        vehicle.lat = vehicle.lon = vehicle.alt = None
    else:
        vehicle.lat, vehicle.lon = position.lat, position.lon
        vehicle.alt = float(position.alt) if position.alt is not None else None


def _given(value: T | UnsetType) -> T | None:
    """An optional field's value, None where the agent left it out."""
    return None if value is UNSET else value


def vehicle_record_hello(
    *, vehicle_id: Any, now: datetime, server: uuid.UUID | None = None
) -> None:
    """Note that ``vehicle_id``'s agent authenticated at ``now``, on an uplink held by
    platform process ``server`` (fleet.servers): last_seen and the server only.

    The status waits for the profile. Writing last_seen also marks the uplink that owns
    the vehicle from now on (see :func:`vehicle_record_disconnect`).
    """
    # One statement: atomic.
    Vehicle.objects.filter(pk=vehicle_id).update(last_seen=now, uplink_server=server)


def vehicle_record_profile(*, vehicle_id: Any, profile: Profile, now: datetime) -> None:
    """Store a validated ``profile`` message and make the vehicle available.

    Stores the control URL, the reported vocabulary, telemetry topics, video, type,
    adapter and attributes (as reported: the declared attributes used for matching
    stay the admin's), position, battery and last_seen. An offline or fail-safe vehicle
    becomes idle (or what its reported ``status`` says), unless in maintenance;
    reserved, in-service and releasing are kept; a vehicle whose agent says it runs a
    task the platform does not hold it for is ``releasing``.

    Then, in the same transaction, the session owner is told the state the agent
    reported (fleet.vehicle_events.agent_connected), so that it converges the agent to
    what the platform wants before anything else is decided about the vehicle.
    """
    with transaction.atomic():
        vehicle = Vehicle.objects.select_for_update().filter(pk=vehicle_id).first()
        if vehicle is None:
            return
        vehicle.control_url = profile.control_url
        vehicle.profile = {
            "vehicle_type": profile.vehicle_type,
            "adapter": profile.adapter,
            "attributes": profile.attributes,
            "commands": msgspec.to_builtins(profile.commands),
            "telemetry": profile.telemetry,
            "video": profile.video,
        }
        # Optional: an agent of an earlier release sends no words for its safe actions.
        if profile.safe_actions is not UNSET:
            vehicle.profile["safe_actions"] = profile.safe_actions
        # Only an agent that says so is sent a task with an SFU section to publish to.
        if profile.sfu:
            vehicle.profile["sfu"] = True
        _set_position(vehicle, profile.position)
        vehicle.battery = profile.battery
        vehicle.last_seen = now
        vehicle.status = _status_after(
            vehicle,
            reported=_given(profile.status),
            registered=True,
            new_profile=True,
            running=_given(profile.session_id) is not None,
        )
        vehicle.save(
            update_fields=[
                "control_url",
                "profile",
                "lat",
                "lon",
                "alt",
                "battery",
                "last_seen",
                "status",
            ]
        )
        fleet_notify([vehicle.pk])
        agent_connected(
            vehicle_id=str(vehicle.pk),
            state={
                "session_id": _given(profile.session_id),
                "controller": bool(profile.controller),
                "status": _given(profile.status),
            },
        )


@dataclass(frozen=True)
class HeartbeatReport:
    """One validated heartbeat, as an uplink hands it to :class:`HeartbeatWriter`."""

    vehicle_id: str
    message: HeartbeatMessage
    now: datetime
    registered: bool  # the uplink has sent its profile (before that, status stays)


def vehicle_record_heartbeats(beats: Sequence[HeartbeatReport]) -> list[str]:
    """Store validated heartbeats of many vehicles in one short transaction.

    For each: last_seen, and position/battery/status if sent. ``registered`` says
    whether the uplink has sent its profile; before that the status is left alone.
    Absent optional fields keep their stored value; ``null`` means the agent does not
    know (e.g. no GPS fix) and is stored as unknown. With two heartbeats of one vehicle
    the later wins. Returns the ids of the vehicles written (unknown ids are skipped).

    No row is locked while Python decides: what the agent owns (last_seen, position,
    battery) is written by one statement, and a status change only if the status is
    still the one read, so a reservation made meanwhile is never overwritten (the next
    heartbeat decides again). Locking the rows instead made every reservation wait for
    whole batches.
    """
    latest: dict[str, HeartbeatReport] = {}
    for beat in beats:
        latest[str(uuid.UUID(str(beat.vehicle_id)))] = beat
    if not latest:
        return []
    with transaction.atomic():
        current = {
            str(v.pk): v
            for v in Vehicle.objects.filter(pk__in=list(latest)).only("id", "status", "maintenance")
        }
        reports = [latest[pk] for pk in sorted(current)]  # one order: fewer lock waits
        if connection.vendor == "postgresql":
            _store_reports_postgresql(reports)
        else:
            for beat in reports:
                Vehicle.objects.filter(pk=beat.vehicle_id).update(**_reported_fields(beat))
        back: list[str] = []
        for pk, vehicle in current.items():
            beat = latest[pk]
            status = _status_after(
                vehicle, reported=_given(beat.message.status), registered=beat.registered
            )
            if status != vehicle.status:
                changed = Vehicle.objects.filter(pk=pk, status=vehicle.status).update(status=status)
                if changed and vehicle.status == Vehicle.Status.OFFLINE:
                    back.append(pk)
        if back:
            # Heard from again on an uplink that never closed (the sweep had found it
            # silent): a vehicle still serving a session gets its session status back
            # from the receivers, in this transaction, before anyone could take it.
            vehicles_back(vehicle_ids=back)
        written = sorted(current)
        fleet_notify(written)  # one push for the batch, not one per vehicle
    return written


def _live_after(previous: Live | None, msg: HeartbeatMessage | Profile, now: datetime) -> Live:
    """What the agent has said by ``now``: ``msg`` over ``previous`` (a field ``msg``
    leaves out keeps its value; ``null`` means not known)."""
    battery = previous.battery if previous is not None else None
    lat, lon, alt = (previous.lat, previous.lon, previous.alt) if previous else (None, None, None)
    if msg.battery is not UNSET:
        battery = msg.battery
    position = msg.position
    if position is None:
        lat = lon = alt = None
    elif position is not UNSET:
        lat, lon = position.lat, position.lon
        alt = float(position.alt) if position.alt is not None else None
    return Live(now.timestamp(), battery, lat, lon, alt)


def _row_outdated(stored: Live | None, live: Live) -> bool:
    """True when the row's battery or position no longer says what the agent does: by
    ``IOUV_LIVENESS_BATTERY_STEP_PCT`` or ``IOUV_LIVENESS_POSITION_STEP_M``, or a
    reading gained or lost. Matching, workflows and pages read the row; finer news
    lives in fleet.liveness."""
    if stored is None:
        return True
    percent = float(settings.IOUV_LIVENESS_BATTERY_STEP_PCT)
    metres = float(settings.IOUV_LIVENESS_POSITION_STEP_M)
    if stored.battery is None or live.battery is None:
        if stored.battery != live.battery:
            return True
    elif abs(live.battery - stored.battery) >= percent:
        return True
    if stored.position is None or live.position is None:
        if stored.position != live.position:
            return True
    elif distance_m(stored.position, live.position) >= metres:
        return True
    if stored.alt is None or live.alt is None:
        return stored.alt != live.alt
    return abs(live.alt - stored.alt) >= metres


def _reported_fields(beat: HeartbeatReport) -> dict[str, Any]:
    """The columns a heartbeat sets (those it carries, and last_seen)."""
    fields: dict[str, Any] = {"last_seen": beat.now}
    position = beat.message.position
    if position is None:
        fields.update(lat=None, lon=None, alt=None)
    elif position is not UNSET:
        alt = position.alt
        fields.update(
            lat=position.lat, lon=position.lon, alt=float(alt) if alt is not None else None
        )
    if beat.message.battery is not UNSET:
        fields["battery"] = beat.message.battery
    return fields


def _store_reports_postgresql(reports: Sequence[HeartbeatReport]) -> None:
    """One UPDATE ... FROM (VALUES ...) for the whole batch; a field a heartbeat did not
    carry keeps the stored value."""
    table = Vehicle._meta.db_table
    row = (
        "(CAST(%s AS uuid), CAST(%s AS timestamptz), CAST(%s AS boolean), "
        "CAST(%s AS double precision), CAST(%s AS double precision), "
        "CAST(%s AS double precision), CAST(%s AS boolean), CAST(%s AS double precision))"
    )
    params: list[Any] = []
    for beat in reports:
        fields = _reported_fields(beat)
        params += [
            beat.vehicle_id,
            beat.now,
            "lat" in fields,
            fields.get("lat"),
            fields.get("lon"),
            fields.get("alt"),
            "battery" in fields,
            fields.get("battery"),
        ]
    sql = (
        f"UPDATE {table} AS v SET last_seen = d.seen, "  # names are ours, values are params
        "lat = CASE WHEN d.has_pos THEN d.lat ELSE v.lat END, "
        "lon = CASE WHEN d.has_pos THEN d.lon ELSE v.lon END, "
        "alt = CASE WHEN d.has_pos THEN d.alt ELSE v.alt END, "
        "battery = CASE WHEN d.has_battery THEN d.battery ELSE v.battery END "
        f"FROM (VALUES {', '.join([row] * len(reports))}) "
        "AS d(id, seen, has_pos, lat, lon, alt, has_battery, battery) WHERE v.id = d.id"
    )
    with connection.cursor() as cursor:
        cursor.execute(sql, params)


class HeartbeatWriter:
    """Writes the heartbeats of every uplink in this process, many per transaction.

    A thousand agents heartbeating every 2 s are 500 writes a second. One transaction
    each (a row lock, an UPDATE, a commit and a feed push) kept a platform process
    behind at about 190 a second, and vehicles that had heartbeated looked offline.
    Here a heartbeat that arrives while a write is in flight waits for the next one,
    together with all the others that arrived meanwhile (group commit): a lone
    heartbeat is written at once, and under load each transaction carries more.
    """

    #: The most heartbeats in one transaction (bounds how long rows stay locked).
    BATCH_MAX = 500
    #: A batch that fails this many times (e.g. chosen as a deadlock victim) is dropped:
    #: its heartbeats are superseded by the next ones within one interval.
    ATTEMPTS = 3

    def __init__(self) -> None:
        self._pending: dict[str, tuple[HeartbeatReport, list[asyncio.Future[None]]]] = {}
        self._flusher: asyncio.Task[None] | None = None

    async def write(self, beat: HeartbeatReport) -> None:
        """Return once ``beat`` (or a later heartbeat of its vehicle) is committed.

        Raises what the database raised if the batch holding it could not be written.
        """
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        entry = self._pending.get(beat.vehicle_id)
        waiters = entry[1] if entry is not None else []
        waiters.append(future)
        self._pending[beat.vehicle_id] = (beat, waiters)
        if self._flusher is None or self._flusher.done():
            self._flusher = asyncio.create_task(self._flush())
        # Shielded: an uplink that closes while it waits must not cancel the batch.
        await asyncio.shield(future)

    async def _flush(self) -> None:
        while self._pending:
            ids = list(self._pending)[: self.BATCH_MAX]
            batch = [self._pending.pop(vehicle_id) for vehicle_id in ids]
            error: BaseException | None = None
            for attempt in range(1, self.ATTEMPTS + 1):
                try:
                    await _db(vehicle_record_heartbeats)([beat for beat, _ in batch])
                    error = None
                    break
                except Exception as exc:  # handed to every waiter below
                    error = exc
                    log.warning(
                        "uplink: writing %d heartbeats failed (attempt %d of %d): %s",
                        len(batch),
                        attempt,
                        self.ATTEMPTS,
                        exc,
                    )
            for _beat, waiters in batch:
                for future in waiters:
                    if future.done():
                        continue
                    if error is None:
                        future.set_result(None)
                    else:
                        future.set_exception(error)


_writers: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, HeartbeatWriter] = (
    weakref.WeakKeyDictionary()
)


def heartbeat_writer() -> HeartbeatWriter:
    """This event loop's writer (a server process runs one loop; tests run many)."""
    loop = asyncio.get_running_loop()
    writer = _writers.get(loop)
    if writer is None:
        writer = _writers[loop] = HeartbeatWriter()
    return writer


def vehicle_record_disconnect(
    *, vehicle_id: Any, last_seen: datetime | None, heard: datetime | None = None
) -> bool:
    """Mark the vehicle offline (unless in maintenance) when its uplink closed.

    ``last_seen`` is the last value this uplink wrote to the row. If the stored one
    differs, a newer uplink of the same vehicle has written since: the vehicle is not
    offline and nothing changes. ``heard``: when this uplink last heard from the agent
    (its heartbeats went to fleet.liveness, not the row); stored as the row's
    last_seen, which says how long an offline vehicle has been silent. Returns True
    when this uplink was still the vehicle's.
    """
    with transaction.atomic():
        vehicle = Vehicle.objects.select_for_update().filter(pk=vehicle_id).first()
        if vehicle is None or vehicle.last_seen != last_seen:
            return False
        fields = []
        if heard is not None and (vehicle.last_seen is None or heard > vehicle.last_seen):
            vehicle.last_seen = heard
            fields.append("last_seen")
        if not vehicle.maintenance and vehicle.status not in (
            Vehicle.Status.OFFLINE,
            Vehicle.Status.MAINTENANCE,
        ):
            vehicle.status = Vehicle.Status.OFFLINE
            fields.append("status")
        if fields:
            vehicle.save(update_fields=fields)
        if "status" in fields:
            fleet_notify([vehicle.pk])
    return True


def _welcome(vehicle_id: str) -> Welcome:
    """The ``welcome`` message, with the optional fields the session owner contributes."""
    welcome = Welcome(v=PROTOCOL_VERSION, heartbeat_interval_s=settings.IOUV_HEARTBEAT_INTERVAL_S)
    extras: dict[str, Any] = {}
    extras.update(agent_welcome(vehicle_id=vehicle_id))
    # Extras may add optional fields, never replace the required ones; an unknown one
    # is a receiver's bug, refused like a bad value.
    optional = set(Welcome.__struct_fields__) - {"v", "heartbeat_interval_s"}
    try:
        if not set(extras) <= optional:
            raise ProtocolError(
                "bad_field", f"welcome has no fields {sorted(set(extras) - optional)}"
            )
        full = msgspec.structs.replace(welcome, **extras)
        encode_message(full, channel="uplink_to_agent")
    except ProtocolError as exc:
        log.error("uplink: dropping bad welcome extras %r: %s", sorted(extras), exc)
        return welcome
    return full


def _admit(
    *,
    vehicle_id: str,
    credential: str,
    now: datetime,
    server: uuid.UUID | None = None,
    queued_at: float | None = None,
) -> tuple[Vehicle, Welcome] | Literal["busy"] | None:
    """A hello's database work in one call: the vehicle if the credential is its own
    (last_seen recorded at ``now``) and the ``welcome`` to send it, else None.

    :data:`BUSY`, with nothing read, when the hello waited for a database thread since
    ``queued_at`` (``time.monotonic()``) for longer than :data:`ADMIT_WITHIN_S`."""
    if queued_at is not None and time.monotonic() - queued_at > ADMIT_WITHIN_S:
        return BUSY
    vehicle = vehicle_authenticate(vehicle_id=vehicle_id, credential=credential)
    if vehicle is None:
        return None
    vehicle_record_hello(vehicle_id=vehicle.pk, now=now, server=server)
    return vehicle, _welcome(str(vehicle.pk))


def _acked(*, vehicle_id: str, ack: Ack) -> None:
    """An ``ack`` from the agent: the message is delivered; the session owner hears of it."""
    acked = agent_message_ack(
        vehicle_id=vehicle_id, key=ack.id, ok=ack.ok, detail=_given(ack.detail) or ""
    )
    if acked is not None:
        agent_acked(vehicle_id=vehicle_id, acked=acked)


def _disconnected(
    *, vehicle_id: str, last_seen: datetime | None, heard: datetime | None, code: int
) -> None:
    """A closed uplink's database work in one call: the vehicle is marked offline and
    the session owner told, if this uplink still was the vehicle's."""
    if vehicle_record_disconnect(vehicle_id=vehicle_id, last_seen=last_seen, heard=heard):
        agent_disconnected(vehicle_id=vehicle_id, code=code)


# --------------------------------------------------------------------------------------
# The consumer
# --------------------------------------------------------------------------------------


class AgentUplinkConsumer(DirectDispatch, AsyncWebsocketConsumer):
    """One vehicle agent's uplink (``/ws/agent/``). See the module docstring.

    Lifecycle: ``hello`` within the timeout (else 4408), authenticated by vehicle
    credential (else 4401); ``welcome`` back; ``profile`` makes the vehicle available;
    heartbeats keep it so. A refused frame after authentication gets an ``error`` reply
    and the uplink stays open, unless frames keep being refused (4429). No exception
    escapes: a failure is logged and answered with error ``internal``.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.vehicle_id: str | None = None
        self._group: str | None = None
        self._first_frame_seen = False
        self._registered = False  # a profile was stored on this uplink
        #: The credential generation this uplink authenticated under (fleet.outbox
        #: closes it when a newer credential is issued).
        self.credential_generation = 0
        self._closed = False  # we closed (or were replaced): ignore what follows
        self._replaced = False
        #: Relayed browsers this uplink has heard from: conn -> the relay's channel, so
        #: the agent's answers go straight there (see fleet.sending.avehicle_send).
        self._relays: dict[str, str] = {}
        self._last_seen: datetime | None = None  # the last last_seen this uplink wrote
        self._heard: datetime | None = None  # when the agent was last heard from
        # With liveness in Redis, heartbeats reach the row only on a state change:
        # what the agent last reported, what the row was last given, the status the
        # agent last reported, and whether the sweep marked the vehicle offline since.
        self._live: Live | None = None
        self._stored: Live | None = None
        self._reported_status: str | None = None
        self._row_stale = False
        self._next_heartbeat_write = 0.0
        self._bad_frames: deque[float] = deque()
        self._hello_timer: asyncio.Task[None] | None = None
        # Database work of this uplink, in arrival order, off the consumer's dispatch
        # (see _backlog_run); None marks the end.
        self._backlog: asyncio.Queue[Callable[[], Awaitable[None]] | None] = asyncio.Queue(
            BACKLOG_MAX
        )
        self._backlog_task: asyncio.Task[None] | None = None

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            # A server shutting down cancels the consumer without a disconnect: the
            # uplink's own tasks end with it instead of being destroyed pending.
            for task in (self._hello_timer, self._backlog_task):
                if task is not None:
                    task.cancel()

    # -- connection ---------------------------------------------------------------------

    async def connect(self) -> None:
        relay_ensure()
        await self.accept()
        self._hello_timer = asyncio.create_task(self._hello_deadline())

    async def _hello_deadline(self) -> None:
        timeout = float(settings.IOUV_HELLO_TIMEOUT_S)
        await asyncio.sleep(timeout)
        if not self._first_frame_seen:
            try:
                await self._refuse(
                    "hello_timeout", f"no hello within {timeout:g} s", CLOSE_HELLO_TIMEOUT
                )
            except Exception:
                log.exception("uplink: closing a silent connection failed")

    async def disconnect(self, code: int) -> None:
        try:
            if code == SERVER_SHUTTING_DOWN:
                # The server is shutting down (a deploy): this process no longer holds
                # its uplinks, and their agents reconnect to another (fleet.servers).
                await uplink_server_stopping()
            if self._hello_timer is not None:
                self._hello_timer.cancel()
            if self.vehicle_id is not None:
                outbox().unregister(self.vehicle_id, self)
            if self._group is not None:
                # Best effort (e.g. the layer's connections all in use while a thousand
                # uplinks drop at once): a stale member only costs messages that expire
                # unread, and ages out; the vehicle must still be marked offline below.
                await group_release(self._group, self.channel_name)
            await self._tell_relays_gone()
            if self._backlog_task is not None and not self._backlog_task.done():
                # What the agent said before it left is stored first: a heartbeat
                # written after the offline mark would make the vehicle look alive.
                await self._backlog.put(None)
                await self._backlog_task
            if self.vehicle_id is None or self._replaced:
                return
            await _db(_disconnected)(
                vehicle_id=self.vehicle_id, last_seen=self._last_seen, heard=self._heard, code=code
            )
        except Exception:
            log.exception("uplink %s: disconnect handling failed", self.vehicle_id)

    # -- frames from the agent ----------------------------------------------------------

    async def receive(self, text_data: str | None = None, bytes_data: bytes | None = None) -> None:
        if self._closed:
            return
        raw: str | bytes | None = text_data if text_data is not None else bytes_data
        await self._guarded(lambda: self._receive(raw))

    async def _guarded(self, handle: Callable[[], Awaitable[None]]) -> None:
        """Run ``handle``; a failure is logged and answered, never raised."""
        try:
            await handle()
        except Exception:
            log.exception("uplink %s: unexpected error on a frame", self.vehicle_id)
            with contextlib.suppress(Exception):
                if self.vehicle_id is None:
                    # Authentication did not finish: let the agent retry from hello.
                    await self._refuse(
                        "internal", "the platform could not handle this message", CLOSE_INTERNAL
                    )
                else:
                    await self._send_error("internal", "the platform could not handle this message")

    async def _receive(self, raw: str | bytes | None) -> None:
        first = not self._first_frame_seen
        self._first_frame_seen = True
        if first and self._hello_timer is not None:
            # The first frame settles authentication either way; the deadline is moot.
            self._hello_timer.cancel()
        try:
            # A binary frame is read as UTF-8 JSON (docs/protocol.md, Transports).
            msg: UplinkToPlatform = parse_message(raw, channel="uplink_to_platform")  # type: ignore[arg-type]
        except ProtocolError as exc:
            if self.vehicle_id is None:
                await self._bad_frame(exc.code, exc.message)
            else:  # answered in turn, after what came before it
                code, text = exc.code, exc.message
                await self._later(lambda: self._bad_frame(code, text))
            return
        if self.vehicle_id is None:
            if first:
                await self._hello(msg)
            return
        if isinstance(msg, RelayToPlatform | RelayClose) and msg.conn:
            await self._relay_to_browser(msg)
        elif isinstance(msg, HeartbeatMessage):
            await self._heartbeat(msg)
        else:
            await self._later(lambda: self._handle(msg))

    async def _relay_to_browser(self, msg: RelayToPlatform | RelayClose) -> None:
        """On the control path: sent now, whatever database work is queued, as the text
        the browser receives (encoded once, here), straight to the relay's channel when
        this uplink knows it, else to the connection's group. With it goes this uplink's
        channel, for the relay's next command. The relay checks the vehicle id, so an
        agent cannot talk into another vehicle's session."""
        conn = str(msg.conn)  # given: checked by the caller
        event: dict[str, Any] = {
            "type": "relay.from_agent",
            "vehicle_id": self.vehicle_id,
            "uplink": self.channel_name,
        }
        if isinstance(msg, RelayToPlatform):
            event["text"] = encode_message(msg.payload)
            reply = self._relays.get(conn)
        else:
            event["close"] = _given(msg.code)
            reply = self._relays.pop(conn, None)
        if reply is not None:
            await self.channel_layer.send(reply, event)
        else:
            await self.channel_layer.group_send(relay_group(conn), event)

    async def _handle(self, msg: UplinkToPlatform) -> None:
        """What an authenticated agent's frame asks of the database, in arrival order."""
        if isinstance(msg, Profile):
            await self._profile(msg)
        elif isinstance(msg, Ack):
            await self._until_stored(
                functools.partial(_db(_acked), vehicle_id=self.vehicle_id, ack=msg)
            )
        elif isinstance(msg, Record):
            await self._until_stored(functools.partial(self._record, msg))
        elif isinstance(msg, Artifact):
            await self._until_stored(functools.partial(self._artifact, msg))
        elif isinstance(msg, RelayToPlatform | RelayClose):
            await self._bad_frame("bad_field", "a relayed message needs its conn")
        elif isinstance(msg, TaskAccepted | TaskRefused | Event):
            await self._until_stored(
                functools.partial(_db(agent_message), vehicle_id=self.vehicle_id, message=msg)
            )
        else:  # hello again
            await self._bad_frame("already_authenticated", "this uplink already said hello")

    async def _record(self, msg: Record) -> None:
        """A flight-record batch: kept (fleet.records), then acknowledged by its id, so
        the agent deletes its copy only once the platform has it."""
        outcome = await _db(record_keep)(vehicle_id=self.vehicle_id, message=msg)
        await self._send_message(Ack(id=msg.id, ok=outcome.ok, detail=outcome.detail))

    async def _artifact(self, msg: Artifact) -> None:
        """A chunk of a mission's file: kept (fleet.artifacts), then acknowledged by
        its id, so the agent deletes its copy only once the platform has all of it."""
        outcome = await _db(artifact_keep)(vehicle_id=self.vehicle_id, message=msg)
        await self._send_message(Ack(id=msg.id, ok=outcome.ok, detail=outcome.detail))

    async def _later(self, handle: Callable[[], Awaitable[None]]) -> None:
        """Queue ``handle`` behind this uplink's earlier database work.

        The consumer handles one message at a time, both the agent's frames and what the
        platform sends it (tasks, relayed commands). Awaiting a heartbeat write there
        held relayed commands and their answers for as long as the database took, which
        under load was seconds. Queued here, the work keeps its order while the
        consumer goes on; a full queue makes the consumer wait, as before.
        """
        if self._backlog_task is None:
            self._backlog_task = asyncio.create_task(self._backlog_run())
        await self._backlog.put(handle)

    async def _backlog_run(self) -> None:
        while (handle := await self._backlog.get()) is not None:
            if not self._closed:  # after a refusal the uplink ignores what follows
                await self._guarded(handle)

    async def _until_stored(self, handle: Callable[[], Awaitable[None]]) -> None:
        """Run ``handle`` (an agent's report: its profile, an event, a task accepted or
        refused, an ack), again while the database cannot be reached: the report waits in this
        uplink's queue, in order, until PostgreSQL is back, instead of being lost. The
        agent sent it once and does not send it again. What follows it waits too;
        relayed control does not (it never enters this queue), and a heartbeat is not
        written again (the next one supersedes it). Work cut by the outage between two
        of its statements may be done twice (an event logged twice), never lost."""
        delay = DATABASE_RETRY_MIN_S
        while True:
            try:
                await handle()
                return
            except DATABASE_UNAVAILABLE as exc:
                if self._closed:
                    raise
                log.warning(
                    "uplink %s: the database is unavailable, the report waits (again in %g s): %s",
                    self.vehicle_id,
                    delay,
                    exc,
                )
            await asyncio.sleep(delay)
            delay = min(2 * delay, DATABASE_RETRY_MAX_S)

    async def _bad_frame(self, code: str, message: str) -> None:
        """Answer a refused frame; before authentication that ends the uplink."""
        if self.vehicle_id is None:
            if code == "bad_version":
                await self._refuse(code, message, CLOSE_BAD_VERSION)
            else:
                await self._refuse(code, message, CLOSE_UNAUTHORIZED)
            return
        now = time.monotonic()
        self._bad_frames.append(now)
        while self._bad_frames and self._bad_frames[0] <= now - BAD_FRAMES_WINDOW_S:
            self._bad_frames.popleft()
        if len(self._bad_frames) >= BAD_FRAMES_MAX:
            log.warning("uplink %s: closed for flooding refused frames", self.vehicle_id)
            await self._refuse(
                "flood",
                f"{BAD_FRAMES_MAX} refused frames within {BAD_FRAMES_WINDOW_S:g} s",
                CLOSE_FLOOD,
            )
            return
        await self._send_error(code, message)

    async def _hello(self, msg: UplinkToPlatform) -> None:
        if not isinstance(msg, Hello):
            await self._refuse(
                "not_authenticated", "the first message must be hello", CLOSE_UNAUTHORIZED
            )
            return
        # This process beats as the holder of uplinks before it admits one (its row
        # must exist whenever a vehicle's names it).
        try:
            server: uuid.UUID | None = await uplink_server_ensure()
        except Exception as exc:
            log.warning("uplink: this process is not registered as a server: %s", exc)
            server = None
        now = timezone.now()
        admitted = await _db(_admit)(
            vehicle_id=msg.vehicle_id,
            credential=msg.credential,
            now=now,
            server=server,
            queued_at=time.monotonic(),
        )
        if admitted == BUSY:
            # Thousands of agents connect at once (a platform restart): the hellos that
            # queued too long are turned away at once, so the process spends its time
            # on those it can still welcome and on the agents already connected; the
            # turned away come back after their backoff.
            log.info("uplink: hello of %.40r turned away, the platform is busy", msg.vehicle_id)
            await self._refuse("busy", "the platform is busy: try again later", CLOSE_TRY_LATER)
            return
        if admitted is None:
            log.warning("uplink: refused hello for vehicle id %.40r", msg.vehicle_id)
            await self._refuse(
                "bad_credential", "unknown vehicle or wrong credential", CLOSE_UNAUTHORIZED
            )
            return
        vehicle, welcome = admitted
        self.vehicle_id = str(vehicle.pk)
        self.credential_generation = vehicle.credential_generation
        self._last_seen = self._heard = now
        self._live = self._stored = Live(
            now.timestamp(), vehicle.battery, vehicle.lat, vehicle.lon, vehicle.alt
        )
        self._write_live()
        self._group = vehicle_group(vehicle.pk)
        # A vehicle is one agent: tell an older uplink of this vehicle to go, before
        # joining the group so this one does not hear its own notice. (The older one
        # no longer owns last_seen, so it will not mark the vehicle offline.)
        try:
            await self.channel_layer.group_send(
                self._group, {"type": "agent.replaced", "channel": self.channel_name}
            )
        except Exception as exc:
            log.warning("uplink %s: telling older uplinks failed: %s", self.vehicle_id, exc)
        await self._join_group()
        try:
            await self._send_message(welcome)
        except Exception as exc:  # the agent stopped waiting and left (its disconnect follows)
            log.info("uplink %s: gone before its welcome: %s", self.vehicle_id, exc)
            return
        log.info("uplink: vehicle %s (%s) connected", vehicle.name, self.vehicle_id)

    async def _profile(self, msg: Profile) -> None:
        now = timezone.now()
        # Records the profile and converges the agent to what the platform wants (the
        # agent_connected receivers) in one transaction; only then does the outbox
        # deliver what the vehicle is owed on this uplink. While the database is away,
        # it waits for it, as the agent's reports do.
        await self._until_stored(
            functools.partial(
                _db(vehicle_record_profile), vehicle_id=self.vehicle_id, profile=msg, now=now
            )
        )
        self._last_seen = self._heard = now
        self._registered = True
        self._reported_status = _given(msg.status)
        self._live = self._stored = _live_after(None, msg, now)
        self._write_live()
        if not self._closed:
            assert self.vehicle_id is not None
            outbox().register(self.vehicle_id, self)

    async def _join_group(self) -> None:
        """Join the vehicle's group and stay in it while the uplink lives, across Redis
        restarts (fleet.memberships); a join that fails is made again from there.

        The group only carries relayed traffic and "look now" nudges: what the vehicle
        is owed reaches it through the database (fleet.outbox), so the agent is
        admitted either way.
        """
        if self._group is not None:
            await group_hold(self._group, self.channel_name)

    async def _heartbeat(self, msg: HeartbeatMessage) -> None:
        """A heartbeat, on the consumer's own turn (not queued behind database work):
        with liveness in Redis most heartbeats end here, handed to the process's
        liveness writer without waiting; one that changes the vehicle's state (or any,
        embedded) queues its row write behind the uplink's earlier database work."""
        # At most two per heartbeat interval: an agent that heartbeats too fast costs
        # nothing more. A skipped heartbeat is superseded by the next.
        mono = time.monotonic()
        if mono < self._next_heartbeat_write:
            return
        self._next_heartbeat_write = mono + float(settings.IOUV_HEARTBEAT_INTERVAL_S) / 2
        now = timezone.now()
        assert self.vehicle_id is not None
        live = self._live = _live_after(self._live, msg, now)
        status = _given(msg.status)
        if in_redis():
            liveness_writer().put(self.vehicle_id, live, self._liveness_lost)
            self._heard = now
            changed = (
                self._row_stale
                or (status is not None and status != self._reported_status)
                or _row_outdated(self._stored, live)
            )
            if not changed:
                return
            # The row gets all the agent has said since its last write, not only this
            # heartbeat's fields (the ones before it went to Redis alone).
            position = (
                None
                if live.lat is None or live.lon is None
                else (Position(lat=live.lat, lon=live.lon, alt=live.alt))
            )
            msg = msgspec.structs.replace(msg, battery=live.battery, position=position)
        # Decided now, so the heartbeats after this one compare with it even before it
        # is written; a write that fails makes the next heartbeat write again.
        row_stale, self._row_stale = self._row_stale, False
        self._stored = live
        if status is not None:
            self._reported_status = status
        await self._later(lambda: self._heartbeat_row(msg, now, row_stale))

    async def _heartbeat_row(self, msg: HeartbeatMessage, now: datetime, row_stale: bool) -> None:
        """Write a heartbeat to the vehicle's row: awaited, so this agent's heartbeats
        are written in order and _last_seen is only what was committed (the disconnect
        compares it with the stored one)."""
        assert self.vehicle_id is not None
        try:
            await heartbeat_writer().write(
                HeartbeatReport(self.vehicle_id, msg, now, self._registered)
            )
        except BaseException:
            self._row_stale = True if in_redis() else row_stale
            raise
        self._last_seen = now
        if self._heard is None or now > self._heard:
            self._heard = now

    def _liveness_lost(self) -> None:
        """Redis did not take this uplink's last report: the next heartbeat goes to the
        row (so while Redis is away, every one does)."""
        self._row_stale = True

    def _write_live(self) -> None:
        """Put what the agent last reported in Redis (fleet.liveness), when it lives
        there."""
        if in_redis() and self._live is not None and self.vehicle_id is not None:
            liveness_writer().put(self.vehicle_id, self._live, self._liveness_lost)

    # -- messages from the platform (channel layer) -------------------------------------

    async def agent_send(self, event: dict[str, Any]) -> None:
        """Forward ``event["text"]`` (an uplink_to_agent frame that
        fleet.sending.avehicle_send checked and encoded) to the agent."""
        if self._closed or self.vehicle_id is None:
            return
        conn, reply = event.get("conn"), event.get("reply")
        if isinstance(conn, str):
            if isinstance(reply, str):
                self._relays.pop(conn, None)  # re-inserted last: the oldest go first
                self._relays[conn] = reply
                while len(self._relays) > RELAYS_MAX:
                    self._relays.pop(next(iter(self._relays)))
            else:  # the browser left (relay_close)
                self._relays.pop(conn, None)
        text = event.get("text")
        if not isinstance(text, str):
            log.error("uplink %s: not sending an event without its text", self.vehicle_id)
            return
        try:
            await self.send(text_data=text)
        except Exception:
            log.exception("uplink %s: sending to the agent failed", self.vehicle_id)

    async def uplink_marked_offline(self, event: dict[str, Any]) -> None:
        """The sweep found this vehicle silent and marked its row offline (a half-open
        socket that recovered, or a loaded platform): the next heartbeat goes to the
        row, which brings the vehicle back. The row's last_seen is now the last time
        this uplink heard the agent: still this uplink's, for its disconnect."""
        self._row_stale = True
        stored = event.get("last_seen")
        if isinstance(stored, str) and self._heard is not None:
            with contextlib.suppress(ValueError):
                at = datetime.fromisoformat(stored)
                if at <= self._heard:
                    self._last_seen = at

    async def agent_outbox(self, event: dict[str, Any]) -> None:
        """Something was written for this vehicle (fleet.outbox): look now, not at the
        next poll."""
        if self.vehicle_id is not None and self._registered:
            outbox().wake()

    async def outbox_send(self, message: Task | Revoke | EndTask) -> None:
        """Send one owed message (it carries its ``id``); raises if the uplink is gone."""
        if self._closed:
            raise ConnectionError("uplink closed")
        await self._send_message(message)

    async def outbox_credential_revoked(self) -> None:
        """The vehicle has a new credential: this uplink's holder is no longer trusted."""
        if self.vehicle_id is not None:
            outbox().unregister(self.vehicle_id, self)
        await self._refuse(
            "credential_revoked", "this vehicle's credential was replaced", CLOSE_UNAUTHORIZED
        )

    async def agent_replaced(self, event: dict[str, Any]) -> None:
        """A newer uplink of this vehicle authenticated: this one closes (4409)."""
        if event.get("channel") == self.channel_name or self._closed:
            return
        self._replaced = True
        if self.vehicle_id is not None:
            outbox().unregister(self.vehicle_id, self)
        try:
            if self._group is not None:
                await group_release(self._group, self.channel_name)
            await self._refuse(
                "replaced", "another uplink of this vehicle took over", CLOSE_REPLACED
            )
        except Exception:
            log.exception("uplink %s: closing a replaced uplink failed", self.vehicle_id)

    # -- helpers ------------------------------------------------------------------------

    async def _tell_relays_gone(self) -> None:
        """The relays this uplink answered address it no more: their next commands
        go to the vehicle's group, where the agent's next uplink hears them."""
        relays, self._relays = set(self._relays.values()), {}
        for reply in relays:
            try:
                await self.channel_layer.send(
                    reply, {"type": "relay.uplink_gone", "uplink": self.channel_name}
                )
            except Exception as exc:  # best effort: the relay falls back on its own
                log.info("uplink %s: telling a relay failed: %s", self.vehicle_id, exc)

    async def _send_message(self, msg: Message) -> None:
        await self.send(text_data=encode_message(msg, channel="uplink_to_agent"))

    async def _send_error(self, code: str, message: str) -> None:
        await self._send_message(error_message(code, message[:_ERROR_TEXT_MAX]))

    async def _refuse(self, code: str, message: str, close_code: int) -> None:
        """Send ``error`` and close with ``close_code``; frames after it are ignored."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            await self._send_error(code, message)
        await self.close(code=close_code)
