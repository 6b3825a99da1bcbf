"""The platform's word to vehicle agents, delivered until the agent acknowledges it.

Every message that changes what a vehicle does (``task``, ``revoke``, ``end_task``)
is an :class:`~fleet.models.AgentMessage` row, written in the transaction that decides
it (:func:`agent_message_enqueue`). The process that holds the vehicle's uplink delivers
it with a fresh ``id`` field, in order, and again after a reconnect or when no ``ack``
came back in time (:class:`Outbox`); the agent answers ``ack`` with that id and ignores
a message it has already handled. So a broker outage, a platform restart or a dropped
uplink delays the platform's word but never loses it: the database is the truth, the
channel layer only a way to say "look now".

A replaced credential is a row too (kind ``disconnect``): the process holding an uplink
authenticated under an older credential closes it.

Each process runs one :class:`Outbox` per event loop. It looks for owed messages of the
uplinks it holds when woken (by the transaction that wrote them, in this process or,
through the channel layer, in another) and at least every :data:`POLL_S` seconds, which
is what makes delivery independent of the channel layer.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import operator
import threading
import uuid
import weakref
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from functools import reduce
from typing import Any, Protocol

import msgspec
from asgiref.sync import async_to_sync
from channels.db import database_sync_to_async
from channels.layers import get_channel_layer
from django.db import connection, transaction
from django.db.models import Exists, F, OuterRef, Q
from django.utils import timezone

from agents.protocol.messages import (
    EndTask,
    Revoke,
    Task,
    encode_message,
    message_from_dict,
    message_to_dict,
    message_type,
)
from fleet.feed import fleet_notify
from fleet.models import AgentMessage, Vehicle
from operations import layer

log = logging.getLogger(__name__)

#: How often an outbox looks for owed messages even when nobody woke it.
POLL_S = 0.5
#: A message sent on a live uplink and not acknowledged is sent again after this, then
#: after twice as long, up to RETRY_MAX_S.
RETRY_S = 1.0
RETRY_MAX_S = 5.0
#: A ``disconnect`` row nobody acted on (no process holds an older uplink) is dropped
#: after this: any uplink opened since authenticated with the new credential.
DISCONNECT_TTL_S = 60.0

_KINDS = {"task", "revoke", "end_task"}
#: Kinds whose acknowledgement means the vehicle gave up its session.
ENDING = (AgentMessage.Kind.REVOKE, AgentMessage.Kind.END_TASK)


def vehicle_group(vehicle_id: Any) -> str:
    """The channel-layer group of a vehicle's uplink: ``vehicle-<uuid hex>``.

    Raises ValueError when ``vehicle_id`` is not a UUID (group names must be plain ASCII).
    """
    return f"vehicle-{uuid.UUID(str(vehicle_id)).hex}"


def _db(func: Any) -> Any:
    # As fleet.uplink: threads with a database server, the one thread on SQLite.
    return database_sync_to_async(func, thread_sensitive=connection.vendor == "sqlite")


# --------------------------------------------------------------------------------------
# Writes and selectors
# --------------------------------------------------------------------------------------


def agent_message_enqueue(
    *, vehicle_id: Any, message: Task | Revoke | EndTask, session_id: Any = None
) -> AgentMessage:
    """Owe ``message`` (a ``task``, ``revoke`` or ``end_task``) to the vehicle's agent.

    Written in the current transaction, so a rolled back decision sends nothing; the
    holder of the uplink is woken once it commits. ``session_id`` defaults to the
    message's own. Raises ProtocolError if ``message`` breaks the protocol's limits,
    ValueError for another type or a ``vehicle_id`` that is not a UUID.
    """
    if not isinstance(message, Task | Revoke | EndTask):
        raise ValueError(f"only {sorted(_KINDS)} are delivered reliably, not {message!r:.80}")
    # Checked here, with an id as it will travel, so a sender's bug shows at the sender
    # (a struct's constructor checks no limits).
    encode_message(msgspec.structs.replace(message, id="0"), channel="uplink_to_agent")
    pk = uuid.UUID(str(vehicle_id))
    row = AgentMessage.objects.create(
        vehicle_id=pk,
        session_id=session_id or getattr(message, "session_id", None),
        kind=message_type(message),
        message=message_to_dict(message),  # stored as the JSON it travels as
    )
    transaction.on_commit(lambda: outbox_nudge(pk), robust=True)
    return row


def stored_message(data: dict[str, Any]) -> Task | Revoke | EndTask:
    """A message read back from its row (it was checked when it was written)."""
    message = message_from_dict(data, channel="uplink_to_agent")
    assert isinstance(message, Task | Revoke | EndTask), message
    return message


def agent_messages_cancel(
    *,
    vehicle_id: Any,
    kinds: Iterable[str],
    session_id: Any = None,
    except_session: Any = None,
) -> int:
    """Cancel the vehicle's pending messages of ``kinds`` (of ``session_id`` only, or of
    every session but ``except_session``); returns how many."""
    return agent_messages_cancel_each(
        vehicle_id=vehicle_id,
        withdrawn=[
            agent_messages_withdrawn(kinds, session_id=session_id, except_session=except_session)
        ],
    )


def agent_messages_withdrawn(
    kinds: Iterable[str], *, session_id: Any = None, except_session: Any = None
) -> Q:
    """The messages of ``kinds`` (of ``session_id`` only, or of every session but
    ``except_session``), as a condition for :func:`agent_messages_cancel_each`."""
    q = Q(kind__in=list(kinds))
    if session_id is not None:
        q &= Q(session_id=session_id)
    if except_session is not None:
        q &= ~Q(session_id=except_session)
    return q


def agent_messages_cancel_each(*, vehicle_id: Any, withdrawn: Sequence[Q]) -> int:
    """Cancel, in one statement, the vehicle's pending messages meeting any of the
    ``withdrawn`` conditions (:func:`agent_messages_withdrawn`); returns how many."""
    return (
        AgentMessage.objects.filter(vehicle_id=vehicle_id, state=AgentMessage.State.PENDING)
        .filter(reduce(operator.or_, withdrawn))
        .update(state=AgentMessage.State.CANCELLED)
    )


def vehicle_disconnect_older_uplinks(*, vehicle_id: Any, generation: int) -> AgentMessage:
    """Close, wherever it is, the vehicle's uplink authenticated under a credential
    older than ``generation`` (called when a new credential is issued)."""
    row = AgentMessage.objects.create(
        vehicle_id=vehicle_id,
        kind=AgentMessage.Kind.DISCONNECT,
        message={"type": "disconnect", "generation": generation},
    )
    transaction.on_commit(lambda: outbox_nudge(vehicle_id), robust=True)
    return row


@dataclass(frozen=True)
class Acked:
    """An acknowledged message, as handed to the session owner (fleet.vehicle_events)."""

    vehicle_id: str
    session_id: str | None
    kind: str
    message: Task | Revoke | EndTask
    ok: bool
    detail: str
    released: bool  # the vehicle left ``releasing`` with this acknowledgement


def agent_message_ack(*, vehicle_id: Any, key: str, ok: bool, detail: str = "") -> Acked | None:
    """Record the agent's ``ack`` of message ``key``; None when it is not one of the
    vehicle's pending messages (a repeat, a stranger's id, a cancelled one).

    When the vehicle owes the platform nothing more that ends a session, a vehicle
    ``releasing`` becomes ``idle``: its agent confirmed it gave the session up.
    """
    try:
        pk = uuid.UUID(str(key))
    except ValueError:
        return None
    detail = detail[:200]
    # A conditional update, no transaction: of two acks of one message (a repeat
    # crossing a redelivery) one changes the row, the other finds it acked already.
    # What the ack is about is then read from the row, which no longer changes.
    mine = AgentMessage.objects.filter(key=pk, vehicle_id=vehicle_id)
    if not mine.filter(state=AgentMessage.State.PENDING).update(
        state=AgentMessage.State.ACKED,
        acked_at=timezone.now(),
        result={"ok": ok, "detail": detail},
    ):
        return None
    session_id, kind, message = mine.values_list("session_id", "kind", "message").get()
    released = kind in ENDING and vehicle_release_if_settled(vehicle_id=vehicle_id)
    return Acked(
        vehicle_id=str(vehicle_id),
        session_id=str(session_id) if session_id else None,
        kind=kind,
        message=stored_message(message),
        ok=ok,
        detail=detail,
        released=released,
    )


def vehicle_release_if_settled(*, vehicle_id: Any) -> bool:
    """A ``releasing`` vehicle whose agent owes no session end becomes ``idle``; True
    if it did. (Its next heartbeat says ``returning`` if it is still flying home.)"""
    # The check and the change in one statement.
    changed = (
        Vehicle.objects.filter(pk=vehicle_id, status=Vehicle.Status.RELEASING, maintenance=False)
        .filter(
            ~Exists(
                AgentMessage.objects.filter(
                    vehicle_id=OuterRef("pk"),
                    state=AgentMessage.State.PENDING,
                    kind__in=ENDING,
                )
            )
        )
        .update(status=Vehicle.Status.IDLE)
    )
    if changed:
        fleet_notify([vehicle_id])
    return bool(changed)


def agent_messages_owed(*, session_id: Any) -> list[AgentMessage]:
    """The messages about ``session_id``, oldest first, with their vehicles."""
    return list(
        AgentMessage.objects.filter(session_id=session_id)
        .exclude(kind=AgentMessage.Kind.DISCONNECT)
        .select_related("vehicle")
        .order_by("id")
    )


def _retry_after(attempts: int) -> float:
    return min(RETRY_MAX_S, RETRY_S * 2.0 ** max(0, attempts - 1))


_DUE_FIELDS = ("id", "key", "vehicle_id", "kind", "message", "sent_at", "attempts", "created_at")


def _take_due(*, vehicle_ids: Collection[str], fresh: Sequence[str], now: datetime) -> list[Any]:
    """The pending messages of ``vehicle_ids`` due now, in order, marked as sent.

    Everything pending is due for a vehicle in ``fresh`` (its uplink just registered:
    whatever was sent on an earlier one may never have arrived); otherwise a message
    not yet sent, or sent and not acknowledged for its retry interval.
    """
    if not vehicle_ids:
        return []
    fresh_set = set(fresh)
    # What is owed is little (the partial index holds only that), and the uplinks of a
    # process are many: read the few pending rows, not a query naming thousands of
    # vehicles twice a second (building that query alone cost 15 % of a process
    # holding 2,000 uplinks).
    ours = vehicle_ids if isinstance(vehicle_ids, (set, frozenset)) else set(vehicle_ids)
    pending = AgentMessage.objects.filter(state=AgentMessage.State.PENDING)
    owed = [
        pk
        for pk, vehicle_id in pending.order_by().values_list("id", "vehicle_id")
        if str(vehicle_id) in ours
    ]
    if not owed:
        return []
    with transaction.atomic():
        # Locked, skipping rows another transaction holds: a task being withdrawn as its
        # session ends is either sent before that decision or not at all, so the
        # decision always knows whether the agent may have it.
        found = (
            pending.select_for_update(skip_locked=True)
            .filter(pk__in=owed)
            .order_by("id")
            .values_list(*_DUE_FIELDS)
        )
        rows = [dict(zip(_DUE_FIELDS, row, strict=True)) for row in found]
        due = []
        stale_disconnects = []
        for row in rows:
            vid = str(row["vehicle_id"])
            if row["kind"] == AgentMessage.Kind.DISCONNECT:
                if (now - row["created_at"]).total_seconds() > DISCONNECT_TTL_S:
                    stale_disconnects.append(row["id"])
                else:
                    due.append(row)  # checked against the uplink on every pass
                continue
            sent = row["sent_at"]
            if (
                vid in fresh_set
                or sent is None
                or now - sent >= timedelta(seconds=_retry_after(row["attempts"]))
            ):
                due.append(row)
        sending = [r["id"] for r in due if r["kind"] != AgentMessage.Kind.DISCONNECT]
        if sending:
            AgentMessage.objects.filter(pk__in=sending).update(
                sent_at=now, attempts=F("attempts") + 1
            )
        if stale_disconnects:
            AgentMessage.objects.filter(pk__in=stale_disconnects).update(
                state=AgentMessage.State.CANCELLED
            )
    return due


def _disconnect_done(*, row_id: int, closed: bool) -> None:
    AgentMessage.objects.filter(pk=row_id, state=AgentMessage.State.PENDING).update(
        state=AgentMessage.State.ACKED,
        acked_at=timezone.now(),
        result={"ok": True, "detail": "uplink closed" if closed else "no older uplink here"},
    )


# --------------------------------------------------------------------------------------
# Delivery
# --------------------------------------------------------------------------------------


class OutboxLink(Protocol):
    """What the outbox needs of an uplink (fleet.uplink.AgentUplinkConsumer)."""

    #: The credential generation the uplink authenticated under.
    credential_generation: int

    async def outbox_send(self, message: Task | Revoke | EndTask) -> None:
        """Put one uplink_to_agent message on the socket; raises if it is gone."""

    async def outbox_credential_revoked(self) -> None:
        """Close the uplink: its credential was replaced."""


class Outbox:
    """Delivers owed messages to the uplinks of this process (one per event loop)."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._links: dict[str, OutboxLink] = {}
        # What a pass reads: the links and their vehicles as they were, remade only
        # after a change. A process holds thousands of uplinks, and copying them for
        # every pass (a pass per task and end sent, and two a second) showed up.
        self._snapshot: tuple[dict[str, OutboxLink], frozenset[str]] | None = None
        self._fresh: set[str] = set()
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    def register(self, vehicle_id: str, link: OutboxLink) -> None:
        """``link`` now serves ``vehicle_id``: everything it is owed goes out on it."""
        self._links[vehicle_id] = link
        self._snapshot = None
        self._fresh.add(vehicle_id)
        self.wake()
        if self._task is None or self._task.done():
            self._task = self._loop.create_task(self._run(), name="agent-outbox")

    def unregister(self, vehicle_id: str, link: OutboxLink) -> None:
        if self._links.get(vehicle_id) is link:
            del self._links[vehicle_id]
            self._snapshot = None
            self._fresh.discard(vehicle_id)

    def holds(self, vehicle_id: str) -> bool:
        return vehicle_id in self._links

    def wake(self) -> None:
        """Look for owed messages now (call from this loop's thread)."""
        self._wake.set()

    def wake_threadsafe(self) -> None:
        with contextlib.suppress(RuntimeError):  # the loop has closed
            self._loop.call_soon_threadsafe(self._wake.set)

    async def _run(self) -> None:
        while self._links:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(POLL_S):
                    await self._wake.wait()
            self._wake.clear()
            try:
                await self.deliver_due()
            except asyncio.CancelledError:
                raise
            except Exception:  # a database hiccup must not end delivery
                log.exception("outbox: delivery failed; retrying")

    async def deliver_due(self) -> int:
        """Send what is due to this process's uplinks now; returns how many were sent."""
        if self._snapshot is None:
            self._snapshot = (dict(self._links), frozenset(self._links))
        links, vehicle_ids = self._snapshot  # never changed, only replaced
        fresh = [v for v in self._fresh if v in links]
        self._fresh.difference_update(fresh)
        rows = await _db(_take_due)(vehicle_ids=vehicle_ids, fresh=fresh, now=timezone.now())
        sent = 0
        for row in rows:
            link = links.get(str(row["vehicle_id"]))
            if link is None or self._links.get(str(row["vehicle_id"])) is not link:
                continue  # gone meanwhile: its next uplink gets everything again
            if row["kind"] == AgentMessage.Kind.DISCONNECT:
                older = link.credential_generation < int(row["message"]["generation"])
                if older:
                    log.warning(
                        "outbox: closing vehicle %s's uplink: credential replaced",
                        row["vehicle_id"],
                    )
                    await link.outbox_credential_revoked()
                await _db(_disconnect_done)(row_id=row["id"], closed=older)
                continue
            try:
                message = stored_message({**row["message"], "id": str(row["key"])})
                await link.outbox_send(message)
                sent += 1
            except Exception as exc:  # the socket closed: the next uplink resends it
                log.info("outbox: vehicle %s gone while sending: %s", row["vehicle_id"], exc)
        return sent


_outboxes: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Outbox] = (
    weakref.WeakKeyDictionary()
)
_lock = threading.Lock()


def outbox() -> Outbox:
    """This event loop's outbox (a server process runs one loop; tests run many)."""
    loop = asyncio.get_running_loop()
    with _lock:
        box = _outboxes.get(loop)
        if box is None:
            box = _outboxes[loop] = Outbox(loop)
    return box


def outbox_nudge(vehicle_id: Any) -> None:
    """Tell whoever holds ``vehicle_id``'s uplink to look at its owed messages now.

    In this process directly; in others through the channel layer, best effort: a
    nudge lost with the broker only costs the wait for the next poll.
    """
    with _lock:
        boxes = list(_outboxes.values())
    for box in boxes:
        if box.holds(str(vehicle_id)):
            box.wake_threadsafe()
            return
    if layer.CROSS_PROCESS and layer.in_memory():
        return  # an embedded worker: the server process's outbox polls
    channel_layer = get_channel_layer()
    if channel_layer is None:
        return
    try:
        async_to_sync(channel_layer.group_send)(vehicle_group(vehicle_id), {"type": "agent.outbox"})
    except Exception as exc:
        log.info("outbox: nudge for %s not sent (%s); it polls", vehicle_id, exc)
