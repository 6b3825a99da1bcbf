"""The relay between a browser and a vehicle's agent, through the platform's consumers
and the real channel layer (Redis): a relayed command reaches the agent and its answer
the browser; once the agent has answered, the relay and the uplink address each other's
channel directly (no group lookup per command); and the relayed browser keeps driving
when the agent's uplink reconnects."""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import AsyncIterator
from typing import Any

import jwt
import pytest
from channels import DEFAULT_CHANNEL_LAYER
from channels.db import database_sync_to_async
from channels.layers import channel_layers, get_channel_layer
from channels.testing import WebsocketCommunicator
from django.db import connections
from prometheus_client import REGISTRY

from agents.protocol import PROTOCOL_VERSION
from fleet.credentials import vehicle_issue_credential
from iouv.asgi import application
from services.sessions.deployment import grant_issue
from tests import factories as f
from tests.deployment import session_requested

pytestmark = [pytest.mark.redis, pytest.mark.django_db(transaction=True)]

PROFILE: dict[str, Any] = {
    "type": "profile",
    "vehicle_type": "ground",
    "adapter": "sim_car",
    "attributes": {},
    "commands": [{"name": "front", "args": {}}],
    "telemetry": ["battery"],
    "control_url": "",
    "video": False,
    "position": {"lat": 40.63, "lon": -8.65},
    "battery": 88,
}


@pytest.fixture(autouse=True)
async def _fresh_layer_and_connections() -> AsyncIterator[None]:
    # Each test runs in its own event loop; a Redis layer that a consumer of an earlier
    # test's loop was receiving on would refuse this one ("two event loops"), so each
    # test gets its own layer. Sync ORM calls run on asgiref's worker thread; its
    # connection must not outlive the test (it would keep the database from dropping).
    channel_layers.backends.pop(DEFAULT_CHANNEL_LAYER, None)
    yield
    channel_layers.backends.pop(DEFAULT_CHANNEL_LAYER, None)
    await database_sync_to_async(connections.close_all)()


@database_sync_to_async
def _relayed_session() -> tuple[str, str, str, str]:
    """(vehicle id, its credential, session id, the owner's grant) of a deployed session
    on a vehicle reachable only through the relay."""
    vehicle = f.vehicle(station=f.station(), vtype=f.vehicle_type(kind="ground"))
    credential = vehicle_issue_credential(vehicle=vehicle)
    alice = f.user(username="alice")
    service = f.service(allowed_commands=["front"])
    session = session_requested(user=alice, service=service).session
    task = grant_issue(session=session, user=alice)
    return str(vehicle.pk), credential, str(session.pk), task.grant


async def _uplink(vehicle_id: str, credential: str) -> WebsocketCommunicator:
    """The agent's uplink: hello, welcome, profile."""
    comm = WebsocketCommunicator(application, "/ws/agent/")
    connected, _ = await comm.connect()
    assert connected
    hello = {"type": "hello", "v": PROTOCOL_VERSION, "vehicle_id": vehicle_id}
    await comm.send_json_to({**hello, "credential": credential})
    assert (await comm.receive_json_from(timeout=10))["type"] == "welcome"
    await comm.send_json_to(PROFILE)
    return comm


async def _browser(session_id: str) -> WebsocketCommunicator:
    """A browser's socket on the session's relay (not yet authenticated)."""
    browser = WebsocketCommunicator(application, f"/ws/relay/{session_id}/")
    connected, _ = await browser.connect()
    assert connected
    return browser


async def _relayed(agent: WebsocketCommunicator) -> dict[str, Any]:
    """The next relayed frame the agent receives (what else the platform owes it, its
    task, is skipped and acknowledged)."""
    while True:
        message = await agent.receive_json_from(timeout=10)
        if message["type"] == "relay":
            return message
        if "id" in message:
            await agent.send_json_to({"type": "ack", "id": message["id"], "ok": True})


async def _answer(agent: WebsocketCommunicator, relayed: dict[str, Any], seq: int) -> None:
    """The agent acknowledges command ``seq`` to the relayed browser."""
    payload = {"type": "ack", "seq": seq, "ok": True, "error": None}
    await agent.send_json_to(
        {"type": "relay", "session_id": relayed["session_id"], "conn": relayed["conn"]}
        | {"payload": payload}
    )


@contextlib.contextmanager
def _group_sends() -> Any:
    """What the channel layer sends to groups while the block runs: (group, type)."""
    layer = get_channel_layer()
    real = layer.group_send
    groups: list[tuple[str, str]] = []

    async def counted(group: str, message: dict[str, Any]) -> None:
        groups.append((group, message["type"]))
        await real(group, message)

    layer.group_send = counted
    try:
        yield groups
    finally:
        layer.group_send = real


