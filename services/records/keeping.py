"""Flight records on the platform: the batches vehicles upload, chained into the
session's log, read back, checked, kept for a while (docs/records.md).

A batch (``record`` on the uplink, agents.recording) is stored once per (session,
vehicle, first sample) with the SHA-256 of its samples; that digest goes into the
session's hash-chained log as a ``record_batch`` event in the same transaction. The
session's recorded video is chained the same way once converted, a ``record_video``
event per stretch (services.sessions.video). So a record is checked in two steps
(:func:`record_verify`): the log's chain holds, and every stored batch's samples and
every stretch of video still hash to the digest the chain holds for them. A sample
changed, added or removed in the database, or a video file replaced on disk, breaks the
second; rewriting the digest in the log breaks the first.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import logging
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Any, Literal

from django.conf import settings
from django.db import IntegrityError, connection, transaction
from django.db.models import Q
from django.utils import timezone

from agents.protocol.messages import Record
from fleet.records import RecordOutcome
from services.models import Assignment, RecordBatch, RecordSample, Session
from services.sessions.log import event_append, session_log, session_log_verify
from services.sessions.video import video_chained, video_digest
from services.sfu import sfu_recorded_sessions, sfu_recording_delete, sfu_recordings

log = logging.getLogger(__name__)


def _canonical(seq: int, t: float, kind: str, data: Any) -> dict[str, Any]:
    return {"seq": seq, "t": t, "kind": kind, "data": data}


def record_digest(samples: Iterable[dict[str, Any]]) -> str:
    """The SHA-256 (hex) of samples given as ``{"seq", "t", "kind", "data"}``, in order."""
    body = json.dumps(list(samples), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(body.encode()).hexdigest()


def record_batch_store(*, vehicle_id: Any, message: Record) -> RecordOutcome:
    """Keep ``message``, a batch from ``vehicle_id``'s agent, and chain its digest into
    the session's log. Returns what the agent is told: stored (or already stored: the
    agent sent it again), or refused for good (not a session this vehicle served)."""
    try:
        session_id = uuid.UUID(message.session_id)
    except ValueError:
        return RecordOutcome(ok=False, detail="not a session of this vehicle")
    if not Assignment.objects.filter(session_id=session_id, vehicle_id=vehicle_id).exists():
        return RecordOutcome(ok=False, detail="not a session of this vehicle")
    # Round-tripped through JSON so the digest covers exactly what the database keeps.
    rows = json.loads(json.dumps([_canonical(s.seq, s.t, s.kind, s.data) for s in message.samples]))
    digest = record_digest(rows)
    last = message.first + len(rows) - 1
    with transaction.atomic():
        session = Session.objects.select_for_update(no_key=True).get(pk=session_id)
        if RecordBatch.objects.filter(
            session=session, vehicle_id=vehicle_id, first=message.first
        ).exists():
            return RecordOutcome(ok=True, detail="already stored")
        try:
            with transaction.atomic():
                batch = RecordBatch.objects.create(
                    session=session,
                    vehicle_id=vehicle_id,
                    first=message.first,
                    last=last,
                    digest=digest,
                )
                RecordSample.objects.bulk_create(
                    RecordSample(
                        batch=batch,
                        session=session,
                        vehicle_id=vehicle_id,
                        seq=row["seq"],
                        t=row["t"],
                        kind=row["kind"],
                        data=row["data"],
                    )
                    for row in rows
                )
        except IntegrityError:
            # Samples of this batch stored under other bounds: the agent's numbering
            # is its own, so this is a different batch claiming the same samples.
            return RecordOutcome(ok=False, detail="samples already stored in another batch")
        event_append(
            session=session,
            kind="record_batch",
            data={
                "vehicle": str(vehicle_id),
                "first": message.first,
                "last": last,
                "digest": digest,
            },
            locked=True,
        )
    return RecordOutcome(ok=True, detail="")


# --- reading ---------------------------------------------------------------------------


def record_samples(*, session: Session, kinds: Iterable[str] | None = None) -> list[RecordSample]:
    """The session's samples (of ``kinds``), by vehicle then number."""
    rows = RecordSample.objects.filter(session=session)
    if kinds is not None:
        rows = rows.filter(kind__in=list(kinds))
    return list(rows.order_by("vehicle_id", "seq"))


