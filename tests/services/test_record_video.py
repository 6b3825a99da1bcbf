"""The session's recorded video under the record's hash chain (services.sessions.video,
services.records.keeping.record_verify), and served a piece at a time: each stretch
janus-pp-rec converts is chained into the session's log once, however often the
conversion runs; the record's check names a stretch whose bytes changed, one missing,
one the log does not hold; the replay's video goes out a piece at a time under ASGI."""

from __future__ import annotations

import asyncio
import hashlib
import json
import math
import zipfile
from io import BytesIO
from typing import Any

import pytest
from django.test import AsyncRequestFactory, Client
from django.urls import reverse

from services import sfu
from services.models import Session
from services.records.keeping import record_delete, record_verify
from services.sessions.log import session_log_verify
from services.sessions.video import RECORD_VIDEO, session_video_chain, session_video_convert
from services.sessions.words import event_text
from services.web import record_views
from services.web.record_views import session_replay_video
from tests.netlab import ensure_packages
from tests.recordings import (
    STARTS_US,
    decoded_frames,
    mjr_header,
    recorded,
    recorded_unconverted,
    stretch_converted,
    stretch_name,
    webm,
)

pytestmark = pytest.mark.django_db


@pytest.fixture
def janus_pp_rec() -> None:
    """Debian's janus-tools, installed when missing (tests.janus does the same)."""
    ensure_packages("janus-tools")


def chained(session: Session) -> list[dict[str, Any]]:
    return [e.data for e in session.events.filter(kind=RECORD_VIDEO).order_by("seq")]


def summary_check(client: Client, session: Session) -> dict[str, Any]:
    """The check the record's page (its JSON summary) shows."""
    answer = client.get(reverse("session_record", args=[session.pk]))
    assert answer.status_code == 200
    check: dict[str, Any] = answer.json()["verification"]
    return check


def zip_check(client: Client, session: Session) -> dict[str, Any]:
    """The check in the record's zip (``verification.json``)."""
    answer = client.get(reverse("session_record_export", args=[session.pk, "zip"]))
    archive = zipfile.ZipFile(BytesIO(b"".join(answer.streaming_content)))
    check: dict[str, Any] = json.loads(archive.read("verification.json"))
    return check


def test_each_converted_stretch_is_chained_once_however_often_the_conversion_runs(
    live_session: tuple[Session, str], janus_settings: Any, janus_pp_rec: None
) -> None:
    session, _ = live_session
    recorded_unconverted(session, [12, 8])

    recordings = session_video_convert(session_id=session.pk)
    assert [decoded_frames(r.path.read_bytes()) for r in recordings] == [12, 8]
    entries = chained(session)
    assert entries == [
        {
            "name": r.path.name,
            "size": r.path.stat().st_size,
            "sha256": hashlib.sha256(r.path.read_bytes()).hexdigest(),
            "started_at": r.started_at,
        }
        for r in recordings
    ]
    assert [r.started_at for r in recordings] == [s / 1e6 for s in STARTS_US]
    assert event_text(RECORD_VIDEO, entries[0]).startswith("recorded video added to the flight")

    # A retried task, a second run: nothing is converted or chained again.
    assert session_video_convert(session_id=session.pk) == recordings
    assert session_video_chain(session_id=session.pk) == 0
    assert chained(session) == entries
    check = record_verify(session=session)
    assert check.ok, check.problems
    assert (check.videos, check.video_check) == (2, "sha256")
    assert session_log_verify(session=session).ok


def test_a_stretch_converted_but_not_chained_is_chained_by_the_next_run(
    live_session: tuple[Session, str], janus_settings: Any, janus_pp_rec: None
) -> None:
    session, _ = live_session
    recorded_unconverted(session, [10])
    # The process died between the conversion's rename and the log: converted only.
    (recording,) = sfu.sfu_recording_convert(session_id=session.pk)
    assert record_verify(session=session).problems == [
        f"video {recording.path.name} is not in the session log"
    ]
    session_video_convert(session_id=session.pk)
    assert [e["name"] for e in chained(session)] == [recording.path.name]
    assert record_verify(session=session).ok


def test_what_was_converted_before_a_failure_is_chained(
    live_session: tuple[Session, str], janus_settings: Any, janus_pp_rec: None
) -> None:
    session, _ = live_session
    folder = recorded_unconverted(session, [10])
    # A second stretch janus-pp-rec cannot read (its packets are garbage).
    broken = folder / f"{stretch_name(session, STARTS_US[1])}.mjr"
    broken.write_bytes(mjr_header(STARTS_US[1]) + b"MEET" + b"\xff" * 40)

    with pytest.raises(sfu.SfuError, match="janus-pp-rec failed"):
        session_video_convert(session_id=session.pk)
    assert [e["name"] for e in chained(session)] == [f"{stretch_name(session, STARTS_US[0])}.webm"]
    assert record_verify(session=session).ok


