"""Mission files on the platform without servers (services.records.artifacts): a file
uploaded in chunks, in any order and some twice, is kept whole once, logged by its digest
only, and its session's kind hears of it once; a forged, short or false chunk is refused
and changes nothing."""

from __future__ import annotations

import base64
import hashlib
import json
import os

import pytest
from django.db import transaction

from agents.protocol import ProtocolError, parse_message
from agents.protocol.messages import ARTIFACT_CHUNK_BYTES, Artifact
from services.kinds import kind_of
from services.models import ArtifactChunk, SessionArtifact
from services.records.artifacts import artifact_chunk_store
from tests import factories as f

pytestmark = pytest.mark.django_db(transaction=True)

BODY = os.urandom(2 * ARTIFACT_CHUNK_BYTES + 1000)  # three chunks, the last one short


def chunk(session_id: str, index: int, body: bytes = BODY, **overrides) -> Artifact:
    start = index * ARTIFACT_CHUNK_BYTES
    fields = {
        "id": f"artifact:{session_id}:photo-0001.jpg:{index}",
        "session_id": session_id,
        "name": "photo-0001.jpg",
        "media_type": "image/jpeg",
        "size": len(body),
        "sha256": hashlib.sha256(body).hexdigest(),
        "index": index,
        "count": -(-len(body) // ARTIFACT_CHUNK_BYTES),
        "meta": {"lat": 40.63, "lon": -8.65, "alt": 30.0, "heading": 90.0},
        "b64": base64.b64encode(body[start : start + ARTIFACT_CHUNK_BYTES]).decode(),
    }
    return Artifact(**{**fields, **overrides})


def test_a_file_in_chunks_is_kept_whole_once_and_logged_by_its_digest(live_session) -> None:
    session, vehicle = live_session
    sid = str(session.pk)
    for index in (2, 0, 0, 1):  # any order, one twice (an ack lost)
        outcome = artifact_chunk_store(vehicle_id=vehicle, message=chunk(sid, index))
        assert outcome.ok, outcome.detail
    again = artifact_chunk_store(vehicle_id=vehicle, message=chunk(sid, 1))
    assert again.ok and again.detail == "already stored"
    kept = SessionArtifact.objects.get(session=session)
    assert bytes(kept.data) == BODY and kept.stored and kept.meta["heading"] == 90.0
    assert not ArtifactChunk.objects.exists()
    logged = [e.data for e in session.events.filter(kind="artifact_stored")]
    assert logged == [
        {
            "vehicle": vehicle,
            "name": "photo-0001.jpg",
            "media_type": "image/jpeg",
            "size": len(BODY),
            "sha256": hashlib.sha256(BODY).hexdigest(),
        }
    ]
    # The photo's bytes are in no log entry.
    assert all("b64" not in e.data for e in session.events.all())


def test_the_sessions_kind_hears_of_each_whole_file_once(live_session, monkeypatch) -> None:
    session, vehicle = live_session
    heard: list[str] = []
    kind = type(kind_of(session.service))
    monkeypatch.setattr(
        kind, "artifact_received", lambda self, *, artifact: heard.append(artifact.name)
    )
    sid = str(session.pk)
    for index in (0, 1):
        artifact_chunk_store(vehicle_id=vehicle, message=chunk(sid, index))
    assert heard == []
    with transaction.atomic():
        artifact_chunk_store(vehicle_id=vehicle, message=chunk(sid, 2))
        assert heard == []  # after the commit, not before
    artifact_chunk_store(vehicle_id=vehicle, message=chunk(sid, 2))
    assert heard == ["photo-0001.jpg"]


def test_a_forged_short_or_false_chunk_is_refused_and_changes_nothing(live_session) -> None:
    session, vehicle = live_session
    sid = str(session.pk)
    other = f.vehicle(station=f.station(), vtype=f.vehicle_type(name="other type"))
    forged = artifact_chunk_store(vehicle_id=other.pk, message=chunk(sid, 0))
    assert not forged.ok and forged.detail == "not a session of this vehicle"
    short = chunk(sid, 0, b64=base64.b64encode(BODY[:100]).decode())
    refused = artifact_chunk_store(vehicle_id=vehicle, message=short)
    assert not refused.ok and "must hold 32768 bytes" in refused.detail
    assert (
        not SessionArtifact.objects.exists()
        and not session.events.filter(kind="artifact_stored").exists()
    )
    # Chunks that are not the file they claim to be: nothing of it is kept.
    lie = bytes(len(BODY))
    for index in range(3):
        outcome = artifact_chunk_store(
            vehicle_id=vehicle,
            message=chunk(sid, index, body=lie, sha256=hashlib.sha256(BODY).hexdigest()),
        )
    assert not outcome.ok and "does not hash" in outcome.detail
    assert not SessionArtifact.objects.exists() and not ArtifactChunk.objects.exists()
    # Another vehicle of the same session may not replace this vehicle's file.
    for index in range(3):
        artifact_chunk_store(vehicle_id=vehicle, message=chunk(sid, index))
    session.assignments.create(vehicle=other, role="spare", distance_m=0)
    taken = artifact_chunk_store(vehicle_id=other.pk, message=chunk(sid, 0, body=BODY[::-1]))
    assert not taken.ok and "another vehicle's file" in taken.detail
    assert bytes(SessionArtifact.objects.get().data) == BODY


def test_an_oversized_or_inconsistent_chunk_is_refused_by_the_protocol() -> None:
    too_big = {**_fields(chunk("s", 0)), "b64": "A" * (ARTIFACT_CHUNK_BYTES * 2)}
    with pytest.raises(ProtocolError) as exc:
        parse_message(_frame(too_big), channel="uplink_to_platform")
    assert exc.value.code in ("too_large", "bad_field")
    wrong_count = {**_fields(chunk("s", 0)), "count": 7}
    with pytest.raises(ProtocolError, match="count"):
        parse_message(_frame(wrong_count), channel="uplink_to_platform")
    path = {**_fields(chunk("s", 0)), "name": "../etc/passwd"}
    with pytest.raises(ProtocolError, match="name"):
        parse_message(_frame(path), channel="uplink_to_platform")


def _fields(message: Artifact) -> dict:
    return {"type": "artifact", **{n: getattr(message, n) for n in message.__struct_fields__}}


def _frame(data: dict) -> str:
    return json.dumps(data)
