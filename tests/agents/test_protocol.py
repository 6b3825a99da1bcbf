"""Behaviour tests for agents.protocol: signed documents, replay, messages, arguments."""

from __future__ import annotations

import base64
import contextlib
import copy
import json
import math
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agents import protocol
from agents.protocol import (
    CLOCK_SKEW_S,
    MAX_MESSAGE_BYTES,
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    ExpiredError,
    Limits,
    ProtocolError,
    ReplayError,
    ReplayGuard,
    SignatureError,
    UserGrant,
    VehicleTask,
    WrongTargetError,
    documents,
    encode_message,
    error_message,
    generate_keypair,
    load_private_key,
    load_public_key,
    new_nonce,
    parse_message,
    sign_document,
    validate_command_args,
    verify_document,
)

NOW = 1_700_000_000.0

PRIVATE_PEM, PUBLIC_PEM = generate_keypair()
PRIVATE = load_private_key(PRIVATE_PEM)
PUBLIC = load_public_key(PUBLIC_PEM)
OTHER_PRIVATE = load_private_key(generate_keypair()[0])


def make_task(**overrides: Any) -> VehicleTask:
    values: dict[str, Any] = {
        "session_id": "s-1",
        "vehicle_id": "car-7",
        "user": "alice",
        "allowed_commands": ("drive", "stop"),
        "limits": Limits(
            max_speed_mps=3.0,
            geofence_center=(43.7, 7.25),
            geofence_radius_m=200.0,
            link_loss_timeout_ms=800,
            failsafe_action="stop",
            latency_soft_ms=150,
            latency_hard_ms=400,
            session_time_limit_s=600,
        ),
        "issued_at": NOW,
        "expires_at": NOW + 60,
        "mission": {"waypoints": [[43.7, 7.25, 10], [43.71, 7.26, 10]]},
    }
    values.update(overrides)
    return VehicleTask(**values)


def make_grant(**overrides: Any) -> UserGrant:
    values: dict[str, Any] = {
        "session_id": "s-1",
        "vehicle_id": "car-7",
        "user": "alice",
        "role": "controller",
        "allowed_commands": ("drive", "stop"),
        "issued_at": NOW,
        "expires_at": NOW + 60,
    }
    values.update(overrides)
    return UserGrant(**values)


# ---------------------------------------------------------------------------------------
# Keys
# ---------------------------------------------------------------------------------------


def test_keypair_is_pem_and_loads() -> None:
    private_pem, public_pem = generate_keypair()
    assert private_pem.startswith("-----BEGIN PRIVATE KEY-----")
    assert public_pem.startswith("-----BEGIN PUBLIC KEY-----")
    key = load_private_key(private_pem)
    assert load_public_key(public_pem).public_bytes_raw() == key.public_key().public_bytes_raw()


@pytest.mark.parametrize("text", ["", "not a key", PUBLIC_PEM])
def test_load_private_key_refuses_garbage(text: str) -> None:
    with pytest.raises(ProtocolError) as info:
        load_private_key(text)
    assert info.value.code == "bad_key"


@pytest.mark.parametrize("text", ["", "not a key", PRIVATE_PEM])
def test_load_public_key_refuses_garbage(text: str) -> None:
    with pytest.raises(ProtocolError) as info:
        load_public_key(text)
    assert info.value.code == "bad_key"


# ---------------------------------------------------------------------------------------
# Signed documents
# ---------------------------------------------------------------------------------------


def test_task_round_trip() -> None:
    task = make_task()
    token = task.sign(PRIVATE)
    assert VehicleTask.verify(token, PUBLIC, vehicle_id="car-7", now=NOW) == task


def test_grant_round_trip() -> None:
    grant = make_grant(role="viewer", allowed_commands=())
    token = grant.sign(PRIVATE)
    assert UserGrant.verify(token, PUBLIC, vehicle_id="car-7", now=NOW) == grant


def test_token_format_is_two_unpadded_base64url_parts_over_canonical_json() -> None:
    token = make_grant().sign(PRIVATE)
    body, sig = token.split(".")
    assert "=" not in token
    raw = documents._b64url_decode(body, "payload")
    payload = json.loads(raw)
    assert raw == json.dumps(payload, sort_keys=True, separators=(",", ":")).encode()
    assert payload["kind"] == "user_grant" and payload["v"] == PROTOCOL_VERSION
    assert len(documents._b64url_decode(sig, "signature")) == 64
    # Same payload, same token: signing is deterministic.
    assert make_grant(nonce="n").sign(PRIVATE) == make_grant(nonce="n").sign(PRIVATE)


def test_signature_from_other_key_refused() -> None:
    token = make_task().sign(OTHER_PRIVATE)
    with pytest.raises(SignatureError) as info:
        VehicleTask.verify(token, PUBLIC, vehicle_id="car-7", now=NOW)
    assert info.value.code == "bad_signature"


def test_tampered_payload_refused() -> None:
    token = make_task().sign(PRIVATE)
    body, sig = token.split(".")
    payload = json.loads(documents._b64url_decode(body, "payload"))
    payload["limits"]["max_speed_mps"] = 50.0
    forged_body = documents._b64url_encode(documents._canonical_json(payload))
    with pytest.raises(SignatureError):
        VehicleTask.verify(f"{forged_body}.{sig}", PUBLIC, vehicle_id="car-7", now=NOW)


