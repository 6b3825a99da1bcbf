"""A program's side of the WebRTC control path, as the browser's controller does it.

It opens the platform's relay socket for a session (``relay_url`` of the user task),
authenticates with the grant, signals one RTCPeerConnection through it
(``webrtc_offer``/``webrtc_answer``, no trickle) with the data channels of
docs/protocol.md (``control``, ``input``, ``urgent``), and then speaks the control
protocol on them. Tests and benchmarks use it where a browser is not needed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Self

from aiortc import (
    RTCConfiguration,
    RTCDataChannel,
    RTCPeerConnection,
    RTCSessionDescription,
)
from aiortc.rtcconfiguration import RTCIceTransportPolicy
from websockets.asyncio.client import ClientConnection, connect

from agents.video.ice import ice_server, restrict_ice_host_addresses

#: ``listener(message, arrived_at, via)``: ``arrived_at`` is ``time.perf_counter()`` taken
#: before the message was parsed, ``via`` is ``"socket"`` or ``"control"`` (the data
#: channel); returning True consumes the message (it is not queued for :meth:`recv`).
Listener = Callable[[dict[str, Any], float, str], bool]


class RtcClientError(Exception):
    """The connection could not be made; ``str(exc)`` says which step failed."""


class RtcControlClient:
    """One user over WebRTC: ``async with RtcControlClient(...) as user:``.

    * ``relay_url``, ``grant``, ``ice_servers``: from the user task.
    * ``ice_host_addresses``: restrict this side's host candidates (loopback tests).
    * ``ice_transport_policy``: ``"relay"`` offers only TURN relay candidates (as a
      browser's ``iceTransportPolicy: "relay"``), so the connection must go through TURN.
    * ``video``: also ask for the camera (a recvonly video section).
    * ``listener``: sees every message first, with its arrival time (see ``Listener``).

    Every message the vehicle sends, on the socket or a data channel, lands in one
    queue read with :meth:`recv` (unless the listener consumed it); ``paths`` lists the
    ``path`` events in order. ``steps`` holds ``time.perf_counter()`` stamps of
    :meth:`start`'s steps: ``start``, ``socket_open``, ``welcome``, ``offer_sent``
    (candidates gathered), ``answer`` and ``channels_open``.
    """

    def __init__(
        self,
        relay_url: str,
        grant: str,
        *,
        ice_servers: Sequence[Mapping[str, Any]] = (),
        ice_host_addresses: Sequence[str] | None = None,
        ice_transport_policy: str = "all",
        video: bool = False,
        timeout_s: float = 15.0,
        listener: Listener | None = None,
    ) -> None:
        self.relay_url = relay_url
        self.grant = grant
        self.ice_servers = [ice_server(s) for s in ice_servers]
        self.ice_host_addresses = ice_host_addresses
        self.ice_transport_policy = RTCIceTransportPolicy(ice_transport_policy)
        self.video = video
        self.listener = listener
        self.steps: dict[str, float] = {}
        self.timeout_s = timeout_s
        self.ws: ClientConnection | None = None
        self.pc: RTCPeerConnection | None = None
        self.channels: dict[str, RTCDataChannel] = {}
        self.inbox: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
        self.paths: list[str] = []
        self.welcome: dict[str, Any] = {}
        self.connect_s: float | None = None  # from start to the data channel open
        self._reader: asyncio.Task[None] | None = None
        self._path_seen = asyncio.Event()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def start(self, *, rtc: bool = True) -> None:
        """Authenticate on the relay socket and, with ``rtc``, bring the WebRTC
        connection up (its ``control`` channel open). Raises RtcClientError."""
        started = self.steps["start"] = time.perf_counter()
        self.ws = await connect(self.relay_url, proxy=None, compression=None, open_timeout=10)
        self.steps["socket_open"] = time.perf_counter()
        self._reader = asyncio.create_task(self._read_socket(self.ws))
        await self.ws.send(json.dumps({"type": "auth", "grant": self.grant}))
        self.welcome = await self.recv("welcome")
        self.steps["welcome"] = time.perf_counter()
        if rtc:
            await self.negotiate()
            self.connect_s = time.perf_counter() - started

    async def negotiate(self) -> None:
        """Offer a connection on the socket and wait for its data channels to open."""
        assert self.ws is not None
        pc = RTCPeerConnection(
            RTCConfiguration(
                iceServers=list(self.ice_servers), iceTransportPolicy=self.ice_transport_policy
            )
        )
        self.pc = pc
        opened = asyncio.Event()
        control = pc.createDataChannel("control")
        self.channels = {
            "control": control,
            "input": pc.createDataChannel("input", ordered=False, maxRetransmits=0),
            "urgent": pc.createDataChannel("urgent", ordered=False),
        }

        def on_open() -> None:
            if all(ch.readyState == "open" for ch in self.channels.values()):
                opened.set()

        for channel in self.channels.values():
            channel.on("open", on_open)

        @control.on("message")
        def on_message(data: str | bytes) -> None:
            at = time.perf_counter()
            with contextlib.suppress(ValueError):
                self._arrived(json.loads(data), at=at, via="control")

        if self.video:
            pc.addTransceiver("video", direction="recvonly")
        with restrict_ice_host_addresses(self.ice_host_addresses):
            await pc.setLocalDescription(await pc.createOffer())
        await self.ws.send(json.dumps({"type": "webrtc_offer", "sdp": pc.localDescription.sdp}))
        self.steps["offer_sent"] = time.perf_counter()
        answer = await self.recv("webrtc_answer", "error")
        self.steps["answer"] = time.perf_counter()
        if answer["type"] == "error":
            raise RtcClientError(f"the vehicle refused the offer: {answer['message']}")
        await pc.setRemoteDescription(RTCSessionDescription(sdp=answer["sdp"], type="answer"))
        try:
            async with asyncio.timeout(self.timeout_s):
                await opened.wait()
        except TimeoutError:
            raise RtcClientError(f"no data channel within {self.timeout_s} s") from None
        self.steps["channels_open"] = time.perf_counter()

    @property
    def path(self) -> str | None:
        """The path the vehicle last said it uses for this user."""
        return self.paths[-1] if self.paths else None

    @property
    def ice_path(self) -> str | None:
        """This side's view of the connection: ``webrtc_turn`` when the candidate pair
        ICE nominated relays through TURN on either side, ``webrtc_direct`` otherwise,
        None before ICE chose one (the agent's own rule, :func:`agents.rtc._path_of`)."""
        from agents.rtc import _path_of

        return _path_of(self.pc) if self.pc is not None else None

    async def path_is(self, *paths: str) -> str:
        """Wait until the vehicle says one of ``paths``; returns it."""
        deadline = time.monotonic() + self.timeout_s
        while self.path not in paths:
            self._path_seen.clear()
            left = deadline - time.monotonic()
            if left <= 0:
                raise RtcClientError(f"path is {self.path}, not one of {paths}")
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(left):
                    await self._path_seen.wait()
        assert self.path is not None
        return self.path

    def send(self, message: Mapping[str, Any], *, channel: str | None = "control") -> None:
        """Send on a data channel (``control``, ``input``, ``urgent``), or with
        ``channel=None`` on the socket. Raises RtcClientError when it is not open."""
        text = json.dumps(dict(message))
        if channel is None:
            if self.ws is None:
                raise RtcClientError("the socket is closed")
            task = asyncio.ensure_future(self.ws.send(text))
            task.add_done_callback(lambda t: t.exception())
            return
        ch = self.channels.get(channel)
        if ch is None or ch.readyState != "open":
            raise RtcClientError(f"data channel {channel} is not open")
        ch.send(text)

    async def command(
        self, seq: int, name: str, *, channel: str | None = "control", **args: Any
    ) -> dict[str, Any]:
        """Send one command and return its ack."""
        msg = {"type": "command", "seq": seq, "name": name, "args": args, "t": time.time() * 1000}
        self.send(msg, channel=channel)
        return await self.recv("ack", where=lambda m: m.get("seq") == seq)

    async def recv(self, *types: str, where: Any = None) -> dict[str, Any]:
        """The next message of one of ``types`` (others are skipped), within the
        timeout. Raises RtcClientError on timeout."""
        deadline = time.monotonic() + self.timeout_s
        while True:
            left = deadline - time.monotonic()
            try:
                # asyncio.timeout: 3.11's wait_for can swallow a cancel (see tests.control).
                async with asyncio.timeout(max(0.0, left)):
                    msg = await self.inbox.get()
            except TimeoutError:
                raise RtcClientError(f"no {'/'.join(types)} within {self.timeout_s} s") from None
            if msg.get("type") in types and (where is None or where(msg)):
                return msg

    async def close_socket(self) -> None:
        """Close the relay socket only (the platform's path), keeping WebRTC."""
        if self.ws is not None:
            await self.ws.close()

    async def close(self) -> None:
        if self.pc is not None:
            await self.pc.close()
        if self.ws is not None:
            await self.ws.close()
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._reader

    def _arrived(self, msg: Any, *, at: float, via: str) -> None:
        if not isinstance(msg, dict):
            return
        if msg.get("type") == "event" and msg.get("event") == "path":
            self.paths.append(str(msg.get("data", {}).get("path")))
            self._path_seen.set()
        elif msg.get("type") == "ping":
            # Answered at once, with this side's clock: the vehicle aligns the clocks.
            with contextlib.suppress(RtcClientError):
                self.send(
                    {"type": "pong", "t": msg["t"], "client_t": time.time() * 1000},
                    channel="control" if self.channels else None,
                )
        if self.listener is not None and self.listener(msg, at, via):
            return
        self.inbox.put_nowait(msg)

    async def _read_socket(self, ws: ClientConnection) -> None:
        with contextlib.suppress(Exception):
            async for raw in ws:
                at = time.perf_counter()
                with contextlib.suppress(ValueError):
                    self._arrived(json.loads(raw), at=at, via="socket")