async def _authenticate(
    browser: WebsocketCommunicator, agent: WebsocketCommunicator, grant: str
) -> dict[str, Any]:
    """The browser's grant, checked by the relay and then by the agent, which answers;
    returns the relayed frame (its ``conn`` names the browser's connection)."""
    await browser.send_json_to({"type": "auth", "grant": grant})
    relayed = await _relayed(agent)
    assert relayed["payload"] == {"type": "auth", "grant": grant}
    await _answer(agent, relayed, 0)
    assert json.loads(await browser.receive_from(timeout=10))["seq"] == 0
    return relayed


async def _command(browser: WebsocketCommunicator, agent: WebsocketCommunicator, seq: int) -> None:
    """One relayed command and its ack, end to end."""
    await browser.send_json_to({"type": "command", "seq": seq, "name": "front", "args": {}})
    relayed = await _relayed(agent)
    assert relayed["payload"] == {"type": "command", "seq": seq, "name": "front", "args": {}}
    await _answer(agent, relayed, seq)
    assert json.loads(await browser.receive_from(timeout=10)) == {
        "type": "ack",
        "seq": seq,
        "ok": True,
        "error": None,
    }


async def test_relayed_commands_go_channel_to_channel_and_survive_an_uplink_reconnect() -> None:
    vehicle_id, credential, session_id, grant = await _relayed_session()
    agent = await _uplink(vehicle_id, credential)
    browser = await _browser(session_id)
    try:
        # The grant first: the relay checks it, then the agent does (it answers).
        await _authenticate(browser, agent, grant)

        # From now on each side knows the other's channel: no group lookups.
        with _group_sends() as sends:
            for seq in range(1, 6):
                await _command(browser, agent, seq)
        relay_kinds = {"agent.send", "relay.from_agent"}
        assert not [(g, kind) for g, kind in sends if kind in relay_kinds], sends

        # The agent's uplink drops and comes back: the browser's next command finds it.
        await agent.disconnect()
        agent = await _uplink(vehicle_id, credential)
        await _command(browser, agent, 6)
        await _command(browser, agent, 7)
    finally:
        await browser.disconnect()
        await agent.disconnect()


async def test_a_relay_that_never_heard_the_agent_still_reaches_it() -> None:
    """Before any answer the relay knows no uplink: its frames go by the vehicle's group,
    and a bad frame is refused by the relay itself without reaching the agent."""
    vehicle_id, credential, session_id, grant = await _relayed_session()
    agent = await _uplink(vehicle_id, credential)
    browser = await _browser(session_id)
    try:
        await browser.send_json_to({"type": "auth", "grant": grant})
        await _relayed(agent)
        await browser.send_to(text_data='{"type": "command", "seq": -1}')
        refused = json.loads(await browser.receive_from(timeout=10))
        assert refused["type"] == "error" and refused["code"] == "bad_field"
        await browser.send_json_to({"type": "command", "seq": 1, "name": "front", "args": {}})
        relayed = await _relayed(agent)
        assert relayed["payload"]["seq"] == 1  # the refused frame never reached it
    finally:
        await browser.disconnect()
        await agent.disconnect()


@pytest.mark.parametrize(
    ("agent_code", "browser_code"),
    [(4403, 4403), (1000, 1000), (1005, 4000), (1011, 4000), (70000, 4000), (None, 4000)],
)
async def test_an_agent_dropping_its_relayed_client_closes_the_browser_with_a_code_a_server_sends(
    agent_code: int | None, browser_code: int
) -> None:
    """The agent's close code reaches the browser when a WebSocket server may send it
    (1000, 3000-4999); any other (reserved, out of range, none) becomes 4000, "closed by
    the agent", rather than an error in the relay that would leave the socket open."""
    vehicle_id, credential, session_id, grant = await _relayed_session()
    agent = await _uplink(vehicle_id, credential)
    browser = await _browser(session_id)
    try:
        relayed = await _authenticate(browser, agent, grant)
        dropped = {"type": "relay_close", "session_id": session_id, "conn": relayed["conn"]}
        if agent_code is not None:
            dropped["code"] = agent_code
        await agent.send_json_to(dropped)
        closed = await browser.receive_output(timeout=10)
        assert (closed["type"], closed["code"]) == ("websocket.close", browser_code)
    finally:
        await browser.disconnect()
        await agent.disconnect()


