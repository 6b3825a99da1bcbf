"""Behaviour tests for agents.video: sources, the shared encoder, WebRTC to aiortc peers
and to headless Chromium, the MJPEG reader.

Everything runs on 127.0.0.1: the VideoService and the test's peers offer only loopback
ICE candidates, Chromium gets the loopback flags from tests/browser.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import statistics
import time
from collections.abc import AsyncIterator, Callable
from fractions import Fraction
from typing import Any

import av
import numpy as np
import pytest
from aiortc import RTCConfiguration, RTCPeerConnection, RTCRtpReceiver, RTCSessionDescription
from aiortc.codecs import vpx

from agents.rtc import RtcPeers
from agents.video import VideoError
from agents.video.encoder import EncodedTrack, SharedEncoder, VideoCodec, _has_sps
from agents.video.framecode import FrameCode, read_frame_code, stamp_frame_code
from agents.video.ice import restrict_ice_host_addresses
from agents.video.service import SPECTATOR_KEYFRAME_GAP_S, VideoService, video_service_create
from agents.video.sources import (
    CameraPose,
    MjpegCamera,
    SyntheticCamera,
    V4L2Camera,
    VideoSource,
    video_source_create,
)
from tests.agents.video_page import signalling_server
from tests.browser import chromium_browser, needs_chromium

LOOPBACK = ["127.0.0.1"]


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


class CountingSource:
    """A SyntheticCamera that counts how often it is polled and closed."""

    def __init__(self, fps: float = 30.0) -> None:
        self.camera = SyntheticCamera(320, 240, fps=fps)
        self.polls = 0
        self.closes = 0

    async def frame(self) -> av.VideoFrame:
        self.polls += 1
        return await self.camera.frame()

    async def close(self) -> None:
        self.closes += 1
        await self.camera.close()


class _Events:
    """What :class:`RtcPeers` tells its owner; a connection for video alone opens no
    data channel, so there is nothing to do here (the agent's hub does the rest)."""

    async def channel_opened(self, peer_id: str, link: Any) -> None:
        return None

    async def received(self, link: Any, raw: str | bytes | Any) -> None:
        return None

    async def path_changed(self, peer_id: str, path: str) -> None:
        return None

    async def channel_closed(self, peer_id: str) -> None:
        return None


async def offered(pc: RTCPeerConnection) -> str:
    """``pc`` offering to receive video (loopback candidates only): its complete SDP."""
    pc.addTransceiver("video", direction="recvonly")
    with restrict_ice_host_addresses(LOOPBACK):
        await pc.setLocalDescription(await pc.createOffer())
    return str(pc.localDescription.sdp)


class Viewer:
    """An aiortc peer offering to receive video alone, as the controller page does
    while control stays on a socket, answered by the agent's :class:`RtcPeers`."""

    def __init__(self, rtc: RtcPeers, peer_id: str) -> None:
        self.rtc, self.peer_id = rtc, peer_id
        self.pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))
        self._track: asyncio.Future[Any] = asyncio.get_running_loop().create_future()

        @self.pc.on("track")
        def on_track(track: Any) -> None:
            if not self._track.done():
                self._track.set_result(track)

    async def connect(self) -> None:
        answer = await self.rtc.accept(self.peer_id, await offered(self.pc))
        await self.pc.setRemoteDescription(RTCSessionDescription(answer, "answer"))

    async def codes(self, n: int, limit_s: float = 15.0) -> list[FrameCode]:
        """Decode ``n`` frames and read their stamped codes (a frame whose code does not
        survive the encoding fails the test)."""
        track = await asyncio.wait_for(asyncio.shield(self._track), limit_s)
        out = []
        for _ in range(n):
            frame = await asyncio.wait_for(track.recv(), limit_s)
            code = read_frame_code(frame.to_ndarray(format="rgb24"))
            assert code is not None, "frame code unreadable after the codec's round trip"
            out.append(code)
        return out

    async def close(self) -> None:
        await self.pc.close()