def test_expired_refused_but_skew_tolerated() -> None:
    token = make_task().sign(PRIVATE)
    expires = NOW + 60
    assert VehicleTask.verify(token, PUBLIC, vehicle_id="car-7", now=expires + CLOCK_SKEW_S)
    with pytest.raises(ExpiredError) as info:
        VehicleTask.verify(token, PUBLIC, vehicle_id="car-7", now=expires + CLOCK_SKEW_S + 0.01)
    assert info.value.code == "expired"


def test_signature_checked_before_expiry() -> None:
    token = make_task().sign(OTHER_PRIVATE)
    with pytest.raises(SignatureError):
        verify_document(token, PUBLIC, now=NOW + 10_000)


def test_grant_presented_as_task_refused_and_vice_versa() -> None:
    grant_token = make_grant().sign(PRIVATE)
    task_token = make_task().sign(PRIVATE)
    with pytest.raises(ProtocolError) as info:
        VehicleTask.verify(grant_token, PUBLIC, vehicle_id="car-7", now=NOW)
    assert info.value.code == "wrong_kind"
    with pytest.raises(ProtocolError) as info:
        UserGrant.verify(task_token, PUBLIC, vehicle_id="car-7", now=NOW)
    assert info.value.code == "wrong_kind"
    with pytest.raises(ProtocolError) as info:
        verify_document(grant_token, PUBLIC, kind="vehicle_task", now=NOW)
    assert info.value.code == "wrong_kind"
    # Without a kind the caller gets the payload and decides.
    assert verify_document(grant_token, PUBLIC, now=NOW)["kind"] == "user_grant"


def test_other_vehicle_refused() -> None:
    for token, cls in (
        (make_task().sign(PRIVATE), VehicleTask),
        (make_grant().sign(PRIVATE), UserGrant),
    ):
        with pytest.raises(WrongTargetError) as info:
            cls.verify(token, PUBLIC, vehicle_id="boat-1", now=NOW)
        assert info.value.code == "wrong_vehicle"


@pytest.mark.parametrize(
    "payload, code",
    [
        ({"kind": "user_grant", "exp": NOW + 5}, "bad_version"),
        ({"v": 2, "kind": "user_grant", "exp": NOW + 5}, "bad_version"),
        ({"v": 1, "kind": "coffee", "exp": NOW + 5}, "bad_field"),
        ({"v": 1, "kind": "user_grant"}, "bad_field"),
        ({"v": 1, "kind": "user_grant", "exp": math.inf}, "bad_field"),
        ({"v": 1, "kind": "user_grant", "exp": "tomorrow"}, "bad_field"),
        ({"v": 1, "kind": "user_grant", "exp": NOW, "x": {1, 2}}, "bad_field"),
    ],
)
def test_sign_document_refuses_bad_headers(payload: dict[str, Any], code: str) -> None:
    with pytest.raises(ProtocolError) as info:
        sign_document(payload, PRIVATE)
    assert info.value.code == code


def test_verify_refuses_other_version_even_if_signed() -> None:
    body = documents._canonical_json({"v": 2, "kind": "user_grant", "exp": NOW + 5})
    token = documents._b64url_encode(body) + "." + documents._b64url_encode(PRIVATE.sign(body))
    with pytest.raises(ProtocolError) as info:
        verify_document(token, PUBLIC, now=NOW)
    assert info.value.code == "bad_version"


def test_signed_unknown_field_refused_fail_closed() -> None:
    payload = make_task().to_payload()
    payload["limits"]["max_depth_m"] = 5
    token = sign_document(payload, PRIVATE)
    with pytest.raises(ProtocolError) as info:
        VehicleTask.verify(token, PUBLIC, vehicle_id="car-7", now=NOW)
    assert info.value.field == "limits.max_depth_m"


@pytest.mark.parametrize(
    "token",
    ["", ".", "a.b.c", "abc", "!!!.???", "YQ.YQ", "YQ==.YQ", "Y.Y", "YR.YQ", 12, None],
)
def test_malformed_tokens_refused(token: Any) -> None:
    with pytest.raises(ProtocolError) as info:
        verify_document(token, PUBLIC, now=NOW)
    assert info.value.code in {"bad_token", "bad_signature"}


def test_huge_token_refused() -> None:
    with pytest.raises(ProtocolError) as info:
        verify_document("A" * (MAX_MESSAGE_BYTES + 1), PUBLIC, now=NOW)
    assert info.value.code == "bad_token"


def test_non_canonical_base64_spelling_refused() -> None:
    token = make_grant().sign(PRIVATE)
    body, sig = token.split(".")
    # Flip the unused low bits of the last signature character: same bytes, other spelling.
    alphabet = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_"
    last = alphabet.index(sig[-1])
    variant = sig[:-1] + alphabet[last ^ 1]
    pad = "=" * (-len(sig) % 4)
    assert base64.urlsafe_b64decode(variant + pad) == base64.urlsafe_b64decode(sig + pad)
    with pytest.raises(ProtocolError) as info:
        verify_document(f"{body}.{variant}", PUBLIC, now=NOW)
    assert info.value.code == "bad_token"


