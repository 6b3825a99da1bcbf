"""The record's zip (services.records.exports.record_archive) with the session's video:
real WebM files where the SFU's conversion leaves them go into ``video/<n>.webm``,
``manifest.json`` lists every file with its size and SHA-256, says whether there is
video and where the log chains each stretch; the archive is streamed, a video a piece at
a time, under WSGI and ASGI alike."""

from __future__ import annotations

import asyncio
import hashlib
import io
import json
import math
import zipfile
from pathlib import Path
from typing import Any

import pytest
from django.test import AsyncRequestFactory, Client

from accounts.tokens import token_issue
from agents.protocol.messages import Record, RecordSample
from services.models import Session
from services.records import exports
from services.records.keeping import record_batch_store
from services.sessions.video import session_video_chain
from services.web.record_views import record_file
from tests import factories as f
from tests.recordings import decoded_frames, recorded, webm

pytestmark = pytest.mark.django_db


def with_a_track(session: Session, vehicle: str) -> None:
    record_batch_store(
        vehicle_id=vehicle,
        message=Record(
            id=f"record:{session.pk}:1",
            session_id=str(session.pk),
            first=1,
            samples=[
                RecordSample(
                    seq=1, t=1.7958564e9, kind="telemetry", data={"lat": 40.0, "lon": -8.0}
                ),
                RecordSample(seq=2, t=1.7958565e9, kind="command", data={"name": "land"}),
            ],
        ),
    )


def opened(pieces: list[bytes]) -> zipfile.ZipFile:
    archive = zipfile.ZipFile(io.BytesIO(b"".join(pieces)))
    assert archive.testzip() is None  # every entry's CRC holds
    return archive


def manifest_checked(archive: zipfile.ZipFile) -> dict[str, Any]:
    """``manifest.json``, having checked that it lists every other file of the archive
    with its size and SHA-256."""
    manifest = json.loads(archive.read("manifest.json"))
    listed = {entry["name"]: entry for entry in manifest["files"]}
    assert set(listed) == set(archive.namelist()) - {"manifest.json"}
    for name, entry in listed.items():
        body = archive.read(name)
        assert entry["size"] == len(body), name
        assert entry["sha256"] == hashlib.sha256(body).hexdigest(), name
    return manifest


def test_the_zip_holds_the_sessions_video_and_its_manifest_lists_every_file(
    live_session: tuple[Session, str], janus_settings: Any, client: Client
) -> None:
    session, vehicle = live_session
    with_a_track(session, vehicle)
    first, second = webm(12, 40), webm(8, 200)
    recorded(session, [first, second])
    assert session_video_chain(session_id=session.pk) == 2  # as the conversion does
    chained = {e.data["started_at"]: e.seq for e in session.events.filter(kind="record_video")}

    answer = client.get(f"/sessions/{session.pk}/record/zip")
    assert answer.status_code == 200 and answer.streaming
    assert answer["Content-Type"] == "application/zip"
    assert (
        answer["Content-Disposition"] == f'attachment; filename="session-{session.pk}-record.zip"'
    )
    archive = opened(list(answer.streaming_content))

    # The stretches in the order the replay plays them, as the replay serves them.
    assert archive.read("video/0.webm") == first
    assert archive.read("video/1.webm") == second
    assert client.get(f"/sessions/{session.pk}/replay/video/1.webm").getvalue() == second
    assert decoded_frames(archive.read("video/0.webm")) == 12
    assert archive.getinfo("video/0.webm").compress_type == zipfile.ZIP_STORED
    manifest = manifest_checked(archive)
    assert manifest["session"] == str(session.pk)
    assert manifest["video"] == {
        "recorded": True,
        "stretches": [
            {
                "name": "video/0.webm",
                "started_at": 1795856400.0,
                "started_utc": "2026-11-28T09:00:00.000Z",
                "log_seq": chained[1795856400.0],
            },
            {
                "name": "video/1.webm",
                "started_at": 1795856460.5,
                "started_utc": "2026-11-28T09:01:00.500Z",
                "log_seq": chained[1795856460.5],
            },
        ],
    }
    # Each stretch's digest in the log (log.json, the event the manifest names) is the
    # one of the file in the archive.
    log = {event["seq"]: event for event in json.loads(archive.read("log.json"))}
    for stretch in manifest["video"]["stretches"]:
        entry = log[stretch["log_seq"]]
        assert entry["kind"] == "record_video"
        assert entry["data"]["sha256"] == hashlib.sha256(archive.read(stretch["name"])).hexdigest()
    # The record's check, the video's every byte included.
    verification = json.loads(archive.read("verification.json"))
    assert verification["ok"] is True, verification
    assert (verification["videos"], verification["video_check"]) == (2, "sha256")
    assert archive.read("samples.jsonl").decode().count("\n") == 2

    # The API's zip is the same archive.
    token = token_issue(user=session.user, name="tests")
    api = Client().get(
        f"/api/v1/sessions/{session.pk}/record/zip", headers={"authorization": f"Bearer {token}"}
    )
    assert api.status_code == 200 and api["Content-Type"] == "application/zip"
    from_api = opened(list(api.streaming_content))
    assert from_api.read("video/1.webm") == second
    assert manifest_checked(from_api)["video"] == manifest["video"]

    stranger = Client()
    stranger.force_login(f.user("mallory"))
    assert stranger.get(f"/sessions/{session.pk}/record/zip").status_code == 404


@pytest.mark.parametrize("sfu_configured", [True, False])
def test_without_video_the_zip_says_so(
    live_session: tuple[Session, str], settings: Any, tmp_path: Path, sfu_configured: bool
) -> None:
    session, vehicle = live_session
    with_a_track(session, vehicle)
    settings.IOUV_JANUS_REC_DIR = str(tmp_path / "recordings") if sfu_configured else ""
    client = Client()
    client.force_login(session.user)
    archive = opened(list(client.get(f"/sessions/{session.pk}/record/zip").streaming_content))
    assert not [name for name in archive.namelist() if name.startswith("video/")]
    assert manifest_checked(archive)["video"] == {
        "recorded": False,
        "stretches": [],
        "detail": exports.NO_VIDEO,
    }


def test_a_video_goes_out_a_piece_at_a_time_under_wsgi_and_asgi(
    live_session: tuple[Session, str],
    janus_settings: Any,
    client: Client,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    session, vehicle = live_session
    with_a_track(session, vehicle)
    video = webm(30, 90)
    recorded(session, [video])
    monkeypatch.setattr(exports, "VIDEO_CHUNK", 256)

    pieces = list(client.get(f"/sessions/{session.pk}/record/zip").streaming_content)
    archive = opened(pieces)
    assert archive.read("video/0.webm") == video
    # A piece per file of the record, one per 256 bytes of the video, and the last one
    # (the manifest and the zip's directory): the video is never held whole.
    assert len(video) > 4 * 256
    others = len(manifest_checked(archive)["files"]) - 1
    assert len(pieces) == others + math.ceil(len(video) / 256) + 1
    assert max(len(piece) for piece in pieces[others:-1]) < 256 + 100

    # Under ASGI Django would read a synchronous iterator whole before sending it: the
    # answer's content is asynchronous there, taken a piece at a time.
    request = AsyncRequestFactory().get(f"/sessions/{session.pk}/record/zip")
    answer = record_file(request, session, "zip")
    assert answer.streaming and answer.is_async

    async def taken() -> list[bytes]:
        return [bytes(piece) async for piece in answer]

    async_pieces = asyncio.run(taken())
    assert opened(async_pieces).read("video/0.webm") == video
    assert len(async_pieces) == len(pieces)