@contextlib.asynccontextmanager
async def viewer(rtc: RtcPeers, peer_id: str) -> AsyncIterator[Viewer]:
    v = Viewer(rtc, peer_id)
    try:
        await v.connect()
        yield v
    finally:
        await v.close()


@contextlib.asynccontextmanager
async def camera(
    source: VideoSource | None = None,
    *,
    keyframe_interval_s: float = 3.0,
    codec: str = "vp8",
    **peers: Any,
) -> AsyncIterator[tuple[VideoService, RtcPeers]]:
    """A loopback VideoService (over a small, fast synthetic camera unless ``source``,
    sending ``codec``) and the agent's WebRTC connections carrying it (``peers``:
    RtcPeers options)."""
    source = source or SyntheticCamera(320, 240, fps=30)
    async with VideoService(
        source, ice_host_addresses=LOOPBACK, keyframe_interval_s=keyframe_interval_s, codec=codec
    ) as svc:
        rtc = RtcPeers(_Events(), video=svc, **peers)
        try:
            yield svc, rtc
        finally:
            await rtc.close()


def increasing(counters: list[int]) -> bool:
    return all(b > a for a, b in itertools.pairwise(counters))


async def wait_until(cond: Callable[[], bool], limit_s: float = 5.0) -> None:
    deadline = time.monotonic() + limit_s
    while not cond():
        assert time.monotonic() < deadline, "condition not met in time"
        await asyncio.sleep(0.02)


# --------------------------------------------------------------------------------------
# frame code and synthetic scene
# --------------------------------------------------------------------------------------


def test_frame_code_round_trips_and_detects_damage() -> None:
    img = np.full((240, 320, 3), 90, dtype=np.uint8)
    stamp_frame_code(img, 123_456, 1_795_000_000_123)
    assert read_frame_code(img) == FrameCode(123_456, 1_795_000_000_123)
    img[2:4, :40] = 255 - img[2:4, :40]  # flip the first blocks' centres
    assert read_frame_code(img) is None
    assert read_frame_code(np.zeros((240, 320, 3), dtype=np.uint8)) is None


def test_synthetic_camera_draws_every_frame_with_its_own_code() -> None:
    # How long a frame takes to draw is a benchmark's to say, not a test's: a loaded
    # machine makes any time bound here fail for no fault of the code.
    cam = SyntheticCamera(640, 480)
    pose = CameraPose(lat=43.7, lon=7.25, heading_deg=30, obstacles=[(43.70003, 7.25, 1, 2)])
    for i in range(20):
        img = cam.render(pose, i, 1_795_000_000_000 + i)
        assert img.shape == (480, 640, 3) and img.dtype == np.uint8
        assert read_frame_code(img) == FrameCode(i, 1_795_000_000_000 + i)


def test_synthetic_scene_follows_heading_and_position() -> None:
    cam = SyntheticCamera(320, 240)
    base = CameraPose(lat=43.7, lon=7.25, heading_deg=0)
    a = cam.render(base, 0, 0)
    sky, ground = slice(20, 110), slice(140, 200)  # above/below the horizon at row 120
    turned = cam.render(CameraPose(lat=43.7, lon=7.25, heading_deg=40), 0, 0)
    moved = cam.render(CameraPose(lat=43.70001, lon=7.25, heading_deg=0), 0, 0)  # 1.1 m N
    again = cam.render(base, 0, 0)
    assert np.array_equal(a, again)
    assert not np.array_equal(a[sky], turned[sky])  # mountains slide with heading
    assert np.array_equal(a[sky], moved[sky])  # the sky does not move with position
    assert not np.array_equal(a[ground], moved[ground])  # the grid does
    looking_down = cam.render(CameraPose(lat=43.7, lon=7.25, tilt_deg=-20), 0, 0)
    # looking down raises the horizon: more ground (green dominant) at row 100
    assert looking_down[100, 100, 1] > looking_down[100, 100, 2]
    assert a[100, 100, 2] > a[100, 100, 1]  # level: row 100 is sky (blue dominant)


