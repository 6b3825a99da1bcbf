"""HTTP through the platform's ASGI application: Django's middleware and view in one
thread hop (iouv.handler), with everything the middleware does still done."""

from __future__ import annotations

import json
import threading
from typing import Any

import pytest
from channels.testing import HttpCommunicator
from django.core.signals import request_finished, request_started
from django.http import HttpRequest, HttpResponse
from django.urls import path

from accounts.roles import CLIENT
from accounts.tokens import token_issue
from iouv.asgi import application
from tests import factories as f

pytestmark = pytest.mark.django_db(transaction=True)

#: Where each part of the last request ran (the test view's urlconf below).
threads: dict[str, int] = {}


def _where(request: HttpRequest) -> HttpResponse:
    threads["view"] = threading.get_ident()
    return HttpResponse("here")


urlpatterns = [path("where/", _where)]


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

    def started(**kwargs: Any) -> None:
        threads["started"] = threading.get_ident()

    def finished(**kwargs: Any) -> None:
        threads["finished"] = threading.get_ident()

    request_started.connect(started, dispatch_uid="test_handler")
    request_finished.connect(finished, dispatch_uid="test_handler")
    try:
        threads.clear()
        response = await _call("GET", "/where/")
    finally:
        request_started.disconnect(dispatch_uid="test_handler")
        request_finished.disconnect(dispatch_uid="test_handler")
    assert response["status"] == 200 and response["body"] == b"here"
    assert threads["started"] == threads["view"] == threads["finished"]
    assert threads["view"] != threading.get_ident()  # not the event loop's
