"""A small front proxy: one address, backends chosen by the first request's path.

    python -m benchmarks.front_proxy --listen 127.0.0.1:8000 \\
        --route /ws/agent/=127.0.0.1:8001 --default 127.0.0.1:8002

It lets the platform run as several daphne processes behind one address, as a real
deployment would behind nginx or HAProxy, using nothing but the standard library: the
agents' uplinks (``/ws/agent/``) go to one process, browsers and API programs to
another, and both processes share PostgreSQL and Redis.

How it routes: for each incoming TCP connection it reads the HTTP request line (``GET
/ws/agent/ HTTP/1.1``), picks the backend of the longest ``--route`` prefix that the
path starts with (else ``--default``), connects to it, replays the bytes read so far
and then pipes bytes both ways untouched until both sides are done. With only a
default backend it forwards everything.

What that implies, on purpose:

* It routes **connections**, not requests: every later request on a keep-alive HTTP
  connection goes to the backend its first request chose. A WebSocket is one request
  per connection, so it is always routed right; an API client's keep-alive
  connection stays on the users' process, which is what we want.
* It does not rewrite anything (no ``X-Forwarded-For``, no TLS): daphne sees the
  client's ``Host`` header, so the URLs it builds (the relay URL in a user task) point
  back at the proxy's address.
* A client that vanishes with a reset is reset towards the backend too (and the
  other way round), so a dead browser still looks dead to the platform; a clean end
  of stream is passed on as a half-close.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import resource
import signal
import socket
import struct
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Self

log = logging.getLogger(__name__)

#: The request line must arrive within this many bytes and seconds, or the
#: connection is dropped (a slow or garbage client cannot hold a slot forever).
REQUEST_LINE_MAX = 8192
REQUEST_LINE_TIMEOUT_S = 10.0
CONNECT_TIMEOUT_S = 5.0
CHUNK = 65536


@dataclass(frozen=True)
class Backend:
    """Where a connection is forwarded."""

    host: str
    port: int

    @classmethod
    def parse(cls, text: str, *, any_port: bool = False) -> Backend:
        """``host:port`` (``[::1]:8000`` for IPv6); port 0 only with ``any_port`` (a
        listening address). Raises ValueError otherwise."""
        host, sep, port = text.rpartition(":")
        low = 0 if any_port else 1
        if not sep or not host or not port.isdigit() or not low <= int(port) < 65536:
            raise ValueError(f"expected host:port, got {text!r}")
        return cls(host.strip("[]"), int(port))

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


@dataclass(frozen=True)
class Rule:
    """Connections whose first request path starts with ``prefix`` go to ``backend``."""

    prefix: str
    backend: Backend

    @classmethod
    def parse(cls, text: str) -> Rule:
        """``/path/prefix=host:port``; raises ValueError otherwise."""
        prefix, sep, target = text.partition("=")
        if not sep or not prefix.startswith("/"):
            raise ValueError(f"expected /prefix=host:port, got {text!r}")
        return cls(prefix, Backend.parse(target))


@dataclass
class Routes:
    """The routing table: prefix rules (longest match wins) and a default backend."""

    default: Backend
    rules: Sequence[Rule] = ()
    counts: Counter[str] = field(default_factory=Counter)

    def backend_for(self, path: str) -> Backend:
        """The backend for a request path (query string ignored)."""
        path = path.split("?", 1)[0]
        matches = [rule for rule in self.rules if path.startswith(rule.prefix)]
        if not matches:
            return self.default
        return max(matches, key=lambda rule: len(rule.prefix)).backend


def request_path(request_line: bytes) -> str | None:
    """The path of an HTTP/1.x request line, or None if it is not one."""
    parts = request_line.strip().split(b" ")
    if len(parts) != 3 or not parts[2].startswith(b"HTTP/"):
        return None
    try:
        return parts[1].decode("ascii")
    except UnicodeDecodeError:
        return None


def _abort(writer: asyncio.StreamWriter) -> None:
    """Close with a TCP reset, not a FIN: the peer must see the connection die the way
    the other side's did, not end cleanly. (``abort()`` alone sends a FIN when nothing
    is left unread; a zero linger time makes the kernel send a reset.)"""
    transport = writer.transport
    if transport.is_closing():
        return
    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    transport.abort()


async def _pipe(
    reader: asyncio.StreamReader, writer: asyncio.StreamWriter, peer: asyncio.StreamWriter
) -> None:
    """Copy ``reader`` to ``writer`` until end of stream, then half-close ``writer``.

    On a reset or any socket error both connections are aborted, so neither end
    mistakes a dead peer for a polite one.
    """
    try:
        while True:
            data = await reader.read(CHUNK)
            if not data:
                break
            writer.write(data)
            await writer.drain()
        if writer.can_write_eof() and not writer.transport.is_closing():
            writer.write_eof()
    except (ConnectionError, OSError, RuntimeError):
        _abort(writer)
        _abort(peer)


class FrontProxy:
    """The proxy as an async context manager: listens on ``host:port`` (0 = any free
    port, see :attr:`port`) until the context exits, then closes every connection."""

    def __init__(self, routes: Routes, *, host: str = "127.0.0.1", port: int = 0) -> None:
        self.routes = routes
        self.host = host
        self.port = port
        self._server: asyncio.Server | None = None
        self._handlers: set[asyncio.Task[None]] = set()

    async def start(self) -> None:
        self._server = await asyncio.start_server(
            self._handle, self.host, self.port, limit=REQUEST_LINE_MAX, backlog=4096
        )
        self.port = self._server.sockets[0].getsockname()[1]
        log.info(
            "front proxy on %s:%d: %s, default %s",
            self.host,
            self.port,
            ", ".join(f"{r.prefix} -> {r.backend}" for r in self.routes.rules) or "no rules",
            self.routes.default,
        )

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
        for task in list(self._handlers):
            task.cancel()
        if self._handlers:
            await asyncio.gather(*self._handlers, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    async def serve_forever(self) -> None:
        assert self._server is not None
        await self._server.serve_forever()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        upstream: asyncio.StreamWriter | None = None
        try:
            try:
                first = await asyncio.wait_for(reader.readuntil(b"\n"), REQUEST_LINE_TIMEOUT_S)
            except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError):
                return
            path = request_path(first)
            if path is None:
                writer.write(b"HTTP/1.1 400 Bad Request\r\nConnection: close\r\n\r\n")
                return
            backend = self.routes.backend_for(path)
            self.routes.counts[str(backend)] += 1
            try:
                up_reader, up_writer = await asyncio.wait_for(
                    asyncio.open_connection(backend.host, backend.port, limit=CHUNK),
                    CONNECT_TIMEOUT_S,
                )
            except (OSError, TimeoutError) as exc:
                log.warning("backend %s unreachable: %s", backend, exc)
                writer.write(b"HTTP/1.1 502 Bad Gateway\r\nConnection: close\r\n\r\n")
                return
            upstream = up_writer  # closed in the finally clause below
            upstream.write(first)
            await asyncio.gather(
                _pipe(reader, up_writer, writer),
                _pipe(up_reader, writer, up_writer),
            )
        except (ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            # Only close() cancels a handler. Ending normally keeps asyncio's stream
            # callback (Python 3.11) from logging the cancellation as an error.
            pass
        finally:
            self._handlers.discard(task)
            for w in (writer, upstream):
                if w is not None:
                    w.close()
                    with contextlib.suppress(Exception):
                        await w.wait_closed()


def raise_open_files_limit() -> int:
    """Raise this process's open-file limit to its hard limit (each proxied connection
    costs two descriptors); returns the new soft limit."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 65536)
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