def test_camera_pose_accepts_mappings_and_state_objects() -> None:
    class State:
        lat, lon, alt, heading_deg = 1.0, 2.0, None, 90.0

    assert CameraPose.coerce(State()) == CameraPose(lat=1.0, lon=2.0, heading_deg=90.0)
    pose = CameraPose.coerce({"lat": 1, "heading": 10, "obstacles": [(1, 2, 3, 4)]})
    assert pose.heading_deg == 10 and pose.obstacles == ((1.0, 2.0, 3.0, 4.0),)


async def test_synthetic_camera_paces_at_fps() -> None:
    cam = SyntheticCamera(320, 240, fps=20)
    t = time.monotonic()
    frames = [await cam.frame() for _ in range(11)]
    elapsed = time.monotonic() - t
    assert 0.45 < elapsed < 1.0  # 10 periods of 50 ms
    assert [read_frame_code(f.to_ndarray(format="rgb24")).counter for f in frames] == list(  # type: ignore[union-attr]
        range(11)
    )


def test_video_source_create() -> None:
    assert isinstance(video_source_create({"source": "synthetic", "fps": 10}), SyntheticCamera)
    v4l2 = video_source_create({"source": "v4l2", "device": "/dev/video9", "input_format": "mjpeg"})
    assert isinstance(v4l2, V4L2Camera) and v4l2.options["input_format"] == "mjpeg"
    mjpeg = video_source_create({"source": "mjpeg", "url": "http://192.168.4.1:81/stream"})
    assert isinstance(mjpeg, MjpegCamera)
    with pytest.raises(VideoError, match="unknown video source"):
        video_source_create({"source": "kinect"})
    with pytest.raises(VideoError, match="colour"):
        video_source_create({"source": "synthetic", "colour": "red"})
    with pytest.raises(VideoError, match="url"):
        video_source_create({"source": "mjpeg"})
    with pytest.raises(VideoError, match="fps"):
        video_source_create({"source": "synthetic", "fps": 0})


async def test_video_service_create_splits_source_and_service_options() -> None:
    config = {
        "source": "synthetic",
        "fps": 10,
        "ice_host_addresses": "127.0.0.1",  # a lone address is a list of one
        "bitrate": 500_000,
    }
    assert isinstance(video_source_create(config), SyntheticCamera)
    async with video_service_create(config) as svc:
        assert isinstance(svc.encoder.source, SyntheticCamera)
        assert svc.encoder.source.fps == 10
        assert svc.ice_host_addresses == ["127.0.0.1"]
    # What the camera's own connections took is the webrtc section's now: an old
    # configuration is told where it went instead of starting without it.
    with pytest.raises(VideoError, match=r"video\.max_peers has moved to .*webrtc\.max_peers"):
        video_service_create({"source": "synthetic", "max_peers": 3})
    with pytest.raises(VideoError, match=r"video\.ice_servers has moved"):
        video_source_create({"ice_servers": ["stun:stun.example.org:3478"]})


async def test_a_codec_the_vehicle_cannot_send_is_refused_by_name() -> None:
    """``video.codec`` and ``video.encoder`` are checked as the agent starts: an unknown
    codec, an encoder this machine's FFmpeg lacks, one that makes another codec, and
    options that are not strings each say what is wrong."""
    for config, said in [
        ({"codec": "h265"}, r"video\.codec 'h265' is not one of: vp8, h264"),
        ({"codec": "h264", "encoder": "h264_nowhere"}, "not in this machine's FFmpeg"),
        ({"codec": "h264", "encoder": "libvpx"}, "'libvpx' makes vp8, not h264"),
        ({"codec": "h264", "encoder_options": {"bf": 0}}, "must map names to strings"),
    ]:
        with pytest.raises(VideoError, match=said):
            video_service_create({"source": "synthetic", **config})
    async with video_service_create(
        {"source": "synthetic", "codec": "h264", "encoder_options": {"preset": "ultrafast"}}
    ) as svc:
        codec = svc.encoder.codec
        assert (codec.name, codec.encoder, codec.options) == (
            "h264",
            "libx264",
            (("preset", "ultrafast"),),
        )