def test_a_video_whose_bytes_changed_fails_the_records_check_naming_it(
    live_session: tuple[Session, str], janus_settings: Any, client: Client
) -> None:
    session, _ = live_session
    folder = recorded(session, [webm(12, 40), webm(8, 200)])
    session_video_chain(session_id=session.pk)
    assert summary_check(client, session)["ok"] is True
    name = f"{stretch_name(session, STARTS_US[1])}.webm"
    body = bytearray((folder / name).read_bytes())
    body[len(body) // 2] ^= 0x01  # one bit of one byte: the same size
    (folder / name).write_bytes(bytes(body))

    problem = f"video {name} does not match its digest"
    assert record_verify(session=session).problems == [problem]
    # The zip hashes every byte; the page, answered on every view, checks sizes only.
    assert zip_check(client, session)["problems"] == [problem]
    page = summary_check(client, session)
    assert (page["ok"], page["video_check"], page["videos"]) == (True, "size", 2)
    # Cut short, the video fails the page's check too.
    (folder / name).write_bytes(bytes(body[:-1]))
    assert summary_check(client, session)["problems"] == [problem]

    # The bytes back, its start moved (the .mjr's header, which places the video on the
    # flight's timeline).
    body[len(body) // 2] ^= 0x01
    (folder / name).write_bytes(bytes(body))
    assert record_verify(session=session).ok
    (folder / name).with_suffix(".mjr").write_bytes(mjr_header(STARTS_US[1] + 5_000_000))
    assert record_verify(session=session).problems == [
        f"video {name} no longer starts when the log says"
    ]


def test_a_video_the_log_does_not_hold_is_reported(
    live_session: tuple[Session, str], janus_settings: Any, client: Client
) -> None:
    session, _ = live_session
    recorded(session, [webm(12, 40)])
    session_video_chain(session_id=session.pk)
    # Another stretch dropped into the folder by someone with access to the disk: the
    # replay would play it, the zip would hold it.
    dropped = stretch_converted(session, STARTS_US[1], webm(5, 120))
    assert len(sfu.sfu_recordings(session_id=session.pk)) == 2
    problem = f"video {dropped.name} is not in the session log"
    assert record_verify(session=session).problems == [problem]
    assert summary_check(client, session)["problems"] == [problem]
    assert zip_check(client, session)["problems"] == [problem]


def test_a_missing_video_is_reported_until_the_record_is_deleted(
    live_session: tuple[Session, str],
    janus_settings: Any,
    django_capture_on_commit_callbacks: Any,
) -> None:
    session, _ = live_session
    folder = recorded(session, [webm(12, 40), webm(8, 200)])
    session_video_chain(session_id=session.pk)
    gone = folder / f"{stretch_name(session, STARTS_US[0])}.webm"
    gone.unlink()
    assert record_verify(session=session, video="size").problems == [
        f"video {gone.name} is missing"
    ]

    with django_capture_on_commit_callbacks(execute=True):
        record_delete(session=session, by="admin")
    assert not folder.exists()
    # The log keeps the digests of a video deleted with its record and says who
    # deleted it: nothing is missing.
    check = record_verify(session=session)
    assert check.ok, check.problems
    assert check.videos == 2


def test_the_replay_video_goes_out_a_piece_at_a_time_under_asgi(
    live_session: tuple[Session, str], janus_settings: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    session, _ = live_session
    video = webm(30, 90)
    recorded(session, [video])
    monkeypatch.setattr(record_views, "VIDEO_PIECE", 256)
    url = reverse("session_replay_video", args=[session.pk, 0])

    def answered(**headers: str) -> tuple[Any, list[bytes]]:
        request = AsyncRequestFactory().get(url, headers=headers)
        request.user = session.user
        answer = session_replay_video(request, str(session.pk), 0)
        # Under ASGI Django reads a synchronous iterator whole before sending any of
        # it: the answer's content is asynchronous, taken a piece at a time.
        assert answer.streaming and answer.is_async

        async def taken() -> list[bytes]:
            return [bytes(piece) async for piece in answer]

        return answer, asyncio.run(taken())

    assert len(video) > 4 * 256
    whole, pieces = answered()
    assert whole.status_code == 200 and b"".join(pieces) == video
    assert whole["Content-Length"] == str(len(video)) and whole["Accept-Ranges"] == "bytes"
    assert whole["Content-Type"] == "video/webm"
    assert len(pieces) == math.ceil(len(video) / 256)
    assert max(len(piece) for piece in pieces) == 256

    part, pieces = answered(Range="bytes=300-1299")
    assert part.status_code == 206 and part["Accept-Ranges"] == "bytes"
    assert part["Content-Range"] == f"bytes 300-1299/{len(video)}"
    assert part["Content-Length"] == "1000"
    assert b"".join(pieces) == video[300:1300] and len(pieces) == 4

    tail, pieces = answered(Range="bytes=-10")
    assert tail["Content-Range"] == f"bytes {len(video) - 10}-{len(video) - 1}/{len(video)}"
    assert b"".join(pieces) == video[-10:]
