"""Limits on an HTTP/1.1 request's head under daphne, answered rather than dropped.

daphne parses HTTP with Twisted's ``HTTPChannel``, a ``LineReceiver``. A request line
or a header line longer than ``MAX_LENGTH`` makes ``LineReceiver`` close the
connection with no answer at all, so a client with an oversized ``Authorization``
header or URL sees the connection close instead of an error it can act on; too many or
too large headers in total get a bare ``400`` followed by an immediate close, which
can reset the answer away while the client is still sending.

:class:`LimitedHTTPChannel` answers every one of them as the platform's own server does
(:mod:`iouv.http_limits`, same limits): ``414 URI Too Long`` for the request line,
``431 Request Header Fields Too Large`` for the headers, each with a short plain-text
body and ``Connection: close``. It then closes its sending half only and reads and
drops what the client still sends, for at most ``LINGER_S`` seconds.

daphne has no setting for its HTTP protocol, so :func:`daphne_use_limited_channel`
sets ``protocol`` (Twisted's ``Factory`` extension point) on daphne's HTTP factory.
``iouv.asgi`` calls it, which covers every way daphne serves the platform (``daphne
iouv.asgi:application``, ``python -m daphne``, ``manage.py runserver``).
"""

from __future__ import annotations

from typing import Any

from twisted.internet.interfaces import ITCPTransport
from twisted.web import http

from iouv.http_limits import LINGER_S, MAX_HEAD_BYTES, MAX_HEADERS, MAX_LINE_BYTES


class LimitedHTTPChannel(http.HTTPChannel):
    """Twisted's ``HTTPChannel`` that answers an oversized request head with a 4xx
    (414 for the request line, 431 for the headers) instead of dropping the connection.
    """

    MAX_LENGTH = MAX_LINE_BYTES
    totalHeadersSize = MAX_HEAD_BYTES
    maxHeaders = MAX_HEADERS

    _refused = False
    # This request's head so far: bytes and lines (the request line included).
    # Counted here, before Twisted's own checks, so that each of its limits is
    # answered by _refuse rather than by its bare 400.
    _head_bytes = 0
    _head_lines = 0

    def dataReceived(self, data: bytes) -> None:
        if self._refused:
            return  # the answer is out; drop the rest of the request (see _refuse)
        super().dataReceived(data)

    def lineReceived(self, line: bytes) -> None:
        if self._refused:
            return
        self._head_bytes += len(line)
        if line and line[:1] not in b" \t":  # a continuation line is not a new header
            self._head_lines += 1
        if self._head_bytes > self.totalHeadersSize:
            self._refuse_head(f"the request's head is over {self.totalHeadersSize} bytes")
            return
        if self._head_lines > self.maxHeaders + 1:
            self._refuse_head(f"the request has more than {self.maxHeaders} header fields")
            return
        super().lineReceived(line)

    def allContentReceived(self) -> None:
        # A request is complete: the next one's head is counted from zero.
        self._head_bytes = 0
        self._head_lines = 0
        super().allContentReceived()

    def lineLengthExceeded(self, line: bytes) -> None:
        # LineReceiver's default closes the connection without a word.
        if self._head_lines == 0:
            self._refuse(414, b"URI Too Long", f"the request line is over {self.MAX_LENGTH} bytes")
        else:
            self._refuse_head(f"a header field is over {self.MAX_LENGTH} bytes")

    def _refuse_head(self, why: str) -> None:
        self._refuse(431, b"Request Header Fields Too Large", why)

    def _refuse(self, status: int, reason: bytes, why: str) -> None:
        """Answer ``status`` with ``why`` as the body, then close (see the module)."""
        self._refused = True
        transport: Any = self.transport  # zope's interfaces give mypy no usable types
        body = f"{why}\n".encode()
        transport.write(
            b"HTTP/1.1 %d %s\r\n"
            b"Content-Type: text/plain; charset=utf-8\r\n"
            b"Content-Length: %d\r\n"
            b"Connection: close\r\n"
            b"\r\n%s" % (status, reason, len(body), body)
        )
        # The idle timeout ends the lingering: timeoutConnection closes the connection
        # (and aborts it if the client does not let go). dataReceived no longer resets it.
        self.setTimeout(LINGER_S)
        if ITCPTransport.providedBy(transport):
            transport.loseWriteConnection()
        else:
            self.loseConnection()


def daphne_use_limited_channel() -> None:
    """Make daphne's HTTP server build :class:`LimitedHTTPChannel` for each connection.

    Twisted's default protocol wraps the channel so that it can switch to HTTP/2 when
    TLS negotiates it; daphne here serves plain HTTP/1.1 (TLS ends at the proxy), which
    the channel speaks by itself. Idempotent.
    """
    from daphne.http_protocol import HTTPFactory

    factory: Any = HTTPFactory
    factory.protocol = LimitedHTTPChannel