@pytest.mark.parametrize("apart", [False, True], ids=["inline", "extradata"])
async def test_every_h264_keyframe_carries_its_parameter_sets(apart: bool) -> None:
    """A viewer joining late starts on the next keyframe, so each one carries the SPS
    and PPS, also from an encoder that gives them once, apart (a hardware encoder does;
    libx264 with FFmpeg's ``global_header`` flag stands in for it). A fresh decoder
    then decodes every frame from any keyframe on, frame codes intact."""
    options = {"flags": "+global_header"} if apart else {}
    encoder = SharedEncoder(
        SyntheticCamera(320, 240, fps=30), codec=VideoCodec.create("h264", options=options)
    )
    track = EncodedTrack(encoder)
    packets = []
    try:
        for i in range(40):
            packets.append(await asyncio.wait_for(track.recv(), 10))
            if i == 20:
                encoder.request_keyframe()  # a viewer's picture-loss request
        # Given apart, the parameter sets are the encoder's extradata, not in its frames.
        assert encoder._codec is not None
        assert bool(encoder._codec.extradata) == apart
    finally:
        track.stop()
        await encoder.close()
    keys = [i for i, packet in enumerate(packets) if packet.is_keyframe]
    assert keys[0] == 0 and len(keys) >= 2, keys
    for start in keys:
        assert _has_sps(bytes(packets[start])), start
        decoder = av.CodecContext.create("h264", "r")
        codes = [
            read_frame_code(frame.to_ndarray(format="rgb24"))
            for packet in packets[start:]
            for frame in decoder.decode(av.Packet(bytes(packet)))
        ]
        assert len(codes) == len(packets) - start and None not in codes
        assert increasing([c.counter for c in codes if c is not None])


async def test_an_h264_vehicle_answers_with_h264_alone_and_its_viewer_decodes_it() -> None:
    """A vehicle configured for H.264 answers a browser's usual offer (VP8 and H.264)
    with constrained baseline H.264 alone; the viewer decodes every frame (codes
    intact). An offer without H.264 is refused, saying why."""
    source = SyntheticCamera(320, 240, fps=30)
    async with VideoService(source, ice_host_addresses=LOOPBACK, codec="h264") as svc:
        rtc = RtcPeers(_Events(), video=svc)
        try:
            watcher = Viewer(rtc, "pilot")
            try:
                answer = await rtc.accept("pilot", await offered(watcher.pc))
                await watcher.pc.setRemoteDescription(RTCSessionDescription(answer, "answer"))
                rtpmap = [line for line in answer.splitlines() if line.startswith("a=rtpmap")]
                assert any("H264/90000" in line for line in rtpmap), rtpmap
                assert not any("VP8" in line for line in rtpmap), rtpmap
                assert "profile-level-id=42e01f" in answer
                codes = await watcher.codes(10)
                assert increasing([c.counter for c in codes])
            finally:
                await watcher.close()
            vp8_only = RTCPeerConnection(RTCConfiguration(iceServers=[]))
            try:
                t = vp8_only.addTransceiver("video", direction="recvonly")
                caps = RTCRtpReceiver.getCapabilities("video").codecs
                t.setCodecPreferences([c for c in caps if c.mimeType == "video/VP8"])
                with restrict_ice_host_addresses(LOOPBACK):
                    await vp8_only.setLocalDescription(await vp8_only.createOffer())
                with pytest.raises(VideoError, match="must offer H264"):
                    await rtc.accept("vp8-only", vp8_only.localDescription.sdp)
            finally:
                await vp8_only.close()
        finally:
            await rtc.close()


async def test_v4l2_camera_without_device_raises_video_error() -> None:
    cam = V4L2Camera("/dev/iouv-no-such-camera")
    with pytest.raises(VideoError, match="cannot open camera"):
        await cam.frame()
    await cam.close()


