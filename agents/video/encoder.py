"""One encoder shared by every viewer (:class:`SharedEncoder`: VP8, or H.264 in software
or on a hardware encoder, :class:`VideoCodec`) and each viewer's track of its packets
(:class:`EncodedTrack`); the bitrate and the picture's size follow the pilot's link
(:mod:`agents.video.rate`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Final, Literal, TypeAlias

import av
import av.video.frame
from aiortc import MediaStreamTrack, RTCRtpCodecCapability, RTCRtpSender
from aiortc.mediastreams import MediaStreamError

from agents.video import VideoError
from agents.video.rate import RateController, fit_size
from agents.video.sources import VideoSource

_Packet: TypeAlias = "av.Packet[Any]"

logger = logging.getLogger(__name__)

#: RTP video clock (90 kHz); packet timestamps are expressed in it.
VIDEO_TIME_BASE: Final = Fraction(1, 90_000)


#: The codecs a vehicle can send, by the name its ``video.codec`` gives, with the FFmpeg
#: encoder used when ``video.encoder`` names none.
DEFAULT_ENCODERS: Final = {"vp8": "libvpx", "h264": "libx264"}


@dataclass(frozen=True)
class VideoCodec:
    """What the shared encoder sends: ``name`` (``vp8`` or ``h264``, the RTP codec every
    viewer receives), the FFmpeg ``encoder`` that makes it (``libvpx``; ``libx264`` in
    software, ``h264_v4l2m2m`` on a Raspberry Pi's hardware encoder) and FFmpeg
    ``options`` of that encoder, added to (or replacing) the encoder's own settings."""

    name: Literal["vp8", "h264"] = "vp8"
    encoder: str = "libvpx"
    options: tuple[tuple[str, str], ...] = ()

    @classmethod
    def create(
        cls, name: str = "vp8", encoder: str | None = None, options: Any = None
    ) -> VideoCodec:
        """The codec an agent's configuration describes; VideoError names what is wrong
        (an unknown codec, an encoder this machine's FFmpeg lacks or that makes another
        codec, options that are not strings)."""
        if name not in DEFAULT_ENCODERS:
            raise VideoError(f"video.codec {name!r} is not one of: {', '.join(DEFAULT_ENCODERS)}")
        encoder = encoder or DEFAULT_ENCODERS[name]
        if not isinstance(encoder, str) or encoder not in av.codecs_available:
            raise VideoError(f"video.encoder {encoder!r} is not in this machine's FFmpeg")
        try:
            makes = av.Codec(encoder, "w").canonical_name
        except (ValueError, av.FFmpegError):
            raise VideoError(f"video.encoder {encoder!r} is not an encoder") from None
        if makes != name:
            raise VideoError(f"video.encoder {encoder!r} makes {makes}, not {name}")
        options = dict(options or {})
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in options.items()):
            raise VideoError("video.encoder_options must map names to strings")
        return cls(name, encoder, tuple(sorted(options.items())))  # type: ignore[arg-type]

    @property
    def rtp_name(self) -> str:
        """Its name in SDP (``VP8``, ``H264``)."""
        return {"vp8": "VP8", "h264": "H264"}[self.name]

    @property
    def mime_type(self) -> str:
        """Its RTP MIME type (``video/VP8``, ``video/H264``)."""
        return f"video/{self.rtp_name}"


#: H.264's start code, before each NAL unit of an Annex B stream.
_START_CODE: Final = b"\x00\x00\x01"
#: The NAL unit type of a sequence parameter set (SPS).
_NAL_SPS: Final = 7


def _has_sps(annex_b: bytes) -> bool:
    """Whether an Annex B access unit holds a sequence parameter set."""
    at = annex_b.find(_START_CODE)
    while at >= 0 and at + 3 < len(annex_b):
        if annex_b[at + 3] & 0x1F == _NAL_SPS:
            return True
        at = annex_b.find(_START_CODE, at + 3)
    return False


