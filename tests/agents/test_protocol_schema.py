"""The published JSON Schema of each channel (docs/protocol/schema/): in step with the
code, a valid draft 2020-12 schema, and obeyed by what real components send over real
sockets, checked with a generic validator (``jsonschema``), not with our own parser."""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any

import jsonschema
import msgspec
import pytest
from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve

from agents.protocol import CHANNELS, PROTOCOL_VERSION, ProtocolError, parse_message
from agents.protocol.messages import CommandSpec, Heartbeat, Position, Profile
from agents.protocol.schema import main, schema_path, stale_files
from agents.uplink import Uplink
from tests.agents.car_rig import Rig, make_grant

VALIDATORS = {
    channel: jsonschema.Draft202012Validator(
        json.loads(schema_path(channel).read_text(encoding="utf-8")),
        format_checker=jsonschema.FormatChecker(),
    )
    for channel in CHANNELS
}


def assert_valid(channel: str, frames: list[str]) -> None:
    for frame in frames:
        errors = list(VALIDATORS[channel].iter_errors(json.loads(frame)))
        assert not errors, f"{channel} frame {frame[:200]} breaks the schema: {errors[0]}"


def test_committed_schema_files_match_the_code() -> None:
    assert stale_files() == [], "run: python -m agents.protocol.schema --write"


def test_a_missions_spec_schema_is_written_and_checked_in_its_own_folder(tmp_path) -> None:
    docs, missions = tmp_path / "docs", tmp_path / "missions"
    assert main(["--write", "--dir", str(docs), "--missions-dir", str(missions)]) == 0
    assert main(["--check", "--dir", str(docs), "--missions-dir", str(missions)]) == 0
    parcel = missions / "parcel" / "spec.schema.json"
    assert json.loads(parcel.read_text())["$ref"] == "#/$defs/ParcelSpec"
    parcel.write_text(parcel.read_text().replace('"parcel"', '"parcels"'))
    assert stale_files(docs, missions) == [parcel]
    assert main(["--check", "--dir", str(docs), "--missions-dir", str(missions)]) == 1


@pytest.mark.parametrize("channel", CHANNELS)
def test_schema_files_are_valid_draft_2020_12(channel: str) -> None:
    schema = json.loads(schema_path(channel).read_text(encoding="utf-8"))
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(schema)


# --- refused by parse_message, refused by the schema -------------------------------------

PROFILE = {
    "type": "profile",
    "vehicle_type": "car",
    "adapter": "car",
    "attributes": {},
    "commands": [{"name": "stop", "args": {}}],
    "telemetry": ["speed"],
    "control_url": "ws://car:8765/",
    "video": False,
    "position": None,
    "battery": None,
}

