"""The session log in words: the session page lists every event as a line a person can
read (services.sessions.words), never a bare code such as "agent event", and the feeds
carry the same line with each event."""

from __future__ import annotations

import html
import re

import pytest
from django.urls import reverse

from services.sessions.log import event_append
from services.sessions.words import event_text

pytestmark = pytest.mark.django_db


def test_the_session_page_says_every_event_in_words(client, live_session) -> None:
    session, vehicle_id = live_session
    vehicle = str(vehicle_id)
    for kind, data in (
        ("user_connected", {"vehicle": vehicle, "user": "alice", "role": "controller"}),
        ("control_path", {"vehicle": vehicle, "user": "alice", "path": "webrtc_direct"}),
        (
            "agent_event",
            {"vehicle": vehicle, "event": "envelope_restored", "data": {"limit": "altitude"}},
        ),
        (
            "agent_event",
            {"vehicle": vehicle, "event": "autopilot_warning", "data": {"text": "PreArm: GPS"}},
        ),
        ("agent_event", {"vehicle": vehicle, "event": "camera_reset", "data": {}}),
        ("unintentional_end", {"vehicle": vehicle, "cause": "link_lost", "action": "land"}),
    ):
        event_append(session=session, kind=kind, data=data)
    page = html.unescape(client.get(reverse("session", args=[session.pk])).content.decode())
    log = page[page.index("data-log") : page.index("</ul>", page.index("data-log"))]
    lines = [re.sub(r"\s+", " ", line).strip() for line in re.findall(r"</time>([^<]*)", log)]
    for said in (
        "alice connected, in control",
        "alice's commands go through WebRTC, direct",
        "back inside the altitude limit",
        "the autopilot warns: PreArm: GPS",
        "the vehicle reported camera reset",
        "the driver's link to the vehicle was lost, so it performed its fail-safe (land)",
    ):
        assert said in lines, (said, lines)
    assert not [line for line in lines if "_" in line or line in ("agent event", "state")]


def test_an_event_it_does_not_know_is_still_said_plainly() -> None:
    assert event_text("mission_state", {"to": "searching", "text": "search-1 searches"}) == (
        "mission state: search-1 searches"
    )
    assert event_text("assigned", None) == "the vehicle reserved as vehicle"
