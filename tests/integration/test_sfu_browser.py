"""Spectating through the SFU, end to end: the platform (with a Celery worker) told of
a private Janus (tests.janus), the car's real agent, and Chromium for the pilot and a
spectator. The vehicle task makes the agent publish to its session's room; the
spectator's page watches there, never on the vehicle; when Janus dies the spectator's
page says the video is unavailable and the pilot's video and control go on; when the
session ends the worker closes the room and converts its recording."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import av
import pytest
from playwright.async_api import expect

from services import sfu
from services.models import Session
from services.records.keeping import RecordCheck, record_verify
from services.sessions.ending import session_end
from tests.browser import needs_chromium
from tests.janus import JanusServer, janus_server
from tests.portal import assert_nothing_refused, controller, demo_world, request_car, wait_for
from tests.servers import db

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    pytest.mark.cost(40),  # a platform, its worker, an agent, Janus and Chromium
    needs_chromium,
]


@pytest.fixture
def janus(tmp_path: Path, settings: Any) -> Any:
    with janus_server(tmp_path / "janus") as server:
        for name, value in server.settings().items():
            setattr(settings, name, value)  # the test's own reads (the recording)
        yield server


async def until(cond: Any, *, within: float, what: str) -> None:
    deadline = time.monotonic() + within
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.1)


def _session_end(session_id: str) -> None:
    session = Session.objects.select_related("service", "user").get(pk=session_id)
    session_end(session=session, reason="the pilot is done", by_user=True)


async def test_a_spectator_watches_through_the_sfu_and_hears_when_it_dies(
    tmp_path: Path, janus: JanusServer
) -> None:
    env = {name: str(value) for name, value in janus.settings().items()}
    env["IOUV_JANUS_ROOMS_CHECK_S"] = "1"
    async with demo_world(tmp_path, names=("car-1",), env=env, worker=True) as world:
        agent = world.agents["car-1"]
        driver = await world.login("client")
        session_id = await request_car(world, driver)
        await wait_for(driver, "c.stats.framesDecoded > 3", 30000)
        # The task named the session's room: the car publishes there by itself.
        await until(
            lambda: agent.sfu is not None and agent.sfu.publishing.is_set(),
            within=60,
            what="the car to publish to the SFU",
        )

        spectator = await world.login("client2")
        await spectator.goto(f"{world.base}/spectate/{session_id}/")
        await wait_for(
            spectator,
            "c.role === 'viewer' && c.sfuState === 'watching' && c.stats.framesDecoded > 5",
            45000,
        )
        # Watching costs the vehicle nothing: its one WebRTC peer is the pilot's.
        assert agent.hub is not None and agent.hub.rtc is not None
        assert agent.hub.rtc.peer_count == 1

        # The car's link to the SFU drops (its network, say): the page waits for the
        # car's video and watches again once the car has published again by itself.
        publisher = agent.sfu
        assert publisher is not None and publisher.pc is not None
        attempts = publisher.attempts
        await publisher.pc.close()
        await until(
            lambda: publisher.attempts > attempts and publisher.publishing.is_set(),
            within=60,
            what="the car to publish again",
        )
        frames = await controller(spectator, "c.stats.framesDecoded")
        await wait_for(
            spectator,
            f"c.sfuState === 'watching' && c.stats.framesDecoded > {frames + 10}",
            45000,
        )

        janus.kill()
        await expect(spectator.locator("[data-video-note]")).to_contain_text(
            "Video unavailable", timeout=30000
        )
        # The pilot's picture and control go on.
        frames = await controller(driver, "c.stats.framesDecoded")
        await wait_for(driver, f"c.stats.framesDecoded > {frames + 20}", 30000)
        await driver.keyboard.down("ArrowUp")
        await wait_for(driver, "c.stats.acks > 2", 15000)
        await driver.keyboard.up("ArrowUp")
        await assert_nothing_refused(driver)
        assert await controller(driver, "c.role") == "controller"

        # Janus back, its rooms lost: the worker makes the room again, the car publishes
        # again by itself (and is recorded), and the spectator's page finds it.
        janus.start()
        await until(
            lambda: agent.sfu is not None and agent.sfu.publishing.is_set(),
            within=60,
            what="the car to publish again",
        )
        await spectator.reload()
        await wait_for(spectator, "c.sfuState === 'watching' && c.stats.framesDecoded > 5", 60000)

        await db(_session_end, session_id)

        # The worker closed the room and converted what the SFU recorded: the replay
        # page plays it in step with the track.
        folder = sfu.sfu_recording_dir(session_id)
        assert folder is not None

        def converted() -> bool:
            # Two stretches: before Janus was killed, and after it came back.
            recorded = [m for m in folder.glob("*.mjr") if m.stat().st_size > 8]
            return len(recorded) >= 2 and all(m.with_suffix(".webm").exists() for m in recorded)

        await until(converted, within=120, what="the recordings to be converted")

        # ... and chained each into the session's log: the record's check holds them
        # to their digests.
        def video_checked() -> RecordCheck:
            return record_verify(session=Session.objects.get(pk=session_id))

        deadline = time.monotonic() + 60
        while (check := await db(video_checked)).videos < 2:
            assert time.monotonic() < deadline, f"the videos were not chained: {check}"
            await asyncio.sleep(0.2)
        assert check.ok and check.video_check == "sha256", check.problems
        stretches = []
        for recording in sfu.sfu_recordings(session_id=session_id):
            with av.open(str(recording.path)) as container:
                frames = list(container.decode(video=0))
                base = container.streams.video[0].time_base
                stretches.append((float((frames[-1].pts - frames[0].pts) * base), recording))
        assert all(d > 0.5 for d, _ in stretches), stretches

        await driver.goto(f"{world.base}/sessions/{session_id}/replay/")
        await expect(driver.locator("#replay")).to_have_attribute("data-loaded", "true")
        video = driver.locator("[data-replay-video-file]")
        await expect(video).to_have_count(1)
        # A position recorded well inside a stretch (the one with the most of them).
        times = await driver.evaluate("() => window.IoUVReplay.times()")

        def inside(stretch: tuple[float, sfu.Recording]) -> list[tuple[int, float]]:
            length, recording = stretch
            start = recording.started_at
            return [(i, t) for i, t in enumerate(times) if start + 0.5 < t < start + length - 0.5]

        recorded_s, last = max(stretches, key=lambda d: len(inside(d)))
        during = inside((recorded_s, last))
        assert during, (times[:3], times[-3:], stretches)
        index, at = during[len(during) // 2]
        await driver.evaluate(
            """(i) => { const s = document.querySelector('[data-replay-slider]');
                        s.value = String(i); s.dispatchEvent(new Event('input')); }""",
            index,
        )
        await driver.wait_for_function(
            """(want) => { const v = document.querySelector('[data-replay-video-file]');
                           return v.readyState >= 1 && Math.abs(v.currentTime - want) < 0.25; }""",
            arg=at - last.started_at,
            timeout=30000,
        )
        duration = await video.evaluate("(v) => v.duration")
        assert abs(duration - recorded_s) < 1.5, (duration, recorded_s)
