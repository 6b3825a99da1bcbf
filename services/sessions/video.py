"""A session's recorded video once the session has ended: the SFU's room closed, the
recording converted to WebM (services.sfu) and each converted stretch chained into the
session's hash-chained log as a ``record_video`` event: its file name, size, SHA-256
and start time (docs/records.md). The record's check
(services.records.keeping.record_verify) holds the files to those events.

Chaining is idempotent and runs after every conversion, whether or not the conversion
failed part way: a stretch is chained once however often the task runs, and a stretch
converted by a run that died before chaining it is chained by the next run.

Here rather than in services.records: the session's end (services.sessions.states)
schedules the task, and services.records imports the sessions' code.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Final

from celery import shared_task
from django.db import OperationalError, transaction

from services.models import Session, SessionEvent
from services.sessions.log import event_append, session_log
from services.sfu import (
    Recording,
    SfuError,
    sfu_configured,
    sfu_recording_convert,
    sfu_recordings,
    sfu_room_close,
)

log = logging.getLogger(__name__)

#: The log's event for one converted stretch of video.
RECORD_VIDEO: Final = "record_video"
#: Bytes read from a video at a time to hash it: all of it that is held in memory.
DIGEST_CHUNK: Final = 1 << 20


def video_digest(path: Path) -> tuple[int, str]:
    """The size and SHA-256 (hex) of the file at ``path``, read a megabyte at a time (an
    hour of video is never held whole). Raises OSError."""
    digest, size = hashlib.sha256(), 0
    with path.open("rb") as source:
        while chunk := source.read(DIGEST_CHUNK):
            digest.update(chunk)
            size += len(chunk)
    return size, digest.hexdigest()


def video_chained(events: Iterable[SessionEvent]) -> dict[str, dict[str, Any]]:
    """The stretches of video a session's log (``events``) chains: file name -> what the
    log holds of it (``name``, ``size``, ``sha256``, ``started_at``)."""
    return {
        str(event.data.get("name")): event.data for event in events if event.kind == RECORD_VIDEO
    }


def session_video_chain(*, session_id: Any) -> int:
    """Chain each of the session's converted stretches (services.sfu.sfu_recordings)
    that its log does not hold yet; idempotent. Returns how many were chained now."""
    session = Session.objects.get(pk=session_id)
    chained = video_chained(session_log(session=session))
    # Hashed before the session's row is locked: reading an hour of video takes seconds,
    # and the lock holds every other writer of the session back meanwhile.
    fresh = [
        (recording, *video_digest(recording.path))
        for recording in sfu_recordings(session_id=session_id)
        if recording.path.name not in chained
    ]
    if not fresh:
        return 0
    done = 0
    with transaction.atomic():
        session = Session.objects.select_for_update(no_key=True).get(pk=session_id)
        events = session_log(session=session)
        # Read again under the lock: another run (a task delivered twice) may have
        # chained some of them meanwhile.
        chained = video_chained(events)
        for recording, size, sha256 in fresh:
            if recording.path.name in chained:
                continue
            event_append(
                session=session,
                kind=RECORD_VIDEO,
                data={
                    "name": recording.path.name,
                    "size": size,
                    "sha256": sha256,
                    "started_at": recording.started_at,
                },
                locked=True,
                log=events,
            )
            done += 1
    return done


def session_video_convert(*, session_id: Any) -> list[Recording]:
    """Convert the session's recorded video to WebM and chain what is converted
    (:func:`session_video_chain`), that too when a conversion fails. Idempotent. Returns
    the session's recordings. Raises SfuError when janus-pp-rec is missing or fails."""
    try:
        sfu_recording_convert(session_id=session_id)
    finally:
        # The stretches converted before a failure are chained all the same: a video
        # that never converts must not keep the others out of the chain.
        session_video_chain(session_id=session_id)
    return sfu_recordings(session_id=session_id)


def session_video_ended(*, session_id: Any) -> list[Recording]:
    """Close the ended session's SFU room (its recording ends), convert what was
    recorded and chain it. Idempotent. Returns the session's recordings. Raises
    SfuError (Janus away, janus-pp-rec failing): the caller tries again later."""
    sfu_room_close(session_id=session_id)
    return session_video_convert(session_id=session_id)


def session_video_end_schedule(*, session_id: Any) -> None:
    """Once the current transaction commits, close the ended session's room and convert
    and chain its recording, from a Celery task (nothing without an SFU)."""
    if not sfu_configured():
        return
    transaction.on_commit(lambda: services_sfu_session_ended.delay(str(session_id)), robust=True)


# Its name is the one the task had in services.sfu: tasks queued before an upgrade run.
@shared_task(
    name="services.sfu_session_ended",
    acks_late=True,
    autoretry_for=(SfuError, OperationalError),
    max_retries=10,
    retry_backoff=5,
    retry_backoff_max=300,
    retry_jitter=True,
)
def services_sfu_session_ended(session_id: str) -> int:
    """Close an ended session's SFU room, convert its recording to WebM and chain it
    into the session's log; retried while Janus, janus-pp-rec or the database fails.
    Returns how many recordings it has."""
    return len(session_video_ended(session_id=session_id))