# --------------------------------------------------------------------------------------
# WebRTC to aiortc peers
# --------------------------------------------------------------------------------------


async def test_viewer_receives_frames_with_increasing_counter() -> None:
    async with camera() as (_svc, rtc):
        async with viewer(rtc, "v1") as v:
            codes = await v.codes(10)
        assert increasing([c.counter for c in codes])
        assert all(abs(c.ts_ms - time.time() * 1000) < 10_000 for c in codes)
        assert rtc.peer_count == 1


async def test_two_viewers_share_one_encoder(monkeypatch: pytest.MonkeyPatch) -> None:
    # aiortc's own per-sender encoder must never run: the senders only packetise.
    def per_sender_encode(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("aiortc encoded a frame per viewer")

    monkeypatch.setattr(vpx.Vp8Encoder, "encode", per_sender_encode)
    async with camera() as (svc, rtc), viewer(rtc, "a") as a, viewer(rtc, "b") as b:
        codes_a, codes_b = await asyncio.gather(a.codes(20), b.codes(20))
        enc = svc.encoder
        # Each source frame was encoded exactly once, for both viewers (one may be in
        # the encoder right now).
        assert enc.frames_captured - 1 <= enc.frames_encoded <= enc.frames_captured
        seen = {c.counter for c in codes_a} & {c.counter for c in codes_b}
        assert len(seen) >= 5  # the same frames reached both
        assert increasing([c.counter for c in codes_a])
        assert increasing([c.counter for c in codes_b])

        # Hanging up one viewer leaves the other streaming.
        await rtc.close_peer("a")
        assert rtc.peer_count == 1
        later = await b.codes(10)
        assert later[0].counter > codes_b[-1].counter and increasing([c.counter for c in later])
        assert enc.running


async def test_picture_loss_from_a_viewer_forces_a_shared_keyframe() -> None:
    # No keyframe falls due on its own in the test: only a request makes one.
    async with camera(keyframe_interval_s=3600) as (svc, rtc), viewer(rtc, "a") as a:
        await a.codes(3)
        before = svc.encoder.keyframes
        # What RTCRtpSender does on an RTCP PLI or FIR from this viewer:
        (sender,) = rtc._peers["a"].pc.getSenders()
        sender._send_keyframe()
        await a.codes(12)  # keyframes are at least 0.25 s apart; 12 frames is 0.4 s
        # At least: on a busy machine the viewer may fall behind its queue, which asks
        # for one more (the encoder cannot tell the two apart, nor need it).
        assert svc.encoder.keyframes >= before + 1


async def test_spectators_picture_loss_brings_a_keyframe_at_most_every_two_seconds() -> None:
    # Janus passes on its spectators' picture-loss requests: 50 spectators took the
    # vehicle to 5 keyframes a second, each one on the pilot's link too. Theirs (and a
    # spectator's on the vehicle) are held to one per SPECTATOR_KEYFRAME_GAP_S; the
    # pilot's go straight to the encoder.
    async with VideoService(SyntheticCamera(320, 240, fps=30)) as svc:
        asked: list[float] = []
        svc.encoder.request_keyframe = lambda: asked.append(time.monotonic())  # type: ignore[method-assign]
        senders, pcs = {}, []
        for role in ("pilot", "sfu", "viewer"):
            pcs.append(pc := RTCPeerConnection(RTCConfiguration(iceServers=[])))
            svc.attach(pc, role=role)
            (senders[role],) = pc.getSenders()
        try:
            for _ in range(5):
                senders["sfu"]._send_keyframe()
                senders["viewer"]._send_keyframe()
            assert len(asked) == 1  # one for all of the spectators' ten
            for _ in range(3):
                senders["pilot"]._send_keyframe()
            assert len(asked) == 4  # each of the pilot's
            svc._spectator_keyframe_at -= SPECTATOR_KEYFRAME_GAP_S  # two seconds later
            senders["sfu"]._send_keyframe()
            assert len(asked) == 5
        finally:
            for pc in pcs:
                await pc.close()


async def test_no_viewer_means_no_capture() -> None:
    source = CountingSource()
    async with camera(source) as (svc, rtc):
        await asyncio.sleep(0.3)
        assert source.polls == 0
        # Answered, but the answer never applied on that side: never connected, so
        # still nothing to send.
        pending = RTCPeerConnection(RTCConfiguration(iceServers=[]))
        await rtc.accept("pending", await offered(pending))
        await asyncio.sleep(0.3)
        assert source.polls == 0 and rtc.peer_count == 1
        await rtc.close_peer("pending")
        await pending.close()

        async with viewer(rtc, "v") as v:
            await v.codes(3)
            assert source.polls >= 3
            await rtc.close_peer("v")
        await wait_until(lambda: not svc.encoder.running)
        polls = source.polls
        assert source.closes >= 1  # the camera is released when the last viewer leaves
        await asyncio.sleep(0.3)
        assert source.polls == polls

        # and capture starts again for the next viewer
        async with viewer(rtc, "w") as w:
            assert increasing([c.counter for c in await w.codes(3)])


async def test_bad_sdp_raises_video_error_and_others_keep_streaming() -> None:
    async with camera() as (_svc, rtc), viewer(rtc, "good") as good:
        await good.codes(2)
        with pytest.raises(VideoError, match="bad SDP offer"):
            await rtc.accept("bad", "garbage\r\nnot sdp at all")
        with pytest.raises(VideoError, match="bad SDP offer"):
            await rtc.accept("bad2", "v=0\r\nm=video 9 UDP/TLS/RTP/SAVPF 96\r\n")
        with pytest.raises(VideoError):
            await rtc.accept("bad3", "")
        assert rtc.peer_count == 1  # the failed peers are dropped
        assert increasing([c.counter for c in await good.codes(5)])


async def test_offer_without_vp8_is_refused() -> None:
    async with camera(SyntheticCamera(320, 240)) as (_svc, rtc):
        pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))
        try:
            t = pc.addTransceiver("video", direction="recvonly")
            h264 = [
                c
                for c in RTCRtpReceiver.getCapabilities("video").codecs
                if c.mimeType == "video/H264"
            ]
            t.setCodecPreferences(h264)
            with restrict_ice_host_addresses(LOOPBACK):
                await pc.setLocalDescription(await pc.createOffer())
            with pytest.raises(VideoError, match="VP8"):
                await rtc.accept("h264-only", pc.localDescription.sdp)
            assert rtc.peer_count == 0
        finally:
            await pc.close()