# ---------------------------------------------------------------------------------------
# Dataclass validation
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"max_altitude_m": -1}, "limits.max_altitude_m"),
        ({"max_speed_mps": math.nan}, "limits.max_speed_mps"),
        ({"max_speed_mps": True}, "limits.max_speed_mps"),
        ({"geofence_center": (91, 0), "geofence_radius_m": 10}, "limits.geofence_center[0]"),
        ({"geofence_center": (0, 181), "geofence_radius_m": 10}, "limits.geofence_center[1]"),
        ({"geofence_center": (1, 2, 3), "geofence_radius_m": 10}, "limits.geofence_center"),
        ({"geofence_center": (1, 2)}, "limits.geofence_center"),
        ({"geofence_radius_m": 0}, "limits.geofence_radius_m"),
        ({"link_loss_timeout_ms": 49}, "limits.link_loss_timeout_ms"),
        ({"link_loss_timeout_ms": 60_001}, "limits.link_loss_timeout_ms"),
        ({"link_loss_timeout_ms": 500.0}, "limits.link_loss_timeout_ms"),
        ({"failsafe_action": "explode"}, "limits.failsafe_action"),
        ({"latency_soft_ms": 500, "latency_hard_ms": 100}, "limits.latency_soft_ms"),
        ({"latency_hard_ms": 0}, "limits.latency_hard_ms"),
        ({"session_time_limit_s": -5}, "limits.session_time_limit_s"),
    ],
)
def test_limits_refuse_bad_values_naming_field(kwargs: dict[str, Any], field: str) -> None:
    with pytest.raises(ProtocolError) as info:
        Limits(**kwargs)
    assert info.value.code == "bad_field"
    assert info.value.field == field
    assert field in str(info.value)


def test_limits_defaults_and_payload_round_trip() -> None:
    limits = Limits()
    assert limits.link_loss_timeout_ms == 500 and limits.failsafe_action == "stop"
    full = make_task().limits
    payload = json.loads(json.dumps(full.to_payload()))
    assert payload["geofence_center"] == [43.7, 7.25]
    assert Limits.from_payload(payload) == full
    assert Limits.from_payload({}) == Limits()


def test_limits_from_payload_refuses_unknown_and_non_object() -> None:
    with pytest.raises(ProtocolError) as info:
        Limits.from_payload({"max_warp": 9})
    assert info.value.field == "limits.max_warp"
    with pytest.raises(ProtocolError):
        Limits.from_payload([1, 2])


@pytest.mark.parametrize(
    "overrides, field",
    [
        ({"session_id": ""}, "session_id"),
        ({"vehicle_id": 7}, "vehicle_id"),
        ({"allowed_commands": ("drive", "")}, "allowed_commands[1]"),
        ({"allowed_commands": "drive"}, "allowed_commands"),
        ({"expires_at": NOW - 1}, "exp"),
        ({"issued_at": math.nan}, "iat"),
        ({"nonce": ""}, "nonce"),
        ({"mission": [1, 2]}, "mission"),
        ({"mission": {"x": math.inf}}, "mission"),
        ({"limits": {"max_speed_mps": 1}}, "limits"),
    ],
)
def test_task_refuses_bad_fields(overrides: dict[str, Any], field: str) -> None:
    with pytest.raises(ProtocolError) as info:
        make_task(**overrides)
    assert info.value.field == field


def test_grant_refuses_bad_role() -> None:
    with pytest.raises(ProtocolError) as info:
        make_grant(role="pilot")
    assert info.value.field == "role"


def test_task_from_payload_reports_missing_field() -> None:
    payload = make_task().to_payload()
    del payload["user"]
    with pytest.raises(ProtocolError) as info:
        VehicleTask.from_payload(payload)
    assert info.value.field == "user"


def test_nonces_are_fresh() -> None:
    assert len({new_nonce() for _ in range(100)}) == 100
    assert make_task().nonce != make_task().nonce


# ---------------------------------------------------------------------------------------
# Replay
# ---------------------------------------------------------------------------------------


def test_replay_refused_then_pruned_after_expiry() -> None:
    guard = ReplayGuard()
    guard.check_and_remember("n1", NOW + 10, now=NOW)
    with pytest.raises(ReplayError) as info:
        guard.check_and_remember("n1", NOW + 10, now=NOW + 5)
    assert info.value.code == "replayed"
    # Once the document could no longer pass the expiry check, the nonce is forgotten.
    guard.check_and_remember("n2", NOW + 100, now=NOW + 10 + CLOCK_SKEW_S + 1)
    assert "n1" not in guard
    assert len(guard) == 1


def test_replay_guard_with_verify_consumes_grant_once() -> None:
    guard = ReplayGuard()
    token = make_grant().sign(PRIVATE)
    UserGrant.verify(token, PUBLIC, vehicle_id="car-7", now=NOW, replay_guard=guard)
    with pytest.raises(ReplayError):
        UserGrant.verify(token, PUBLIC, vehicle_id="car-7", now=NOW + 1, replay_guard=guard)
    # A fresh grant for the reconnect is accepted.
    fresh = make_grant().sign(PRIVATE)
    UserGrant.verify(fresh, PUBLIC, vehicle_id="car-7", now=NOW + 1, replay_guard=guard)


