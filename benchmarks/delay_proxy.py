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

:class:`UdpDelayProxy` is the same link for UDP, for WebRTC traffic, which the TCP proxy
cannot carry: the benchmarks put it between a user and the TURN server. It draws the
jitter once per burst (see its docstring), so that one message exchange meets the same
link statistics as one WebSocket frame through the TCP proxy.

The proxies run in the caller's event loop. Use one as an async context manager; it
returns the port it listens on::

    async with DelayProxy(target_port=8000, delay_ms=12, jitter_ms=3) as port:
        ...  # connect to 127.0.0.1:port instead of 127.0.0.1:8000
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import random
import socket
from collections.abc import Callable
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


class UdpDelayProxy:
    """Forward UDP datagrams from a local port to ``target`` over an emulated link: the
    datagram counterpart of :class:`DelayProxy`, for paths the TCP proxy cannot carry
    (WebRTC's ICE/DTLS/SCTP, e.g. a user's traffic to a TURN server).

    Each client address seen on the listening port gets its own socket towards the
    target (a "flow"), so the target sees one peer per client, as behind a NAT. In each
    flow and direction a datagram that finds the link idle (nothing held) is released
    after ``delay_ms + Exp(jitter_ms)``; one that arrives while earlier ones are still
    held queues behind them: released after ``delay_ms`` and never before its
    predecessor, with no draw of its own. Packets sent back to back share one queueing
    delay, as in a real queue, and an exchange such as SCTP's data chunk preceded by a
    SACK meets the link like one WebSocket frame through :class:`DelayProxy` (where the
    kernel's TCP acknowledgements never cross the emulated link). The link neither
    reorders nor loses (a full socket buffer drops, as a queue would). As an async
    context manager it returns the port it listens on; leaving it closes every socket.
    Counters: :attr:`flows` opened, :attr:`datagrams` forwarded.
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
        max_flows: int = 256,
    ) -> None:
        self.link = link or Link("custom", delay_ms=delay_ms, jitter_ms=jitter_ms)
        self.target = (target_host, target_port)
        self.listen = (listen_host, listen_port)
        self.max_flows = max_flows
        self.port = 0
        self.flows = 0
        self.datagrams = 0
        self._random = random.Random(seed)
        self._front: socket.socket | None = None
        self._by_client: dict[tuple[str, int], _UdpFlow] = {}

    async def __aenter__(self) -> int:
        loop = asyncio.get_running_loop()
        front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        front.setblocking(False)
        front.bind(self.listen)
        self._front = front
        self.port = int(front.getsockname()[1])
        loop.add_reader(front.fileno(), self._from_clients)
        return self.port

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Stop listening and close every flow (idempotent)."""
        loop = asyncio.get_running_loop()
        for flow in self._by_client.values():
            flow.close(loop)
        self._by_client.clear()
        if self._front is not None:
            loop.remove_reader(self._front.fileno())
            self._front.close()
            self._front = None

    def _draw_s(self) -> float:
        """The jitter of a datagram that finds the link idle, in seconds."""
        extra = self._random.expovariate(1 / self.link.jitter_ms) if self.link.jitter_ms else 0.0
        return extra / 1000

    def _from_clients(self) -> None:
        front = self._front
        if front is None:
            return
        loop = asyncio.get_running_loop()
        while True:
            try:
                data, client = front.recvfrom(CHUNK_BYTES)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # an ICMP error for an earlier send; readable again if more came
            flow = self._by_client.get(client)
            if flow is None:
                if len(self._by_client) >= self.max_flows:
                    continue
                flow = _UdpFlow(self, client, loop)
                self._by_client[client] = flow
                self.flows += 1
            flow.up.put(loop, data)

    def _to_client(self, client: tuple[str, int], data: bytes) -> None:
        if self._front is None:
            return
        with contextlib.suppress(OSError):
            self._front.sendto(data, client)
            self.datagrams += 1


class _UdpDirection:
    """One direction of a flow: datagrams waiting for their release time, in order."""

    def __init__(self, proxy: UdpDelayProxy, send: Callable[[bytes], None]) -> None:
        self._proxy = proxy
        self._send = send
        self._queue: collections.deque[tuple[float, bytes]] = collections.deque()
        self._timer: asyncio.TimerHandle | None = None
        self._last = 0.0

    def put(self, loop: asyncio.AbstractEventLoop, data: bytes) -> None:
        # An idle link draws the jitter; behind held datagrams, the queue is the jitter.
        delay_s = self._proxy.link.delay_ms / 1000
        if not self._queue:
            delay_s += self._proxy._draw_s()
        # Never before the previous datagram: the link does not reorder.
        self._last = max(loop.time() + delay_s, self._last)
        self._queue.append((self._last, data))
        if self._timer is None:
            self._timer = loop.call_at(self._last, self._release, loop)

    def _release(self, loop: asyncio.AbstractEventLoop) -> None:
        self._timer = None
        now = loop.time()
        while self._queue and self._queue[0][0] <= now:
            self._send(self._queue.popleft()[1])
        if self._queue:
            self._timer = loop.call_at(self._queue[0][0], self._release, loop)

    def cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._queue.clear()


class _UdpFlow:
    """One client of a :class:`UdpDelayProxy` and its socket towards the target."""

    def __init__(
        self, proxy: UdpDelayProxy, client: tuple[str, int], loop: asyncio.AbstractEventLoop
    ) -> None:
        self.proxy = proxy
        self.client = client
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.sock.connect(proxy.target)
        self.up = _UdpDirection(proxy, self._to_target)
        self.down = _UdpDirection(proxy, lambda data: proxy._to_client(client, data))
        loop.add_reader(self.sock.fileno(), self._from_target, loop)

    def _to_target(self, data: bytes) -> None:
        with contextlib.suppress(OSError):
            self.sock.send(data)
            self.proxy.datagrams += 1

    def _from_target(self, loop: asyncio.AbstractEventLoop) -> None:
        while True:
            try:
                data = self.sock.recv(CHUNK_BYTES)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # e.g. the target's port was closed (ICMP unreachable)
            self.down.put(loop, data)

    def close(self, loop: asyncio.AbstractEventLoop) -> None:
        self.up.cancel()
        self.down.cancel()
        loop.remove_reader(self.sock.fileno())
        self.sock.close()


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
