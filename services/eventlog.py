"""The session log: append-only and hash-chained.

Each event stores the SHA-256 of its own canonical content plus the previous event's
hash, so changing, removing or reordering a stored event breaks the chain from that
point on, and ``session_log_verify`` names the first broken event.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import Any

from django.core.serializers.json import DjangoJSONEncoder
from django.db import transaction
from django.utils import timezone

from services.feed import session_notify
from services.models import Session, SessionEvent

GENESIS_HASH = "0" * 64


def _event_hash(
    *, session_id: str, seq: int, kind: str, data: Any, created_at: str, prev_hash: str
) -> str:
    canonical = json.dumps(
        {
            "session": session_id,
            "seq": seq,
            "kind": kind,
            "data": data,
            "created_at": created_at,
            "prev": prev_hash,
        },
        sort_keys=True,
        separators=(",", ":"),
        cls=DjangoJSONEncoder,
    )
    return hashlib.sha256(canonical.encode()).hexdigest()


def event_append(
    *, session: Session, kind: str, data: dict[str, Any] | None = None
) -> SessionEvent:
    """Append one event to ``session``'s log and return it.

    The session row is locked so concurrent writers (the supervisor, a worker, a view)
    get consecutive sequence numbers and a single chain.
    """
    # Round-trip through JSON so the hash covers exactly what the database stores.
    payload = json.loads(json.dumps(data or {}, cls=DjangoJSONEncoder))
    with transaction.atomic():
        Session.objects.select_for_update().filter(pk=session.pk).first()
        last = SessionEvent.objects.filter(session=session).order_by("-seq").first()
        seq = last.seq + 1 if last else 1
        prev_hash = last.hash if last else GENESIS_HASH
        created_at = timezone.now()
        event = SessionEvent(
            session=session,
            seq=seq,
            kind=kind,
            data=payload,
            created_at=created_at,
            prev_hash=prev_hash,
            hash=_event_hash(
                session_id=str(session.pk),
                seq=seq,
                kind=kind,
                data=payload,
                created_at=created_at.isoformat(),
                prev_hash=prev_hash,
            ),
        )
        event.save()
        session_notify(
            session_id=session.pk,
            event={"seq": seq, "kind": kind, "data": payload, "at": created_at.isoformat()},
        )
    return event


@dataclass(frozen=True)
class LogCheck:
    """Result of a chain check: ``ok``, else the first bad sequence number and why."""

    ok: bool
    events: int
    bad_seq: int | None = None
    problem: str = ""


def session_log_verify(*, session: Session) -> LogCheck:
    """Recompute the chain of ``session``'s log from the stored rows."""
    prev_hash = GENESIS_HASH
    count = 0
    for expected_seq, event in enumerate(session.events.order_by("seq"), start=1):
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
        )
        if recomputed != event.hash:
            return LogCheck(False, count, event.seq, "content does not match its hash")
        prev_hash = event.hash
    return LogCheck(True, count)
