"""Spectators through the SFU: a real Janus (tests.janus, Debian's package with
deploy/janus's configuration), the agent's real parts (its shared encoder, its WebRTC
peers for the pilot, its SFU publisher) and aiortc spectators over real sockets.

The pilot keeps its direct connection to the vehicle; the vehicle sends one more copy
to Janus, whatever the number of spectators; Janus itself refuses whoever has no token,
a forged one, or another session's; when Janus dies the spectators hear it and the
pilot flies on; what the vehicle published plays back from the recording.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
import uuid
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import av
import pytest
from aiortc import RTCConfiguration, RTCPeerConnection, RTCSessionDescription

from agents import sfu as agents_sfu
from agents.rtc import RtcPeers
from agents.sfu import JanusError, JanusSession, SfuPublisher
from agents.video.ice import restrict_ice_host_addresses
from agents.video.service import VideoService
from agents.video.sources import SyntheticCamera
from services import sfu
from tests.janus import JanusServer, Spectator, janus_server

pytestmark = pytest.mark.realtime

LOOPBACK = ["127.0.0.1"]
#: Spectators of the big test; IOUV_SFU_SPECTATORS changes it (docs/video.md has what
#: 50 cost on the 2-core machine).
SPECTATORS = int(os.environ.get("IOUV_SFU_SPECTATORS", "50"))


class _Events:
    """The owner RtcPeers reports to: a video-only pilot opens no data channel."""

    async def channel_opened(self, peer_id: str, link: Any) -> None:
        return None

    async def received(self, link: Any, raw: Any) -> None:
        return None

    async def path_changed(self, peer_id: str, path: str) -> None:
        return None

    async def channel_closed(self, peer_id: str) -> None:
        return None


class Pilot:
    """The controller's video, straight from the vehicle (agents.rtc), counting frames."""

    def __init__(self, rtc: RtcPeers, peer_id: str = "pilot") -> None:
        self.rtc = rtc
        self.peer_id = peer_id
        self.pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))
        self.frames = 0
        self._pulling: set[asyncio.Task[None]] = set()

        @self.pc.on("track")
        def on_track(track: Any) -> None:
            async def pull() -> None:
                with contextlib.suppress(Exception):
                    while True:
                        await track.recv()
                        self.frames += 1

            task = asyncio.ensure_future(pull())
            self._pulling.add(task)
            task.add_done_callback(self._pulling.discard)

    async def connect(self) -> None:
        self.pc.addTransceiver("video", direction="recvonly")
        with restrict_ice_host_addresses(LOOPBACK):
            await self.pc.setLocalDescription(await self.pc.createOffer())
        answer = await self.rtc.accept(self.peer_id, self.pc.localDescription.sdp, controller=True)
        await self.pc.setRemoteDescription(RTCSessionDescription(answer, "answer"))


async def sent_bytes(pc: RTCPeerConnection | None) -> int:
    """Video bytes ``pc`` has sent (RTP payload and headers, as WebRTC counts them)."""
    if pc is None:
        return 0
    stats = await pc.getStats()
    return sum(s.bytesSent for s in stats.values() if s.type == "outbound-rtp")


async def until(cond: Any, *, within: float, what: str) -> None:
    """Wait for ``cond()`` (sync or async) to hold; the bound only catches a hang."""
    deadline = time.monotonic() + within
    while True:
        value = cond()
        if asyncio.iscoroutine(value):
            value = await value
        if value:
            return
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.05)


@pytest.fixture
def janus(tmp_path: Path, settings: Any) -> Iterator[JanusServer]:
    with janus_server(tmp_path) as server:
        for name, value in server.settings().items():
            setattr(settings, name, value)
        yield server


@contextlib.asynccontextmanager
async def vehicle(
    session_id: uuid.UUID, *, fps: int = 10, codec: str = "vp8"
) -> AsyncIterator[tuple[RtcPeers, SfuPublisher]]:
    """The vehicle's camera (a small synthetic one, sending ``codec``), its WebRTC peers
    for the pilot, and its SFU publisher for the session's room, publishing."""
    task = sfu.sfu_publish_for(session_id=session_id)
    assert task is not None
    async with VideoService(
        SyntheticCamera(320, 240, fps=fps),
        ice_host_addresses=LOOPBACK,
        bitrate=300_000,
        codec=codec,
    ) as video:
        rtc = RtcPeers(_Events(), video=video)
        publisher = SfuPublisher.for_room(video, task)
        job = asyncio.create_task(publisher.run())
        try:
            yield rtc, publisher
        finally:
            job.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await job
            await rtc.close()


def spectator_for(session_id: uuid.UUID, **override: Any) -> Spectator:
    viewer = sfu.sfu_viewer_for(session_id=session_id)
    assert viewer is not None
    return Spectator(
        viewer["url"],
        feed=viewer["feed"],
        token=override.get("token", viewer["token"]),
        room=override.get("room", viewer["room"]),
        pin=override.get("pin", viewer["pin"]),
    )


