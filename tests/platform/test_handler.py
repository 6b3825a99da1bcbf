"""HTTP through the platform's ASGI application: Django's middleware and view in one
thread hop (iouv.handler), with everything the middleware does still done."""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from channels.testing import HttpCommunicator
from django.core.signals import request_finished, request_started
from django.http import HttpRequest, HttpResponse, StreamingHttpResponse
from django.urls import path

from accounts.roles import CLIENT
from accounts.tokens import token_issue
from iouv.asgi import application
from tests import factories as f

pytestmark = pytest.mark.django_db(transaction=True)

#: Where each part of the last request ran (the test view's urlconf below).
threads: dict[str, Any] = {}


def _where(request: HttpRequest) -> HttpResponse:
    threads["view"] = threading.get_ident()
    return HttpResponse("here")


def _stream(request: HttpRequest) -> StreamingHttpResponse:
    threads["view"] = threading.get_ident()

    def parts() -> Iterator[bytes]:
        yield b"one,"
        yield b"two"
        threads["streamed"] = threading.get_ident()

    return StreamingHttpResponse(parts())


urlpatterns = [path("where/", _where), path("stream/", _stream)]


@contextlib.contextmanager
def _signals_recorded() -> Iterator[None]:
    """request_started and request_finished record their thread in ``threads``."""

    def started(**kwargs: Any) -> None:
        threads["started"] = threading.get_ident()

    def finished(**kwargs: Any) -> None:
        threads["finished"] = threading.get_ident()
        threads["finished_after_streaming"] = "streamed" in threads

    request_started.connect(started, dispatch_uid="test_handler")
    request_finished.connect(finished, dispatch_uid="test_handler")
    try:
        yield
    finally:
        request_started.disconnect(dispatch_uid="test_handler")
        request_finished.disconnect(dispatch_uid="test_handler")


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
    from asgiref.sync import sync_to_async

    token = await sync_to_async(
        lambda: token_issue(user=f.user(username="alice", roles=(CLIENT,)), name="tests")
    )()
    await sync_to_async(lambda: f.service("fly"))()
    bearer = [(b"authorization", f"Bearer {token}".encode())]
    response = await _call("GET", "/api/v1/services", headers=bearer)
    assert response["status"] == 200, response["body"]
    assert [s["slug"] for s in json.loads(response["body"])["services"]] == ["fly"]
    refused = await _call("GET", "/api/v1/services", headers=[(b"authorization", b"Bearer x")])
    assert refused["status"] == 401


async def test_the_request_signals_and_the_view_run_on_one_thread_off_the_loop(settings):
    # The database connection a view used is the one its thread gives back when the
    # request finishes (request_finished closes it, or returns it to the pool): both
    # must run on the view's thread.
    settings.ROOT_URLCONF = __name__
    with _signals_recorded():
        threads.clear()
        response = await _call("GET", "/where/")
        first = dict(threads)
        threads.clear()
        again = await _call("GET", "/where/")
    assert response["status"] == 200 and response["body"] == b"here"
    assert first["started"] == first["view"] == first["finished"]
    assert first["view"] != threading.get_ident()  # not the event loop's
    # The next request runs on the same thread: kept, not a new one for each.
    assert again["body"] == b"here" and threads["view"] == first["view"]
    assert threads["started"] == threads["finished"] == first["view"]


async def test_a_streaming_response_is_sent_whole_then_finished_on_its_thread(settings):
    settings.ROOT_URLCONF = __name__
    with _signals_recorded():
        threads.clear()
        communicator = HttpCommunicator(
            application, "GET", "/stream/", headers=[(b"host", b"testserver")]
        )
        await communicator.send_input({"type": "http.request", "body": b""})
        start = await communicator.receive_output(timeout=10)
        # Read part by part: the closing part of a stream has no body, which
        # HttpCommunicator.get_response does not take (Django's own handler sends it so).
        parts = []
        while (part := await communicator.receive_output(timeout=10)).get("more_body"):
            parts.append(part["body"])
        parts.append(part.get("body", b""))
        await communicator.wait(timeout=10)
    assert start["status"] == 200
    assert b"".join(parts) == b"one,two"
    # Its content was read while it was sent; only then did the request finish, on the
    # view's thread, where its database connection is.
    assert threads["finished_after_streaming"] is True
    assert threads["started"] == threads["view"] == threads["finished"]