@dataclass(frozen=True)
class VideoStatus:
    """What the shared encoder sends now: the picture's size, its frame rate (the
    ladder's step, or the camera's own when slower) and the target bitrate (bit/s)."""

    width: int
    height: int
    fps: int
    bitrate: int


class _Subscriber:
    """One viewer's queue of encoded packets. A viewer starts on (and after an overflow
    resumes at) a keyframe: delta frames without their reference are useless to it."""

    QUEUE_FRAMES: Final = 8

    def __init__(self) -> None:
        self.queue: asyncio.Queue[_Packet] = asyncio.Queue(self.QUEUE_FRAMES)
        self.waiting_keyframe = True

    def offer(self, packet: _Packet) -> bool:
        """Queue ``packet``; False when the viewer fell behind and needs a keyframe."""
        if self.waiting_keyframe:
            if not packet.is_keyframe:
                return True
            self.waiting_keyframe = False
        try:
            self.queue.put_nowait(packet)
        except asyncio.QueueFull:
            while not self.queue.empty():
                self.queue.get_nowait()
            self.waiting_keyframe = True
            return False
        return True


class SharedEncoder:
    """Encodes the source's frames once (``codec``: VP8 unless told) for every
    subscribed viewer.

    Runs a capture task only while there are subscribers. Keyframes are produced on
    request (a viewer joining, PLI/FIR from any viewer, a viewer's queue overflowing;
    at most one every ``min_keyframe_gap_s``) and at least every
    ``keyframe_interval_s``. Counters: ``frames_captured``, ``frames_encoded`` (libvpx
    calls), ``keyframes``.

    The bitrate follows the receivers' estimates through :attr:`rate` (a
    :class:`~agents.video.rate.RateController`; ``bitrate`` is its ceiling and what is
    sent with no estimate), and with it the size and frame rate (its ladder): frames
    are scaled down and skipped here, after capture. :attr:`status` is what is sent
    now; the functions given to :meth:`add_listener` are called when it changes.

    Why VP8 by default: every WebRTC browser must decode it (RFC 7742), PyAV's wheels
    ship libvpx, and aiortc's ``Vp8Encoder.pack`` turns a whole VP8 frame into RTP
    payloads with no codec state per viewer (its picture id is per sender, which is
    what RTP wants). H.264 (constrained baseline, what WebRTC browsers decode) goes the
    same way through aiortc's ``H264Encoder.pack``; each keyframe carries the stream's
    parameter sets (an encoder that gives them apart, as a hardware one does, has them
    put in front), so that a viewer can start on any keyframe.
    """

    def __init__(
        self,
        source: VideoSource,
        *,
        bitrate: int = 1_000_000,
        keyframe_interval_s: float = 3.0,
        min_keyframe_gap_s: float = 0.25,
        codec: VideoCodec | None = None,
    ) -> None:
        self.source = source
        self.codec = codec or VideoCodec()
        self.bitrate = bitrate
        self.rate = RateController(max_bitrate=bitrate)
        #: What is sent now (None before the first frame).
        self.status: VideoStatus | None = None
        self._listeners: list[Callable[[VideoStatus], None]] = []
        self._source_fps = 0.0  # measured, smoothed
        self.keyframe_interval_s = keyframe_interval_s
        self.min_keyframe_gap_s = min_keyframe_gap_s
        self.frames_captured = 0
        self.frames_encoded = 0
        self.keyframes = 0
        self._subscribers: set[_Subscriber] = set()
        self._task: asyncio.Task[None] | None = None
        self._stopping: asyncio.Task[None] | None = None  # a run closing the source
        self._keyframe_wanted = False
        self._codec: av.VideoCodecContext | None = None

    @property
    def running(self) -> bool:
        """Whether the capture task is running (some viewer is pulling frames)."""
        return self._task is not None and not self._task.done()

    def subscribe(self) -> _Subscriber:
        """Add a viewer (starting capture if it was idle) and ask for a keyframe."""
        sub = _Subscriber()
        self._subscribers.add(sub)
        self.request_keyframe()
        if self._task is None or self._task.done():
            self._task = asyncio.create_task(self._run(self._stopping), name="video encoder")
        return sub

    def unsubscribe(self, sub: _Subscriber) -> None:
        """Remove a viewer; the last one leaving stops capture and closes the source."""
        self._subscribers.discard(sub)
        if not self._subscribers and self._task is not None:
            self._task.cancel()
            self._stopping, self._task = self._task, None

    def add_listener(self, listener: Callable[[VideoStatus], None]) -> None:
        """Call ``listener`` (on the event loop) whenever :attr:`status` changes."""
        self._listeners.append(listener)

    def remove_listener(self, listener: Callable[[VideoStatus], None]) -> None:
        """Stop calling ``listener``."""
        with contextlib.suppress(ValueError):
            self._listeners.remove(listener)

    def request_keyframe(self) -> None:
        """Make the next frame (or the first allowed by the gap) a keyframe."""
        self._keyframe_wanted = True

    async def close(self) -> None:
        """Stop capture and wait for the source to be closed."""
        self._subscribers.clear()
        tasks = [t for t in (self._task, self._stopping) if t is not None]
        self._task = self._stopping = None
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _run(self, previous: asyncio.Task[None] | None) -> None:
        if previous is not None:  # let the previous run finish closing the source
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.wait([previous])
        self._codec = None
        t0 = time.monotonic()
        last_key = last_capture = -math.inf
        key_gap = self.min_keyframe_gap_s  # for requested keyframes; see below
        credit = 1.0  # frames the ladder's frame rate allows now (see below)
        try:
            while self._subscribers:
                try:
                    frame = await self.source.frame()
                    self.frames_captured += 1
                    now = time.monotonic()
                    interval, last_capture = now - last_capture, now
                    if interval < 5.0:  # not the first frame (nor one after a stall)
                        fps = 1 / max(interval, 1e-3)
                        self._source_fps += (fps - self._source_fps) * (
                            0.1 if self._source_fps else 1.0
                        )
                    self.rate.tick()
                    rung = self.rate.rung
                    # The ladder's frame rate: each captured frame earns fps x interval
                    # of a frame; one is sent per whole frame earned. A 30 fps camera on
                    # a 20 fps step sends two frames of three, evenly.
                    if rung.fps is not None:
                        credit = min(1.5, credit + rung.fps * min(interval, 1.0))
                        if credit < 0.95:  # a little slack for a camera's jitter
                            continue
                        credit = max(0.0, credit - 1)
                    force = (
                        self._keyframe_wanted and now - last_key >= key_gap
                    ) or now - last_key >= self.keyframe_interval_s
                    if force:
                        self._keyframe_wanted = False
                    pts = int((now - t0) * 90_000)
                    size = fit_size(frame.width, frame.height, rung)
                    bitrate = self.rate.target_bitrate
                    # The frame rate sent: the camera's (measured), or the ladder's
                    # step when slower; 30 until measured.
                    fps = self._source_fps or 30.0
                    if rung.fps is not None:
                        fps = min(fps, rung.fps)
                    packets = await asyncio.to_thread(
                        self._encode, frame, pts, force, size, bitrate, fps
                    )
                except Exception as exc:
                    # A camera or codec hiccup must not end the viewers' connections:
                    # release the source, wait, and try again with a fresh encoder.
                    logger.warning("video capture failed (%s); retrying in 1 s", exc)
                    with contextlib.suppress(Exception):
                        await self.source.close()
                    self._codec = None
                    await asyncio.sleep(1.0)
                    continue
                self._report(size, rung.fps, bitrate)
                for packet in packets:
                    if packet.is_keyframe:
                        last_key = now
                        self.keyframes += 1
                        # A keyframe is several frames' worth of bits: on a link that
                        # is barely enough, one every quarter second (a lossy viewer's
                        # picture-loss requests) would fill it, lose more packets and
                        # bring more requests: a picture frozen for good. Requested
                        # ones leave the link at least half its time for the rest.
                        key_gap = max(self.min_keyframe_gap_s, 2 * 8 * packet.size / bitrate)
                    for sub in list(self._subscribers):
                        if not sub.offer(packet):
                            self.request_keyframe()
        finally:
            with contextlib.suppress(Exception):
                await self.source.close()

    def _report(self, size: tuple[int, int], rung_fps: float | None, bitrate: int) -> None:
        """Update :attr:`status` and tell the listeners when it changed."""
        if not self._source_fps:
            return  # the first frame: no frame rate measured yet
        fps = round(self._source_fps)
        if rung_fps is not None:
            fps = min(fps, round(rung_fps))
        status = VideoStatus(width=size[0], height=size[1], fps=fps, bitrate=bitrate)
        previous = self.status
        # A camera's measured rate wanders (more so on a busy machine): news only when
        # it moved by a fifth, each message going to every watching user.
        if (
            previous is not None
            and (previous.width, previous.height, previous.bitrate)
            == (status.width, status.height, status.bitrate)
            and abs(previous.fps - fps) < max(2, previous.fps / 5)
        ):
            return
        self.status = status
        for listener in list(self._listeners):
            try:
                listener(status)
            except Exception:  # one listener's bug must not stop the video
                logger.exception("video status listener failed")

    def _encode(
        self,
        frame: av.VideoFrame,
        pts: int,
        force_keyframe: bool,
        size: tuple[int, int],
        bitrate: int,
        fps: float = 30.0,
    ) -> list[_Packet]:
        """Encode one frame at ``size`` and ``bitrate`` (worker thread; the codec is only
        touched from here, one call at a time). Settings follow aiortc's encoders:
        real-time, no lag, no reordering, a steady rate. ``fps``, the frame rate sent,
        is what an encoder that budgets its bits per frame (x264) shares the bitrate
        by; it is read when the encoder opens (a new size or bitrate)."""
        if (frame.width, frame.height) != size or frame.format.name != "yuv420p":
            frame = frame.reformat(width=size[0], height=size[1], format="yuv420p")
        codec = self._codec
        # A new size or bitrate starts a new stream with a keyframe, as aiortc's own
        # encoders do: FFmpeg's libvpx wrapper takes neither once it is open.
        if codec is not None and (
            (frame.width, frame.height) != (codec.width, codec.height) or codec.bit_rate != bitrate
        ):
            codec = None
        if codec is None:
            created = av.CodecContext.create(self.codec.encoder, "w")
            assert isinstance(created, av.VideoCodecContext)  # VideoCodec checked it
            codec = created
            codec.width, codec.height = frame.width, frame.height
            codec.pix_fmt = "yuv420p"
            codec.time_base = VIDEO_TIME_BASE
            if self.codec.name == "h264":
                # Whole frames a second: x264 would otherwise take the 90 kHz time base
                # for the frame rate and give each frame 1/90,000 of a second's bits.
                codec.framerate = Fraction(max(1, round(fps)), 1)
            codec.bit_rate = bitrate
            codec.gop_size = 100_000  # keyframes are placed by us (request/interval)
            options: dict[str, str] = {}
            if self.codec.encoder == "libvpx":
                codec.qmin, codec.qmax = 2, 56
                options = _vp8_options(bitrate)
            elif self.codec.encoder == "libx264":
                options = _x264_options(bitrate)
            codec.options = {**options, **dict(self.codec.options)}
            self._codec = codec
        frame.pts, frame.time_base = pts, VIDEO_TIME_BASE
        frame.pict_type = (
            av.video.frame.PictureType.I if force_keyframe else av.video.frame.PictureType.NONE
        )
        packets = list(codec.encode(frame))
        self.frames_encoded += 1
        if self.codec.name == "h264":
            packets = [self._with_parameter_sets(codec, packet) for packet in packets]
        for packet in packets:
            # The encoders' pack() read pts in time_base to make the RTP timestamp.
            packet.pts, packet.time_base = pts, VIDEO_TIME_BASE
        return packets

    @staticmethod
    def _with_parameter_sets(codec: av.VideoCodecContext, packet: _Packet) -> _Packet:
        """``packet``, a keyframe with the stream's SPS and PPS in front when it came
        without (an encoder that gives them once, in its extradata: a viewer joining
        later could not decode a thing)."""
        if not packet.is_keyframe or not codec.extradata:
            return packet
        data = bytes(packet)
        if _has_sps(data):
            return packet
        whole = av.Packet(codec.extradata + data)
        whole.is_keyframe = True
        return whole


