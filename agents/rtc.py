"""WebRTC peers of the agent: one RTCPeerConnection per user, carrying the control
protocol on data channels and the camera on a track.

The vehicle never listens for these connections: the browser's SDP offer reaches the
agent as a control message (``webrtc_offer``) on a link the user already authenticated
on with a grant (the platform's relay over the uplink, or on a LAN the direct
WebSocket), and the answer goes back the same way. ICE then finds a path, direct
(host or server-reflexive candidates) or through a TURN server, with the STUN/TURN
servers the platform attached to the relayed offer (short-lived credentials) and the
agent's own configuration.

The DTLS fingerprints in that exchange bind the connection to the authenticated link,
so its data channels speak for the same user without a second ``auth``: they are extra
paths of that user's control link (see ``ControlHub``), not new users. The browser
opens them (its offer holds them; the agent accepts only these labels):

* ``control``: ordered and reliable, the same messages as the WebSocket; the agent
  sends everything on it while it is open.
* ``input``: unordered, no retransmissions, for continuous stick input where a late
  command is worthless; acks still come on ``control``.
* ``urgent``: unordered but reliable, for the safe commands (stop, land, return home):
  they never wait behind the other channels' traffic.

:class:`RtcPeers` reports to its owner (a :class:`PeerEvents`, the control hub) when a
peer's channels open, every message they carry, the path ICE chose (``webrtc_direct``
or ``webrtc_turn``) and when the connection is gone.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, Protocol

from aiortc import (
    RTCConfiguration,
    RTCDataChannel,
    RTCIceServer,
    RTCPeerConnection,
    RTCSessionDescription,
)

from agents.protocol import MAX_MESSAGE_BYTES, encode_message
from agents.protocol.messages import Message
from agents.video import VideoError
from agents.video.ice import ice_server, restrict_ice_host_addresses

log = logging.getLogger(__name__)

#: The data channels a browser may open, and whether the agent sends on them.
CHANNELS: Final = frozenset({"control", "input", "urgent"})
#: Above this many bytes queued on ``control`` the user is not reading: the link is
#: treated as broken rather than buffering without end.
MAX_BUFFERED: Final = 1 << 20
#: Messages received from one peer and not yet handled; more are dropped (the hub's
#: own rate limit refuses a flood long before).
INBOX: Final = 256
#: An offer whose ICE does not connect within this is hung up (the user falls back).
CONNECT_TIMEOUT_S: Final = 30.0
#: How often a connected peer's candidate pairs are looked at again: the browser, which
#: controls ICE, may nominate a better pair after the first one (a direct pair that
#: became usable after a TURN pair, behind NATs that need a moment of hole punching).
#: aioice says nothing when it moves to such a pair, so the path is polled (and see
#: :func:`_resume_nominated_checks`).
PATH_CHECK_S: Final = 1.0

_APPLICATION = re.compile(r"^m=application ", re.MULTILINE)
_VIDEO = re.compile(r"^m=video ", re.MULTILINE)


class PeerEvents(Protocol):
    """What :class:`RtcPeers` tells its owner; ``peer_id`` is the id of the user's
    authenticated link the offer came on."""

    async def channel_opened(self, peer_id: str, link: ChannelLink) -> None:
        """The ``control`` channel is open: the user's messages may use it."""

    async def received(self, link: Any, raw: str | bytes | Message) -> None:
        """One message from any of the peer's channels (``link.id == peer_id``)."""

    async def path_changed(self, peer_id: str, path: str) -> None:
        """ICE chose (or changed) its pair: ``webrtc_direct`` or ``webrtc_turn``."""

    async def channel_closed(self, peer_id: str) -> None:
        """The connection is gone (closed, failed, or never connected in time)."""


class ChannelLink:
    """A user's ClientLink over their ``control`` data channel."""

    def __init__(self, peer_id: str, channel: RTCDataChannel, peers: RtcPeers) -> None:
        self.id = peer_id
        self.channel = channel
        self._peers = peers

    @property
    def open(self) -> bool:
        return self.channel.readyState == "open"

    async def send(self, message: Message) -> None:
        if not self.open:
            raise ConnectionError("data channel closed")
        if self.channel.bufferedAmount > MAX_BUFFERED:
            raise ConnectionError("the user is not reading the data channel")
        self.channel.send(encode_message(message))

    async def close(self, code: int, reason: str) -> None:
        await self._peers.close_peer(self.id)


