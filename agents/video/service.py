"""The vehicle's camera behind every WebRTC connection (:class:`VideoService`)."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from types import TracebackType
from typing import Any, Self

from aiortc import MediaStreamTrack, RTCPeerConnection, RTCRtpSender
from aiortc.rtp import (
    RTCP_PSFB_APP,
    RTCP_RTPFB_NACK,
    AnyRtcpPacket,
    RtcpPsfbPacket,
    RtcpRrPacket,
    RtcpRtpfbPacket,
    RtcpSrPacket,
    unpack_remb_fci,
)

from agents.video import VideoError
from agents.video.encoder import EncodedTrack, SharedEncoder, VideoCodec, codec_preferences
from agents.video.rate import RetransmitBudget, Role
from agents.video.sources import SERVICE_OPTIONS, VideoSource, video_source_create

#: Picture-loss requests from anyone but the pilot (spectators on the vehicle, the SFU
#: on behalf of all of its spectators) bring a keyframe at most this often. Each
#: keyframe is several frames' worth on the pilot's link too, and the shared encoder
#: sends it to everyone: with 50 spectators behind Janus, their requests took the
#: vehicle from 0.3 to 5 keyframes a second and the pilot's latency from 52 to 126 ms
#: (benchmarks/video_spectators.py). A spectator waits a little longer for a clean
#: picture; the pilot's own requests are never held back.
SPECTATOR_KEYFRAME_GAP_S = 2.0


def video_service_create(
    config: Mapping[str, Any],
    *,
    pose: Callable[[], Any] | None = None,
    sources: Mapping[str, Callable[[Mapping[str, Any]], VideoSource]] | None = None,
) -> VideoService:
    """The :class:`VideoService` for an agent's whole ``video`` configuration: the
    source from :func:`video_source_create`, the :data:`SERVICE_OPTIONS` for the
    service. Raises VideoError on a bad configuration."""
    source = video_source_create(config, pose=pose, sources=sources)
    options = {k: v for k, v in config.items() if k in SERVICE_OPTIONS}
    try:
        return VideoService(source, **options)
    except (TypeError, ValueError) as exc:
        raise VideoError(f"bad video option: {exc}") from exc


class VideoService:
    """The vehicle's camera for every WebRTC connection, fed by one shared encoder.

    Use as ``async with VideoService(source) as video:``; leaving the block stops
    capture and closes the source (the service owns it). The connections are
    :class:`agents.rtc.RtcPeers`'s: each that asks for video gets the camera with
    :meth:`attach`.

    * ``ice_host_addresses``: the local addresses the connections offer as ICE host
      candidates (``["127.0.0.1"]`` for loopback-only tests); None lets aioice choose
      (all but loopback). RtcPeers uses them unless its own configuration says.
    * ``bitrate``: the shared encoder's target (bit/s); one bitrate for every viewer,
      since they share the stream.
    * ``keyframe_interval_s``: a keyframe at least this often.
    * ``codec``: ``vp8`` (the default) or ``h264``; ``encoder``: the FFmpeg encoder
      that makes it (``libvpx``, ``libx264``, or ``h264_v4l2m2m`` for a Raspberry Pi's
      hardware encoder); ``encoder_options``: FFmpeg options of that encoder
      (:class:`~agents.video.encoder.VideoCodec`).
    """

    def __init__(
        self,
        source: VideoSource,
        *,
        ice_host_addresses: Sequence[str] | None = None,
        bitrate: int = 1_000_000,
        keyframe_interval_s: float = 3.0,
        codec: str = "vp8",
        encoder: str | None = None,
        encoder_options: Mapping[str, str] | None = None,
    ) -> None:
        self.encoder = SharedEncoder(
            source,
            bitrate=bitrate,
            keyframe_interval_s=keyframe_interval_s,
            codec=VideoCodec.create(codec, encoder, encoder_options),
        )
        # A lone address (a common configuration slip) means a list of one.
        if isinstance(ice_host_addresses, str):
            ice_host_addresses = [ice_host_addresses]
        self._ice_hosts = list(ice_host_addresses) if ice_host_addresses is not None else None
        self._closed = False
        self._spectator_keyframe_at = -SPECTATOR_KEYFRAME_GAP_S

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    @property
    def frames_encoded(self) -> int:
        """Frames the shared encoder has encoded (once per captured frame, whatever the
        number of viewers)."""
        return self.encoder.frames_encoded

    def attach(self, pc: RTCPeerConnection, *, role: Role = "viewer") -> MediaStreamTrack:
        """Add the camera to ``pc`` (a connection another part of the agent negotiates,
        see :mod:`agents.rtc`): a sendonly transceiver of the shared encoder's codec,
        fed by it.
        ``role``: whom it serves (``pilot``, ``sfu`` or ``viewer``), which says whether
        its receiver's bandwidth estimate sets the shared bitrate (the pilot's does;
        without a pilot, the SFU's). Returns its track; stop it when the connection ends
        (the last viewer's stop ends capture)."""
        track = EncodedTrack(self.encoder)
        transceiver = pc.addTransceiver(track, direction="sendonly")
        transceiver.setCodecPreferences(codec_preferences(self.encoder.codec))
        sender = transceiver.sender
        # PLI/FIR from this viewer: aiortc would force a keyframe in the sender's own
        # encoder, which this sender does not use; ask the shared encoder instead (for
        # a spectator, or the SFU, within SPECTATOR_KEYFRAME_GAP_S).
        sender._send_keyframe = (  # type: ignore[method-assign]
            self.encoder.request_keyframe if role == "pilot" else self._spectator_keyframe
        )
        self._handle_feedback(sender, role)
        rate = self.encoder.rate
        track.on_stop = lambda: rate.forget(sender)
        return track

    def _spectator_keyframe(self) -> None:
        """A spectator's (or the SFU's) picture-loss request: a keyframe, unless one
        was asked for by a spectator within SPECTATOR_KEYFRAME_GAP_S."""
        now = time.monotonic()
        if now - self._spectator_keyframe_at >= SPECTATOR_KEYFRAME_GAP_S:
            self._spectator_keyframe_at = now
            self.encoder.request_keyframe()

    def _handle_feedback(self, sender: RTCRtpSender, role: Role) -> None:
        """Hand the shared encoder's rate controller every REMB and loss report this
        sender receives, and keep its retransmissions within a
        :class:`RetransmitBudget`.

        aiortc reads REMB only to set the ``target_bitrate`` of the sender's own
        encoder, which this sender never uses (it packetises the shared encoder's
        packets), and it has no public event or statistic for it; and it resends every
        packet a NACK names, however full the link. So this one sender's RTCP handler
        is wrapped: a NACK reaches aiortc with the packets the budget allows (the
        first ones, oldest first as the receiver lists them), everything else exactly
        as before, then a REMB naming the sender's SSRC is read with aiortc's own
        parser, as is the fraction lost of a receiver report about it. No aiortc class is
        changed, and only this instance."""
        rate = self.encoder.rate
        rate.attach(sender, role)
        budget = RetransmitBudget()
        handle = sender._handle_rtcp_packet

        async def handle_rtcp(packet: AnyRtcpPacket) -> None:
            if isinstance(packet, RtcpRtpfbPacket) and packet.fmt == RTCP_RTPFB_NACK:
                packet.lost = packet.lost[: budget.allow(len(packet.lost), rate.target_bitrate)]
            await handle(packet)
            if isinstance(packet, RtcpRrPacket | RtcpSrPacket):
                for report in packet.reports:
                    if report.ssrc == sender._ssrc:
                        rate.loss(sender, report.fraction_lost / 256)
            elif isinstance(packet, RtcpPsfbPacket) and packet.fmt == RTCP_PSFB_APP:
                try:
                    bitrate, ssrcs = unpack_remb_fci(packet.fci)
                except ValueError:  # another application-layer feedback than REMB
                    return
                if sender._ssrc in ssrcs:
                    rate.estimate(sender, bitrate)

        sender._handle_rtcp_packet = handle_rtcp  # type: ignore[method-assign]

    @property
    def ice_host_addresses(self) -> list[str] | None:
        """The local addresses ICE may offer (None: aioice's choice)."""
        return self._ice_hosts

    async def close(self) -> None:
        """Stop capture and close the source. Idempotent."""
        if self._closed:
            return
        self._closed = True
        await self.encoder.close()
        await self.encoder.source.close()
