"""What an unauthenticated client can send gets an answer, never a traceback: a path out
of the static folder is not found, and frames sent on the relay before the first one was
refused are dropped. The health checks say what they found.

A platform process as production runs it (tests/servers.py), its log read after."""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import json
import urllib.error
import urllib.request
import uuid
from typing import Any

import pytest
import websockets

from tests.servers import platform_log, platform_process

#: One database for the module and its platform (conftest's ``module_database``).
pytestmark = pytest.mark.usefixtures("module_database")


@pytest.fixture(scope="module")
def platform(module_database: None) -> Any:
    with platform_process() as base:
        yield base


def _get(base: str, path: str) -> tuple[int, dict[str, str], bytes]:
    host, port = base.removeprefix("http://").split(":")
    connection = http.client.HTTPConnection(host, int(port), timeout=10)
    try:
        connection.request("GET", path)  # sent as written: no client normalises it
        response = connection.getresponse()
        return response.status, dict(response.getheaders()), response.read()
    finally:
        connection.close()


@pytest.mark.parametrize(
    "path",
    [
        "/static/%2e%2e/%2e%2e/etc/passwd",
        "/static/%2e%2e/%2e%2e/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
        "/static/..%2f..%2fmanage.py",
        "/static/css/%2e%2e/%2e%2e/%2e%2e/pyproject.toml",
    ],
)
def test_a_path_out_of_the_static_folder_is_not_found(platform: str, path: str) -> None:
    status, _, body = _get(platform, path)
    assert status == 404
    assert b"root:" not in body and b"[project]" not in body
    assert "Traceback" not in platform_log(platform).read_text()


def test_frames_sent_after_a_refused_first_frame_are_dropped_without_a_traceback(
    platform: str,
) -> None:
    url = platform.replace("http", "ws") + f"/ws/relay/{uuid.uuid4()}/"

    async def two_frames(first: dict[str, Any]) -> tuple[list[dict[str, Any]], int | None]:
        async with websockets.connect(url) as ws:
            await ws.send(json.dumps(first))
            await ws.send(json.dumps({"type": "ping", "t": 1}))  # before any answer
            frames = []
            with pytest.raises(websockets.ConnectionClosed):
                while True:
                    frames.append(json.loads(await asyncio.wait_for(ws.recv(), 10)))
            return frames, ws.close_code

    for first in ({"type": "auth", "grant": "a.b.c"}, {"type": "ping", "t": 1}, {"type": "?"}):
        frames, code = asyncio.run(two_frames(first))
        # One answer, to the first frame, saying why; then the close.
        assert len(frames) == 1 and frames[0]["type"] == "error", frames
        assert frames[0]["code"] in ("no_session", "unauthorized", "unknown_type"), frames
        assert code == 4401
    assert "Traceback" not in platform_log(platform).read_text()


def _health(base: str, path: str) -> tuple[int, dict[str, Any]]:
    try:
        with urllib.request.urlopen(f"{base}{path}", timeout=10) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read())


def test_the_health_checks_say_what_they_found(platform: str) -> None:
    for path in ("/healthz", "/readyz"):
        status, body = _health(platform, path)
        assert status == 200, body
        assert body["ok"] and body["live"] and body["ready"]
        assert set(body["checks"]) == {"database", "redis"}
        assert all(check["ok"] for check in body["checks"].values())


def test_no_frame_before_authentication_leaves_a_traceback(platform: str) -> None:
    """Whatever an unauthenticated client sends on any socket, back to back: answered
    or dropped, never an error in the platform's log."""
    ws_base = platform.replace("http", "ws")
    frames: list[str | bytes] = [
        json.dumps({"type": "hello", "v": 2, "vehicle_id": str(uuid.uuid4()), "credential": "x"}),
        json.dumps({"type": "auth", "grant": "a.b.c"}),
        "not json",
        b"\xff\xfe binary",
        json.dumps({"type": "heartbeat", "seq": 1}),
        json.dumps([1, 2, 3]),
        "{" * 10_000,
    ]

    async def flood(path: str, first: int) -> None:
        try:
            async with websockets.connect(ws_base + path, origin=platform) as ws:
                for frame in frames[first:] + frames[:first]:  # each kind of frame first
                    await ws.send(frame)
                with contextlib.suppress(asyncio.TimeoutError, websockets.ConnectionClosed):
                    while True:
                        await asyncio.wait_for(ws.recv(), 3)
        except websockets.InvalidStatus:
            pass  # refused at the handshake (a browser socket without a login)

    for path in (
        "/ws/agent/",
        f"/ws/relay/{uuid.uuid4()}/",
        f"/ws/sessions/{uuid.uuid4()}/",
        "/ws/sessions/",
        "/ws/fleet/",
    ):
        for first in range(len(frames)):
            asyncio.run(flood(path, first))
    log = platform_log(platform).read_text()
    assert "Traceback" not in log and " ERROR " not in log, log[-3000:]
