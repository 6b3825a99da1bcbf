"""Oversized request heads get an HTTP answer from the platform, not a dropped connection.

The platform runs as the project runs it (``python -m iouv.serve``: uvicorn with
``iouv.http_limits``), and under daphne (``iouv.http_limits_twisted``), its documented
alternative (tests/servers.py); the requests go over real sockets, as a client would
send them.
"""

from __future__ import annotations

import http.client
import socket
from collections.abc import Iterator
from urllib.parse import urlsplit

import pytest

from iouv.http_limits import MAX_HEAD_BYTES, MAX_HEADERS, MAX_LINE_BYTES
from tests.servers import SERVERS, platform_process

# The platform process uses the test database (tests/servers.py), which it only finds
# on PostgreSQL; the tests themselves touch no rows.
pytestmark = pytest.mark.postgres


@pytest.fixture(scope="module", params=SERVERS)
def address(request: pytest.FixtureRequest, django_db_setup: None) -> Iterator[tuple[str, int]]:
    with platform_process(server=request.param) as base:
        parts = urlsplit(base)
        assert parts.hostname and parts.port
        yield parts.hostname, parts.port


def _get(
    address: tuple[str, int], path: str = "/healthz", headers: dict[str, str] | None = None
) -> tuple[int, dict[str, str], bytes]:
    connection = http.client.HTTPConnection(*address, timeout=10)
    try:
        connection.request("GET", path, headers=headers or {})
        response = connection.getresponse()
        return response.status, dict(response.getheaders()), response.read()
    finally:
        connection.close()


def test_a_100_kb_authorization_header_is_answered_431(address) -> None:
    status, headers, body = _get(address, headers={"Authorization": "Bearer " + "a" * 100_000})
    assert status == 431
    assert headers["Connection"] == "close" and headers["Content-Type"].startswith("text/plain")
    assert f"over {MAX_LINE_BYTES} bytes".encode() in body


def test_a_huge_url_is_answered_414(address) -> None:
    status, _, body = _get(address, path="/healthz?q=" + "x" * 100_000)
    assert status == 414 and b"request line" in body


def test_too_many_headers_are_answered_431(address) -> None:
    many = {f"X-Field-{i}": "1" for i in range(MAX_HEADERS + 10)}
    status, _, body = _get(address, headers=many)
    assert status == 431 and b"header fields" in body


def test_headers_too_large_together_are_answered_431(address) -> None:
    # Each one is short; together they are over the head's limit.
    fields = {f"X-Pad-{i}": "p" * 1000 for i in range(MAX_HEAD_BYTES // 1000 + 4)}
    status, _, _ = _get(address, headers=fields)
    assert status == 431


def test_a_client_still_sending_megabytes_reads_the_answer(address) -> None:
    """The platform reads and drops the rest of the request after answering: closing at
    once with bytes unread would reset the connection and could lose the answer."""
    with socket.create_connection(address, timeout=10) as sock:
        sock.sendall(
            b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer "
            + b"a" * 4_000_000
            + b"\r\n\r\n"
        )
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 431 ")


def test_requests_within_the_limits_are_served_on_one_connection(address) -> None:
    # Heads just under the limit, one after another on a kept-alive connection: each
    # request's head is counted on its own.
    connection = http.client.HTTPConnection(*address, timeout=10)
    try:
        for _ in range(3):
            connection.request("GET", "/healthz", headers={"X-Pad": "p" * (MAX_HEAD_BYTES - 500)})
            response = connection.getresponse()
            assert response.status == 200 and response.read().startswith(b'{"ok": true')
    finally:
        connection.close()
    assert _get(address)[0] == 200
