"""HTTP through the platform's ASGI application (``iouv.asgi``: Django's own handler), as
the demo and the integration tests serve it: the middleware's work done, a streaming
answer sent whole, and a slow request never in the way of an agent's uplink."""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import AsyncIterator
from typing import Any

import pytest
from channels.testing import HttpCommunicator
from django.http import HttpRequest, HttpResponse, StreamingHttpResponse
from django.urls import path

from accounts.roles import CLIENT
from accounts.tokens import token_issue
from iouv.asgi import application
from tests import factories as f
from tests.servers import db
from tests.uplink import uplink_welcomed, vehicle_enrolled

#: One database for the module (conftest's ``module_database``): each test writes rows
#: of its own, so the database is emptied after the module only.
pytestmark = pytest.mark.usefixtures("module_database")

#: The slow view below: it has started, and the test lets it finish.
slow_started = threading.Event()
slow_release = threading.Event()


def _slow(request: HttpRequest) -> HttpResponse:
    slow_started.set()
    released = slow_release.wait(timeout=10)
    return HttpResponse("released" if released else "timed out")


def _stream(request: HttpRequest) -> StreamingHttpResponse:
    async def parts() -> AsyncIterator[bytes]:
        yield b"one,"
        yield b"two"

    return StreamingHttpResponse(parts())


urlpatterns = [path("slow/", _slow), path("stream/", _stream)]


def _headers(response: dict[str, Any]) -> dict[str, str]:
    return {k.decode().lower(): v.decode() for k, v in response["headers"]}


async def _call(
    method: str, path_: str, body: bytes = b"", headers: list[tuple[bytes, bytes]] | None = None
) -> dict[str, Any]:
    communicator = HttpCommunicator(
        application, method, path_, body=body, headers=[(b"host", b"testserver"), *(headers or [])]
    )
    response: dict[str, Any] = dict(await communicator.get_response(timeout=10))
    await communicator.wait(timeout=10)  # the request finished: its response closed
    return response


async def test_a_page_gets_its_security_headers_and_its_csrf_cookie():
    response = await _call("GET", "/accounts/login/")
    assert response["status"] == 200
    headers = _headers(response)
    assert headers["x-frame-options"] == "DENY"
    assert headers["x-content-type-options"] == "nosniff"
    assert "default-src" in headers["content-security-policy"]
    assert "csrftoken=" in headers["set-cookie"]


async def test_a_form_posted_without_its_csrf_token_is_refused():
    response = await _call(
        "POST",
        "/accounts/login/",
        b"username=alice&password=secret",
        [(b"content-type", b"application/x-www-form-urlencoded")],
    )
    assert response["status"] == 403


async def test_an_api_call_with_a_bearer_token_reads_the_database():
    token = await db(
        lambda: token_issue(user=f.user(username="alice", roles=(CLIENT,)), name="tests")
    )
    await db(f.service, "fly")
    bearer = [(b"authorization", f"Bearer {token}".encode())]
    response = await _call("GET", "/api/v1/services", headers=bearer)
    assert response["status"] == 200, response["body"]
    assert [s["slug"] for s in json.loads(response["body"])["services"]] == ["fly"]
    refused = await _call("GET", "/api/v1/services", headers=[(b"authorization", b"Bearer x")])
    assert refused["status"] == 401


async def test_a_streaming_response_is_sent_whole(settings):
    settings.ROOT_URLCONF = __name__
    communicator = HttpCommunicator(
        application, "GET", "/stream/", headers=[(b"host", b"testserver")]
    )
    await communicator.send_input({"type": "http.request", "body": b""})
    start = await communicator.receive_output(timeout=10)
    # Read part by part: the closing part of a stream has no body, which
    # HttpCommunicator.get_response does not take.
    parts = []
    while (part := await communicator.receive_output(timeout=10)).get("more_body"):
        parts.append(part["body"])
    parts.append(part.get("body", b""))
    await communicator.wait(timeout=10)
    assert start["status"] == 200
    assert b"".join(parts) == b"one,two"


async def test_an_agent_is_welcomed_while_a_slow_request_runs(settings):
    """A view runs on a thread of its own: the event loop, which carries every socket,
    goes on meanwhile."""
    settings.ROOT_URLCONF = __name__
    vehicle, credential = await vehicle_enrolled()
    slow_started.clear()
    slow_release.clear()
    slow = asyncio.create_task(_call("GET", "/slow/"))
    try:
        assert await asyncio.to_thread(slow_started.wait, 10), "the slow view never started"
        comm, welcome = await uplink_welcomed(vehicle, credential, within=5)
        assert welcome["type"] == "welcome"
        assert not slow.done()  # still in its view
    finally:
        slow_release.set()
    response = await slow
    assert response["status"] == 200 and response["body"] == b"released"
    await comm.disconnect()