async def test_spectators_watch_through_the_sfu_and_the_vehicle_sends_one_copy(
    janus: JanusServer,
) -> None:
    session_id = uuid.uuid4()
    assert await asyncio.to_thread(sfu.sfu_room_open, session_id=session_id) is True
    assert await asyncio.to_thread(sfu.sfu_room_open, session_id=session_id) is False
    async with vehicle(session_id) as (rtc, publisher):
        pilot = Pilot(rtc)
        await pilot.connect()
        await asyncio.wait_for(publisher.publishing.wait(), 60)
        await until(lambda: pilot.frames >= 10, within=60, what="the pilot's picture")

        async def window(frames: int) -> tuple[int, int, float]:
            """Bytes the vehicle sent to the pilot and to the SFU while the pilot
            received ``frames`` more frames."""
            p0, s0 = await sent_bytes(to_pilot), await sent_bytes(publisher.pc)
            t0, start = time.monotonic(), pilot.frames
            await until(lambda: pilot.frames >= start + frames, within=120, what="pilot frames")
            p1, s1 = await sent_bytes(to_pilot), await sent_bytes(publisher.pc)
            return p1 - p0, s1 - s0, time.monotonic() - t0

        to_pilot = rtc._peers["pilot"].pc  # the vehicle's side of the pilot's connection
        alone_pilot, alone_sfu, alone_s = await window(30)

        spectators = [spectator_for(session_id) for _ in range(SPECTATORS)]
        started = time.monotonic()
        joining = asyncio.Semaphore(10)

        async def join(spectator: Spectator) -> None:
            async with joining:
                await spectator.watch()

        try:
            await asyncio.gather(*(join(s) for s in spectators))

            async def all_watching() -> bool:
                return all([await s.packets() > 20 for s in spectators])

            await until(all_watching, within=240, what=f"{SPECTATORS} spectators' packets")
            joined_s = time.monotonic() - started
            crowd_pilot, crowd_sfu, crowd_s = await window(30)
            # The pilot never lost its place, and no spectator took one on the vehicle:
            # the pilot's page reloading with the crowd watching is taken at once.
            assert rtc.peer_count == 1 and pilot.pc.connectionState == "connected"
            reloaded = Pilot(rtc, peer_id="pilot-reloaded")
            try:
                await reloaded.connect()
                await until(lambda: reloaded.frames >= 5, within=60, what="the reloaded pilot")
            finally:
                await reloaded.pc.close()
        finally:
            await asyncio.gather(*(s.close() for s in spectators))

    alone = (alone_pilot + alone_sfu) / alone_s
    crowd = (crowd_pilot + crowd_sfu) / crowd_s
    print(
        f"\n{SPECTATORS} spectators joined in {joined_s:.1f} s; vehicle out: "
        f"{alone * 8 / 1000:.0f} kbit/s with none, {crowd * 8 / 1000:.0f} kbit/s with "
        f"{SPECTATORS} (pilot {crowd_pilot / crowd_s * 8 / 1000:.0f}, "
        f"SFU copy {crowd_sfu / crowd_s * 8 / 1000:.0f})"
    )
    # One copy to the SFU however many watch: about one viewer's worth...
    assert crowd_sfu / crowd_s <= 1.2 * crowd_pilot / crowd_s
    # ...and the vehicle sends no more with the crowd than without it.
    assert crowd <= 1.2 * alone


async def test_the_sfu_itself_refuses_whoever_the_platform_did_not_let_in(
    janus: JanusServer, settings: Any
) -> None:
    session_id, other = uuid.uuid4(), uuid.uuid4()
    for room in (session_id, other):
        await asyncio.to_thread(sfu.sfu_room_open, session_id=room)
    async with vehicle(session_id) as (_, publisher):
        await asyncio.wait_for(publisher.publishing.wait(), 60)
        good = spectator_for(session_id)
        try:
            await good.watch()  # the platform's token and pin: in
        finally:
            await good.close()
        settings.IOUV_JANUS_TOKEN_SECRET = "not-the-platform's"
        forged_token = sfu.janus_token(expires_at=time.time() + 600)
        settings.IOUV_JANUS_TOKEN_SECRET = janus.token_secret
        expired = sfu.janus_token(expires_at=time.time() - 1)
        refusals = {
            "no token": ({"token": None}, 403),
            "forged token": ({"token": forged_token}, 403),
            "expired token": ({"token": expired}, 403),
            # A genuine token, but the pin of another session's room (or none).
            "another session's pin": ({"pin": sfu._derived("pin", other)}, 433),
            "no pin": ({"pin": ""}, 433),
        }
        for name, (override, code) in refusals.items():
            spectator = spectator_for(session_id, **override)
            try:
                with pytest.raises(JanusError) as refused:
                    await spectator.watch()
                assert refused.value.code == code, name
            finally:
                await spectator.close()

        # A spectator's token and pin do not let anyone publish into the room.
        viewer = sfu.sfu_viewer_for(session_id=session_id)
        assert viewer is not None
        async with JanusSession(viewer["url"], token=viewer["token"]) as session:
            handle = await session.attach()
            with pytest.raises(JanusError) as refused:
                await handle.request(
                    {
                        "request": "join",
                        "ptype": "publisher",
                        "room": viewer["room"],
                        "pin": viewer["pin"],
                        "id": 7,
                    }
                )
            assert refused.value.code == 433