def _vp8_options(bitrate: int) -> dict[str, str]:
    """libvpx's settings at ``bitrate`` (aiortc's Vp8Encoder's, CBR)."""
    rate = str(bitrate)
    return {
        "bufsize": rate,
        # A keyframe at most three average frames (libwebrtc's floor for this libvpx
        # setting): one that overflows a slow link's queue is lost, and asked for again.
        "max-intra-rate": "300",
        "cpu-used": "-6",
        "deadline": "realtime",
        "lag-in-frames": "0",  # one packet out per frame in, no reordering
        "minrate": rate,
        "maxrate": rate,
        "noise-sensitivity": "4",
        "overshoot-pct": "15",
        "partitions": "0",
        "static-thresh": "1",
        "undershoot-pct": "100",
        "error-resilient": "1",  # decodable after a lost packet's frame is skipped
    }


def _x264_options(bitrate: int) -> dict[str, str]:
    """libx264's settings at ``bitrate``: aiortc's H264Encoder's (zero latency: no
    lookahead, no B-frames, one slice a frame out at once), a fast preset for a small
    computer, and a rate held to ``bitrate`` over a second (its VBV)."""
    rate = str(bitrate)
    return {
        # Baseline as x264 makes it is constrained baseline (no FMO, ASO or redundant
        # slices), which every WebRTC browser decodes.
        "profile": "baseline",
        "preset": "veryfast",
        "tune": "zerolatency",
        "level": "31",
        "maxrate": rate,
        "bufsize": rate,
        "sc_threshold": "0",  # keyframes where we place them, not at every scene cut
    }