async def test_viewer_limit_and_replacing_a_peer() -> None:
    clients = [RTCPeerConnection(RTCConfiguration(iceServers=[])) for _ in range(4)]
    try:
        async with camera(SyntheticCamera(320, 240), max_peers=3) as (_svc, rtc):
            # Spectators get all places but the last, which is the pilot's.
            await rtc.accept("a", await offered(clients[0]))
            await rtc.accept("b", await offered(clients[1]))
            with pytest.raises(VideoError, match="too many"):
                await rtc.accept("c", await offered(clients[2]))
            # The same viewer offering again replaces its connection.
            await rtc.accept("a", await offered(clients[3]))
            assert rtc.peer_count == 2
        assert rtc.peer_count == 0
        with pytest.raises(VideoError, match="shutting down"):
            await rtc.accept("late", "v=0\r\n")
    finally:
        for pc in clients:
            await pc.close()


async def test_a_connection_that_never_comes_up_is_dropped() -> None:
    ghost = RTCPeerConnection(RTCConfiguration(iceServers=[]))
    try:
        async with camera(SyntheticCamera(320, 240), connect_timeout_s=0.2) as (_svc, rtc):
            await rtc.accept("ghost", await offered(ghost))  # its answer never applied
            await wait_until(lambda: rtc.peer_count == 0, limit_s=3)
    finally:
        await ghost.close()