def test_refused_document_does_not_burn_nonce() -> None:
    guard = ReplayGuard()
    task = make_task()
    with pytest.raises(WrongTargetError):
        VehicleTask.verify(task.sign(PRIVATE), PUBLIC, vehicle_id="x", now=NOW, replay_guard=guard)
    assert len(guard) == 0


def test_replay_guard_cap_evicts_oldest() -> None:
    guard = ReplayGuard(max_entries=3)
    for i in range(5):
        guard.check_and_remember(f"n{i}", NOW + 1000, now=NOW)
    assert len(guard) == 3
    assert "n0" not in guard and "n1" not in guard and "n4" in guard
    with pytest.raises(ReplayError):
        guard.check_and_remember("n4", NOW + 1000, now=NOW)
    # Many evictions never let the internal heap grow without bound.
    for i in range(100):
        guard.check_and_remember(f"m{i}", NOW + 1000, now=NOW)
    assert len(guard._heap) <= 2 * 3 + 1


# ---------------------------------------------------------------------------------------
# Messages
# ---------------------------------------------------------------------------------------

COMMAND_SPEC: dict[str, Any] = {
    "name": "drive",
    "args": {
        "throttle": {"type": "number", "min": -1, "max": 1, "default": 0},
        "steer": {"type": "number", "min": -1, "max": 1, "unit": "rad"},
        "gear": {"type": "integer", "min": 1, "max": 5, "default": 1},
        "lights": {"type": "boolean", "default": False},
        "mode": {"type": "string", "default": "manual"},
    },
    "description": "Drive the car",
    "group": "motion",
}

# Minimal examples: exactly the required fields of each message type.
MINIMAL: dict[str, dict[str, dict[str, Any]]] = {
    "uplink_to_platform": {
        "hello": {"v": 1, "vehicle_id": "car-7", "credential": "secret"},
        "profile": {
            "vehicle_type": "car",
            "adapter": "sim_car",
            "attributes": {"camera": True},
            "commands": [COMMAND_SPEC, {"name": "stop", "args": {}}],
            "telemetry": ["position", "speed"],
            "control_url": "ws://10.0.0.7:8765/control",
            "video": True,
            "position": {"lat": 43.7, "lon": 7.25, "alt": 0},
            "battery": 87.5,
        },
        "heartbeat": {"seq": 3},
        "task_accepted": {"session_id": "s-1"},
        "task_refused": {"code": "busy", "reason": "already running s-0"},
        "ack": {"id": "0b1c5e2e-4d7f-4a8e-9f0a-3c2b1a0d9e8f", "ok": True},
        "event": {"session_id": None, "event": "failsafe", "data": {}},
        "relay": {
            "session_id": "s-1",
            "payload": {"type": "ack", "seq": 1, "ok": True, "error": None},
        },
        "relay_close": {"session_id": "s", "conn": "c-1"},
    },
    "uplink_to_agent": {
        "welcome": {"v": 1, "heartbeat_interval_s": 5},
        "task": {"token": "abc.def"},
        "revoke": {"session_id": "s-1", "reason": "kill switch", "action": "land"},
        "end_task": {"session_id": "s-1", "reason": "user ended"},
        "relay": {
            "session_id": "s-1",
            "payload": {"type": "command", "seq": 1, "name": "stop"},
        },
        "relay_close": {"session_id": "s", "conn": "c-1"},
        "error": {"code": "bad_credential", "message": "unknown vehicle"},
    },
    "control_to_agent": {
        "auth": {"grant": "abc.def"},
        "command": {"seq": 0, "name": "stop"},
        "subscribe": {"topics": ["position"], "rate_hz": 10},
        "unsubscribe": {"topics": ["position"]},
        "ping": {"t": 12.5},
        "pong": {"t": 99.0},
        "keepalive": {},
        "take_control": {},
        "release_control": {},
        "webrtc_offer": {"sdp": "v=0..."},
        "webrtc_request": {},
        "webrtc_answer": {"sdp": "v=0..."},
    },
    "control_to_client": {
        "welcome": {
            "role": "viewer",
            "vehicle": {"id": "car-7"},
            "commands": [COMMAND_SPEC],
            "telemetry": ["speed"],
        },
        "ack": {"seq": 4, "ok": False, "error": "not allowed"},
        "telemetry": {"t": 1.5, "data": {"speed": 1.2}},
        "pong": {"t": 1.5, "server_t": 1.6},
        "ping": {"t": 99.0},
        "event": {"event": "role_changed", "data": {}},
        "webrtc_offer": {"sdp": "v=0..."},
        "webrtc_answer": {"sdp": "v=0..."},
        "error": {"code": "bad_json", "message": "nope"},
        "role": {"role": "controller"},
    },
}