class EncodedTrack(MediaStreamTrack):
    """One viewer's video track: yields the shared encoder's packets. Subscribes on the
    first ``recv()`` (the sender only pulls once the connection is up), unsubscribes on
    ``stop()``."""

    kind = "video"

    def __init__(self, encoder: SharedEncoder) -> None:
        super().__init__()
        self._encoder = encoder
        self._sub: _Subscriber | None = None
        #: Called once on stop (the service forgets this viewer's estimate).
        self.on_stop: Callable[[], None] | None = None

    async def recv(self) -> _Packet:
        if self.readyState != "live":
            raise MediaStreamError
        if self._sub is None:
            self._sub = self._encoder.subscribe()
        return await self._sub.queue.get()

    def stop(self) -> None:
        super().stop()
        if self._sub is not None:
            self._encoder.unsubscribe(self._sub)
            self._sub = None
        if self.on_stop is not None:
            self.on_stop()
            self.on_stop = None


def codec_preferences(codec: VideoCodec) -> list[RTCRtpCodecCapability]:
    """``codec`` (and its RTX) only: the shared encoder's packets are of that codec. For
    H.264, constrained baseline (``42e01f``) first, then baseline, both in
    packetization mode 1 (what aiortc's packetizer sends)."""
    caps = RTCRtpSender.getCapabilities("video").codecs
    ours = [c for c in caps if c.mimeType.lower() == codec.mime_type.lower()]
    ours.sort(key=lambda c: c.parameters.get("profile-level-id") != "42e01f")
    rtx = [c for c in caps if c.mimeType.lower() == "video/rtx"]
    return ours + rtx
