"""The SFU's part in the portal without servers: what a viewer's and a pilot's user task
say about it, what a vehicle task carries, and the recorded video on the replay page
(served in byte ranges, so the page can seek; only to whoever may open the record)."""

from __future__ import annotations

import time
from datetime import timedelta
from typing import Any

import pytest
from django.test import Client
from django.urls import reverse
from django.utils import timezone

from agents.protocol import VehicleTask
from services import sfu
from services.models import Session
from services.records.keeping import records_expire
from services.sessions.deployment import _user_task, _vehicle_task_sign
from tests import factories as f

pytestmark = pytest.mark.django_db


def _publishing(session: Session) -> Any:
    assignment = session.assignments.select_related("vehicle").get(active=True)
    assignment.vehicle.profile = {**assignment.vehicle.profile, "video": True, "sfu": True}
    assignment.vehicle.save(update_fields=["profile"])
    return assignment


def test_only_viewers_are_sent_to_the_sfu_and_the_vehicle_is_told_where(
    live_session: tuple[Session, str], janus_settings: Any
) -> None:
    session, _ = live_session
    assignment = _publishing(session)
    viewer = _user_task(session=session, assignment=assignment, user=f.user("bob"), role="viewer")
    pilot = _user_task(session=session, assignment=assignment, user=session.user, role="controller")
    assert pilot.sfu is None  # the pilot's video stays direct
    assert viewer.sfu is not None
    assert viewer.sfu["room"] == sfu.sfu_room(session.pk) and viewer.sfu["feed"] == sfu.FEED
    expiry = int(viewer.sfu["token"].split(",", 1)[0])
    assert time.time() < expiry <= time.time() + janus_settings.IOUV_JANUS_TOKEN_TTL_S + 1

    task, _ = _vehicle_task_sign(session=session, assignment=assignment)
    assert task.sfu is not None and task.sfu.room == viewer.sfu["room"]
    assert task.sfu.pin == viewer.sfu["pin"]  # a spectator's pin is the room's...
    assert task.sfu.publish_token not in (viewer.sfu["token"], viewer.sfu["pin"])  # ...not its key


def test_a_vehicle_whose_agent_does_not_say_sfu_gets_a_task_without_it(
    live_session: tuple[Session, str], janus_settings: Any
) -> None:
    session, _ = live_session
    assignment = session.assignments.select_related("vehicle").get(active=True)
    task, _ = _vehicle_task_sign(session=session, assignment=assignment)
    assert task.sfu is None
    # Left out of the signed claims, not null: an older agent refuses claims it does
    # not know.
    assert "sfu" not in task.to_payload()
    assert VehicleTask.from_payload(task.to_payload()).sfu is None


def test_without_an_sfu_nobody_is_sent_there(live_session: tuple[Session, str]) -> None:
    session, _ = live_session
    assignment = _publishing(session)
    viewer = _user_task(session=session, assignment=assignment, user=f.user("bob"), role="viewer")
    assert viewer.sfu is None


def test_the_recorded_video_is_served_in_ranges_to_whoever_may_see_the_record(
    live_session: tuple[Session, str], janus_settings: Any, client: Client
) -> None:
    session, _ = live_session
    folder = sfu.sfu_recording_dir(session.pk)
    assert folder is not None
    folder.mkdir(parents=True)
    name = f"videoroom-{sfu.sfu_room(session.pk)}-user-1-1795856399887241-video-0"
    # Janus's header: when the first packet was written ("u", µs) is the WebM's time 0.
    header = b'{"t":"v","c":"vp8","s":1795856399887241,"u":1795856400000000}'
    (folder / f"{name}.mjr").write_bytes(b"MJR00002" + len(header).to_bytes(2, "big") + header)
    body = bytes(range(256)) * 40
    (folder / f"{name}.webm").write_bytes(body)
    assert sfu.sfu_recordings(session_id=session.pk) == [
        sfu.Recording(folder / f"{name}.webm", 1795856400.0)
    ]

    page = client.get(reverse("session_replay", args=[session.pk])).content.decode()
    assert "data-replay-video-file" in page and "No video was recorded" not in page
    url = reverse("session_replay_video", args=[session.pk, 0])
    whole = client.get(url)
    assert whole.status_code == 200 and whole["Accept-Ranges"] == "bytes"
    assert b"".join(whole.streaming_content) == body
    part = client.get(url, HTTP_RANGE="bytes=100-199")
    assert part.status_code == 206 and part["Content-Range"] == f"bytes 100-199/{len(body)}"
    assert b"".join(part.streaming_content) == body[100:200]
    tail = client.get(url, HTTP_RANGE="bytes=-10")
    assert b"".join(tail.streaming_content) == body[-10:]
    assert client.get(reverse("session_replay_video", args=[session.pk, 1])).status_code == 404

    stranger = Client()
    stranger.force_login(f.user("mallory"))
    assert stranger.get(url).status_code == 404


def test_the_recorded_video_goes_with_the_record(
    live_session: tuple[Session, str],
    janus_settings: Any,
    settings: Any,
    django_capture_on_commit_callbacks: Any,
) -> None:
    session, _ = live_session
    folder = sfu.sfu_recording_dir(session.pk)
    assert folder is not None
    folder.mkdir(parents=True)
    name = f"videoroom-{sfu.sfu_room(session.pk)}-user-1-1795856399887241-video-0"
    (folder / f"{name}.mjr").write_bytes(b"MJR00002")
    (folder / f"{name}.webm").write_bytes(b"webm")
    settings.IOUV_RECORD_RETENTION_DAYS = 30
    with django_capture_on_commit_callbacks(execute=True):
        assert records_expire(now=timezone.now() + timedelta(days=29)) == 0
    assert folder.exists()
    with django_capture_on_commit_callbacks(execute=True):
        assert records_expire(now=timezone.now() + timedelta(days=31)) == 1
    assert not folder.exists()
    assert session.events.get(kind="record_deleted").data["video"] is True