def record_tlog(*, session: Session) -> bytes:
    """The session's raw MAVLink stream as a ``.tlog`` (empty without one)."""
    return b"".join(
        base64.b64decode(sample.data.get("b64", ""))
        for sample in record_samples(session=session, kinds=["tlog"])
    )


#: How far :func:`record_verify` checks the video: each file's size (a ``stat``), or its
#: size and SHA-256 (every byte read).
VideoCheck = Literal["size", "sha256"]


@dataclass(frozen=True)
class RecordCheck:
    """The result of :func:`record_verify`: ``ok``, else ``problems`` in words;
    ``videos``: the stretches of video the log chains, checked by ``video_check``."""

    ok: bool
    batches: int
    samples: int
    problems: list[str] = field(default_factory=list)
    videos: int = 0
    video_check: VideoCheck = "sha256"

    def as_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "batches": self.batches,
            "samples": self.samples,
            "videos": self.videos,
            "video_check": self.video_check,
            "problems": self.problems,
        }


@contextlib.contextmanager
def _one_snapshot() -> Iterator[None]:
    """A transaction whose reads all see the database as of its first one (PostgreSQL's
    REPEATABLE READ; SQLite's transactions read one snapshot anyway). Inside a caller's
    transaction, that transaction as it is."""
    if connection.in_atomic_block:
        yield
        return
    with transaction.atomic():
        if connection.vendor == "postgresql":
            with connection.cursor() as cursor:
                cursor.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ, READ ONLY")
        yield


def record_verify(*, session: Session, video: VideoCheck = "sha256") -> RecordCheck:
    """Check ``session``'s record against its log (module docstring): the chain holds,
    every batch the log names is stored and hashes to its digest, every stored batch is
    named, each vehicle's samples are numbered without a gap, and the same for the
    video's stretches (:func:`_video_problems`), each checked by ``video``: its size
    only, or its SHA-256 too (which reads all of it).

    The log and the record are read as they were at one moment: an agent's batch stored
    meanwhile (with its log event, in one transaction) is in both or in neither, never
    found stored but not logged."""
    with _one_snapshot():
        return _record_verified(session=session, video=video)


def _record_verified(*, session: Session, video: VideoCheck) -> RecordCheck:
    problems: list[str] = []
    events = session_log(session=session)
    chain = session_log_verify(session=session, events=events)
    if not chain.ok:
        problems.append(f"the session log breaks at event #{chain.bad_seq}: {chain.problem}")
    chained = {
        (e.data.get("vehicle"), e.data.get("first")): e.data
        for e in events
        if e.kind == "record_batch"
    }
    deleted = any(e.kind == "record_deleted" for e in events)
    batches = list(RecordBatch.objects.filter(session=session).order_by("vehicle_id", "first"))
    samples = record_samples(session=session)
    by_batch: dict[int, list[RecordSample]] = {}
    for sample in samples:
        by_batch.setdefault(sample.batch_id, []).append(sample)
    seen: set[tuple[str, int]] = set()
    for batch in batches:
        key = (str(batch.vehicle_id), batch.first)
        seen.add(key)
        entry = chained.get(key)
        rows = by_batch.get(batch.pk, [])
        digest = record_digest(_canonical(s.seq, s.t, s.kind, s.data) for s in rows)
        if entry is None:
            problems.append(f"batch {batch.first}-{batch.last} is not in the session log")
        elif entry.get("digest") != digest or entry.get("last") != batch.last:
            problems.append(f"batch {batch.first}-{batch.last} does not match its digest")
        if [s.seq for s in rows] != list(range(batch.first, batch.last + 1)):
            problems.append(f"batch {batch.first}-{batch.last} lacks samples")
    if not deleted:
        for vehicle, first in sorted(set(chained) - seen, key=str):
            problems.append(f"batch from {first} of vehicle {vehicle} is missing")
    last_by_vehicle: dict[Any, int] = {}
    for sample in samples:
        previous = last_by_vehicle.get(sample.vehicle_id, 0)
        if sample.seq != previous + 1:
            problems.append(f"samples {previous + 1}-{sample.seq - 1} were never received")
        last_by_vehicle[sample.vehicle_id] = sample.seq
    videos = video_chained(events)
    problems += _video_problems(session=session, chained=videos, deleted=deleted, check=video)
    return RecordCheck(not problems, len(batches), len(samples), problems, len(videos), video)


