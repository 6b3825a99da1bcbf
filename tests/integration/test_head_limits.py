"""Oversized request heads are refused in front of the platform, which goes on serving
everyone else.

The production shape from deploy/'s own files (tests.production): nginx with TLS in
front of one HTTP process (gunicorn) and one WebSocket process (uvicorn, whose parser
sets no head limit of its own). nginx refuses a request line or a header line over its
buffer (``large_client_header_buffers`` in deploy/nginx/iouv.conf, read from the file)
and a head over all its buffers; gunicorn refuses more header fields than it takes
(``limit_request_fields``, deploy/gunicorn.conf.py). The requests go over real sockets,
as a client would send them.
"""

from __future__ import annotations

import http.client
import re
import socket
import ssl
from collections.abc import Iterator
from urllib.parse import urlsplit

import pytest
from websockets.sync.client import connect

from benchmarks.nginx_proxy import NginxUnavailable, nginx_binary
from tests.production import SITE, ProductionShape

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    # Not ``transaction=True``: the processes live across the module's tests (the
    # module_database fixture, tests/integration's conftest.py); no test writes a row.
    pytest.mark.django_db,
]


def _buffers() -> tuple[int, int]:
    """``large_client_header_buffers`` of the shipped site: (how many, bytes each)."""
    found = re.search(r"^\s*large_client_header_buffers (\d+) (\d+)k;", SITE.read_text(), re.M)
    assert found, f"no large_client_header_buffers in {SITE}"
    return int(found[1]), int(found[2]) * 1024


BUFFERS, BUFFER_BYTES = _buffers()
#: gunicorn's most header fields in one request (deploy/gunicorn.conf.py).
MAX_FIELDS = 100


@pytest.fixture(scope="module")
def shape(
    module_database: None, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[ProductionShape]:
    try:
        nginx_binary()  # Debian's, installed if missing
    except NginxUnavailable as exc:
        pytest.skip(f"needs nginx: {exc}")
    workdir = tmp_path_factory.mktemp("heads")
    production = ProductionShape(workdir, web=1, ws=1, worker=False, env={})
    with production.running():
        yield production


def _address(shape: ProductionShape) -> tuple[str, int]:
    parts = urlsplit(shape.base)
    assert parts.hostname and parts.port
    return parts.hostname, parts.port


def _get(
    shape: ProductionShape, path: str = "/healthz", headers: dict[str, str] | None = None
) -> tuple[int, dict[str, str], bytes]:
    connection = http.client.HTTPSConnection(*_address(shape), timeout=10, context=shape.context)
    try:
        connection.request("GET", path, headers=headers or {})
        response = connection.getresponse()
        return response.status, dict(response.getheaders()), response.read()
    finally:
        connection.close()


def _serving(shape: ProductionShape) -> bool:
    """The platform answers an ordinary request through nginx."""
    status, _, body = _get(shape)
    return status == 200 and body.startswith(b'{"ok": true')


#: A WebSocket handshake's own headers (the key is the RFC's example).
HANDSHAKE = {
    "Upgrade": "websocket",
    "Connection": "Upgrade",
    "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
    "Sec-WebSocket-Version": "13",
}


@pytest.mark.parametrize(
    ("path", "headers"), [("/api/v1/services", {}), ("/ws/agent/", HANDSHAKE)], ids=["http", "ws"]
)
def test_a_100_kb_authorization_header_is_refused_with_400(shape, path, headers) -> None:
    status, answer, body = _get(
        shape, path, headers={**headers, "Authorization": "Bearer " + "a" * 100_000}
    )
    assert status == 400 and b"Request Header Or Cookie Too Large" in body
    assert answer["Connection"] == "close"
    assert _serving(shape)


def test_a_huge_url_is_refused_with_414(shape) -> None:
    status, _, body = _get(shape, path="/healthz?q=" + "x" * 100_000)
    assert status == 414 and b"Request-URI Too Large" in body
    assert _serving(shape)


def test_headers_too_large_together_are_refused_with_400(shape) -> None:
    # Each one is short; together they are over nginx's buffers.
    count = BUFFERS * BUFFER_BYTES // 1000 + 4
    status, _, body = _get(shape, headers={f"X-Pad-{i}": "p" * 1000 for i in range(count)})
    assert status == 400 and b"Request Header Or Cookie Too Large" in body
    assert _serving(shape)


def test_too_many_header_fields_are_refused_with_431(shape) -> None:
    # Within nginx's buffers: gunicorn counts them.
    many = {f"X-Field-{i}": "1" for i in range(MAX_FIELDS + 10)}
    status, _, body = _get(shape, headers=many)
    assert status == 431 and b"limit request headers fields" in body.lower()
    assert _serving(shape)


def test_a_client_still_sending_megabytes_reads_the_answer(shape) -> None:
    """nginx reads and drops the rest of the request after answering (its lingering
    close): closing at once with bytes unread would reset the connection and could lose
    the answer."""
    host, port = _address(shape)
    with (
        socket.create_connection((host, port), timeout=10) as raw,
        shape.context.wrap_socket(raw, server_hostname=host) as sock,
    ):
        sock.sendall(
            b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer "
            + b"a" * 4_000_000
            + b"\r\n\r\n"
        )
        answer = b""
        try:
            while chunk := sock.recv(65536):
                answer += chunk
        except ssl.SSLZeroReturnError:
            pass
    assert answer.startswith(b"HTTP/1.1 400 "), answer[:200]
    assert _serving(shape)


def test_heads_within_the_limits_reach_the_platform_on_one_connection(shape) -> None:
    # A request line and a header line each just under a buffer, one request after
    # another on a kept-alive connection: each request's head is counted on its own.
    pad = "p" * (BUFFER_BYTES - 500)
    connection = http.client.HTTPSConnection(*_address(shape), timeout=10, context=shape.context)
    try:
        for _ in range(3):
            connection.request("GET", f"/healthz?q={pad}", headers={"X-Pad": pad})
            response = connection.getresponse()
            assert response.status == 200 and response.read().startswith(b'{"ok": true')
    finally:
        connection.close()


def test_a_websocket_handshake_within_the_limits_reaches_the_platform(shape) -> None:
    host, port = _address(shape)
    pad = "p" * (BUFFER_BYTES - 500)
    with connect(
        f"wss://{host}:{port}/ws/agent/",
        ssl=shape.context,
        additional_headers={"X-Pad": pad},
        open_timeout=10,
    ) as uplink:
        # Open: the platform's uplink took it, and waits for the agent's hello.
        assert uplink.response is not None and uplink.response.status_code == 101