async def test_answer_sdp_is_complete_vp8_and_loopback_only() -> None:
    client = RTCPeerConnection(RTCConfiguration(iceServers=[]))
    try:
        async with camera(SyntheticCamera(320, 240)) as (_svc, rtc):
            sdp = await rtc.accept("x", await offered(client))
    finally:
        await client.close()
    assert "a=sendonly" in sdp and "VP8/90000" in sdp and "H264" not in sdp
    candidates = [line for line in sdp.splitlines() if line.startswith("a=candidate")]
    assert candidates and all(" 127.0.0.1 " in c for c in candidates)


# --------------------------------------------------------------------------------------
# headless Chromium
# --------------------------------------------------------------------------------------


@needs_chromium
@pytest.mark.parametrize("codec", ["vp8", "h264"])
async def test_headless_chromium_decodes_the_video(
    codec: str, capsys: pytest.CaptureFixture[str]
) -> None:
    async with (
        camera(SyntheticCamera(640, 480, fps=15), codec=codec) as (svc, rtc),
        signalling_server(rtc) as url,
        chromium_browser(webrtc_loopback=True) as browser,
    ):
        page = await browser.new_page()
        await page.goto(url)
        await page.wait_for_function(
            "() => window.result.codes.length >= 10 || window.result.error", timeout=20_000
        )
        result = await page.evaluate("window.result")
        quality = await page.evaluate(
            "document.getElementById('v').getVideoPlaybackQuality().totalVideoFrames"
        )
        assert result["error"] is None, result["error"]
        assert result["width"] == 640
        assert quality >= 10
        codes = result["codes"]
        assert codes[-1] > codes[0] and codes == sorted(codes)
        enc = svc.encoder
        assert enc.frames_captured - 1 <= enc.frames_encoded <= enc.frames_captured
        first_ms = result["firstFrameMs"]  # since navigation start (performance.now())
        latency = statistics.median(result["latencies"])
        with capsys.disabled():
            print(
                f"\n[chromium, {codec}] first frame {first_ms:.0f} ms after page load "
                f"started; capture-to-display latency median {latency:.0f} ms"
            )
        assert first_ms < 10_000
        await page.close()
        await wait_until(lambda: rtc.peer_count == 0, limit_s=10)


# --------------------------------------------------------------------------------------
# MJPEG
# --------------------------------------------------------------------------------------


def make_jpeg(counter: int, encoder: av.VideoCodecContext) -> bytes:
    img = np.full((240, 320, 3), 60, dtype=np.uint8)
    img[120:, :, 1] = 160
    stamp_frame_code(img, counter, 1_795_000_000_000 + counter)
    frame = av.VideoFrame.from_ndarray(img, format="rgb24").reformat(format="yuvj420p")
    return b"".join(bytes(p) for p in encoder.encode(frame))