BOTH_REFUSE = [
    ("control_to_agent", {"type": "ping"}),  # missing field
    ("control_to_agent", {"type": "ping", "t": "now"}),  # mistyped
    ("control_to_agent", {"type": "task", "token": "x"}),  # type of another channel
    ("control_to_agent", {"t": 1}),  # no type
    ("control_to_agent", {"type": "command", "seq": -1, "name": "x"}),
    ("control_to_agent", {"type": "command", "seq": 1.5, "name": "x"}),
    ("control_to_agent", {"type": "command", "seq": 1, "name": ""}),
    ("control_to_agent", {"type": "subscribe", "topics": ["a"], "rate_hz": 0}),
    ("control_to_agent", {"type": "subscribe", "topics": ["a"], "rate_hz": 51}),
    ("uplink_to_agent", {"type": "welcome", "v": PROTOCOL_VERSION + 1, "heartbeat_interval_s": 1}),
    ("uplink_to_agent", {"type": "welcome", "v": PROTOCOL_VERSION, "heartbeat_interval_s": 0}),
    ("uplink_to_agent", {"type": "revoke", "session_id": "s", "reason": "r", "action": "dance"}),
    ("uplink_to_agent", {"type": "relay", "session_id": "s", "payload": {"type": "hello"}}),
    ("uplink_to_platform", {"type": "heartbeat", "seq": 1, "battery": 101}),
    ("uplink_to_platform", {"type": "heartbeat", "seq": 1, "position": {"lat": 91, "lon": 0}}),
    ("uplink_to_platform", {"type": "heartbeat", "seq": 1, "telemetry": None}),
    ("uplink_to_platform", {**PROFILE, "control_url": "http://car/"}),
    ("uplink_to_platform", {**PROFILE, "control_url": "\n"}),
    ("uplink_to_platform", {**PROFILE, "safe_actions": {"dance": "a jig"}}),
    ("uplink_to_platform", {**PROFILE, "safe_actions": {"stop": "x" * 161}}),
    ("uplink_to_platform", {**PROFILE, "commands": [{"name": "a", "args": {"x": {}}}]}),
    (
        "uplink_to_platform",
        {**PROFILE, "commands": [{"name": "a", "args": {"x": {"type": "float"}}}]},
    ),
    ("control_to_client", {"type": "ack", "seq": 1, "ok": "yes", "error": None}),
    ("control_to_client", {"type": "role", "role": "pilot"}),
]

# Cross-field rules JSON Schema does not express: parse_message alone refuses these.
PARSER_ONLY = [
    (
        "uplink_to_platform",
        {**PROFILE, "commands": [{"name": "a", "args": {}}, {"name": "a", "args": {}}]},
    ),
    (
        "uplink_to_platform",
        {
            **PROFILE,
            "commands": [{"name": "a", "args": {"x": {"type": "number", "max": 1, "default": 2}}}],
        },
    ),
    (
        "uplink_to_platform",
        {**PROFILE, "commands": [{"name": "a", "args": {"x": {"type": "string", "min": 1}}}]},
    ),
]


@pytest.mark.parametrize("channel, msg", BOTH_REFUSE)
def test_what_the_parser_refuses_the_schema_refuses(channel: str, msg: dict[str, Any]) -> None:
    with pytest.raises(ProtocolError):
        parse_message(json.dumps(msg), channel=channel)  # type: ignore[arg-type]
    assert not VALIDATORS[channel].is_valid(msg)


@pytest.mark.parametrize("channel, msg", PARSER_ONLY)
def test_cross_field_rules_are_the_parsers_alone(channel: str, msg: dict[str, Any]) -> None:
    with pytest.raises(ProtocolError):
        parse_message(json.dumps(msg), channel=channel)  # type: ignore[arg-type]
    assert VALIDATORS[channel].is_valid(msg)


# --- captured from real components over real sockets --------------------------------------


async def test_control_session_frames_obey_the_schemas(rig: Rig) -> None:
    """A user drives the simulated car through the agent's control server; every frame
    in both directions is recorded as it crossed the socket, then validated."""
    sent: list[str] = []
    received: list[str] = []
    async with connect(rig.url, compression=None, proxy=None) as ws:

        async def say(msg: dict[str, Any]) -> None:
            frame = json.dumps(msg)
            sent.append(frame)
            await ws.send(frame)

        async def until(kind: str) -> dict[str, Any]:
            deadline = time.monotonic() + 3
            while True:
                frame = await asyncio.wait_for(ws.recv(), deadline - time.monotonic())
                assert isinstance(frame, str)
                received.append(frame)
                msg = json.loads(frame)
                if msg["type"] == "ping":
                    await say({"type": "pong", "t": msg["t"]})
                if msg["type"] == kind:
                    return msg

        await say({"type": "auth", "grant": make_grant()})
        welcome = await until("welcome")
        await say({"type": "subscribe", "topics": welcome["telemetry"][:3], "rate_hz": 20})
        await until("telemetry")
        await say({"type": "unsubscribe", "topics": []})
        await say({"type": "ping", "t": time.time()})
        await until("pong")
        await say({"type": "command", "seq": 1, "name": "forward", "args": {}})
        await until("ack")
        await say({"type": "command", "seq": 2, "name": "self_destruct"})
        await until("ack")
        await say({"type": "keepalive"})
        await say({"type": "subscribe", "topics": ["no_such_topic"], "rate_hz": 1})
        await until("error")
        await say({"type": "webrtc_offer", "sdp": "v=0\r\n"})  # no media: refused
        await until("error")
        await say({"type": "release_control"})
        await until("role")
        await say({"type": "take_control"})
        await until("role")
        await say({"type": "command", "seq": 3, "name": "stop"})
        await until("ack")
        await say({"type": "subscribe", "topics": ["a"], "rate_hz": 99})  # refused
        await until("error")
    assert {json.loads(f)["type"] for f in received} >= {
        "welcome",
        "telemetry",
        "pong",
        "ack",
        "error",
        "role",
    }
    assert_valid("control_to_agent", sent[:-1])  # the last one is meant to be refused
    assert not VALIDATORS["control_to_agent"].is_valid(json.loads(sent[-1]))
    assert_valid("control_to_client", received)