@dataclass
class _RtcPeer:
    pc: RTCPeerConnection
    inbox: asyncio.Queue[tuple[ChannelLink | _InputLink, str | bytes]] = field(
        default_factory=lambda: asyncio.Queue(INBOX)
    )
    link: ChannelLink | None = None
    path: str | None = None
    track: Any | None = None
    tasks: set[asyncio.Task[Any]] = field(default_factory=set)
    closed: bool = False
    #: Offered by a holder of the session's controlling grant (not a spectator's).
    controller: bool = False


class _InputLink:
    """Where ``input``/``urgent`` messages come from: the same user (same id); answers
    go on ``control`` through the hub, never back on a lossy channel."""

    def __init__(self, peer_id: str) -> None:
        self.id = peer_id


class RtcPeers:
    """The agent's WebRTC connections, one per user link (see the module docstring).

    * ``events``: the owner told about channels, messages, paths and ends.
    * ``video``: a :class:`~agents.video.service.VideoService` whose camera each connection
      carries when the offer asks for video; None for a vehicle without one.
    * ``ice_servers``: the agent's own STUN/TURN servers, used beside the ones each
      offer brings; ``ice_host_addresses``: restrict host candidates (loopback tests).
    * ``max_peers``: connections beyond this are refused; the last place is kept for
      the session's controller: spectators get at most ``max_peers - 1``, so however
      many come, they never push the pilot off WebRTC onto the relay.
    """

    def __init__(
        self,
        events: PeerEvents,
        *,
        video: Any | None = None,
        ice_servers: Sequence[RTCIceServer | Mapping[str, Any] | str] = (),
        ice_host_addresses: Sequence[str] | None = None,
        max_peers: int = 8,
        connect_timeout_s: float = CONNECT_TIMEOUT_S,
    ) -> None:
        self.events = events
        self.video = video
        self.ice_servers = [ice_server(s) for s in ice_servers]
        if ice_host_addresses is None and video is not None:
            ice_host_addresses = video.ice_host_addresses
        self._ice_hosts = list(ice_host_addresses) if ice_host_addresses is not None else None
        self.max_peers = max_peers
        self.connect_timeout_s = connect_timeout_s
        self._peers: dict[str, _RtcPeer] = {}
        self._closed = False

    @property
    def peer_count(self) -> int:
        return len(self._peers)

    def path(self, peer_id: str) -> str | None:
        """The path of ``peer_id``'s connection once ICE chose one, else None."""
        peer = self._peers.get(peer_id)
        return peer.path if peer is not None else None

    async def accept(
        self,
        peer_id: str,
        sdp: str,
        *,
        ice_servers: Sequence[RTCIceServer | Mapping[str, Any] | str] = (),
        controller: bool = False,
    ) -> str:
        """Apply the browser's offer for ``peer_id`` (replacing its previous connection)
        and return the complete SDP answer (every candidate gathered: no trickle).
        ``ice_servers`` come with this offer (the platform's, for this session);
        ``controller``: the offer comes from a holder of the controlling grant, who may
        take the place spectators may not. Raises VideoError, with a sentence for the
        user, on bad SDP, a video offer from a vehicle without a camera, too many peers,
        or a closed service."""
        if self._closed:
            raise VideoError("this vehicle is shutting down")
        await self.close_peer(peer_id)
        if len(self._peers) >= self.max_peers:
            raise VideoError(f"too many WebRTC connections (at most {self.max_peers})")
        spectators = sum(1 for p in self._peers.values() if not p.controller)
        if not controller and spectators >= self.max_peers - 1:
            raise VideoError(
                f"too many spectators over WebRTC (at most {self.max_peers - 1}; the last "
                "place is kept for the pilot)"
            )
        if not (_APPLICATION.search(sdp) or _VIDEO.search(sdp)):
            raise VideoError("bad SDP offer: it asks for neither data channels nor video")
        wants_video = bool(_VIDEO.search(sdp))
        if wants_video and self.video is None:
            raise VideoError("this vehicle has no camera: offer data channels only")
        codec = self.video.encoder.codec if self.video is not None else None
        if wants_video and codec is not None and f"{codec.rtp_name}/90000" not in sdp:
            raise VideoError(
                f"bad SDP offer: the video must offer {codec.rtp_name} (this vehicle sends it; "
                "every WebRTC browser decodes VP8 and H.264)"
            )
        try:
            servers = [*self.ice_servers, *(ice_server(s) for s in ice_servers)]
        except (TypeError, ValueError) as exc:
            raise VideoError(f"bad ICE server: {exc}") from exc
        pc = RTCPeerConnection(RTCConfiguration(iceServers=servers))
        peer = _RtcPeer(pc, controller=controller)
        self._peers[peer_id] = peer
        if wants_video:
            peer.track = self.video.attach(  # type: ignore[union-attr]  # checked above
                pc, role="pilot" if controller else "viewer"
            )
        self._wire(peer_id, peer)
        try:
            await pc.setRemoteDescription(RTCSessionDescription(sdp=sdp, type="offer"))
            with restrict_ice_host_addresses(self._ice_hosts):
                await pc.setLocalDescription(await pc.createAnswer())
        except Exception as exc:  # aiortc raises many types for bad SDP; one answer
            await self.close_peer(peer_id, notify=False)
            raise VideoError(f"bad SDP offer: {exc or type(exc).__name__}") from exc
        self._spawn(peer, self._connect_deadline(peer_id, peer))
        self._spawn(peer, self._deliver(peer))
        self._spawn(peer, self._watch_path(peer_id, peer))
        return str(pc.localDescription.sdp)

    async def close_peer(self, peer_id: str, *, notify: bool = True) -> None:
        """Hang up ``peer_id``'s connection (unknown ids are ignored); the owner hears
        ``channel_closed`` unless ``notify`` is False."""
        peer = self._peers.pop(peer_id, None)
        if peer is None or peer.closed:
            return
        peer.closed = True
        current = asyncio.current_task()
        for task in peer.tasks:
            if task is not current:
                task.cancel()
        if peer.track is not None:
            peer.track.stop()  # the last viewer leaving stops capture
        try:
            await peer.pc.close()
        except Exception:  # a half-negotiated connection may fail to close cleanly
            log.exception("closing WebRTC peer %s", peer_id)
        if notify:
            await self.events.channel_closed(peer_id)

    async def close(self) -> None:
        """Hang up everyone. Idempotent."""
        self._closed = True
        for peer_id in list(self._peers):
            await self.close_peer(peer_id)

    # --- internals ----------------------------------------------------------------------
    def _wire(self, peer_id: str, peer: _RtcPeer) -> None:
        pc = peer.pc
        input_link = _InputLink(peer_id)

        @pc.on("datachannel")
        def on_datachannel(channel: RTCDataChannel) -> None:
            if channel.label not in CHANNELS:
                log.info("peer %s opened unknown data channel %r; closed", peer_id, channel.label)
                channel.close()
                return
            source: ChannelLink | _InputLink = input_link
            if channel.label == "control":
                link = ChannelLink(peer_id, channel, self)
                peer.link = source = link
                # Announced once the channel is open (it usually already is when the
                # datachannel event fires, after the remote's DCEP open).
                if channel.readyState == "open":
                    self._spawn(peer, self.events.channel_opened(peer_id, link))
                else:
                    channel.once(
                        "open",
                        lambda: self._spawn(peer, self.events.channel_opened(peer_id, link)),
                    )

            @channel.on("message")
            def on_message(data: str | bytes) -> None:
                if len(data) > MAX_MESSAGE_BYTES:
                    return  # oversized: the WebSocket would refuse the frame too
                with contextlib.suppress(asyncio.QueueFull):
                    peer.inbox.put_nowait((source, data))

        @pc.on("connectionstatechange")
        async def on_state() -> None:
            state = pc.connectionState
            if state == "connected":
                await self._path_update(peer_id, peer)
            elif state in ("failed", "closed") and self._peers.get(peer_id) is peer:
                log.info("WebRTC peer %s %s", peer_id, state)
                self._spawn(peer, self.close_peer(peer_id))

    async def _deliver(self, peer: _RtcPeer) -> None:
        """Hand the peer's messages to the owner one at a time, in arrival order (an
        ordered channel's order is the user's)."""
        while True:
            source, data = await peer.inbox.get()
            try:
                await self.events.received(source, data)
            except Exception:  # the hub never raises for user input; a bug must not
                log.exception("handling a data channel message")  # silence the peer

    async def _path_update(self, peer_id: str, peer: _RtcPeer) -> None:
        """Tell the owner when the pair ICE uses now gives another path."""
        path = _path_of(peer.pc)
        if path is not None and path != peer.path and not peer.closed:
            peer.path = path
            await self.events.path_changed(peer_id, path)

    async def _watch_path(self, peer_id: str, peer: _RtcPeer) -> None:
        """Follow the pair the browser nominates while connected (see PATH_CHECK_S)."""
        while True:
            await asyncio.sleep(PATH_CHECK_S)
            if peer.pc.connectionState == "connected":
                _resume_nominated_checks(peer.pc)
                await self._path_update(peer_id, peer)

    async def _connect_deadline(self, peer_id: str, peer: _RtcPeer) -> None:
        await asyncio.sleep(self.connect_timeout_s)
        if self._peers.get(peer_id) is peer and peer.pc.connectionState != "connected":
            log.info("WebRTC peer %s did not connect in time; hung up", peer_id)
            await self.close_peer(peer_id)

    def _spawn(self, peer: _RtcPeer, coro: Any) -> asyncio.Task[Any]:
        task = asyncio.create_task(coro)
        peer.tasks.add(task)
        task.add_done_callback(peer.tasks.discard)
        return task


