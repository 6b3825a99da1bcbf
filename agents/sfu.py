"""The vehicle's one copy of its video to the platform's SFU (Janus's VideoRoom plugin),
for everyone but the pilot.

The pilot's picture comes straight from the vehicle (:mod:`agents.rtc`); spectators
watch through the SFU, which forwards the one stream to any number of them and records
it. The agent is behind NAT and never listens: it dials out to Janus's WebSocket API
(``janus-protocol``), joins the session's room as its only publisher with the token the
platform put in the signed vehicle task (:class:`~agents.protocol.documents.SfuPublish`),
and offers the camera from the shared encoder (:meth:`agents.video.service.VideoService.attach`):
one more packetiser, no second encode. When Janus goes away the publisher tries again
with backoff until the task ends; the pilot's connection is never touched.

:class:`JanusSession` is a small client of Janus's public API over a WebSocket (create,
attach, plugin requests, keepalives, events); the tests' spectators use it too.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import random
import secrets
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, Final

from aiortc import RTCConfiguration, RTCIceServer, RTCPeerConnection, RTCSessionDescription
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI

from agents.video.ice import ice_server, restrict_ice_host_addresses

if TYPE_CHECKING:
    from agents.protocol import SfuPublish

log = logging.getLogger(__name__)

VIDEOROOM: Final = "janus.plugin.videoroom"
#: Janus drops a session it has not heard from in ``session_timeout`` (60 s by default).
KEEPALIVE_S: Final = 20.0
#: How long one request may wait for Janus's answer.
REQUEST_TIMEOUT_S: Final = 15.0
#: Backoff between attempts to (re)publish: the first, and the longest.
RETRY_MIN_S: Final = 1.0
RETRY_MAX_S: Final = 15.0
#: A publish whose connection does not come up within this is started again.
CONNECT_TIMEOUT_S: Final = 30.0
#: Refusals, logged louder since trying again will not mend them: Janus's for a bad or
#: expired token, VideoRoom's for a wrong publish token or pin.
FORBIDDEN: Final = 403
UNAUTHORIZED: Final = 433


class JanusError(Exception):
    """Janus (or its plugin) refused a request; ``code`` is Janus's error code (433:
    unauthorized, 426: no such room, 428: no such feed), 0 when the link failed."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(f"Janus error {code}: {reason}")
        self.code = code
        self.reason = reason


class JanusHandle:
    """A handle attached to a plugin in a :class:`JanusSession`. ``events`` holds the
    plugin's and the core's messages that answer no request (``webrtcup``,
    ``hangup``, ``media``, a publisher leaving...) as Janus sent them."""

    def __init__(self, session: JanusSession, handle_id: int) -> None:
        self.session = session
        self.id = handle_id
        self.events: asyncio.Queue[dict[str, Any]] = asyncio.Queue()

    async def request(
        self, body: Mapping[str, Any], *, jsep: Mapping[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any] | None]:
        """Send a plugin request and wait for its answer, synchronous (``success``) or
        not (``ack`` then ``event``). Returns the plugin's data and the JSEP Janus sent
        with it, if any. Raises JanusError with the plugin's ``error_code`` when it
        refuses, and code 0 when the link closes or the answer takes too long."""
        message: dict[str, Any] = {"janus": "message", "handle_id": self.id, "body": dict(body)}
        if jsep is not None:
            message["jsep"] = dict(jsep)
        reply = await self.session.send(message)
        data = reply.get("plugindata", {}).get("data", {})
        if "error_code" in data or "error" in data:
            raise JanusError(int(data.get("error_code", 0)), str(data.get("error", "")))
        return data, reply.get("jsep")

    async def detach(self) -> None:
        """Hang up and detach (ignored when the link is gone)."""
        with contextlib.suppress(JanusError):
            await self.session.send({"janus": "detach", "handle_id": self.id})


