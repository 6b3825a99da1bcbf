"""WebSocket consumers of the services app: live session feeds."""

from __future__ import annotations

import asyncio
import functools
import json
import secrets
import time
import uuid
from typing import Any

import msgspec
from asgiref.sync import sync_to_async
from channels.db import database_sync_to_async
from channels.generic.websocket import AsyncJsonWebsocketConsumer, AsyncWebsocketConsumer

from accounts.addresses import client_address_of_scope
from agents.protocol import (
    ProtocolError,
    UserGrant,
    encode_message,
    error_message,
    parse_message,
)
from agents.protocol.messages import (
    Auth,
    Command,
    ControlToAgent,
    IceServer,
    RelayClose,
    RelayToAgent,
    WebrtcOffer,
)
from fleet.memberships import group_hold, group_release
from fleet.sending import avehicle_send, relay_group
from operations.consumers import DirectDispatch
from operations.layer import relay_ensure
from operations.outages import DATABASE_UNAVAILABLE
from services.sessions.feed import SESSIONS_GROUP, session_group
from services.sessions.ice import ice_servers_for
from services.supervision.metrics import RELAY_ACKS, RELAY_ROUND_TRIP
from services.web.throttle import Throttled, counted_address, throttle_check

#: The relay's own budget per browser, on top of the agent's: it protects the platform.
RELAY_RATE_PER_S = 200.0
RELAY_BURST = 400.0
CLOSED_BY_AGENT = 4000
#: A relayed connection whose vehicle has not answered its authentication in this long
#: is closed with CLOSE_TRY_LATER: the page connects again with a fresh grant.
RELAY_ANSWER_S = 3.0
#: The relay's close codes for a refused first frame: not admitted, or the platform
#: could not check the grant now (its database is away: come back later).
CLOSE_UNAUTHORIZED = 4401
CLOSE_TRY_LATER = 4503


class SessionFeedConsumer(DirectDispatch, AsyncJsonWebsocketConsumer):
    """One session's log as it grows, for its user and for monitors.

    Sends ``{"type": "session", "session": {...}}`` on connect, then
    ``{"type": "event", "event": {seq, kind, data, at}, "session": {...}}`` per logged
    event. Others are refused (4403); an unknown session too (no existence leak).
    """

    async def connect(self) -> None:
        relay_ensure()
        self.session_id = self.scope["url_route"]["kwargs"]["session_id"]
        summary = await _session_for(self.scope.get("user"), self.session_id)
        if summary is None:
            await self.close(code=4403)
            return
        await group_hold(session_group(self.session_id), self.channel_name)
        await self.accept()
        await self.send_json({"type": "session", "session": summary})

    async def disconnect(self, code: int) -> None:
        if hasattr(self, "session_id"):
            await group_release(session_group(self.session_id), self.channel_name)

    async def receive_json(self, content: Any, **kwargs: Any) -> None:
        await self.send_json({"type": "error", "code": "read_only", "message": "feed is read-only"})

    async def session_event(self, message: dict[str, Any]) -> None:
        summary = await _session_for(self.scope.get("user"), self.session_id)
        await self.send_json({"type": "event", "event": message["event"], "session": summary})

    async def session_events(self, message: dict[str, Any]) -> None:
        # Several events of one transaction: the page sees them one by one, as ever.
        summary = await _session_for(self.scope.get("user"), self.session_id)
        for event in message["events"]:
            await self.send_json({"type": "event", "event": event, "session": summary})