def _ice_connection(pc: RTCPeerConnection) -> Any:
    """aioice's Connection behind ``pc`` (no public API for its pairs), or None."""
    sctp = pc.sctp
    if sctp is None:
        return None
    return getattr(sctp.transport.transport, "_connection", None)


def _resume_nominated_checks(pc: RTCPeerConnection) -> None:
    """Let the agent follow the browser to the pair it nominates after the first.

    aioice (0.13) cancels the checks still in progress once ICE completes, and leaves
    their pairs "in progress" for good; an incoming check for such a pair starts no new
    check (RFC 8445 section 7.3.1.4 says it must), so when the browser moves to it
    (USE-CANDIDATE) the agent never takes it and keeps sending on the first nominated
    pair. Behind endpoint-independent NATs with TURN configured that first pair is often
    a relayed one (it works before the NATs' holes are punched), and everything the
    vehicle sends, video included, would go through TURN for the whole session. The
    check of a pair in that state that the browser nominated is started again; once it
    succeeds aioice nominates the pair and sends on it.
    """
    connection = _ice_connection(pc)
    if connection is None:
        return
    for pair in list(getattr(connection, "_check_list", ())):
        task = pair.task
        if (
            pair.remote_nominated
            and not pair.nominated
            and pair.state is pair.State.IN_PROGRESS
            and task is not None
            and task.done()
        ):
            log.info("restarting the check of the pair the browser nominated: %s", pair)
            pair.task = None
            connection.check_start_task(pair)


def _path_of(pc: RTCPeerConnection) -> str | None:
    """``webrtc_turn`` when the chosen candidate pair relays through a TURN server on
    either side, ``webrtc_direct`` otherwise; None before ICE chose a pair."""
    connection = _ice_connection(pc)
    try:
        pair = next(iter(connection._nominated.values()))
    except (AttributeError, StopIteration):
        return None
    kinds = {pair.local_candidate.type, pair.remote_candidate.type}
    return "webrtc_turn" if "relay" in kinds else "webrtc_direct"
