"""Limits on an HTTP/1.1 request's head, answered rather than dropped or ignored.

The platform's server (:mod:`iouv.serve`: uvicorn) parses HTTP with httptools, which
sets no limit of its own on a request's head: a client could send an endless URL or
header and the process would buffer it. :class:`LimitedHttpToolsProtocol` is uvicorn's
httptools protocol with limits, each answered: ``414 URI Too Long`` for the request
line, ``431 Request Header Fields Too Large`` for a header line, the whole head or the
number of header fields, each with a short plain-text body and ``Connection: close``.

It then closes its sending half only and reads and drops what the client still sends,
for at most :data:`LINGER_S` seconds: closing outright while request bytes are unread
makes the kernel send a reset, which can destroy the answer before the client reads it.

A head still arriving is checked after every read (at most one read, 256 KiB, is
buffered beyond a limit); a head that arrived whole is checked once complete, before
the request reaches Django. Under daphne, :mod:`iouv.http_limits_twisted` answers the
same limits.
"""

from __future__ import annotations

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

#: Longest request line (method, target, version), and longest single header line, in
#: bytes.
MAX_LINE_BYTES = 16 * 1024
#: Most bytes in the request line and all header lines together.
MAX_HEAD_BYTES = 16 * 1024
#: Most header lines in one request.
MAX_HEADERS = 500
#: After refusing a request, how long to keep reading (and dropping) what the client
#: still sends before closing the connection.
LINGER_S = 2.0

#: (status, reason phrase, why) of a refused head.
Refusal = tuple[int, bytes, str]

_URI_TOO_LONG = b"URI Too Long"
_HEADERS_TOO_LARGE = b"Request Header Fields Too Large"


def head_refusal(url: bytes, headers: list[tuple[bytes, bytes]]) -> Refusal | None:
    """Why a complete request head breaks a limit, or None. ``url`` is the request
    target, ``headers`` the (name, value) pairs as parsed."""
    if len(url) > MAX_LINE_BYTES:
        return (414, _URI_TOO_LONG, f"the request line is over {MAX_LINE_BYTES} bytes")
    if len(headers) > MAX_HEADERS:
        return (431, _HEADERS_TOO_LARGE, f"the request has more than {MAX_HEADERS} header fields")
    # Each line is "name: value\r\n"; the request line about the target and 14 bytes.
    total = len(url) + 14
    for name, value in headers:
        line = len(name) + len(value) + 4
        if line > MAX_LINE_BYTES:
            return (431, _HEADERS_TOO_LARGE, f"a header field is over {MAX_LINE_BYTES} bytes")
        total += line
    if total > MAX_HEAD_BYTES:
        return (431, _HEADERS_TOO_LARGE, f"the request's head is over {MAX_HEAD_BYTES} bytes")
    return None


class LimitedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol that answers an oversized request head with a 4xx
    (see the module); ``uvicorn --http iouv.http_limits:LimitedHttpToolsProtocol``."""

    # The current request's head: still arriving, bytes read for it after the read
    # that began it, and a refusal found when it completed.
    _in_head = False
    _head_bytes = 0
    _refusal: Refusal | None = None
    _refused = False

    def data_received(self, data: bytes) -> None:
        if self._refused:
            return  # the answer is out; drop the rest of the request (see _refuse)
        was_in_head = self._in_head
        super().data_received(data)
        if self._refusal is not None:
            self._refuse(*self._refusal)
            return
        if not self._in_head or self.transport.is_closing():
            return
        # The head is still arriving: what has come of it so far.
        if was_in_head:
            self._head_bytes += len(data)
        refusal = None
        if len(self.url) > MAX_LINE_BYTES:  # the target arrives piece by piece
            refusal = head_refusal(self.url, [])
        elif len(self.headers) > MAX_HEADERS:
            refusal = head_refusal(b"", self.headers)
        elif self._head_bytes > MAX_HEAD_BYTES:
            refusal = (
                431,
                _HEADERS_TOO_LARGE,
                f"the request's head is over {MAX_HEAD_BYTES} bytes",
            )
        if refusal is not None:
            self._refuse(*refusal)

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._in_head, self._head_bytes = True, 0

    def on_headers_complete(self) -> None:
        self._in_head = False
        self._refusal = head_refusal(self.url, self.headers)
        if self._refusal is None:
            super().on_headers_complete()

    def handle_websocket_upgrade(self) -> None:
        if self._refusal is None:
            super().handle_websocket_upgrade()

    def on_body(self, body: bytes) -> None:
        if self._refusal is None:
            super().on_body(body)

    def on_message_complete(self) -> None:
        if self._refusal is None:
            super().on_message_complete()

    def _refuse(self, status: int, reason: bytes, why: str) -> None:
        """Answer ``status`` with ``why`` as the body, then close (see the module)."""
        self._refused = True
        self._unset_keepalive_if_required()
        body = f"{why}\n".encode()
        self.transport.write(
            b"HTTP/1.1 %d %s\r\n"
            b"Content-Type: text/plain; charset=utf-8\r\n"
            b"Content-Length: %d\r\n"
            b"Connection: close\r\n"
            b"\r\n%s" % (status, reason, len(body), body)
        )
        if not self.transport.can_write_eof():
            self.transport.close()
            return
        # Reading goes on (and drops) until the client closes, or LINGER_S at most.
        self.transport.write_eof()
        self.loop.call_later(LINGER_S, self.transport.abort)
