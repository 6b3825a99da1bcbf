"""A TCP proxy in front of a server whose open connections can be frozen, as when the
machine behind one of them drops off the network while the proxy (nginx, in production)
stays up: nothing more passes on a frozen connection, either way, and nobody closes it.
Connections opened later pass as before::

    async with FreezingProxy(target_port=8000) as proxy:
        ...  # connect to 127.0.0.1:proxy.port
        proxy.freeze(lambda first_line: "/ws/relay/" in first_line)
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType

#: Bytes read per chunk.
CHUNK_BYTES = 65_536


@dataclass
class _Connection:
    """One proxied connection: its first line (an HTTP request line, for a browser's),
    whether it is frozen, and its two sockets' writers."""

    first_line: str = ""
    frozen: bool = False
    writers: list[asyncio.StreamWriter] = field(default_factory=list)


class FreezingProxy:
    """Listens on 127.0.0.1 (:attr:`port`, once entered) and forwards each connection
    to ``target_host:target_port``; :meth:`freeze` stops the connections it picks."""

    def __init__(self, *, target_port: int, target_host: str = "127.0.0.1") -> None:
        self.target = (target_host, target_port)
        self.port = 0
        self.connections: list[_Connection] = []
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    async def __aenter__(self) -> FreezingProxy:
        self._server = await asyncio.start_server(self._accept, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._server is not None:
            self._server.close()
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError, OSError):
                await task
        for connection in self.connections:
            for writer in connection.writers:
                writer.close()

    def freeze(self, which: Callable[[str], bool]) -> int:
        """Freeze the open connections whose first line ``which`` picks; returns how
        many. Their sockets stay open until the proxy closes."""
        picked = [c for c in self.connections if not c.frozen and which(c.first_line)]
        for connection in picked:
            connection.frozen = True
        return len(picked)

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        connection = _Connection(writers=[writer])
        try:
            upstream_reader, upstream_writer = await asyncio.open_connection(*self.target)
        except OSError:
            writer.close()
            return
        connection.writers.append(upstream_writer)
        self.connections.append(connection)
        for source, sink, first in (
            (reader, upstream_writer, True),
            (upstream_reader, writer, False),
        ):
            task = asyncio.create_task(self._pipe(connection, source, sink, first=first))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _pipe(
        self,
        connection: _Connection,
        source: asyncio.StreamReader,
        sink: asyncio.StreamWriter,
        *,
        first: bool,
    ) -> None:
        """Copy ``source`` to ``sink`` until either ends or the connection is frozen;
        a frozen connection's sockets are left open (the proxy's exit closes them)."""
        try:
            while not connection.frozen:
                data = await source.read(CHUNK_BYTES)
                if not data or connection.frozen:
                    break
                if first and not connection.first_line:
                    connection.first_line = data.split(b"\r\n", 1)[0].decode("latin-1")
                sink.write(data)
                await sink.drain()
        except OSError:
            pass
        if not connection.frozen:
            sink.close()