# Examples using the optional fields too.
FULL: list[tuple[str, str, dict[str, Any]]] = [
    (
        "uplink_to_platform",
        "heartbeat",
        {
            "seq": 4,
            "position": {"lat": 1, "lon": 2},
            "battery": None,
            "status": "idle",
            "telemetry": {"speed": 0},
        },
    ),
    ("uplink_to_platform", "task_refused", {"session_id": None, "code": "c", "reason": ""}),
    ("uplink_to_platform", "ack", {"id": "m-1", "ok": False, "detail": "handler failed"}),
    (
        "uplink_to_platform",
        "profile",
        {
            **MINIMAL["uplink_to_platform"]["profile"],
            "session_id": "s-1",
            "controller": True,
            "status": "in_service",
            "safe_actions": {"stop": "stop where it is", "land": "land where it is"},
        },
    ),
    ("uplink_to_agent", "revoke", {**MINIMAL["uplink_to_agent"]["revoke"], "id": "m-2"}),
    (
        "uplink_to_platform",
        "profile",
        {
            **MINIMAL["uplink_to_platform"]["profile"],
            "position": None,
            "battery": None,
            "control_url": "",
        },
    ),
    (
        "uplink_to_platform",
        "relay",
        {
            "session_id": "s",
            "conn": "c-2",
            "payload": {"type": "telemetry", "t": 1, "data": {}},
        },
    ),
    (
        "uplink_to_agent",
        "welcome",
        {
            "v": 1,
            "heartbeat_interval_s": 2.5,
            "platform_public_key": PUBLIC_PEM,
        },
    ),
    ("control_to_agent", "command", {"seq": 9, "name": "drive", "args": {"steer": 0.1}}),
    ("control_to_client", "ack", {"seq": 4, "ok": True, "error": None, "code": None}),
    ("control_to_client", "error", {"code": "x", "message": "y", "seq": 3}),
]

MINIMAL_CASES = [
    (channel, msg_type, fields)
    for channel, types in MINIMAL.items()
    for msg_type, fields in types.items()
]


def test_examples_cover_every_message_type() -> None:
    assert {c: set(t) for c, t in MINIMAL.items()} == {c: set(t) for c, t in MESSAGE_TYPES.items()}


@pytest.mark.parametrize("channel, msg_type, fields", MINIMAL_CASES)
def test_good_message_parses(channel: Any, msg_type: str, fields: dict[str, Any]) -> None:
    msg = {"type": msg_type, **fields}
    parsed = parse_message(json.dumps(msg), channel=channel)
    assert parsed["type"] == msg_type
    for key in fields:
        assert key in parsed
    # Bytes are accepted too, and encode_message round-trips with validation.
    assert parse_message(json.dumps(msg).encode(), channel=channel) == parsed
    assert parse_message(encode_message(msg, channel=channel), channel=channel) == parsed


@pytest.mark.parametrize("channel, msg_type, fields", FULL)
def test_optional_fields_parse(channel: Any, msg_type: str, fields: dict[str, Any]) -> None:
    parsed = parse_message(json.dumps({"type": msg_type, **fields}), channel=channel)
    for key, value in fields.items():
        if key != "payload":
            assert parsed[key] == value


MISSING_CASES = [
    (channel, msg_type, fields, name)
    for channel, msg_type, fields in MINIMAL_CASES
    for name in fields
]


@pytest.mark.parametrize("channel, msg_type, fields, name", MISSING_CASES)
def test_missing_field_is_named(
    channel: Any, msg_type: str, fields: dict[str, Any], name: str
) -> None:
    msg = {"type": msg_type, **fields}
    del msg[name]
    with pytest.raises(ProtocolError) as info:
        parse_message(json.dumps(msg), channel=channel)
    assert info.value.code == "bad_field"
    assert info.value.field == name
    assert f"'{name}'" in str(info.value)


@pytest.mark.parametrize("channel, msg_type, fields, name", MISSING_CASES)
def test_mistyped_field_is_named(
    channel: Any, msg_type: str, fields: dict[str, Any], name: str
) -> None:
    msg = {"type": msg_type, **fields}
    # A list holding a list is the wrong type for every field of every message.
    msg[name] = [[]]
    with pytest.raises(ProtocolError) as info:
        parse_message(json.dumps(msg), channel=channel)
    assert info.value.code in {"bad_field", "bad_version"}
    assert info.value.field is not None and info.value.field.startswith(name)
    assert name in str(info.value)