async def test_when_the_sfu_dies_spectators_are_told_and_the_pilot_flies_on(
    janus: JanusServer,
) -> None:
    session_id = uuid.uuid4()
    await asyncio.to_thread(sfu.sfu_room_open, session_id=session_id)
    async with vehicle(session_id) as (rtc, publisher):
        pilot = Pilot(rtc)
        await pilot.connect()
        await asyncio.wait_for(publisher.publishing.wait(), 60)
        spectators = [spectator_for(session_id) for _ in range(3)]
        try:
            for s in spectators:
                await s.watch()

            async def watching() -> bool:
                return all([await s.packets() > 10 for s in spectators])

            await until(watching, within=60, what="the spectators' packets")
            janus.kill()
            # Their link to the SFU closes: the page says the video is unavailable.
            await until(
                lambda: all(s.janus is not None and s.janus.closed.is_set() for s in spectators),
                within=30,
                what="the spectators to hear the SFU is gone",
            )
            await until(
                lambda: not publisher.publishing.is_set(), within=60, what="the publisher to notice"
            )
            # The pilot's picture goes on, on the same connection.
            frames = pilot.frames
            await until(lambda: pilot.frames >= frames + 30, within=60, what="the pilot's picture")
            assert rtc.peer_count == 1 and pilot.pc.connectionState == "connected"

            # Janus back (a restart loses its rooms; the platform makes it again): the
            # vehicle publishes again by itself.
            janus.start()
            await asyncio.to_thread(sfu.sfu_room_open, session_id=session_id)
            await asyncio.wait_for(publisher.publishing.wait(), 90)
        finally:
            await asyncio.gather(*(s.close() for s in spectators))


@pytest.mark.parametrize("codec", ["vp8", "h264"])
async def test_a_sessions_recording_plays_back_as_long_as_it_was_published(
    janus: JanusServer, codec: str
) -> None:
    """The vehicle publishes its codec (VP8, or H.264: the room takes either); a
    spectator watches it, and the recording converts to a file a browser plays (WebM,
    or MP4 for H.264) that spans what was published."""
    session_id = uuid.uuid4()
    await asyncio.to_thread(sfu.sfu_room_open, session_id=session_id)
    async with vehicle(session_id, fps=15, codec=codec) as (_, publisher):
        await asyncio.wait_for(publisher.publishing.wait(), 60)
        spectator = spectator_for(session_id)
        try:
            await spectator.watch()

            async def watching() -> bool:
                return await spectator.packets() > 20

            await until(watching, within=60, what="the spectator's packets")
        finally:
            await spectator.close()
        # Published while the encoder makes 90 frames (6 s at 15 fps).
        encoder = publisher.video.encoder
        first, started = encoder.frames_encoded, time.monotonic()
        await until(lambda: encoder.frames_encoded >= first + 90, within=120, what="90 frames")
        published_s = time.monotonic() - started
    assert await asyncio.to_thread(sfu.sfu_room_close, session_id=session_id) is True
    recordings = await asyncio.to_thread(sfu.sfu_recording_convert, session_id=session_id)
    assert len(recordings) == 1
    recording = recordings[0]
    assert (recording.path.suffix, recording.content_type) == {
        "vp8": (".webm", "video/webm"),
        "h264": (".mp4", "video/mp4"),
    }[codec]
    assert abs(recording.started_at - time.time()) < 120  # when it was, by the wall clock
    with av.open(str(recording.path)) as container:
        stream = container.streams.video[0]
        frames = list(container.decode(stream))
        base = stream.time_base
        duration = float((frames[-1].pts - frames[0].pts) * base)
    print(f"\npublished {published_s:.1f} s; recording: {len(frames)} frames over {duration:.1f} s")
    assert len(frames) >= 80
    # The recording spans what was published (from joining to leaving: a little more).
    assert published_s - 1.0 <= duration <= published_s + 10.0


async def test_a_session_lives_on_keepalives_until_its_token_runs_out(
    janus: JanusServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Janus checks the token on every request, keepalives included: a link whose token
    ran out is closed (the publisher then connects again with its fresher token)."""
    monkeypatch.setattr(agents_sfu, "KEEPALIVE_S", 0.2)
    lasting = sfu.janus_token(expires_at=time.time() + 600)
    # Janus compares whole seconds: valid for the next 2 to 3 s.
    brief = sfu.janus_token(expires_at=time.time() + 3)
    async with (
        JanusSession(janus.ws_url, token=lasting) as kept,
        JanusSession(janus.ws_url, token=brief) as expiring,
    ):
        await until(lambda: kept.keepalives >= 3, within=30, what="keepalives")
        await until(expiring.closed.is_set, within=30, what="the expired link to close")
        assert expiring.keepalives >= 1  # it lived while its token did
        assert not kept.closed.is_set()