class JanusSession:
    """One session on Janus's WebSocket API; use as ``async with JanusSession(url) as
    janus:``. ``token``: a Janus core token, when the server has ``token_auth`` on.
    ``closed`` is set once the link is gone (Janus stopped, the network broke, or the
    block was left)."""

    def __init__(self, url: str, *, token: str | None = None) -> None:
        self.url = url
        self.token = token
        self.id: int | None = None
        self.closed = asyncio.Event()
        self._ws: ClientConnection | None = None
        self._waiting: dict[str, asyncio.Future[dict[str, Any]]] = {}
        #: Transactions of keepalives in flight: Janus answers those with an ``ack``.
        self._keepalives: set[str] = set()
        #: Keepalives Janus acknowledged.
        self.keepalives = 0
        self._handles: dict[int, JanusHandle] = {}
        self._tasks: list[asyncio.Task[None]] = []

    async def __aenter__(self) -> JanusSession:
        try:
            async with asyncio.timeout(REQUEST_TIMEOUT_S):
                self._ws = await connect(
                    self.url,
                    subprotocols=["janus-protocol"],  # type: ignore[list-item]
                    max_size=1 << 20,
                )
        except (OSError, InvalidHandshake, InvalidURI, TimeoutError) as exc:
            raise JanusError(0, f"cannot reach the SFU at {self.url}: {exc}") from exc
        self._tasks.append(asyncio.create_task(self._read(), name="janus reader"))
        try:
            reply = await self.send({"janus": "create"})
        except BaseException:
            await self.close()
            raise
        self.id = int(reply["data"]["id"])
        self._tasks.append(asyncio.create_task(self._keepalive(), name="janus keepalive"))
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def attach(self, plugin: str = VIDEOROOM) -> JanusHandle:
        """A new handle on ``plugin``. Raises JanusError as :meth:`send`."""
        reply = await self.send({"janus": "attach", "plugin": plugin})
        handle = JanusHandle(self, int(reply["data"]["id"]))
        self._handles[handle.id] = handle
        return handle

    async def send(self, message: dict[str, Any]) -> dict[str, Any]:
        """Send a Janus API message (its transaction, session and token are added) and
        return the answer: ``success``, or the ``event`` after an ``ack``. Raises
        JanusError for an ``error`` answer, and with code 0 when the link is down or
        Janus takes longer than REQUEST_TIMEOUT_S."""
        if self._ws is None or self.closed.is_set():
            raise JanusError(0, "the SFU link is closed")
        transaction = secrets.token_hex(8)
        message = {**message, "transaction": transaction}
        if self.id is not None:
            message["session_id"] = self.id
        if self.token:
            message["token"] = self.token
        future: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._waiting[transaction] = future
        try:
            await self._ws.send(json.dumps(message))
            async with asyncio.timeout(REQUEST_TIMEOUT_S):
                reply = await future
        except (ConnectionClosed, TimeoutError) as exc:
            raise JanusError(0, f"no answer from the SFU ({type(exc).__name__})") from exc
        finally:
            self._waiting.pop(transaction, None)
        if reply.get("janus") == "error":
            error = reply.get("error", {})
            raise JanusError(int(error.get("code", 0)), str(error.get("reason", "")))
        return reply

    async def close(self) -> None:
        """Destroy the session and close the link. Idempotent."""
        if self._ws is not None and not self.closed.is_set() and self.id is not None:
            with contextlib.suppress(Exception):
                async with asyncio.timeout(2.0):
                    await self.send({"janus": "destroy"})
        self.closed.set()
        for task in self._tasks:
            task.cancel()
        if self._ws is not None:
            await self._ws.close()
        for future in self._waiting.values():
            if not future.done():
                future.set_exception(JanusError(0, "the SFU link closed"))

    async def _read(self) -> None:
        assert self._ws is not None
        try:
            async for raw in self._ws:
                try:
                    message = json.loads(raw)
                except ValueError:
                    continue
                kind = message.get("janus")
                transaction = message.get("transaction", "")
                if kind == "ack" and transaction not in self._keepalives:
                    continue  # an asynchronous request was taken; its event follows
                future = self._waiting.get(transaction)
                if future is not None and not future.done():
                    future.set_result(message)
                    continue
                handle = self._handles.get(int(message.get("sender", 0) or 0))
                if handle is not None:
                    handle.events.put_nowait(message)
        except ConnectionClosed:
            pass
        finally:
            self.closed.set()
            for future in self._waiting.values():
                if not future.done():
                    future.set_exception(JanusError(0, "the SFU link closed"))
            for handle in self._handles.values():
                handle.events.put_nowait({"janus": "closed"})

    async def _keepalive(self) -> None:
        assert self._ws is not None
        while not self.closed.is_set():
            await asyncio.sleep(KEEPALIVE_S)
            transaction = secrets.token_hex(8)
            future: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
            self._waiting[transaction] = future
            self._keepalives.add(transaction)  # answered by its ack alone
            message: dict[str, Any] = {
                "janus": "keepalive",
                "session_id": self.id,
                "transaction": transaction,
            }
            if self.token:
                message["token"] = self.token
            try:
                await self._ws.send(json.dumps(message))
                async with asyncio.timeout(REQUEST_TIMEOUT_S):
                    reply = await future
                if reply.get("janus") == "error":  # the token ran out, the session went
                    raise JanusError(int(reply.get("error", {}).get("code", 0)), "keepalive")
                self.keepalives += 1
            except (ConnectionClosed, TimeoutError, JanusError) as exc:
                log.info("the SFU refused or missed a keepalive (%s); closing the link", exc)
                await self._ws.close()
                return
            finally:
                self._waiting.pop(transaction, None)
                self._keepalives.discard(transaction)