def _video_problems(
    *, session: Session, chained: dict[str, dict[str, Any]], deleted: bool, check: VideoCheck
) -> list[str]:
    """What does not hold between the session's converted video and the stretches its
    log chains (``chained``): a chained stretch missing (unless the record was deleted),
    one whose size, digest (``check`` "sha256") or start no longer match, a converted
    one the log does not hold."""
    problems: list[str] = []
    converted = {r.path.name: r for r in sfu_recordings(session_id=session.pk)}
    for name, entry in chained.items():
        recording = converted.get(name)
        if recording is None:
            if not deleted:  # deleting the record deletes its video (record_delete)
                problems.append(f"video {name} is missing")
            continue
        try:
            if check == "sha256":
                size, digest = video_digest(recording.path)
            else:
                size, digest = recording.path.stat().st_size, None
        except OSError as exc:
            problems.append(f"video {name} cannot be read: {exc.strerror}")
            continue
        if size != entry.get("size") or digest not in (None, entry.get("sha256")):
            problems.append(f"video {name} does not match its digest")
        elif recording.started_at != entry.get("started_at"):
            # Its start comes from the .mjr's header: changed, the replay and the zip
            # would place the video at another time of the flight.
            problems.append(f"video {name} no longer starts when the log says")
    for name in sorted(set(converted) - set(chained)):
        problems.append(f"video {name} is not in the session log")
    return problems


def record_visible(*, session: Session, user: Any) -> bool:
    """Who may open a record: the session's user, monitors (who may view every
    session), admins."""
    return bool(
        user.is_authenticated
        and (
            session.user_id == user.pk
            or user.is_superuser
            or user.has_perm("services.view_session")
        )
    )


# --- keeping ---------------------------------------------------------------------------


def record_delete(*, session: Session, by: str) -> int:
    """Delete ``session``'s record (its batches and samples, and the SFU's video of it);
    the log keeps the batches' digests and says who deleted it and when. Returns the
    samples deleted."""
    with transaction.atomic():
        session = Session.objects.select_for_update(no_key=True).get(pk=session.pk)
        count = RecordSample.objects.filter(session=session).count()
        video = bool(sfu_recordings(session_id=session.pk))
        if not RecordBatch.objects.filter(session=session).exists() and not video:
            return 0
        RecordBatch.objects.filter(session=session).delete()
        data: dict[str, Any] = {"by": by, "samples": count}
        if video:
            data["video"] = True
            # The files go once the deletion is committed (a rollback keeps them).
            session_id = session.pk
            transaction.on_commit(lambda: sfu_recording_delete(session_id=session_id))
        event_append(session=session, kind="record_deleted", data=data, locked=True)
    return count


def records_expire(*, now: Any = None) -> int:
    """Delete the records of sessions created more than ``IOUV_RECORD_RETENTION_DAYS``
    ago (none when it is 0). Returns how many records went."""
    days = settings.IOUV_RECORD_RETENTION_DAYS
    if days <= 0:
        return 0
    cutoff = (now or timezone.now()) - timedelta(days=days)
    expired = Session.objects.filter(created_at__lt=cutoff).filter(
        Q(pk__in=RecordBatch.objects.values("session_id")) | Q(pk__in=sfu_recorded_sessions())
    )
    done = 0
    for session in expired:
        try:
            record_delete(session=session, by=f"retention ({days} days)")
            done += 1
        except Exception:  # one failing record must not keep the others
            log.exception("could not delete the record of session %s", session.pk)
    return done
