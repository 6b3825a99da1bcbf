"""A minimal aiortc peer for the network lab (tests/netlab.py), run inside a site's
namespace, plus ``PeerProcess``, the test-side handle that drives it.

Run: ``ip netns exec NS python -m tests.netlab_peer --role offer|answer
[--ice-servers JSON] [--stun-retries N] [--consent-interval S --consent-failures N]``.

It speaks JSON lines: commands on stdin, events on stdout (one object per line).

Events (stdout), each with ``"t"``, seconds since the program started:
    ``{"event": "gathered", "candidates": ["host", "srflx", ...]}``
        local candidate types once gathering ended.
    ``{"event": "offer"|"answer", "sdp": ...}``
        the local description, with all candidates (aiortc gathers before it is set).
    ``{"event": "state", "state": ...}``
        every RTCPeerConnection.connectionState change. aiortc has no "disconnected":
        when consent freshness expires (a cut link) its DTLS transport closes and the
        connection closes itself, so the state goes "connected" -> "closed".
    ``{"event": "selected", "local": type, "remote": type, "local_addr": [h, p],
    "remote_addr": [h, p]}``
        the nominated ICE candidate pair, right after the state became "connected".
    ``{"event": "echo", "ok": bool, "rtt_ms": float | None}``
        the result of an ``echo`` command.
    ``{"event": "error", "error": ...}``
        a command failed.

Commands (stdin):
    ``{"cmd": "offer", "sdp": ...}`` (answerer) and ``{"cmd": "answer", "sdp": ...}``
    (offerer); ``{"cmd": "echo", "timeout": s}``: send a token on the data channel and
    wait for the other peer to send it back; ``{"cmd": "close"}`` (or EOF): close, exit 0.

The offerer opens the data channel "echo"; both peers send back what arrives with a
``ping:`` prefix as ``pong:``.

aioice's timeouts suit the internet, not a test: a STUN transaction gives up after 7
tries over 63.5 s and consent freshness after 6 misses at 5 s intervals. The options
shorten them (module globals of aioice, read when used; ``--stun-retries`` applies to
every STUN transaction: connectivity checks, srflx and TURN requests) so that a
connection that cannot work fails within seconds, and a cut link is noticed within
seconds. Candidate gathering has its own fixed 5 s cap in aioice.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import queue
import secrets
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from typing import IO, Any

# -- the peer program ------------------------------------------------------------------


_STARTED = time.monotonic()


def _emit(event: str, **fields: Any) -> None:
    # "t": seconds since the program started, to read timings from a failure message.
    fields["t"] = round(time.monotonic() - _STARTED, 3)
    sys.stdout.write(json.dumps({"event": event, **fields}) + "\n")
    sys.stdout.flush()


def _selected_pair(pc: Any) -> dict[str, Any] | None:
    """Types and addresses of the nominated candidate pair (component 1), read from
    aioice's Connection behind aiortc's ICE transport (no public API for it)."""
    sctp = pc.sctp
    if sctp is None:
        return None
    connection = sctp.transport.transport._connection
    pair = connection._nominated.get(1)
    if pair is None:
        return None
    local, remote = pair.local_candidate, pair.remote_candidate
    return {
        "local": local.type,
        "remote": remote.type,
        "local_addr": [local.host, local.port],
        "remote_addr": list(pair.remote_addr),
    }


async def stdin_lines() -> asyncio.Queue[str | None]:
    """stdin lines in a queue (None at EOF), read by a thread: portable and simple."""
    loop = asyncio.get_running_loop()
    lines: asyncio.Queue[str | None] = asyncio.Queue()

    def reader() -> None:
        for line in sys.stdin:
            loop.call_soon_threadsafe(lines.put_nowait, line)
        loop.call_soon_threadsafe(lines.put_nowait, None)

    threading.Thread(target=reader, daemon=True).start()
    return lines


async def peer_main(args: argparse.Namespace) -> int:
    # Imported here so that the test process can import PeerProcess without aiortc.
    import aioice.ice
    import aioice.stun
    from aiortc import RTCConfiguration, RTCIceServer, RTCPeerConnection, RTCSessionDescription

    if args.stun_retries is not None:
        aioice.stun.RETRY_MAX = args.stun_retries
    if args.consent_interval is not None:
        aioice.ice.CONSENT_INTERVAL = args.consent_interval
    if args.consent_failures is not None:
        aioice.ice.CONSENT_FAILURES = args.consent_failures

    servers = [RTCIceServer(**server) for server in json.loads(args.ice_servers)]
    # Always an explicit list: aiortc's default is a public STUN server.
    pc = RTCPeerConnection(RTCConfiguration(iceServers=servers))
    channels: list[Any] = []
    pongs: dict[str, asyncio.Future[None]] = {}
    channel_open = asyncio.Event()

    def wire(channel: Any) -> None:
        channels.append(channel)

        @channel.on("open")
        def on_open() -> None:
            channel_open.set()

        @channel.on("message")
        def on_message(message: Any) -> None:
            if isinstance(message, str) and message.startswith("ping:"):
                channel.send("pong:" + message[5:])
            elif isinstance(message, str) and message.startswith("pong:"):
                waiter = pongs.get(message[5:])
                if waiter is not None and not waiter.done():
                    waiter.set_result(None)

        if channel.readyState == "open":
            channel_open.set()

    @pc.on("datachannel")
    def on_datachannel(channel: Any) -> None:
        wire(channel)

    @pc.on("connectionstatechange")
    def on_state() -> None:
        _emit("state", state=pc.connectionState)
        if pc.connectionState == "connected":
            pair = _selected_pair(pc)
            if pair is not None:
                _emit("selected", **pair)

    async def describe(kind: str) -> None:
        description = await (pc.createOffer() if kind == "offer" else pc.createAnswer())
        await pc.setLocalDescription(description)  # waits for gathering to end
        gatherer = pc.sctp.transport.transport.iceGatherer
        _emit("gathered", candidates=[c.type for c in gatherer.getLocalCandidates()])
        _emit(kind, sdp=pc.localDescription.sdp)

    async def echo(limit_s: float) -> None:
        token = secrets.token_hex(8)
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        pongs[token] = waiter
        started = time.monotonic()
        try:
            async with asyncio.timeout(limit_s):
                await channel_open.wait()
                channels[0].send("ping:" + token)
                await waiter
        except Exception as exc:  # a timeout, or a channel already closed: report it
            _emit("echo", ok=False, rtt_ms=None, error=type(exc).__name__)
        else:
            _emit("echo", ok=True, rtt_ms=round((time.monotonic() - started) * 1000, 1))
        finally:
            pongs.pop(token, None)

    if args.role == "offer":
        wire(pc.createDataChannel("echo"))
        await describe("offer")

    lines = await stdin_lines()
    tasks: set[asyncio.Task[None]] = set()
    try:
        while (line := await lines.get()) is not None:
            if not line.strip():
                continue
            command = json.loads(line)
            cmd = command.get("cmd")
            try:
                if cmd == "offer" and args.role == "answer":
                    await pc.setRemoteDescription(RTCSessionDescription(command["sdp"], "offer"))
                    await describe("answer")
                elif cmd == "answer" and args.role == "offer":
                    await pc.setRemoteDescription(RTCSessionDescription(command["sdp"], "answer"))
                elif cmd == "echo":
                    task = asyncio.create_task(echo(float(command.get("timeout", 5))))
                    tasks.add(task)
                    task.add_done_callback(tasks.discard)
                elif cmd == "close":
                    break
                else:
                    _emit("error", error=f"unknown command for {args.role}: {cmd}")
            except Exception as exc:
                _emit("error", error=f"{cmd}: {type(exc).__name__}: {exc}")
    finally:
        for task in tasks:
            task.cancel()
        await pc.close()
        _emit("state", state=pc.connectionState)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.netlab_peer", description=__doc__)
    parser.add_argument("--role", choices=["offer", "answer"], required=True)
    parser.add_argument("--ice-servers", default="[]", help="JSON list of RTCIceServer dicts")
    parser.add_argument("--stun-retries", type=int, help="aioice STUN retransmissions")
    parser.add_argument("--consent-interval", type=float, help="aioice consent check every S")
    parser.add_argument("--consent-failures", type=int, help="misses before consent expires")
    parser.add_argument("--verbose", action="store_true", help="aioice/aiortc debug on stderr")
    args = parser.parse_args(argv)
    if args.verbose:
        import logging

        logging.basicConfig(level=logging.DEBUG, stream=sys.stderr)
    return asyncio.run(peer_main(args))


# -- the test-side handle --------------------------------------------------------------


class PeerProcess:
    """Drives one peer program through its stdin/stdout (see the module docstring).

    ``proc`` is the started process (e.g. ``NetLab.popen(site, PeerProcess.argv(...),
    stdin=PIPE, stdout=PIPE, stderr=log)``); a thread reads its events into a queue
    that ``expect`` waits on, so every wait has a deadline and none is a sleep.
    """

    def __init__(self, proc: subprocess.Popen[str], name: str = "peer") -> None:
        self.proc = proc
        self.name = name
        self.events: list[dict[str, Any]] = []  # everything seen, for failure messages
        self._queue: queue.Queue[dict[str, Any] | None] = queue.Queue()
        assert proc.stdout is not None
        threading.Thread(target=self._read, args=(proc.stdout,), daemon=True).start()

    @staticmethod
    def argv(
        role: str,
        ice_servers: list[dict[str, Any]],
        *,
        stun_retries: int | None = None,
        consent_interval: float | None = None,
        consent_failures: int | None = None,
        verbose: bool = False,
    ) -> list[str]:
        """The command line of a peer (to run inside a namespace)."""
        argv = [sys.executable, "-m", "tests.netlab_peer", "--role", role]
        argv += ["--ice-servers", json.dumps(ice_servers)]
        if stun_retries is not None:
            argv += ["--stun-retries", str(stun_retries)]
        if consent_interval is not None:
            argv += ["--consent-interval", str(consent_interval)]
        if consent_failures is not None:
            argv += ["--consent-failures", str(consent_failures)]
        if verbose:
            argv.append("--verbose")
        return argv

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            with contextlib.suppress(ValueError):
                self._queue.put(json.loads(line))
        self._queue.put(None)

    def send(self, **command: Any) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(command) + "\n")
        self.proc.stdin.flush()

    def expect(self, event: str, timeout: float, **match: Any) -> dict[str, Any]:
        """The next event named ``event`` (whose fields equal ``match``), skipping
        others; AssertionError after ``timeout`` s or when the peer exits."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            try:
                item = self._queue.get(timeout=max(0.0, remaining))
            except queue.Empty:
                raise AssertionError(
                    f"{self.name}: no {event} {match or ''} within {timeout}s; saw {self.events}"
                ) from None
            if item is None:
                self._queue.put(None)  # keep reporting the exit
                raise AssertionError(
                    f"{self.name} exited ({self.proc.poll()}) before {event}; saw {self.events}"
                )
            self.events.append(item)
            if item.get("event") == event and all(item.get(k) == v for k, v in match.items()):
                return item

    def state(self, *states: str, timeout: float) -> str:
        """Wait until the connection state is one of ``states``; that state."""
        deadline = time.monotonic() + timeout
        while True:
            item = self.expect("state", max(0.0, deadline - time.monotonic()))
            if item["state"] in states:
                return str(item["state"])

    def echo(self, timeout: float = 5.0) -> dict[str, Any]:
        """Ask for a data-channel round trip; the ``echo`` event (``ok``, ``rtt_ms``)."""
        self.send(cmd="echo", timeout=timeout)
        return self.expect("echo", timeout + 5.0)

    def close(self, timeout: float = 10.0) -> int | None:
        """Ask the peer to close and wait for it to exit; its return code."""
        with contextlib.suppress(BrokenPipeError, OSError, ValueError):
            self.send(cmd="close")
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()


def connect_peers(
    offerer: PeerProcess, answerer: PeerProcess, *, timeout: float = 20.0
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Signal between two peers (offer -> answerer, answer -> offerer); returns the
    ``gathered`` events of offerer and answerer. Connection is then up to ICE."""
    offered_gathered = offerer.expect("gathered", timeout)
    offer = offerer.expect("offer", timeout)
    answerer.send(cmd="offer", sdp=offer["sdp"])
    answered_gathered = answerer.expect("gathered", timeout)
    answer = answerer.expect("answer", timeout)
    offerer.send(cmd="answer", sdp=answer["sdp"])
    return offered_gathered, answered_gathered


if __name__ == "__main__":
    sys.exit(main())