@pytest.mark.parametrize(
    "channel, msg, field",
    [
        ("control_to_agent", {"type": "command", "seq": -1, "name": "x"}, "seq"),
        ("control_to_agent", {"type": "command", "seq": True, "name": "x"}, "seq"),
        ("control_to_agent", {"type": "command", "seq": 1.0, "name": "x"}, "seq"),
        ("control_to_agent", {"type": "command", "seq": 1, "name": "x", "args": []}, "args"),
        ("control_to_agent", {"type": "subscribe", "topics": ["a"], "rate_hz": 0}, "rate_hz"),
        ("control_to_agent", {"type": "subscribe", "topics": ["a"], "rate_hz": 51}, "rate_hz"),
        ("control_to_agent", {"type": "subscribe", "topics": [""], "rate_hz": 1}, "topics[0]"),
        ("control_to_agent", {"type": "ping", "t": "now"}, "t"),
        (
            "uplink_to_agent",
            {"type": "revoke", "session_id": "s", "reason": "r", "action": "dance"},
            "action",
        ),
        (
            "uplink_to_agent",
            {"type": "welcome", "v": 1, "heartbeat_interval_s": 0},
            "heartbeat_interval_s",
        ),
        ("uplink_to_platform", {"type": "heartbeat", "seq": 1, "battery": 101}, "battery"),
        (
            "uplink_to_platform",
            {"type": "heartbeat", "seq": 1, "position": {"lat": 1}},
            "position.lon",
        ),
        (
            "uplink_to_platform",
            {"type": "heartbeat", "seq": 1, "position": {"lat": 95, "lon": 0}},
            "position.lat",
        ),
        (
            "uplink_to_platform",
            {
                **MINIMAL["uplink_to_platform"]["profile"],
                "type": "profile",
                "control_url": "http://x",
            },
            "control_url",
        ),
        (
            "uplink_to_platform",
            {
                **MINIMAL["uplink_to_platform"]["profile"],
                "type": "profile",
                "safe_actions": {"dance": "dance a jig"},
            },
            "safe_actions.dance",
        ),
        (
            "uplink_to_platform",
            {
                **MINIMAL["uplink_to_platform"]["profile"],
                "type": "profile",
                "safe_actions": {"stop": "x" * 161},
            },
            "safe_actions.stop",
        ),
        (
            "uplink_to_platform",
            {
                **MINIMAL["uplink_to_platform"]["profile"],
                "type": "profile",
                "safe_actions": {"land": 3},
            },
            "safe_actions.land",
        ),
        (
            "uplink_to_platform",
            {
                **MINIMAL["uplink_to_platform"]["profile"],
                "type": "profile",
                "commands": [{"name": "a", "args": {}}, {"name": "a", "args": {}}],
            },
            "commands[1].name",
        ),
        (
            "uplink_to_platform",
            {
                **MINIMAL["uplink_to_platform"]["profile"],
                "type": "profile",
                "commands": [{"name": "a", "args": {"x": {"type": "float"}}}],
            },
            "commands[0].args.x.type",
        ),
        (
            "uplink_to_platform",
            {
                **MINIMAL["uplink_to_platform"]["profile"],
                "type": "profile",
                "commands": [
                    {"name": "a", "args": {"x": {"type": "number", "max": 1, "default": 2}}}
                ],
            },
            "commands[0].args.x.default",
        ),
        (
            "uplink_to_platform",
            {
                **MINIMAL["uplink_to_platform"]["profile"],
                "type": "profile",
                "commands": [{"name": "a", "args": {"x": {"type": "string", "min": 1}}}],
            },
            "commands[0].args.x.min",
        ),
        (
            "uplink_to_platform",
            {
                "type": "relay",
                "session_id": "s",
                "payload": {"type": "ack", "seq": 1, "ok": "yes", "error": None},
            },
            "payload.ok",
        ),
        (
            "control_to_client",
            {"type": "welcome", "role": "pilot", "vehicle": {}, "commands": [], "telemetry": []},
            "role",
        ),
    ],
)
def test_bad_values_are_named(channel: Any, msg: dict[str, Any], field: str) -> None:
    with pytest.raises(ProtocolError) as info:
        parse_message(json.dumps(msg), channel=channel)
    assert info.value.code == "bad_field"
    assert info.value.field == field
    assert f"'{field}'" in str(info.value)


def test_command_args_default_to_empty_object() -> None:
    parsed = parse_message('{"type":"command","seq":1,"name":"stop"}', channel="control_to_agent")
    assert parsed["args"] == {}
    parsed["args"]["x"] = 1
    again = parse_message('{"type":"command","seq":2,"name":"stop"}', channel="control_to_agent")
    assert again["args"] == {}


def test_unknown_fields_are_kept_and_ignored() -> None:
    parsed = parse_message('{"type":"ping","t":1,"future":true}', channel="control_to_agent")
    assert parsed == {"type": "ping", "t": 1, "future": True}


def test_hello_of_other_version_refused() -> None:
    msg = {"type": "hello", "v": 2, "vehicle_id": "car-7", "credential": "c"}
    with pytest.raises(ProtocolError) as info:
        parse_message(json.dumps(msg), channel="uplink_to_platform")
    assert info.value.code == "bad_version"


@pytest.mark.parametrize(
    "channel, msg_type",
    [
        ("control_to_agent", "task"),  # exists on another channel only
        ("uplink_to_agent", "command"),
        ("control_to_client", "hello"),
        ("uplink_to_platform", "nope"),
    ],
)
def test_unknown_type_for_channel_refused(channel: Any, msg_type: str) -> None:
    with pytest.raises(ProtocolError) as info:
        parse_message(json.dumps({"type": msg_type}), channel=channel)
    assert info.value.code == "unknown_type"


@pytest.mark.parametrize("raw", ['{"t":1}', '{"type":5}', '{"type":null}'])
def test_missing_or_non_string_type_refused(raw: str) -> None:
    with pytest.raises(ProtocolError) as info:
        parse_message(raw, channel="control_to_agent")
    assert info.value.code == "unknown_type"


