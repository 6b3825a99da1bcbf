"""The session log: append-only and hash-chained.

Each event stores the SHA-256 of its own canonical content plus the previous event's
hash, so changing, removing or reordering a stored event breaks the chain from that
point on, and ``session_log_verify`` names the first broken event.

Appending reads the log's tail and inserts the next event only if its place (the
session's next sequence number, unique) is still free; a writer that finds it taken
reads the tail again and follows the event that took it. So an agent's report, which
runs in no transaction of its own, appends with two statements and no lock: it used
to take five (BEGIN, the session's row locked, the tail, the event, COMMIT), and a
session has several such reports. A writer inside a transaction still locks the
session's row first, as it did: that transaction may go on to lock the row itself,
and taking the lock first keeps every writer's locks in one order; its insert runs in
a savepoint, so that a place found taken does not abort the transaction. Session rows are
locked ``FOR NO KEY UPDATE`` everywhere: the lock keeps writers of the session in
turn without blocking the inserts that refer to it, such as a report's event (an
insert's foreign-key check waits for ``FOR UPDATE``, and a report waiting there while
the lock's holder waits for the report's event's place would deadlock).

A session being created writes its first events in one go instead
(:func:`events_staged`): nobody else can see it before its transaction commits, so
there is no tail to read and no writer to wait for. A writer that holds the lock and
has read the whole log (:func:`session_log`, to answer with it) appends after what it
read, without reading the tail again.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from django.core.serializers.json import DjangoJSONEncoder
from django.db import IntegrityError, transaction
from django.db.transaction import get_connection
from django.utils import timezone

from services.models import Session, SessionEvent
from services.sessions.feed import session_notify, session_notify_many
from services.sessions.words import event_text

GENESIS_HASH = "0" * 64

# How often a writer may find its event's place taken before it gives up: each time,
# another event was written in between, so only a flood of writers to one session
# gets near it.
_PLACE_TRIES = 100


def _event_hash(
    *,
    session_id: str,
    seq: int,
    kind: str,
    data: Any,
    created_at: str,
    prev_hash: str,
    occurred_at: str | None = None,
) -> str:
    # The vehicle's time joins the hashed content only when there is one: the events
    # stored before it existed keep their hashes.
    occurred = {"occurred_at": occurred_at} if occurred_at is not None else {}
    canonical = json.dumps(
        {
            "session": session_id,
            "seq": seq,
            "kind": kind,
            "data": data,
            "created_at": created_at,
            "prev": prev_hash,
            **occurred,
        },
        sort_keys=True,
        separators=(",", ":"),
        cls=DjangoJSONEncoder,
    )
    return hashlib.sha256(canonical.encode()).hexdigest()


def _event_new(
    *,
    session: Session,
    seq: int,
    prev_hash: str,
    kind: str,
    data: dict[str, Any] | None,
    occurred_at: datetime | None = None,
) -> SessionEvent:
    """The event ``seq`` of ``session``'s log, hashed and not yet saved. Its
    ``occurred_at`` is ``occurred_at``, else the time :func:`events_occurred_at` gives."""
    # Round-trip through JSON so the hash covers exactly what the database stores.
    payload = json.loads(json.dumps(data or {}, cls=DjangoJSONEncoder))
    created_at = timezone.now()
    occurred = occurred_at or _occurred.get()
    return SessionEvent(
        session=session,
        seq=seq,
        kind=kind,
        data=payload,
        created_at=created_at,
        occurred_at=occurred,
        prev_hash=prev_hash,
        hash=_event_hash(
            session_id=str(session.pk),
            seq=seq,
            kind=kind,
            data=payload,
            created_at=created_at.isoformat(),
            prev_hash=prev_hash,
            occurred_at=occurred.isoformat() if occurred is not None else None,
        ),
    )


_occurred: ContextVar[datetime | None] = ContextVar("iouv_events_occurred_at", default=None)


@contextmanager
def events_occurred_at(when: datetime | None) -> Iterator[None]:
    """Within the block, the events appended to any session's log happened at ``when``
    on a vehicle (their ``occurred_at``; None: the platform's own events). The
    supervisor handles an agent's report inside one: what the report is logged as, and
    what the platform logs because of it, carry the time it happened."""
    token = _occurred.set(when)
    try:
        yield
    finally:
        _occurred.reset(token)


def _feed_item(event: SessionEvent) -> dict[str, Any]:
    """An event as the session feeds carry it, with its line in words (``text``)."""
    return {
        "seq": event.seq,
        "kind": event.kind,
        "data": event.data,
        "text": event_text(event.kind, event.data),
        "at": event.created_at.isoformat(),
    }


@dataclass
class _Staged:
    """Events of one new session waiting to be written (see :func:`events_staged`)."""

    session_id: Any
    events: list[SessionEvent] = field(default_factory=list)

    @property
    def tail(self) -> tuple[int, str]:
        last = self.events[-1] if self.events else None
        return (last.seq, last.hash) if last else (0, GENESIS_HASH)


_staging: ContextVar[_Staged | None] = ContextVar("iouv_events_staged", default=None)


@contextmanager
def events_staged(*, session_id: Any) -> Iterator[list[SessionEvent]]:
    """Within the block, :func:`event_append` for the session ``session_id`` stages its
    events; when the block ends without an error they are written with one INSERT, in
    order, and announced to the monitors' feed in one message. Yields the staged
    events' list.

    Only for a session created in the block's transaction, with no event logged yet:
    nobody else can write to its log before the transaction commits, so no lock is
    taken and no tail is read. Run the block inside that transaction: on an error the
    staged events are dropped, as the transaction's other writes are rolled back.
    Nothing in the block may read the session's log back (it is not written yet).
    """
    if _staging.get() is not None:
        raise RuntimeError("events_staged blocks do not nest")
    staged = _Staged(session_id=session_id)
    token = _staging.set(staged)
    try:
        yield staged.events
    finally:
        _staging.reset(token)
    if staged.events:
        SessionEvent.objects.bulk_create(staged.events)
        # The session is new: no page follows it yet (its id is not even known
        # outside this transaction), so only the monitors' feed is told.
        session_notify_many(
            session_id=session_id, events=[_feed_item(e) for e in staged.events], new=True
        )


def session_log(*, session: Session) -> list[SessionEvent]:
    """``session``'s whole log, in order. Read by a holder of the session's lock, it is
    where the next event goes (:func:`event_append`'s ``log``)."""
    return list(SessionEvent.objects.filter(session_id=session.pk).order_by("seq"))


def event_append(
    *,
    session: Session,
    kind: str,
    data: dict[str, Any] | None = None,
    locked: bool = False,
    log: list[SessionEvent] | None = None,
) -> SessionEvent:
    """Append one event to ``session``'s log and return it (unsaved while staged by
    :func:`events_staged`, which writes it when its block ends).

    Concurrent writers (the supervisor, a worker, a view) get consecutive sequence
    numbers and a single chain: each event takes the next free place (module
    docstring). Inside a transaction the session's row is locked first; ``locked``: the
    caller already holds that lock in the current transaction. ``log``: the caller
    holds it and read the whole log under it (:func:`session_log`); the event follows
    its last and is added to it (the log is read again if another writer's event came
    in between).
    """
    staged = _staging.get()
    if staged is not None and staged.session_id == session.pk:
        seq, prev_hash = staged.tail
        event = _event_new(session=session, seq=seq + 1, prev_hash=prev_hash, kind=kind, data=data)
        staged.events.append(event)
        return event
    if log is None and not locked and get_connection().in_atomic_block:
        # Inside a transaction: lock first, as every writer in one does (above).
        list(
            Session.objects.select_for_update(no_key=True)
            .filter(pk=session.pk)
            .values_list("pk", flat=True)
        )
    event = _event_next(session=session, kind=kind, data=data, log=log)
    if log is None:
        _event_place(session=session, event=event, log=None)
        return event

    # The caller holds the lock and read the log: the event follows what it read. Only
    # a lock-free writer (an agent's report) can have taken its place meanwhile.
    if _event_saved_unless_taken(event):
        _event_placed(session=session, event=event, log=log)
    else:
        log[:] = session_log(session=session)
        _event_renew(event, session=session, log=log)
        _event_place(session=session, event=event, log=log)
    return event


def _event_saved_unless_taken(event: SessionEvent) -> bool:
    """Insert ``event``; False, with nothing written, if another event holds its place
    (its session's ``seq``, unique). Raises IntegrityError for any other constraint."""
    try:
        if get_connection().in_atomic_block:
            # A savepoint: the place found taken must not abort the caller's transaction.
            with transaction.atomic():
                event.save(force_insert=True)
        else:
            event.save(force_insert=True)
    except IntegrityError:
        if SessionEvent.objects.filter(session_id=event.session_id, seq=event.seq).exists():
            return False
        raise
    return True


def _event_next(
    *,
    session: Session,
    kind: str,
    data: dict[str, Any] | None,
    log: list[SessionEvent] | None,
    occurred_at: datetime | None = None,
) -> SessionEvent:
    """The event that follows ``log`` (the log's tail, read now, if None)."""
    if log is not None:
        last = (log[-1].seq, log[-1].hash) if log else None
    else:
        last = (
            SessionEvent.objects.filter(session_id=session.pk)
            .order_by("-seq")
            .values_list("seq", "hash")
            .first()
        )
    seq, prev_hash = last if last else (0, GENESIS_HASH)
    return _event_new(
        session=session,
        seq=seq + 1,
        prev_hash=prev_hash,
        kind=kind,
        data=data,
        occurred_at=occurred_at,
    )


def _event_renew(event: SessionEvent, *, session: Session, log: list[SessionEvent] | None) -> None:
    """``event`` moved to the place after ``log`` (its tail read now, if None)."""
    fresh = _event_next(
        session=session, kind=event.kind, data=event.data, log=log, occurred_at=event.occurred_at
    )
    for name in ("seq", "prev_hash", "hash", "created_at"):
        setattr(event, name, getattr(fresh, name))


def _event_place(*, session: Session, event: SessionEvent, log: list[SessionEvent] | None) -> None:
    """Write ``event`` in its place, or after the events that took it."""
    for _ in range(_PLACE_TRIES):
        if _event_saved_unless_taken(event):
            break
        # Another writer's event took the place: follow it.
        if log is not None:
            log[:] = session_log(session=session)
        _event_renew(event, session=session, log=log)
    else:
        raise RuntimeError(
            f"session {session.pk}: no free place in its log after {_PLACE_TRIES} tries"
        )
    _event_placed(session=session, event=event, log=log)


def _event_placed(*, session: Session, event: SessionEvent, log: list[SessionEvent] | None) -> None:
    """``event`` is written: the session's feeds are told once its transaction commits."""
    session_notify(session_id=session.pk, event=_feed_item(event))
    if log is not None:
        log.append(event)


@dataclass(frozen=True)
class LogCheck:
    """Result of a chain check: ``ok``, else the first bad sequence number and why."""

    ok: bool
    events: int
    bad_seq: int | None = None
    problem: str = ""


def session_log_verify(
    *, session: Session, events: Iterable[SessionEvent] | None = None
) -> LogCheck:
    """Recompute the chain of ``session``'s log from the stored rows, or from
    ``events`` (those rows, already read in ``seq`` order)."""
    prev_hash = GENESIS_HASH
    count = 0
    rows = session_log(session=session) if events is None else events
    for expected_seq, event in enumerate(rows, start=1):
        count += 1
        if event.seq != expected_seq:
            return LogCheck(False, count, event.seq, f"expected event #{expected_seq} here")
        if event.prev_hash != prev_hash:
            return LogCheck(False, count, event.seq, "does not follow the previous event")
        recomputed = _event_hash(
            session_id=str(session.pk),
            seq=event.seq,
            kind=event.kind,
            data=event.data,
            created_at=event.created_at.isoformat(),
            prev_hash=event.prev_hash,
            occurred_at=event.occurred_at.isoformat() if event.occurred_at else None,
        )
        if recomputed != event.hash:
            return LogCheck(False, count, event.seq, "content does not match its hash")
        prev_hash = event.hash
    return LogCheck(True, count)
