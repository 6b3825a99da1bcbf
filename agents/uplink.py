"""The agent's link to the platform: register, heartbeat, receive tasks, report.

The uplink is not in the control path: when the platform is unreachable the vehicle
keeps serving the user already connected to it (and its fail-safes keep working), and
reports queue up in a bounded outbox to be sent after reconnecting. Reconnection
uses exponential backoff with full jitter so a fleet does not reconnect in lockstep
after a platform restart.

The platform sends the messages that change what the vehicle does (``task``,
``revoke``, ``end_task``) with an ``id``, again and again until they are acknowledged.
The uplink answers ``ack`` with that id once the message has been handled, and hands a
message it has already handled (a resend after a reconnect) to nobody: it only
acknowledges it again.

A platform machine that drops off the network closes nothing: the agent's TCP
connection to nginx stays up while nginx's to the dead machine hears nothing. Only the
agent's own WebSocket pings notice (websockets' public keepalive options): a ping every
``ping_interval_s``, the uplink failed when its pong has not come ``ping_timeout_s``
later, and closed for good :data:`CLOSE_TIMEOUT_S` after that (nobody answers the close
frame either). A blackholed uplink is therefore given up at most ``ping_interval_s +
ping_timeout_s + CLOSE_TIMEOUT_S`` after the cut (6 s by default), and the agent
reconnects, through nginx, to a platform process that is there
(tests/integration/test_two_machines.py). The price is ``1 / ping_interval_s`` pings per
agent per second, each answered by the platform's WebSocket server without reaching
Django (a heartbeat costs far more).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
from collections import OrderedDict, deque
from collections.abc import Awaitable, Callable, Mapping
from typing import Any

import msgspec
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI

from agents.protocol import (
    MAX_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    ProtocolError,
    encode_message,
    parse_message,
)
from agents.protocol.messages import (
    Ack,
    Error,
    Heartbeat,
    Hello,
    Message,
    Profile,
    Welcome,
    message_type,
)

log = logging.getLogger(__name__)

WELCOME_TIMEOUT_S = 10.0
#: Keepalive defaults (see the module docstring): a blackholed uplink is given up within
#: PING_INTERVAL_S + PING_TIMEOUT_S + CLOSE_TIMEOUT_S = 6 s.
PING_INTERVAL_S = 2.0
PING_TIMEOUT_S = 3.0
#: How long a closing uplink waits for the platform's side of the close before dropping
#: the connection. A live platform answers in a round trip; a machine cut off never does,
#: and websockets' default (10 s) would be most of the reconnect time.
CLOSE_TIMEOUT_S = 1.0
OUTBOX_SIZE = 1000
#: Ids of handled platform messages remembered, to recognise resends.
HANDLED_IDS = 4096


class PlatformBusy(Exception):
    """The platform turned the hello away for now (``error`` ``busy``); retry later."""


def backoff_delay(attempt: int, *, base: float, cap: float) -> float:
    """Seconds to wait before reconnect ``attempt`` (0-based): full jitter over an
    exponentially growing window, never above ``cap``."""
    return random.uniform(base / 2, min(cap, base * 2**attempt))


class Uplink:
    """Keeps one authenticated WebSocket to the platform, reconnecting forever.

    ``on_message`` gets every validated platform message except ``welcome``, which goes
    to ``on_welcome`` (if given) before the profile is sent; ``profile()`` and
    ``heartbeat()`` build the messages sent on connect and at the interval the platform
    asks for. ``ping_interval_s`` and ``ping_timeout_s`` bound how long a silent
    uplink is kept (see the module docstring). ``connect_options`` are passed on to
    websockets' ``connect`` and from there to the event loop's ``create_connection``:
    e.g. ``local_addr`` to leave from one interface's address (a vehicle with two
    links), ``ssl`` for a platform whose certificate a private CA signs.
    """

    def __init__(
        self,
        *,
        url: str,
        vehicle_id: str,
        credential: str,
        on_message: Callable[[Any], Awaitable[None]],
        profile: Callable[[], Profile],
        heartbeat: Callable[[], Heartbeat],
        reconnect_min_s: float = 0.5,
        reconnect_max_s: float = 30.0,
        on_welcome: Callable[[Any], None] | None = None,
        ping_interval_s: float = PING_INTERVAL_S,
        ping_timeout_s: float = PING_TIMEOUT_S,
        connect_options: Mapping[str, Any] | None = None,
    ) -> None:
        self.url = url
        self.connect_options = dict(connect_options or {})
        self.ping_interval_s = ping_interval_s
        self.ping_timeout_s = ping_timeout_s
        self.on_welcome = on_welcome
        self.vehicle_id = vehicle_id
        self.credential = credential
        self.on_message = on_message
        self.profile = profile
        self.heartbeat = heartbeat
        self.reconnect_min_s = reconnect_min_s
        self.reconnect_max_s = reconnect_max_s
        self.heartbeat_interval_s = 2.0
        self.connected = asyncio.Event()
        self.connections = 0  # successful registrations, for tests and status
        self._outbox: deque[str] = deque(maxlen=OUTBOX_SIZE)
        self._handled: OrderedDict[str, None] = OrderedDict()
        self._wake = asyncio.Event()
        self._hb_seq = 0

    def send(self, message: Message) -> None:
        """Queue a message for the platform (dropped oldest-first when the outbox is
        full during a long outage)."""
        self._outbox.append(encode_message(message))
        self._wake.set()

    async def run(self) -> None:
        """Connect, serve, and reconnect until cancelled."""
        attempt = 0
        while True:
            try:
                async with connect(
                    self.url,
                    max_size=MAX_MESSAGE_BYTES,
                    compression=None,
                    proxy=None,
                    open_timeout=10,
                    ping_interval=self.ping_interval_s,
                    ping_timeout=self.ping_timeout_s,
                    close_timeout=CLOSE_TIMEOUT_S,
                    **self.connect_options,
                ) as ws:
                    await self._register(ws)
                    attempt = 0
                    await self._serve(ws)
            except asyncio.CancelledError:
                raise
            except (OSError, ConnectionClosed, InvalidHandshake, InvalidURI, TimeoutError) as exc:
                log.warning("uplink to %s lost: %s", self.url, exc)
            except PlatformBusy as exc:
                log.info("uplink to %s turned away: %s", self.url, exc)
            except ProtocolError as exc:
                log.error("platform sent something invalid: %s", exc)
            finally:
                self.connected.clear()
            delay = backoff_delay(attempt, base=self.reconnect_min_s, cap=self.reconnect_max_s)
            attempt += 1
            await asyncio.sleep(delay)

    async def _register(self, ws: ClientConnection) -> None:
        await ws.send(
            encode_message(
                Hello(v=PROTOCOL_VERSION, vehicle_id=self.vehicle_id, credential=self.credential)
            )
        )
        async with asyncio.timeout(WELCOME_TIMEOUT_S):
            raw = await ws.recv()
        msg = parse_message(raw, channel="uplink_to_agent")
        if isinstance(msg, Error) and msg.code == "busy":
            # Thousands of agents connecting at once: come back after the backoff, which
            # keeps growing while the platform turns us away.
            raise PlatformBusy(msg.message)
        if not isinstance(msg, Welcome):
            # The platform refused us (bad credential, version): wait and retry.
            raise ProtocolError("refused", f"platform answered {message_type(msg)}: {msg}")
        self.heartbeat_interval_s = msg.heartbeat_interval_s
        if self.on_welcome is not None:
            # Before the profile: a task may follow at once and need the welcome's keys.
            self.on_welcome(msg)
        await ws.send(encode_message(self.profile()))
        self.connections += 1
        self.connected.set()
        log.info("registered with %s", self.url)

    async def _serve(self, ws: ClientConnection) -> None:
        tasks = [
            asyncio.create_task(self._receive(ws)),
            asyncio.create_task(self._heartbeats(ws)),
            asyncio.create_task(self._flush(ws)),
        ]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                task.result()  # re-raise what ended the connection
        finally:
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task

    async def _receive(self, ws: ClientConnection) -> None:
        async for raw in ws:
            try:
                msg = parse_message(raw, channel="uplink_to_agent")
            except ProtocolError as exc:
                log.warning("ignored a bad message from the platform: %s", exc)
                continue
            await self._handle(msg)

    async def _handle(self, msg: Message) -> None:
        """Hand ``msg`` to ``on_message`` (once per id) and acknowledge it if it has one."""
        if isinstance(msg, Ack):
            # The platform acknowledging what the agent sent (a flight-record batch):
            # an answer, never itself acknowledged.
            await self.on_message(msg)
            return
        mid = getattr(msg, "id", None)  # task, revoke, end_task; UNSET when absent
        if isinstance(mid, str) and mid in self._handled:
            self._handled.move_to_end(mid)
            self.send(Ack(id=mid, ok=True, detail="already handled"))
            return
        ok, detail = True, ""
        try:
            await self.on_message(msg)
        except Exception as exc:
            # A bug handling one message must not take the vehicle off the platform;
            # the platform hears that it failed instead of sending it for ever.
            log.exception("handling platform message %s failed", message_type(msg))
            ok, detail = False, f"{type(exc).__name__}: {exc}"[:200]
        if isinstance(mid, str):
            self._handled[mid] = None
            while len(self._handled) > HANDLED_IDS:
                self._handled.popitem(last=False)
            # Queued behind what handling it queued (task_accepted...), so the platform
            # hears the outcome before the acknowledgement.
            self.send(Ack(id=mid, ok=ok, detail=detail))

    async def _heartbeats(self, ws: ClientConnection) -> None:
        while True:
            self._hb_seq += 1
            beat = msgspec.structs.replace(self.heartbeat(), seq=self._hb_seq)
            await ws.send(encode_message(beat))
            await asyncio.sleep(self.heartbeat_interval_s)

    async def _flush(self, ws: ClientConnection) -> None:
        while True:
            while self._outbox:
                # Peek, send, then pop: a message is lost only if the send never happened.
                await ws.send(self._outbox[0])
                self._outbox.popleft()
            self._wake.clear()
            await self._wake.wait()