class SessionsMonitorConsumer(DirectDispatch, AsyncJsonWebsocketConsumer):
    """Every live session for monitors: a snapshot, then each logged event.

    Requires ``services.view_session``; others are refused (4403).
    """

    async def connect(self) -> None:
        relay_ensure()
        user = self.scope.get("user")
        if user is None or not await database_sync_to_async(user.has_perm)("services.view_session"):
            await self.close(code=4403)
            return
        await group_hold(SESSIONS_GROUP, self.channel_name)
        await self.accept()
        await self.send_json({"type": "sessions", "sessions": await _live_sessions()})

    async def disconnect(self, code: int) -> None:
        await group_release(SESSIONS_GROUP, self.channel_name)

    async def receive_json(self, content: Any, **kwargs: Any) -> None:
        await self.send_json({"type": "error", "code": "read_only", "message": "feed is read-only"})

    async def session_event(self, message: dict[str, Any]) -> None:
        summary = await _session_for(None, message["session_id"], monitor=True)
        await self.send_json({"type": "event", "event": message["event"], "session": summary})

    async def session_events(self, message: dict[str, Any]) -> None:
        # One read of the session for the whole batch (they were committed together).
        summary = await _session_for(None, message["session_id"], monitor=True)
        for event in message["events"]:
            await self.send_json({"type": "event", "event": event, "session": summary})


@database_sync_to_async
def _session_for(user: Any, session_id: str, *, monitor: bool = False) -> dict[str, Any] | None:
    from services.models import Session
    from services.sessions.selectors import session_summary

    try:
        pk = uuid.UUID(str(session_id))
    except ValueError:
        return None
    session = Session.objects.select_related("service", "user").filter(pk=pk).first()
    if session is None:
        return None
    if not monitor and not (
        user is not None
        and user.is_authenticated
        and (session.user_id == user.pk or user.has_perm("services.view_session"))
    ):
        return None
    return session_summary(session)


@database_sync_to_async
def _live_sessions() -> list[dict[str, Any]]:
    from services.models import Session
    from services.sessions.selectors import session_summary
    from services.sessions.states import FINAL

    live = Session.objects.exclude(state__in=FINAL).select_related("service", "user")
    return [session_summary(s) for s in live.order_by("-created_at")[:200]]


