"""Files missions upload (``artifact`` chunks: the photos a mission takes), kept with their
session (docs/protocol.md, "Mission files").

:func:`artifact_chunk_store` keeps each chunk once by (session, name, index); when the
last one is there and the whole hashes to the file's SHA-256, the file is assembled into
its :class:`~services.models.SessionArtifact`, its name, size and digest (never its
bytes) go into the session's hash-chained log (``artifact_stored``), and, once that is
committed, the session's kind hears of it (``ServiceKind.artifact_received``). Anything
else (a session the vehicle never served, a name another vehicle's file holds, a chunk
of the wrong length, a file that does not hash to what it claims) is refused for good
and changes nothing.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import logging
import uuid
from typing import Any

from django.db import IntegrityError, transaction
from django.utils import timezone

from agents.protocol.messages import Artifact
from fleet.records import RecordOutcome
from services.kinds import UnknownKind, kind_of
from services.models import ArtifactChunk, Assignment, Session, SessionArtifact
from services.sessions.log import event_append

log = logging.getLogger(__name__)


def _refused(detail: str) -> RecordOutcome:
    return RecordOutcome(ok=False, detail=detail)


def artifact_chunk_store(*, vehicle_id: Any, message: Artifact) -> RecordOutcome:
    """Keep chunk ``message`` from ``vehicle_id``'s agent (module docstring). Returns
    what the agent is told: kept (or kept already), or refused for good."""
    try:
        session_id = uuid.UUID(message.session_id)
    except ValueError:
        return _refused("not a session of this vehicle")
    if not Assignment.objects.filter(session_id=session_id, vehicle_id=vehicle_id).exists():
        return _refused("not a session of this vehicle")
    try:
        chunk = base64.b64decode(message.b64, validate=True)
    except (binascii.Error, ValueError):
        return _refused("the chunk is not base64")
    if len(chunk) != message.chunk_bytes():
        return _refused(f"chunk {message.index} must hold {message.chunk_bytes()} bytes")
    with transaction.atomic():
        session = Session.objects.select_for_update(no_key=True).get(pk=session_id)
        artifact, _ = SessionArtifact.objects.get_or_create(
            session=session,
            name=message.name,
            defaults={
                "vehicle_id": vehicle_id,
                "media_type": message.media_type,
                "size": message.size,
                "sha256": message.sha256,
                "count": message.count,
                "meta": message.meta,
            },
        )
        if str(artifact.vehicle_id) != str(vehicle_id):
            return _refused(f"{message.name} is another vehicle's file in this session")
        if (artifact.size, artifact.sha256, artifact.media_type) != (
            message.size,
            message.sha256,
            message.media_type,
        ):
            return _refused(f"{message.name} is another file of this session")
        if artifact.stored:
            return RecordOutcome(ok=True, detail="already stored")
        try:
            with transaction.atomic():
                ArtifactChunk.objects.create(artifact=artifact, index=message.index, data=chunk)
        except IntegrityError:
            return RecordOutcome(ok=True, detail="already stored")
        if artifact.chunks.count() < artifact.count:
            return RecordOutcome(ok=True, detail="")
        body = b"".join(
            bytes(part) for part in artifact.chunks.order_by("index").values_list("data", flat=True)
        )
        if hashlib.sha256(body).hexdigest() != artifact.sha256:
            # Whatever it is, it is not the file it says: nothing of it is kept.
            artifact.delete()
            return _refused(f"{message.name} does not hash to its sha256")
        artifact.data = body
        artifact.stored_at = timezone.now()
        artifact.save(update_fields=["data", "stored_at"])
        artifact.chunks.all().delete()
        event_append(
            session=session,
            kind="artifact_stored",
            data={
                "vehicle": str(vehicle_id),
                "name": artifact.name,
                "media_type": artifact.media_type,
                "size": artifact.size,
                "sha256": artifact.sha256,
            },
            locked=True,
        )
        transaction.on_commit(lambda: _tell_kind(artifact.pk), robust=True)
    return RecordOutcome(ok=True, detail="")


def _tell_kind(artifact_id: Any) -> None:
    artifact = SessionArtifact.objects.select_related("session__service").get(pk=artifact_id)
    try:
        kind = kind_of(artifact.session.service)
    except UnknownKind:
        return
    kind.artifact_received(artifact=artifact)