def routes_from_args(route: Sequence[str], default: str) -> Routes:
    """A routing table from CLI-style texts; raises ValueError naming a bad one."""
    return Routes(default=Backend.parse(default), rules=[Rule.parse(r) for r in route])


async def _main(listen: Backend, routes: Routes) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    async with FrontProxy(routes, host=listen.host, port=listen.port) as proxy:
        print(f"listening on {proxy.host}:{proxy.port}", flush=True)
        await stop.wait()
    log.info("connections routed: %s", dict(routes.counts))


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.front_proxy",
        description="Route each connection by its first request path to a backend.",
    )
    parser.add_argument("--listen", default="127.0.0.1:8000", help="host:port (port 0: any)")
    parser.add_argument(
        "--route",
        action="append",
        default=[],
        metavar="/PREFIX=HOST:PORT",
        help="connections whose first path starts with PREFIX go to HOST:PORT (repeatable)",
    )
    parser.add_argument("--default", required=True, metavar="HOST:PORT", help="all the rest")
    args = parser.parse_args(argv)
    try:
        listen = Backend.parse(args.listen, any_port=True)
        routes = routes_from_args(args.route, args.default)
    except ValueError as exc:
        parser.error(str(exc))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    raise_open_files_limit()
    asyncio.run(_main(listen, routes))


if __name__ == "__main__":
    main()