def test_relay_payload_must_be_an_object() -> None:
    msg = {"type": "relay", "session_id": "s", "payload": "ping"}
    with pytest.raises(ProtocolError) as info:
        parse_message(json.dumps(msg), channel="uplink_to_agent")
    assert info.value.field == "payload"


def test_oversized_message_refused() -> None:
    big = json.dumps({"type": "ping", "t": 1, "pad": "x" * MAX_MESSAGE_BYTES})
    for raw in (big, big.encode()):
        with pytest.raises(ProtocolError) as info:
            parse_message(raw, channel="control_to_agent")
        assert info.value.code == "too_large"
    # Multi-byte characters count as bytes, not characters.
    wide = json.dumps({"type": "ping", "t": 1, "pad": "é" * 40_000}, ensure_ascii=False)
    assert len(wide) < MAX_MESSAGE_BYTES < len(wide.encode())
    with pytest.raises(ProtocolError) as info:
        parse_message(wide, channel="control_to_agent")
    assert info.value.code == "too_large"


@pytest.mark.parametrize(
    "raw",
    [
        b"\xff\xfe\x00garbage",
        b"\x80",
        "not json",
        "",
        '{"type":"ping","t":NaN}',
        '{"type":"ping","t":Infinity}',
        "[" * 30_000 + "]" * 30_000,
        "\ud800",
    ],
)
def test_garbage_refused_as_bad_json(raw: str | bytes) -> None:
    with pytest.raises(ProtocolError) as info:
        parse_message(raw, channel="control_to_agent")
    assert info.value.code == "bad_json"


@pytest.mark.parametrize("raw", ["[]", "1", '"ping"', "null", "true"])
def test_non_object_refused(raw: str) -> None:
    with pytest.raises(ProtocolError) as info:
        parse_message(raw, channel="control_to_agent")
    assert info.value.code == "bad_json"


def test_huge_number_does_not_escape_as_other_exception() -> None:
    raw = '{"type":"ping","t":1e999}'  # parses as inf
    with pytest.raises(ProtocolError) as info:
        parse_message(raw, channel="control_to_agent")
    assert info.value.field == "t"


def test_encode_message_refuses_bad_input() -> None:
    with pytest.raises(ProtocolError):
        encode_message({"t": 1})
    with pytest.raises(ProtocolError):
        encode_message({"type": "ping", "t": math.nan})
    with pytest.raises(ProtocolError) as info:
        encode_message({"type": "ping", "pad": "x" * MAX_MESSAGE_BYTES})
    assert info.value.code == "too_large"
    with pytest.raises(ProtocolError) as info:
        encode_message({"type": "ping"}, channel="control_to_agent")
    assert info.value.field == "t"


def test_error_message_shape() -> None:
    assert error_message("bad_json", "oops") == {
        "type": "error",
        "code": "bad_json",
        "message": "oops",
    }
    msg = error_message("bad_args", "argument 'x'", seq=7)
    assert parse_message(encode_message(msg), channel="control_to_client")["seq"] == 7
    assert parse_message(encode_message(error_message("a", "b")), channel="uplink_to_agent")


def test_protocol_error_code_reaches_error_message() -> None:
    try:
        parse_message("{", channel="control_to_agent")
    except ProtocolError as exc:
        msg = error_message(exc.code, str(exc))
    assert msg["code"] == "bad_json" and msg["message"]


# ---------------------------------------------------------------------------------------
# Command arguments
# ---------------------------------------------------------------------------------------

ARGS = COMMAND_SPEC["args"]


def test_args_defaults_filled() -> None:
    assert validate_command_args(ARGS, {"steer": 0.5}) == {
        "throttle": 0,
        "steer": 0.5,
        "gear": 1,
        "lights": False,
        "mode": "manual",
    }
    assert validate_command_args({}, {}) == {}


def test_args_do_not_mutate_input() -> None:
    sent = {"steer": 0.5}
    spec = copy.deepcopy(ARGS)
    validate_command_args(spec, sent)
    assert sent == {"steer": 0.5} and spec == ARGS


@pytest.mark.parametrize(
    "args, name",
    [
        ({"steer": 0, "warp": 9}, "warp"),  # unknown
        ({}, "steer"),  # required, no default
        ({"steer": True}, "steer"),  # bool is not a number
        ({"steer": "0.5"}, "steer"),
        ({"steer": math.nan}, "steer"),
        ({"steer": math.inf}, "steer"),
        ({"steer": 1.01}, "steer"),  # above max
        ({"steer": -1.01}, "steer"),  # below min
        ({"steer": 0, "gear": 2.5}, "gear"),  # integer refuses fractions
        ({"steer": 0, "gear": True}, "gear"),
        ({"steer": 0, "gear": 6}, "gear"),
        ({"steer": 0, "lights": 1}, "lights"),
        ({"steer": 0, "mode": 3}, "mode"),
    ],
)
def test_bad_args_refused_naming_argument(args: dict[str, Any], name: str) -> None:
    with pytest.raises(ProtocolError) as info:
        validate_command_args(ARGS, args)
    assert info.value.code == "bad_args"
    assert f"'{name}'" in str(info.value)