@contextlib.asynccontextmanager
async def mjpeg_server(
    *,
    chunked: bool = True,
    part_length: bool = True,
    fps: float = 25.0,
    frames_per_connection: int | None = None,
) -> AsyncIterator[dict[str, Any]]:
    """An ESP32-CAM-like MJPEG server on 127.0.0.1; yields {"url", "connections",
    "served"}. The defaults are what the ESP32-CAM sketch sends: chunked transfer
    coding, a Content-Length in each part's headers. ``frames_per_connection``: hang up
    after that many frames."""
    state: dict[str, Any] = {"connections": 0, "served": 0}
    tasks: set[asyncio.Task[Any]] = set()
    encoder = av.CodecContext.create("mjpeg", "w")
    encoder.width, encoder.height, encoder.pix_fmt = 320, 240, "yuvj420p"
    encoder.time_base = Fraction(1, 25)
    boundary = "123456789000000000000987654321"

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        tasks.add(asyncio.current_task())  # type: ignore[arg-type]
        state["connections"] += 1
        try:
            while (await reader.readline()) not in (b"\r\n", b""):
                pass
            head = (
                "HTTP/1.1 200 OK\r\n"
                f"Content-Type: multipart/x-mixed-replace;boundary={boundary}\r\n"
                + ("Transfer-Encoding: chunked\r\n" if chunked else "")
                + "\r\n"
            )
            writer.write(head.encode())
            counter = 0
            while frames_per_connection is None or counter < frames_per_connection:
                jpeg = make_jpeg(counter, encoder)
                part = (
                    f"\r\n--{boundary}\r\nContent-Type: image/jpeg\r\n".encode()
                    + (f"Content-Length: {len(jpeg)}\r\n".encode() if part_length else b"")
                    + b"\r\n"
                    + jpeg
                )
                if chunked:  # send it in two chunks, as a streaming server may
                    for piece in (part[:700], part[700:]):
                        writer.write(f"{len(piece):x}\r\n".encode() + piece + b"\r\n")
                else:
                    writer.write(part)
                await writer.drain()
                state["served"] += 1
                counter += 1
                await asyncio.sleep(1 / fps)
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    state["url"] = f"http://127.0.0.1:{port}/stream"
    try:
        yield state
    finally:
        server.close()
        for task in list(tasks):
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await server.wait_closed()


@pytest.mark.parametrize(
    ("chunked", "part_length"),
    [(True, True), (True, False), (False, True), (False, False)],
    ids=["esp32", "chunked-no-length", "identity-length", "identity-no-length"],
)
async def test_mjpeg_camera_reads_a_local_stream(chunked: bool, part_length: bool) -> None:
    async with mjpeg_server(chunked=chunked, part_length=part_length) as server:
        cam = MjpegCamera(server["url"])
        try:
            frames = [await asyncio.wait_for(cam.frame(), 5) for _ in range(6)]
        finally:
            await cam.close()
        codes = [read_frame_code(f.to_ndarray(format="rgb24")) for f in frames]
        assert all(c is not None for c in codes)
        counters = [c.counter for c in codes if c is not None]
        assert increasing(counters)
        assert (frames[0].width, frames[0].height) == (320, 240)
        # closing drops the connection; the next frame() reconnects
        await wait_until(lambda: server["connections"] == 1)
        try:
            await asyncio.wait_for(cam.frame(), 5)
        finally:
            await cam.close()
        assert server["connections"] == 2


async def test_mjpeg_camera_reconnects_after_a_dropped_stream() -> None:
    # The server hangs up after every 3 frames, as a flaky Wi-Fi camera might.
    async with mjpeg_server(frames_per_connection=3) as server:
        cam = MjpegCamera(server["url"], reconnect_s=0.05)
        try:
            frames = [await asyncio.wait_for(cam.frame(), 5) for _ in range(8)]
        finally:
            await cam.close()
    assert server["connections"] >= 3
    assert all(read_frame_code(f.to_ndarray(format="rgb24")) is not None for f in frames)


async def test_mjpeg_camera_rejects_non_multipart_responses() -> None:
    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.readline()
        writer.write(b"HTTP/1.1 200 OK\r\nContent-Type: text/html\r\n\r\n<html></html>")
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        cam = MjpegCamera(f"http://127.0.0.1:{port}/", reconnect_s=0.05)
        with pytest.raises(VideoError, match="not an MJPEG stream"):
            await cam._read_stream()
        await cam.close()
    finally:
        server.close()
        await server.wait_closed()
    with pytest.raises(VideoError, match="http"):
        MjpegCamera("rtsp://camera/stream")


async def test_mjpeg_camera_through_video_service_to_a_viewer() -> None:
    async with mjpeg_server(fps=20) as server:
        cam = MjpegCamera(server["url"])
        async with camera(cam) as (_svc, rtc):
            assert server["connections"] == 0  # nobody watching: camera not opened
            async with viewer(rtc, "v") as v:
                codes = await v.codes(8)
            assert increasing([c.counter for c in codes])