async def test_uplink_frames_obey_the_schemas(rig: Rig) -> None:
    """The agent's real uplink client against a recording platform: hello, profile
    (the simulated car's real command vocabulary), heartbeats and acks one way,
    welcome and revoke the other."""
    from_agent: list[str] = []
    to_agent: list[str] = []
    acked = asyncio.Event()

    async def platform(ws: ServerConnection) -> None:
        async def say(msg: dict[str, Any]) -> None:
            frame = json.dumps(msg)
            to_agent.append(frame)
            await ws.send(frame)

        async for frame in ws:
            assert isinstance(frame, str)
            from_agent.append(frame)
            kind = json.loads(frame)["type"]
            if kind == "hello":
                await say(
                    {
                        "type": "welcome",
                        "v": PROTOCOL_VERSION,
                        "heartbeat_interval_s": 0.05,
                        "platform_jwks": {"keys": []},
                    }
                )
            elif kind == "profile":
                revoke = {"session_id": "s-1", "reason": "kill switch", "action": "stop"}
                await say({"type": "revoke", **revoke, "id": "m-1"})
            elif kind == "ack":
                acked.set()

    car = rig.car
    state = car.state()

    def profile() -> Profile:
        return Profile(
            vehicle_type="car",
            adapter=car.name,
            attributes={},
            commands=[msgspec.convert(c.to_profile(), CommandSpec) for c in car.commands()],
            telemetry=car.telemetry_topics(),
            control_url=rig.url,
            video=False,
            position=Position(lat=state.lat, lon=state.lon) if state.lat is not None else None,
            battery=state.battery,
            safe_actions=dict(car.safe_action_words),
            session_id=None,
            controller=False,
            status="idle",
        )

    def heartbeat() -> Heartbeat:
        return Heartbeat(seq=0, battery=car.state().battery, status="idle", telemetry={})

    async def on_message(msg: Any) -> None:
        pass

    async with serve(platform, "127.0.0.1", 0) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        uplink = Uplink(
            url=f"ws://127.0.0.1:{port}/",
            vehicle_id="car-test-1",
            credential="c",
            on_message=on_message,
            profile=profile,
            heartbeat=heartbeat,
        )
        run = asyncio.create_task(uplink.run())
        try:
            await asyncio.wait_for(acked.wait(), 5)
            await asyncio.sleep(0.15)  # a few heartbeats
        finally:
            run.cancel()
            with pytest.raises(asyncio.CancelledError):
                await run
    kinds = [json.loads(f)["type"] for f in from_agent]
    assert {"hello", "profile", "heartbeat", "ack"} <= set(kinds)
    assert_valid("uplink_to_platform", from_agent)
    assert_valid("uplink_to_agent", to_agent)
