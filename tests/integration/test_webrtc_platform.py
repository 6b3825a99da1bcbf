"""Control over WebRTC data channels, signalled through the platform, end to end.

Real sockets: the platform (iouv.serve, Postgres, Redis), a car agent on its simulator,
and a user (an aiortc program in place of the browser) that authenticates on the
platform's relay socket, offers a connection there, and once its data channels open
drives the car on them. The vehicle never accepts an inbound connection: the offer and
the answer travel over its uplink.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator

import pytest

from agents.runtime import Agent
from benchmarks.rtc_client import RtcClientError, RtcControlClient
from services.models import Session, SessionEvent
from tests import factories as f
from tests.servers import agent_running, db, platform_process, until
from tests.vehicles import agent_registered, car_served, session_deployed

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
]


@pytest.fixture
async def deployed() -> AsyncIterator[tuple[str, Agent, Session, str]]:
    """A car agent registered on a running platform and a session deployed on it:
    (relay URL, agent, session, the owner's grant)."""
    car, credential, service = await db(
        car_served, "car-rtc", service="drive-car-rtc", features=["camera_arm"]
    )
    with platform_process() as base:
        async with agent_running(
            base=base,
            vehicle=car,
            credential=credential,
            adapter="car",
            options={"camera_arm": True, "origin": [f.HOME[0], f.HOME[1]]},
        ) as agent:
            await agent_registered(car)
            session, task = await session_deployed(agent, service)
            relay_url = f"{base.replace('http', 'ws')}/ws/relay/{session.pk}/"
            yield relay_url, agent, session, task.grant


async def _session(session: Session) -> Session:
    return await db(Session.objects.get, pk=session.pk)


async def test_the_user_drives_on_data_channels_and_keeps_driving_when_the_platform_drops(
    deployed,
):
    relay_url, agent, session, grant = deployed
    assert agent.hub is not None
    async with RtcControlClient(relay_url, grant) as user:
        assert user.welcome["role"] == "controller"
        # Authenticated on the relay first, then the agent moves the user to WebRTC.
        assert await user.path_is("webrtc_direct") == "webrtc_direct"
        assert user.paths[0] == "relay"

        world = agent.adapter.sensors
        start = world.position
        # A held motion on the lossy channel, a stop on the urgent one, a camera move on
        # the ordered one: each is acked on "control".
        assert (await user.command(1, "forward", channel="input", speed=1.0))["ok"] is True
        for _ in range(5):
            user.send({"type": "keepalive"})
            await asyncio.sleep(0.1)
        assert world.position != start
        assert (await user.command(2, "stop", channel="urgent"))["ok"] is True
        assert (await user.command(3, "camera_up", step_deg=10))["ok"] is True

        # The platform records the path on the session, from the agent's report.
        async def recorded() -> bool:
            return (await _session(session)).control_path == "webrtc_direct"

        await until(recorded, what="the session to record the WebRTC path")
        kinds = await db(
            lambda: list(
                SessionEvent.objects.filter(session=session, kind="control_path").values_list(
                    "data", flat=True
                )
            )
        )
        assert [k["path"] for k in kinds][-1] == "webrtc_direct"

        # The platform's socket goes away: the data channel carries on, no fail-safe.
        failsafes = agent.hub.stats["failsafes"]
        await user.close_socket()

        async def relay_gone() -> bool:
            hub = agent.hub
            return hub is not None and all(c.link.signal is None for c in hub.clients.values())

        await until(relay_gone, what="the agent to hear that the relay closed")
        for seq in range(10, 16):
            assert (await user.command(seq, "camera_down", step_deg=1))["ok"] is True
        assert agent.hub.stats["failsafes"] == failsafes
        assert agent.hub.controller is not None

        # Now the WebRTC connection goes too: the last path is gone, the car is made safe.
        assert (await user.command(20, "forward", channel="input", speed=0.5))["ok"] is True
        assert user.pc is not None
        await user.pc.close()

        async def made_safe() -> bool:
            return agent.hub is not None and agent.hub.stats["failsafes"] > failsafes

        await until(made_safe, what="the fail-safe after the last path closed")
        assert agent.hub.controller is None


async def test_a_vehicle_refusing_webrtc_leaves_the_user_on_the_relay(deployed):
    relay_url, agent, _session_row, grant = deployed
    assert agent.hub is not None
    agent.hub.webrtc_options = {"enabled": False}
    user = RtcControlClient(relay_url, grant, timeout_s=10)
    try:
        await user.start(rtc=False)
        assert await user.path_is("relay") == "relay"
        with pytest.raises(RtcClientError, match="does not accept WebRTC"):
            await user.negotiate()
        ack = await user.command(1, "camera_up", channel=None, step_deg=5)
        assert ack["ok"] is True
        assert user.path == "relay"
    finally:
        await user.close()


async def test_commands_that_arrive_too_late_are_dropped_but_a_stop_never_is(deployed):
    relay_url, _agent, _session_row, grant = deployed
    async with RtcControlClient(relay_url, grant) as user:
        await user.path_is("webrtc_direct")
        # The agent pings its controller; the answers (with this side's clock) align
        # the clocks. Wait for a couple of them.
        await user.recv("ping")
        await user.recv("ping")
        old = time.time() * 1000 - 5_000
        user.send({"type": "command", "seq": 7, "name": "forward", "args": {}, "t": old})
        ack = await user.recv("ack", where=lambda m: m.get("seq") == 7)
        assert ack["ok"] is False and ack["code"] == "stale"
        assert "forward" in ack["error"] and "ms ago" in ack["error"]
        user.send(
            {"type": "command", "seq": 8, "name": "stop", "args": {}, "t": old}, channel="urgent"
        )
        assert (await user.recv("ack", where=lambda m: m.get("seq") == 8))["ok"] is True
        # A fresh one still goes through.
        assert (await user.command(9, "camera_up", step_deg=5))["ok"] is True
