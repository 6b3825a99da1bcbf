"""Rate limits (services.web.throttle): session requests and grants have a budget per user and
one per client address, on the API and on the portal; one over a budget is answered 429
with Retry-After and does nothing (no session row, no grant in the log).

The budgets are lowered for these tests (``IOUV_RATE_LIMITS``), per hour: a counter is
a fixed window, and a test's few requests must not straddle the end of one. The
counters live in the test's Redis (Django's cache) under a key prefix of the test's own
(``rate_counters``), and each test has addresses of its own."""

from __future__ import annotations

import itertools
import json
from typing import Any

import pytest
from django.test import Client
from django.urls import reverse

from accounts.roles import CLIENT
from accounts.tokens import token_issue
from services.models import Session, SessionEvent
from services.web.throttle import Throttled, throttle_check
from tests import factories as f

pytestmark = pytest.mark.django_db

_addresses = (f"198.51.100.{n}" for n in itertools.count(1))


@pytest.fixture
def budgets(settings: Any, rate_counters: str) -> dict[str, dict[str, str]]:
    settings.BEHIND_PROXY = True
    settings.IOUV_RATE_LIMITS = {
        "session_request": {"user": "3/h", "address": "5/h"},
        "grant": {"user": "2/h", "address": "off"},
        "webrtc_offer": {"user": "off", "address": "off"},
    }
    return settings.IOUV_RATE_LIMITS


def _api(method: str, path: str, token: str, address: str, body: Any = None) -> Any:
    return Client().generic(
        method,
        f"/api/v1{path}",
        json.dumps(body) if body is not None else "",
        content_type="application/json",
        HTTP_AUTHORIZATION=f"Bearer {token}",
        HTTP_X_FORWARDED_FOR=address,
    )


def _rate_limited(response: Any) -> str:
    assert response.status_code == 429, response.content
    assert 1 <= int(response["Retry-After"]) <= 3600
    error = response.json()["error"]
    assert error["code"] == "rate_limited"
    return str(error["message"])


def _user_token() -> tuple[Any, str]:
    user = f.user(roles=(CLIENT,))
    return user, token_issue(user=user, name="tests")


def test_a_user_over_the_session_request_budget_is_refused_and_nothing_is_recorded(
    budgets: Any,
) -> None:
    f.service("fly")  # no vehicle: each request is refused, and recorded as failed
    user, token = _user_token()
    address = next(_addresses)
    for _ in range(3):
        assert _api("POST", "/sessions", token, address, {"service": "fly"}).status_code == 422
    message = _rate_limited(_api("POST", "/sessions", token, address, {"service": "fly"}))
    assert "at most 3 per 3600 s from one user" in message
    assert Session.objects.filter(user=user).count() == 3
    # Another user from another address is not held back by it.
    _, other = _user_token()
    assert _api("POST", "/sessions", other, next(_addresses), {"service": "fly"}).status_code == 422


def test_users_sharing_an_address_share_its_budget(budgets: Any) -> None:
    f.service("fly")
    address = next(_addresses)
    tokens = [_user_token()[1] for _ in range(3)]
    answers = [
        _api("POST", "/sessions", token, address, {"service": "fly"}).status_code
        for token in (*tokens, *tokens)
    ]
    assert answers == [422] * 5 + [429]
    assert "from one address" in _rate_limited(
        _api("POST", "/sessions", _user_token()[1], address, {"service": "fly"})
    )


def test_grants_over_the_budget_are_refused_and_not_logged(budgets: Any, live_session: Any) -> None:
    session, _ = live_session
    token = token_issue(user=session.user, name="tests")
    address = next(_addresses)
    issued = SessionEvent.objects.filter(session=session, kind="grant_issued").count()
    path = f"/sessions/{session.pk}/grant"
    assert [_api("POST", path, token, address).status_code for _ in range(2)] == [200, 200]
    _rate_limited(_api("POST", path, token, address))
    assert SessionEvent.objects.filter(session=session, kind="grant_issued").count() == issued + 2


def test_the_portal_answers_its_controller_script_in_json_and_counts_only_grants_given(
    budgets: Any, client: Client, live_session: Any
) -> None:
    session, _ = live_session
    url = reverse("session_grant", args=[session.pk])
    address = next(_addresses)
    # While the session waits for a vehicle the page asks every few seconds: not counted.
    Session.objects.filter(pk=session.pk).update(state=Session.State.REQUESTED)
    for _ in range(4):
        answer = client.post(url, HTTP_X_FORWARDED_FOR=address)
        assert answer.json()["error"]["code"] == "no_vehicle_yet"
    Session.objects.filter(pk=session.pk).update(state=Session.State.ACTIVE)
    assert [client.post(url, HTTP_X_FORWARDED_FOR=address).status_code for _ in range(2)] == [
        200,
        200,
    ]
    _rate_limited(client.post(url, HTTP_X_FORWARDED_FOR=address))


def test_the_portal_request_page_over_the_budget_says_so(budgets: Any, client: Client) -> None:
    service = f.service("fly")
    user = f.user(roles=(CLIENT,))
    client.force_login(user)
    url = reverse("service_request", args=[service.slug])
    address = next(_addresses)
    budgets["session_request"]["user"] = "1/h"
    client.post(url, {}, HTTP_X_FORWARDED_FOR=address)
    refused = client.post(url, {}, HTTP_X_FORWARDED_FOR=address)
    assert refused.status_code == 429 and int(refused["Retry-After"]) >= 1
    assert b"Too many requests" in refused.content
    # Looking at the page is not a request.
    assert client.get(url, HTTP_X_FORWARDED_FOR=address).status_code == 200


def test_local_clients_are_counted_per_user_only(budgets: Any) -> None:
    """A loopback client is a program beside the platform, or every client at once
    behind a proxy that passes no addresses: no per-address budget for it."""
    for _ in range(3):
        user_id = f.user().pk
        for _ in range(3):
            throttle_check(action="session_request", user_id=user_id, address=None)
    with pytest.raises(Throttled, match="from one user"):
        throttle_check(action="session_request", user_id=user_id, address=None)


def test_without_a_cache_the_limits_let_calls_through(budgets: Any, settings: Any) -> None:
    # Redis away: better serve than refuse everyone (the log says so).
    settings.CACHES = {
        "default": {
            "BACKEND": "django.core.cache.backends.redis.RedisCache",
            "LOCATION": "redis://127.0.0.1:1/0",
            "OPTIONS": {"socket_connect_timeout": 0.2},
        }
    }
    user_id = f.user().pk
    for _ in range(5):
        throttle_check(action="session_request", user_id=user_id, address="192.0.2.1")
