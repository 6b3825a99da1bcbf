"""ICE servers for a session (services.sessions.ice): STUN as configured, TURN with credentials
of the TURN REST scheme minted per session. coturn itself accepts them in
tests/integration/test_netlab.py and tests/integration/test_webrtc_nat.py."""

from __future__ import annotations

import base64
import hashlib
import hmac
import time
from typing import Any

import pytest
from django.urls import reverse

from services.sessions.ice import ice_servers_for, turn_credentials


def test_a_credential_is_the_hmac_of_its_username_and_expires_on_its_own() -> None:
    username, password = turn_credentials("s3cret", "session-1", ttl_s=600, now=1_000_000)
    assert username == "1000600:session-1"
    # What coturn computes from its static-auth-secret (RFC 2104 HMAC-SHA1, base64).
    expected = hmac.new(b"s3cret", b"1000600:session-1", hashlib.sha1).digest()
    assert base64.b64decode(password) == expected
    assert turn_credentials("other", "session-1", ttl_s=600, now=1_000_000)[1] != password
    with pytest.raises(ValueError, match="':'"):
        turn_credentials("s3cret", "a:b", ttl_s=600)


def test_servers_follow_the_configuration(settings: Any) -> None:
    settings.IOUV_STUN_URLS = []
    settings.IOUV_TURN_URLS = ["turn:turn.example.org:3478"]
    settings.IOUV_TURN_SECRET = ""
    # Nothing usable: TURN without its secret would only fail at the TURN server.
    assert ice_servers_for("s1") == []
    settings.IOUV_STUN_URLS = ["stun:a.example.org", "stun:b.example.org:3479"]
    assert ice_servers_for("s1") == [{"urls": ["stun:a.example.org", "stun:b.example.org:3479"]}]
    settings.IOUV_TURN_SECRET = "shh"
    servers = ice_servers_for("s1")
    assert servers[1]["urls"] == ["turn:turn.example.org:3478"]
    assert servers[1]["username"].endswith(":s1")
    # Two sessions never share a credential.
    assert ice_servers_for("s2")[1]["credential"] != servers[1]["credential"]


def test_turn_credentials_end_with_the_grant_they_come_with(settings: Any) -> None:
    settings.IOUV_STUN_URLS = ["stun:a.example.org"]
    settings.IOUV_TURN_URLS = ["turn:turn.example.org:3478"]
    settings.IOUV_TURN_SECRET = "shh"
    settings.IOUV_TURN_TTL_S = 3600
    now = 1_000_000.0
    # A grant of five minutes: its TURN credential ends with it, not an hour later.
    stun, turn = ice_servers_for("s1", expires_at=now + 300, now=now)
    assert turn["username"] == "1000300:s1"
    # The configured lifetime still bounds a longer grant.
    assert ice_servers_for("s1", expires_at=now + 7200, now=now)[1]["username"] == "1003600:s1"
    # A grant already over brings no TURN server at all (STUN still).
    assert ice_servers_for("s1", expires_at=now - 1, now=now) == [stun]
    assert ice_servers_for("s1", expires_at=now + 0.5, now=now) == [stun]


@pytest.mark.django_db
def test_a_user_tasks_turn_credential_ends_with_its_grant(settings: Any, client, live_session):
    """A viewer or a controller who kept a user task cannot use its TURN credential
    after the grant's end (it used to stay valid an hour)."""
    settings.IOUV_TURN_URLS = ["turn:turn.example.org:3478"]
    settings.IOUV_TURN_SECRET = "shh"
    settings.IOUV_TURN_TTL_S = 3600
    session, _ = live_session
    task = client.post(reverse("session_grant", args=[session.pk])).json()
    (turn,) = task["ice_servers"]
    expiry = int(turn["username"].split(":")[0])
    assert time.time() < expiry <= task["expires_at"] <= time.time() + settings.IOUV_GRANT_TTL_S