async def test_a_relayed_webrtc_offer_brings_the_agent_turn_credentials_of_its_own(
    settings: Any,
) -> None:
    """The relay is where a WebRTC connection is signalled: an offer reaches the agent
    with the platform's STUN/TURN servers, TURN credentials minted for this session
    (coturn checks them: tests/integration/test_netlab.py) that end with the grant the
    browser authenticated with, not the hour TURN credentials may last; other frames
    carry none."""
    settings.IOUV_STUN_URLS = ["stun:turn.example.org:3478"]
    settings.IOUV_TURN_URLS = ["turn:turn.example.org:3478?transport=udp"]
    settings.IOUV_TURN_SECRET = "coturn-shared-secret"
    settings.IOUV_TURN_TTL_S = 3600
    vehicle_id, credential, session_id, grant = await _relayed_session()
    agent = await _uplink(vehicle_id, credential)
    browser = await _browser(session_id)
    try:
        await browser.send_json_to({"type": "auth", "grant": grant})
        assert "ice_servers" not in await _relayed(agent)
        offer = {"type": "webrtc_offer", "sdp": "v=0\r\n"}
        await browser.send_json_to(offer)
        relayed = await _relayed(agent)
        assert relayed["payload"] == offer
        stun, turn = relayed["ice_servers"]
        assert stun == {"urls": ["stun:turn.example.org:3478"]}
        assert turn["urls"] == ["turn:turn.example.org:3478?transport=udp"]
        expiry, name = turn["username"].split(":")
        assert name == session_id
        grant_exp = jwt.decode(grant, options={"verify_signature": False})["exp"]
        assert time.time() < int(expiry) <= grant_exp
        assert turn["credential"] and turn["credential"] != settings.IOUV_TURN_SECRET
    finally:
        await browser.disconnect()
        await agent.disconnect()


async def test_webrtc_offers_over_the_users_budget_are_refused_and_not_forwarded(
    settings: Any, rate_counters: str
) -> None:
    """Each offer reaches the vehicle (aiortc work, TURN credentials minted): past the
    user's budget (services.web.throttle) the relay answers ``rate_limited`` itself."""
    settings.IOUV_RATE_LIMITS = {"webrtc_offer": {"user": "2/h", "address": "off"}}
    vehicle_id, credential, session_id, grant = await _relayed_session()
    agent = await _uplink(vehicle_id, credential)
    browser = await _browser(session_id)
    try:
        await _authenticate(browser, agent, grant)
        offer = {"type": "webrtc_offer", "sdp": "v=0\r\n"}
        for _ in range(2):
            await browser.send_json_to(offer)
            assert (await _relayed(agent))["payload"] == offer
        await browser.send_json_to(offer)
        refused = await browser.receive_json_from(timeout=10)
        assert refused["type"] == "error" and refused["code"] == "rate_limited"
        assert "WebRTC offers" in refused["message"]
        # Other frames still go through, and the refused offer never reached the agent.
        await browser.send_json_to({"type": "ping", "t": 1})
        assert (await _relayed(agent))["payload"]["type"] == "ping"
    finally:
        await browser.disconnect()
        await agent.disconnect()


async def test_a_relayed_commands_acknowledgement_and_round_trip_are_counted() -> None:
    """What operators watch (services.supervision.metrics): each relayed command the vehicle
    acknowledged, accepted or refused, and the time it took through the platform."""
    counts = _relay_counts()
    vehicle_id, credential, session_id, grant = await _relayed_session()
    agent = await _uplink(vehicle_id, credential)
    browser = await _browser(session_id)
    try:
        relayed = await _authenticate(browser, agent, grant)
        for seq, ok in ((1, True), (2, False)):
            await browser.send_json_to({"type": "command", "seq": seq, "name": "front"})
            await _relayed(agent)
            payload = {"type": "ack", "seq": seq, "ok": ok, "error": None if ok else "no"}
            await agent.send_json_to(
                {"type": "relay", "session_id": session_id, "conn": relayed["conn"]}
                | {"payload": payload}
            )
            assert json.loads(await browser.receive_from(timeout=10))["seq"] == seq
        assert _relay_counts() == (counts[0] + 1, counts[1] + 1, counts[2] + 2)
    finally:
        await browser.disconnect()
        await agent.disconnect()


def _relay_counts() -> tuple[float, float, float]:
    """(commands acknowledged ok, refused, round trips timed) as /metrics reads them."""

    def value(name: str, **labels: str) -> float:
        return REGISTRY.get_sample_value(name, labels) or 0.0

    return (
        value("iouv_relay_commands_acked_total", ok="true"),
        value("iouv_relay_commands_acked_total", ok="false"),
        value("iouv_relay_round_trip_seconds_count"),
    )


async def test_an_authentication_the_vehicle_never_answers_is_closed_to_be_tried_again():
    """The vehicle's uplink is not there (its agent reconnecting after a platform
    process restarted): the relayed authentication is lost on the way, and the browser
    is told to connect again (4503) instead of waiting for ever."""
    _vehicle_id, _credential, session_id, grant = await _relayed_session()
    browser = await _browser(session_id)
    await browser.send_json_to({"type": "auth", "grant": grant})
    error = await browser.receive_json_from(timeout=10)
    assert error["type"] == "error" and error["code"] == "vehicle_unreachable", error
    closed = await browser.receive_output(timeout=10)
    assert closed == {"type": "websocket.close", "code": 4503}
    await browser.disconnect()
