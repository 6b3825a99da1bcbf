"""A userspace TCP proxy that makes loopback behave like a slower network link.

    python -m benchmarks.delay_proxy --target 127.0.0.1:8000 --delay-ms 11.65 --jitter-ms 3.4

The benchmarks need "remote" and "LTE" links, and this kernel has no ``netem``; so every
emulated network hop is a :class:`DelayProxy` in front of the real server. Each chunk of
bytes read from one side is written to the other side after

    one-way delay = delay_ms + Exp(jitter_ms)

where ``Exp(jitter_ms)`` is an exponentially distributed extra delay with mean
``jitter_ms`` (0 disables it). The delay never goes below ``delay_ms``: it is the link's
minimum, as a real path has one (propagation), and the jitter only ever adds queueing.
Per connection each direction has its own queue of (release time, chunk), and a chunk
is never released before the one read before it: when a short draw follows a long one
the chunk waits for its predecessor, as in TCP, where bytes are delivered in order.
The end of a stream (EOF) travels the same queue, so a close reaches the other side
after the data sent before it, delayed like any other segment.

A round trip through one proxy therefore costs at least ``2 * delay_ms``, plus a mean
of ``2 * jitter_ms``; the mean absolute deviation of the sum of the two draws is about
``1.08 * jitter_ms``. Timers are the event loop's: asyncio wakes up to a millisecond
late, so each direction adds up to 1 ms (0.5 ms on average) on top; the raw echo the
benchmarks measure through the same proxy carries the same error, which is the point of
measuring it.

The proxy runs in the caller's event loop. Use it as an async context manager; it
returns the port it listens on::

    async with DelayProxy(target_port=8000, delay_ms=12, jitter_ms=3) as port:
        ...  # connect to 127.0.0.1:port instead of 127.0.0.1:8000
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import random
from dataclasses import dataclass
from types import TracebackType

#: Bytes read per chunk; a control message is far smaller, so one message is one chunk.
CHUNK_BYTES = 65_536


@dataclass(frozen=True)
class Link:
    """One emulated network path, applied the same way in both directions.

    ``delay_ms`` is the one-way minimum (half the path's minimum round trip);
    ``jitter_ms`` the mean of the exponential extra delay per chunk and direction.
    """

    name: str
    delay_ms: float = 0.0
    jitter_ms: float = 0.0

    def __post_init__(self) -> None:
        if self.delay_ms < 0 or self.jitter_ms < 0:
            raise ValueError("delay_ms and jitter_ms must not be negative")

    @property
    def rtt_min_ms(self) -> float:
        """The smallest round trip over this link: twice the one-way delay."""
        return 2 * self.delay_ms

    @property
    def rtt_mean_ms(self) -> float:
        """The mean round trip over this link, without any software in the path."""
        return 2 * (self.delay_ms + self.jitter_ms)


class DelayProxy:
    """Forward TCP connections from a local port to ``target`` over an emulated link.

    ``link`` (or ``delay_ms`` and ``jitter_ms``) sets the delay added per chunk and
    direction; ``seed`` makes the jitter reproducible. As an async context manager it
    listens on ``listen_host:listen_port`` (0: any free port) and returns that port;
    leaving it stops listening and aborts every connection still open.

    Counters: :attr:`connections` accepted, :attr:`chunks` forwarded (both directions).
    """

    def __init__(
        self,
        *,
        target_port: int,
        target_host: str = "127.0.0.1",
        link: Link | None = None,
        delay_ms: float = 0.0,
        jitter_ms: float = 0.0,
        listen_host: str = "127.0.0.1",
        listen_port: int = 0,
        seed: int | None = None,
    ) -> None:
        self.link = link or Link("custom", delay_ms=delay_ms, jitter_ms=jitter_ms)
        self.target = (target_host, target_port)
        self.listen = (listen_host, listen_port)
        self.port = 0
        self.connections = 0
        self.chunks = 0
        self._random = random.Random(seed)
        self._server: asyncio.Server | None = None
        self._pipes: set[asyncio.Task[None]] = set()

    # --- lifecycle ----------------------------------------------------------------------
    async def __aenter__(self) -> int:
        self._server = await asyncio.start_server(self._accept, *self.listen)
        self.port = int(self._server.sockets[0].getsockname()[1])
        return self.port

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Stop listening and abort every open connection (idempotent)."""
        if self._server is not None:
            self._server.close()
            self._server = None
        for pipe in list(self._pipes):
            pipe.cancel()
        # The pipes close their sockets on cancellation; wait so none outlives us.
        await asyncio.gather(*self._pipes, return_exceptions=True)

    # --- one connection ------------------------------------------------------------------
    def _draw_s(self) -> float:
        """One chunk's one-way delay in seconds."""
        extra = self._random.expovariate(1 / self.link.jitter_ms) if self.link.jitter_ms else 0.0
        return (self.link.delay_ms + extra) / 1000

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        # Tracked so aclose() can abort connections that are still open.
        task = asyncio.current_task()
        assert task is not None
        self._pipes.add(task)
        self.connections += 1
        try:
            await self._pipe(reader, writer)
        except asyncio.CancelledError:
            # Only aclose() (or loop shutdown) cancels a pipe, and the sockets are closed
            # by then. Ending quietly matters: asyncio 3.11's stream callback calls
            # task.exception() on the handler and would log a cancelled one as an error.
            pass
        finally:
            self._pipes.discard(task)

    async def _pipe(
        self, down_reader: asyncio.StreamReader, down_writer: asyncio.StreamWriter
    ) -> None:
        up_writer: asyncio.StreamWriter | None = None
        try:
            up_reader, up_writer = await asyncio.open_connection(*self.target)
            async with asyncio.TaskGroup() as group:
                group.create_task(self._direction(down_reader, up_writer))
                group.create_task(self._direction(up_reader, down_writer))
        except* OSError:
            # Nobody at the target, or a reset on either side. The client then sees its
            # connection drop, as behind a real link.
            pass
        finally:
            # Abort, not close: after both EOFs there is nothing left to flush, and on
            # an error or a cancellation the peers must see the link drop at once.
            down_writer.transport.abort()
            if up_writer is not None:
                up_writer.transport.abort()

    async def _direction(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Carry one direction: read chunks, release each at its time, in order."""
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

        async def receive() -> None:
            released = 0.0
            while True:
                try:
                    chunk = await reader.read(CHUNK_BYTES)
                except ConnectionError:
                    chunk = b""  # a reset ends this direction like an EOF
                # Never before the previous chunk: the link does not reorder.
                released = max(loop.time() + self._draw_s(), released)
                queue.put_nowait((released, chunk))
                if not chunk:
                    return

        async def deliver() -> None:
            while True:
                at, chunk = await queue.get()
                wait = at - loop.time()
                if wait > 0:
                    await asyncio.sleep(wait)
                if not chunk:
                    # Half-close: the peer may still answer in the other direction.
                    if writer.can_write_eof() and not writer.is_closing():
                        with contextlib.suppress(OSError):
                            writer.write_eof()
                    return
                writer.write(chunk)
                await writer.drain()
                self.chunks += 1

        async with asyncio.TaskGroup() as group:
            group.create_task(receive())
            group.create_task(deliver())


async def _serve(target: str, link: Link, port: int, seed: int | None) -> None:
    host, _, target_port = target.rpartition(":")
    proxy = DelayProxy(
        target_host=host or "127.0.0.1",
        target_port=int(target_port),
        link=link,
        listen_port=port,
        seed=seed,
    )
    async with proxy as listening:
        print(
            f"127.0.0.1:{listening} -> {target}: one-way {link.delay_ms:g} ms "
            f"+ Exp(mean {link.jitter_ms:g} ms) per chunk; Ctrl-C to stop",
            flush=True,
        )
        await asyncio.Event().wait()


def main(argv: list[str] | None = None) -> None:
    """Run one proxy from the command line until interrupted."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.delay_proxy",
        description="TCP proxy adding one-way delay and jitter per chunk, never reordering.",
    )
    parser.add_argument("--target", required=True, help="HOST:PORT to forward to")
    parser.add_argument("--port", type=int, default=0, help="port to listen on (0: any)")
    parser.add_argument("--delay-ms", type=float, default=0.0, help="one-way minimum delay")
    parser.add_argument("--jitter-ms", type=float, default=0.0, help="mean extra delay")
    parser.add_argument("--seed", type=int, default=None)
    args = parser.parse_args(argv)
    link = Link("cli", delay_ms=args.delay_ms, jitter_ms=args.jitter_ms)
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(_serve(args.target, link, args.port, args.seed))


if __name__ == "__main__":
    main()