class RelayConsumer(DirectDispatch, AsyncWebsocketConsumer):
    """Control through the platform, for clients that cannot reach the vehicle.

    The client speaks the same control protocol as on a direct socket. Its first frame
    must be ``auth`` with a grant the platform signed for this session's vehicle: the
    relay checks it (signature, expiry, session, vehicle) before forwarding anything,
    so no login cookie is involved and any client holding a user task may use it
    (browsers and API programs alike). Each frame is validated, wrapped in a ``relay``
    message and sent to the vehicle's uplink over the channel layer; the agent's
    answers come back through this connection's group. The agent checks the grant
    again (and refuses a replay), so the relay adds transport, not trust.

    It is also the WebRTC signalling path: a ``webrtc_offer`` is forwarded with the
    platform's STUN/TURN servers for the agent (``ice_servers``, TURN credentials minted
    for this session, expiring with the grant the connection authenticated with), and
    the agent's ``webrtc_answer`` comes back like any answer. Offers count against the
    user's and the address's budgets (services.web.throttle); one over them is answered
    ``rate_limited`` and not forwarded.

    A refused first frame closes the socket (4401, or 4503 when the grant could not be
    checked now); frames the client had already sent after it are dropped unanswered.
    """

    async def connect(self) -> None:
        relay_ensure()
        self.session_id = str(self.scope["url_route"]["kwargs"]["session_id"])
        self.vehicle_id: str | None = None
        self.conn = secrets.token_hex(8)
        # The vehicle's uplink channel, once it has answered: commands go straight
        # there, not through the vehicle's group (see fleet.sending.avehicle_send).
        self.uplink: str | None = None
        self.tokens, self.refill_at = RELAY_BURST, time.monotonic()
        #: Set once the relay closed the socket: later frames are dropped, not answered.
        self.closing = False
        #: The admitted grant's user and end (Unix seconds), and the client's address.
        self.user_id: str | None = None
        self.grant_expires_at: float | None = None
        self.address = counted_address(client_address_of_scope(self.scope))
        #: Relayed commands awaiting the vehicle's ack: seq -> when they came (monotonic),
        #: for the relay's round trip (services.supervision.metrics).
        self.commands_out: dict[int, float] = {}
        #: Closes the socket when the vehicle never answers its authentication.
        self.answer_watch: asyncio.Task[None] | None = None
        self.answered = False
        await self.accept()

    async def disconnect(self, code: int) -> None:
        if self.answer_watch is not None:
            self.answer_watch.cancel()
        if self.vehicle_id is None:
            return
        await group_release(relay_group(self.conn), self.channel_name)
        if code != CLOSED_BY_AGENT:
            await avehicle_send(
                vehicle_id=self.vehicle_id,
                message=RelayClose(
                    session_id=self.session_id, conn=self.conn, reason="client left"
                ),
                via=self.uplink,
            )

    async def receive(self, text_data: str | None = None, bytes_data: bytes | None = None) -> None:
        if self.closing:
            return  # sent before the client saw the close: there is no one to answer
        raw = text_data if text_data is not None else bytes_data or b""
        now = time.monotonic()
        self.tokens = min(RELAY_BURST, self.tokens + (now - self.refill_at) * RELAY_RATE_PER_S)
        self.refill_at = now
        if self.tokens < 1:
            await self._error("rate_limited", "slow down")
            return
        self.tokens -= 1
        try:
            payload: ControlToAgent = parse_message(raw, channel="control_to_agent")
        except ProtocolError as exc:
            if self.vehicle_id is None:
                await self._refuse(exc.code, exc.message, CLOSE_UNAUTHORIZED)
            else:
                await self._error(exc.code, exc.message)
            return
        if self.vehicle_id is None:
            refusal = await self._admit(payload)
            if refusal is not None:
                await self._refuse(*refusal)
                return
            self.answer_watch = asyncio.create_task(self._expect_answer())
        assert self.vehicle_id is not None
        if isinstance(payload, Command):
            if len(self.commands_out) >= COMMANDS_TIMED_MAX:
                self.commands_out.pop(next(iter(self.commands_out)))  # never acknowledged
            self.commands_out[payload.seq] = now
        message = RelayToAgent(session_id=self.session_id, conn=self.conn, payload=payload)
        if isinstance(payload, WebrtcOffer):
            try:
                await _offer_count(user_id=self.user_id, address=self.address)
            except Throttled as exc:
                await self._error("rate_limited", str(exc))
                return
            # The agent's STUN/TURN for this connection, with TURN credentials of its own
            # that end with the grant this connection was admitted with.
            servers = ice_servers_for(self.session_id, expires_at=self.grant_expires_at)
            message = msgspec.structs.replace(
                message, ice_servers=msgspec.convert(servers, list[IceServer])
            )
        await avehicle_send(
            vehicle_id=self.vehicle_id,
            message=message,
            via=self.uplink,
            reply_to=self.channel_name,
        )

    async def _admit(self, payload: ControlToAgent) -> tuple[str, str, int] | None:
        """Check the first frame's grant; on success join this connection's group.
        Returns (code, message, close code) when refused."""
        if not isinstance(payload, Auth):
            return ("unauthorized", "authenticate first", CLOSE_UNAUTHORIZED)
        try:
            vehicle_id = await _session_vehicle(self.session_id)
            keys = await _platform_keys()
        except DATABASE_UNAVAILABLE:
            return (
                "unavailable",
                "the platform cannot check grants right now; connect again shortly",
                CLOSE_TRY_LATER,
            )
        if vehicle_id is None:
            return ("no_session", "this session is over or has no vehicle", CLOSE_UNAUTHORIZED)
        try:
            grant = UserGrant.verify(payload.grant, keys, vehicle_id=vehicle_id)
        except ProtocolError as exc:
            return (exc.code, exc.message, CLOSE_UNAUTHORIZED)
        if grant.session_id != self.session_id:
            return ("wrong_session", "this grant is for another session", CLOSE_UNAUTHORIZED)
        self.vehicle_id = vehicle_id
        self.user_id = grant.user
        self.grant_expires_at = grant.expires_at
        await group_hold(relay_group(self.conn), self.channel_name)
        return None

    async def _expect_answer(self) -> None:
        """The vehicle answers an authentication at once when its uplink is there; when
        it was not (the agent reconnecting after a platform process restarted, or gone),
        the authentication was lost on the way: the client is told to connect again
        (4503) rather than wait for an answer that never comes."""
        await asyncio.sleep(RELAY_ANSWER_S)
        if not self.answered and not self.closing:
            await self._refuse(
                "vehicle_unreachable",
                "the vehicle did not answer: connect again shortly",
                CLOSE_TRY_LATER,
            )

    async def relay_from_agent(self, event: dict[str, Any]) -> None:
        """The agent's answer, as the frame's text (the uplink checked and encoded it),
        or ``close`` (the agent dropped this client, with its close code or none)."""
        if event["vehicle_id"] != self.vehicle_id:
            return  # only the session's vehicle may answer on this connection
        self.answered = True
        self.uplink = event.get("uplink") or self.uplink
        if "text" in event:
            await self.send(text_data=event["text"])
            if self.commands_out and event["text"].startswith(_ACK_PREFIX):
                _ack_timed(event["text"], self.commands_out)
        else:
            await self.close(code=_sendable_close_code(event.get("close")))

    async def relay_uplink_gone(self, event: dict[str, Any]) -> None:
        """The uplink that answered closed: back to the vehicle's group, where the
        agent's next uplink hears the next command."""
        if event.get("uplink") == self.uplink:
            self.uplink = None

    async def _error(self, code: str, message: str) -> None:
        await self.send(text_data=encode_message(error_message(code, message)))

    async def _refuse(self, code: str, message: str, close_code: int) -> None:
        """Answer ``error`` and close the socket; nothing it sent after is looked at."""
        self.closing = True
        await self._error(code, message)
        await self.close(code=close_code)