def test_args_bounds_are_inclusive() -> None:
    out = validate_command_args(ARGS, {"steer": -1, "throttle": 1, "gear": 5})
    assert out["steer"] == -1 and out["throttle"] == 1 and out["gear"] == 5


# ---------------------------------------------------------------------------------------
# Fuzzing: hostile input only ever raises ProtocolError
# ---------------------------------------------------------------------------------------

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=20,
)

ALL_TYPES = sorted({t for types in MESSAGE_TYPES.values() for t in types})
FIELD_NAMES = sorted(
    {name for types in MINIMAL.values() for fields in types.values() for name in fields}
)
messages = st.builds(
    lambda msg_type, fields: {**fields, "type": msg_type},
    st.sampled_from(ALL_TYPES),
    st.dictionaries(st.sampled_from(FIELD_NAMES), json_values, max_size=8),
)
channels = st.sampled_from(protocol.CHANNELS)
FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@FUZZ
@given(raw=st.text() | st.binary(), channel=channels)
def test_fuzz_parse_message_raw(raw: str | bytes, channel: Any) -> None:
    with contextlib.suppress(ProtocolError):
        parse_message(raw, channel=channel)


@FUZZ
@given(msg=messages, channel=channels)
def test_fuzz_parse_message_structured(msg: dict[str, Any], channel: Any) -> None:
    try:
        parsed = parse_message(json.dumps(msg), channel=channel)
    except ProtocolError:
        return
    assert parsed["type"] in MESSAGE_TYPES[channel]


arg_specs = st.dictionaries(
    st.sampled_from(["type", "min", "max", "default", "unit", "description"]),
    st.sampled_from(["number", "integer", "boolean", "string", 0, -1.5, 2, True, "m"])
    | json_values,
    max_size=5,
)
command_specs = st.dictionaries(
    st.sampled_from(["name", "args", "description", "group"]),
    st.sampled_from(["drive", "stop", ""])
    | st.dictionaries(st.text(max_size=4), arg_specs | json_values, max_size=3)
    | json_values,
    max_size=4,
)


@FUZZ
@given(commands=st.lists(command_specs | json_values, max_size=4))
def test_fuzz_profile_commands(commands: list[Any]) -> None:
    msg = {
        "type": "welcome",
        "role": "viewer",
        "vehicle": {},
        "telemetry": [],
        "commands": commands,
    }
    try:
        parse_message(json.dumps(msg), channel="control_to_client")
    except ProtocolError as exc:
        if exc.code != "bad_json":  # the strategy can emit Infinity, which is not JSON
            assert exc.field is not None and exc.field.startswith("commands")


@FUZZ
@given(token=st.text() | st.from_regex(r"[A-Za-z0-9_-]{0,120}\.[A-Za-z0-9_-]{0,120}"))
def test_fuzz_verify_document_text(token: str) -> None:
    with pytest.raises(ProtocolError):
        verify_document(token, PUBLIC, now=NOW)


@FUZZ
@given(body=st.binary(max_size=200))
def test_fuzz_verify_document_validly_signed_garbage(body: bytes) -> None:
    # Past the signature check the payload is trusted bytes; a platform bug there must
    # still surface as ProtocolError, never as a crash in the agent.
    token = documents._b64url_encode(body) + "." + documents._b64url_encode(PRIVATE.sign(body))
    with contextlib.suppress(ProtocolError):
        verify_document(token, PUBLIC, now=NOW)


@FUZZ
@given(
    extra=st.dictionaries(
        st.sampled_from(sorted(VehicleTask._FIELDS | UserGrant._FIELDS)),
        json_values,
        max_size=6,
    ),
    base=st.sampled_from(["task", "grant"]),
)
def test_fuzz_signed_document_fields(extra: dict[str, Any], base: str) -> None:
    payload = (make_task() if base == "task" else make_grant()).to_payload()
    payload.update(extra)
    body = json.dumps(payload, sort_keys=True).encode()
    token = documents._b64url_encode(body) + "." + documents._b64url_encode(PRIVATE.sign(body))
    for cls in (VehicleTask, UserGrant):
        with contextlib.suppress(ProtocolError):
            cls.verify(token, PUBLIC, vehicle_id="car-7", now=NOW, replay_guard=ReplayGuard())


@FUZZ
@given(position=st.integers(min_value=0, max_value=200), char=st.sampled_from("A_-.x="))
def test_fuzz_mutated_token_never_verifies(position: int, char: str) -> None:
    token = make_grant(nonce="fixed").sign(PRIVATE)
    index = position % len(token)
    mutated = token[:index] + char + token[index + 1 :]
    if mutated == token:
        return
    try:
        verify_document(mutated, PUBLIC, now=NOW)
    except ProtocolError:
        return
    pytest.fail(f"mutated token verified: {mutated}")


@FUZZ
@given(args=st.dictionaries(st.sampled_from([*ARGS, "other"]), json_values, max_size=5))
def test_fuzz_validate_command_args(args: dict[str, Any]) -> None:
    try:
        out = validate_command_args(ARGS, args)
    except ProtocolError as exc:
        assert exc.code == "bad_args"
        return
    assert set(out) == set(ARGS)