class SfuPublisher:
    """Publishes the vehicle's camera to one VideoRoom room until stopped.

    * ``video``: the :class:`~agents.video.service.VideoService` (its shared encoder);
    * ``url``: Janus's WebSocket API; ``token``: a Janus core token (``token_auth``);
      ``room``, ``feed``: the room and the publisher id spectators subscribe to;
      ``publish_token``: the room's ``allowed`` token for its one publisher; ``pin``:
      the room's pin (see :class:`agents.protocol.SfuPublish`);
    * ``ice_servers``, ``ice_host_addresses``: as :class:`agents.rtc.RtcPeers`, except
      that None (aioice's choice: every address but loopback) is the default whatever
      the camera's ``ice_host_addresses`` say.

    :meth:`run` keeps publishing, again after every failure (Janus restarted, the room
    not created yet, the network broke) with backoff, until cancelled. ``state`` is
    ``connecting``, ``publishing`` (Janus said ``webrtcup``) or ``down``; ``pc`` is the
    current connection (for its statistics) or None.
    """

    def __init__(
        self,
        video: Any,
        *,
        url: str,
        room: int,
        feed: int,
        token: str,
        publish_token: str,
        pin: str,
        display: str = "",
        ice_servers: Sequence[RTCIceServer | Mapping[str, Any] | str] = (),
        ice_host_addresses: Sequence[str] | None = None,
    ) -> None:
        self.video = video
        self.url = url
        self.room = room
        self.feed = feed
        self.token = token
        self.publish_token = publish_token
        self.pin = pin
        self.display = display
        self.ice_servers = [ice_server(s) for s in ice_servers]
        # Not the camera's own restriction: Janus (libnice) never gathers loopback
        # addresses, so a loopback-only publisher could not reach it.
        self._ice_hosts = list(ice_host_addresses) if ice_host_addresses is not None else None
        self.state = "down"
        self.publishing = asyncio.Event()
        self.pc: RTCPeerConnection | None = None
        self.attempts = 0
        self.last_error = ""

    @classmethod
    def for_room(
        cls,
        video: Any,
        publish: SfuPublish,
        *,
        display: str = "",
        ice_servers: Sequence[RTCIceServer | Mapping[str, Any] | str] = (),
    ) -> SfuPublisher:
        """The publisher a task's ``sfu`` section (what the platform minted) asks for."""
        return cls(
            video,
            url=publish.url,
            room=publish.room,
            feed=publish.feed,
            token=publish.token,
            publish_token=publish.publish_token,
            pin=publish.pin,
            display=display,
            ice_servers=ice_servers,
        )

    async def run(self) -> None:
        """Publish until cancelled; never raises anything but CancelledError."""
        delay = RETRY_MIN_S
        while True:
            self.attempts += 1
            try:
                await self._publish_once()
                delay = RETRY_MIN_S  # it worked for a while: come back quickly
            except JanusError as exc:
                self.last_error = str(exc)
                level = logging.WARNING if exc.code in (FORBIDDEN, UNAUTHORIZED) else logging.INFO
                log.log(level, "publishing to the SFU: %s; again in %.0f s", exc, delay)
            except Exception as exc:  # aiortc and the network raise many kinds
                self.last_error = f"{type(exc).__name__}: {exc}"
                log.warning("publishing to the SFU failed: %s", self.last_error, exc_info=True)
            self.state = "down"
            self.publishing.clear()
            await asyncio.sleep(delay * (0.5 + random.random() / 2))
            delay = min(RETRY_MAX_S, delay * 2)

    async def _publish_once(self) -> None:
        self.state = "connecting"
        async with JanusSession(self.url, token=self.token) as janus:
            handle = await janus.attach(VIDEOROOM)
            await handle.request(
                {
                    "request": "join",
                    "ptype": "publisher",
                    "room": self.room,
                    "id": self.feed,
                    "token": self.publish_token,
                    "pin": self.pin,
                    "display": self.display or "vehicle",
                }
            )
            pc = RTCPeerConnection(RTCConfiguration(iceServers=self.ice_servers))
            track = self.video.attach(pc, role="sfu")
            self.pc = pc
            gone = asyncio.Event()

            @pc.on("connectionstatechange")
            def on_state() -> None:
                if pc.connectionState in ("failed", "closed"):
                    gone.set()

            try:
                with restrict_ice_host_addresses(self._ice_hosts):
                    await pc.setLocalDescription(await pc.createOffer())
                _, jsep = await handle.request(
                    {"request": "publish", "audio": False, "data": False},
                    jsep={"type": "offer", "sdp": pc.localDescription.sdp},
                )
                if not jsep or jsep.get("type") != "answer":
                    raise JanusError(0, "the SFU answered the publish without SDP")
                await pc.setRemoteDescription(RTCSessionDescription(jsep["sdp"], "answer"))
                await self._until_gone(janus, handle, pc, gone)
            finally:
                self.pc = None
                track.stop()
                await pc.close()

    async def _until_gone(
        self, janus: JanusSession, handle: JanusHandle, pc: RTCPeerConnection, gone: asyncio.Event
    ) -> None:
        """Serve the published connection until Janus or the connection goes away."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + CONNECT_TIMEOUT_S
        waiters = {
            asyncio.create_task(janus.closed.wait()),
            asyncio.create_task(gone.wait()),
        }
        try:
            while True:
                event_task = asyncio.create_task(handle.events.get())
                timeout = None if self.state == "publishing" else max(0.0, deadline - loop.time())
                done, _ = await asyncio.wait(
                    {*waiters, event_task}, timeout=timeout, return_when=asyncio.FIRST_COMPLETED
                )
                if event_task not in done:
                    event_task.cancel()
                if not done:
                    raise JanusError(
                        0, f"the SFU connection did not come up in {CONNECT_TIMEOUT_S:g} s"
                    )
                if done & waiters:
                    raise JanusError(0, "the SFU link or its connection closed")
                event = event_task.result()
                kind = event.get("janus")
                if kind == "webrtcup":
                    self.state = "publishing"
                    self.publishing.set()
                    log.info("publishing to SFU room %s as feed %s", self.room, self.feed)
                elif kind in ("hangup", "detached", "closed"):
                    raise JanusError(0, f"the SFU hung up ({event.get('reason', kind)})")
        finally:
            for waiter in waiters:
                waiter.cancel()