#: How a command's acknowledgement starts as the uplink encodes it (agents.protocol).
_ACK_PREFIX = '{"type":"ack",'
#: Commands a relayed connection times at once (the controller keeps one in flight).
COMMANDS_TIMED_MAX = 64


def _ack_timed(text: str, commands_out: dict[int, float]) -> None:
    """Count the vehicle's acknowledgement of a relayed command and its round trip."""
    try:
        ack = json.loads(text)
        sent = commands_out.pop(int(ack["seq"]))
    except (ValueError, KeyError, TypeError):
        return
    RELAY_ACKS.labels(ok="true" if ack.get("ok") else "false").inc()
    RELAY_ROUND_TRIP.observe(time.monotonic() - sent)


def _sendable_close_code(code: Any) -> int:
    """The agent's close code for its relayed client, if a server may send it (1000 or
    the range for applications and libraries, 3000-4999: daphne sends no other, and
    uvicorn refuses the reserved ones), else :data:`CLOSED_BY_AGENT`. An agent's code is
    any number its message carries; another would raise in the relay instead of
    closing the client's socket."""
    if isinstance(code, int) and (code == 1000 or 3000 <= code <= 4999):
        return code
    return CLOSED_BY_AGENT


#: A WebRTC offer counted against its user's and address's budgets, off the event loop
#: (the counters live in Redis: a slow Redis must not hold the relay's other frames).
_offer_count = sync_to_async(
    functools.partial(throttle_check, action="webrtc_offer"), thread_sensitive=False
)


@database_sync_to_async
def _session_vehicle(session_id: str) -> str | None:
    """The primary vehicle of a live session, else None."""
    from services.models import Session
    from services.sessions.states import FINAL

    try:
        session = Session.objects.get(pk=uuid.UUID(session_id))
    except (ValueError, Session.DoesNotExist):
        return None
    if session.state in FINAL:
        return None
    assignment = session.assignments.filter(active=True).order_by("created_at").first()
    return str(assignment.vehicle_id) if assignment else None


@database_sync_to_async
def _platform_keys() -> Any:
    # The current key and, during a rotation, the previous ones: a grant issued just before
    # the switch still opens its relayed connection.
    from services.sessions.signing import platform_keys

    return platform_keys()
