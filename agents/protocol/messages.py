"""The JSON messages of the four WebSocket channels, and command arguments."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any, Final

from agents.protocol.base import (
    MAX_MESSAGE_BYTES,
    Channel,
    Checker,
    ProtocolError,
    _bad,
    _bad_arg,
    _check_action,
    _check_arg_value,
    _check_battery,
    _check_bool,
    _check_commands,
    _check_control_url,
    _check_id,
    _check_id_list,
    _check_int,
    _check_number,
    _check_object,
    _check_position,
    _check_positive_number,
    _check_rate_hz,
    _check_role,
    _check_safe_actions,
    _check_str,
    _check_uint,
    _check_version,
)


def _nullable(checker: Checker) -> Checker:
    def check(value: Any, path: str) -> Any:
        return None if value is None else checker(value, path)

    return check


def _relay_payload(channel: Channel) -> Checker:
    # A relayed payload is an ordinary control message; validate it as one so the relay
    # path cannot carry anything the direct path would refuse.
    def check(value: Any, path: str) -> dict[str, Any]:
        return _validate_message(value, channel, prefix=f"{path}.")

    return check


# Type names used in the message table below.
_TYPES: Final[dict[str, Checker]] = {
    "str": _check_str,
    "id": _check_id,
    "int": _check_int,
    "uint": _check_uint,
    "number": _check_number,
    "positive_number": _check_positive_number,
    "bool": _check_bool,
    "object": _check_object,
    "list[id]": _check_id_list,
    "version": _check_version,
    "position": _check_position,
    "battery": _check_battery,
    "action": _check_action,
    "safe_actions": _check_safe_actions,
    "role": _check_role,
    "rate_hz": _check_rate_hz,
    "control_url": _check_control_url,
    "commands": _check_commands,
    "relay_to_agent": _relay_payload("control_to_agent"),
    "relay_to_client": _relay_payload("control_to_client"),
}

# --------------------------------------------------------------------------------------
# Message table
#
# channel -> message type -> field -> type name. A trailing "?" marks an optional field,
# a "|null" suffix allows JSON null. Fields not listed are ignored, so a newer peer can add
# optional fields without breaking an older one (see docs/protocol.md, "Versioning").
# --------------------------------------------------------------------------------------

_SCHEMAS: Final[dict[str, dict[str, dict[str, str]]]] = {
    "uplink_to_platform": {
        "hello": {"v": "version", "vehicle_id": "id", "credential": "id"},
        "profile": {
            "vehicle_type": "id",
            "adapter": "id",
            "attributes": "object",
            "commands": "commands",
            "telemetry": "list[id]",
            "control_url": "control_url",
            "video": "bool",
            "position": "position|null",
            "battery": "battery|null",
            # What each fail-safe action does to this vehicle, in words the platform
            # shows before a user ends a session or a monitor stops it.
            "safe_actions": "safe_actions?",
            # What the agent is doing as it (re)registers, so the platform can converge
            # it: the session of the task it runs, whether a user controls it, and its
            # status word (as in heartbeats).
            "session_id": "id|null?",
            "controller": "bool?",
            "status": "str?",
        },
        "heartbeat": {
            "seq": "uint",
            "position": "position|null?",
            "battery": "battery|null?",
            "status": "str?",
            "telemetry": "object?",
        },
        "task_accepted": {"session_id": "id"},
        "task_refused": {"session_id": "id|null?", "code": "id", "reason": "str"},
        # The agent handled the platform message carrying this id (see "Delivery").
        "ack": {"id": "id", "ok": "bool", "detail": "str?"},
        "event": {"session_id": "id|null", "event": "id", "data": "object"},
        "relay": {"session_id": "id", "conn": "id?", "payload": "relay_to_client"},
        # The agent dropped a relayed client (bad grant, revoked, flooding).
        "relay_close": {"session_id": "id", "conn": "id", "code": "uint?", "reason": "str?"},
    },
    "uplink_to_agent": {
        "welcome": {
            "v": "version",
            "heartbeat_interval_s": "positive_number",
            "platform_public_key": "str?",
            # The platform's signing keys as a JWKS (RFC 7517): during a key rotation it
            # holds both keys, so a task signed with either verifies on the agent.
            "platform_jwks": "object?",
        },
        # These three carry an id and are sent again until the agent acknowledges it.
        "task": {"token": "id", "id": "id?"},
        "revoke": {"session_id": "id", "reason": "str", "action": "action", "id": "id?"},
        "end_task": {"session_id": "id", "reason": "str", "id": "id?"},
        "relay": {"session_id": "id", "conn": "id?", "payload": "relay_to_agent"},
        # The relayed browser went away: for the agent, that client's socket closed.
        "relay_close": {"session_id": "id", "conn": "id", "code": "uint?", "reason": "str?"},
        "error": {"code": "id", "message": "str"},
    },
    "control_to_agent": {
        "auth": {"grant": "id"},
        "command": {"seq": "uint", "name": "id", "args": "object?"},
        "subscribe": {"topics": "list[id]", "rate_hz": "rate_hz"},
        "unsubscribe": {"topics": "list[id]"},
        "ping": {"t": "number"},
        # Answer to the agent's ping: lets the agent measure latency for its limits.
        "pong": {"t": "number"},
        "keepalive": {},
        "take_control": {},
        "release_control": {},
        "webrtc_request": {},
        "webrtc_offer": {"sdp": "str"},
        "webrtc_answer": {"sdp": "str"},
    },
    "control_to_client": {
        "welcome": {
            "role": "role",
            "vehicle": "object",
            "commands": "commands",
            "telemetry": "list[id]",
            # How to show each topic: {topic: {label, unit?, decimals?, yes?, no?}}.
            "telemetry_info": "object?",
        },
        "ack": {"seq": "uint", "ok": "bool", "error": "str|null", "code": "str|null?"},
        "telemetry": {"t": "number", "data": "object"},
        "pong": {"t": "number", "server_t": "number"},
        "ping": {"t": "number"},
        "event": {"event": "id", "data": "object"},
        "webrtc_offer": {"sdp": "str"},
        "webrtc_answer": {"sdp": "str"},
        "error": {"code": "id", "message": "str", "seq": "uint?"},
        "role": {"role": "role"},
    },
}

# Values filled in by parse_message when an optional field is absent.
_DEFAULTS: Final[dict[tuple[str, str], dict[str, Any]]] = {
    ("control_to_agent", "command"): {"args": {}},
}

#: channel -> the message types it accepts (read-only view of the table, for docs and tests).
MESSAGE_TYPES: Final[dict[str, frozenset[str]]] = {
    channel: frozenset(types) for channel, types in _SCHEMAS.items()
}


def _resolve(type_spec: str) -> tuple[Checker, bool]:
    """Turn ``"position|null?"`` into (checker, optional)."""
    optional = type_spec.endswith("?")
    name = type_spec.removesuffix("?")
    if name.endswith("|null"):
        return _nullable(_TYPES[name.removesuffix("|null")]), optional
    return _TYPES[name], optional


# Resolved once at import so a typo in the table fails loudly at start-up, not mid-session.
_COMPILED: Final[dict[str, dict[str, dict[str, tuple[Checker, bool]]]]] = {
    channel: {
        msg_type: {name: _resolve(spec) for name, spec in fields.items()}
        for msg_type, fields in types.items()
    }
    for channel, types in _SCHEMAS.items()
}

# --------------------------------------------------------------------------------------
# Messages
# --------------------------------------------------------------------------------------


def _reject_constant(name: str) -> Any:
    # NaN and Infinity are not JSON; Python's json accepts them unless told otherwise.
    raise ValueError(f"{name} is not valid JSON")


def _loads(text: str) -> Any:
    """Parse JSON strictly. Raises ValueError or RecursionError on bad input."""
    return json.loads(text, parse_constant=_reject_constant)


def _validate_message(msg: Any, channel: Channel, *, prefix: str = "") -> dict[str, Any]:
    if not isinstance(msg, dict):
        if prefix:  # a nested message (relay payload) is a field of the outer one
            raise _bad(prefix.rstrip("."), "must be a message object")
        raise ProtocolError("bad_json", "message must be a JSON object")
    types = _COMPILED.get(channel)
    if types is None:
        # A caller bug, not peer input: fail like any other misuse of the API.
        raise ValueError(f"unknown channel {channel!r}")
    msg_type = msg.get("type")
    if not isinstance(msg_type, str) or msg_type not in types:
        raise ProtocolError(
            "unknown_type",
            f"{prefix}type {msg_type!r} is not a known {channel} message type",
            field=f"{prefix}type",
        )
    out = dict(msg)
    for name, default in _DEFAULTS.get((channel, msg_type), {}).items():
        if name not in out:
            # Copy so a caller mutating the result never alters the shared default.
            out[name] = json.loads(json.dumps(default))
    for name, (checker, optional) in types[msg_type].items():
        if name not in out:
            if optional:
                continue
            path = f"{prefix}{name}"
            raise ProtocolError(
                "bad_field", f"{msg_type} message: field '{path}' is missing", field=path
            )
        try:
            out[name] = checker(out[name], f"{prefix}{name}")
        except ProtocolError as exc:
            # Name the message type too: the same field name exists in several types.
            if exc.message.startswith(f"{msg_type} message: "):
                raise
            raise ProtocolError(
                exc.code, f"{msg_type} message: {exc.message}", field=exc.field
            ) from None
    return out


def parse_message(raw: str | bytes, *, channel: Channel) -> dict[str, Any]:
    """Decode and validate one WebSocket message received on ``channel``.

    Returns the message as a dict: validated fields normalised, absent optional fields with
    a default filled in (``command.args`` -> ``{}``), unknown fields kept untouched.
    A relayed ``payload`` is validated as a message of the matching control channel.

    Raises ProtocolError with code ``too_large`` (over :data:`MAX_MESSAGE_BYTES`),
    ``bad_json`` (not UTF-8, not JSON, not an object), ``unknown_type`` (type not
    accepted on this channel), ``bad_field`` (missing or mistyped field, named in the
    message) or ``bad_version`` (a ``hello``/``welcome`` of another protocol version).
    Raises ValueError only if ``channel`` itself is not one of :data:`CHANNELS`.
    """
    if isinstance(raw, str):
        # A character is at least one UTF-8 byte: cheap early refusal before encoding.
        if len(raw) > MAX_MESSAGE_BYTES:
            raise ProtocolError("too_large", f"message exceeds {MAX_MESSAGE_BYTES} bytes")
        try:
            size = len(raw.encode("utf-8"))
        except UnicodeEncodeError:  # lone surrogates
            raise ProtocolError("bad_json", "message is not valid UTF-8 text") from None
        text = raw
    elif isinstance(raw, bytes):
        size = len(raw)
        text = ""
    else:
        raise ProtocolError("bad_json", "message must be text or bytes")
    if size > MAX_MESSAGE_BYTES:
        raise ProtocolError("too_large", f"message exceeds {MAX_MESSAGE_BYTES} bytes")
    if isinstance(raw, bytes):
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise ProtocolError("bad_json", "message is not valid UTF-8 text") from None
    try:
        msg = _loads(text)
    except (ValueError, RecursionError) as exc:
        # RecursionError: deeply nested arrays fit easily in 64 KiB.
        raise ProtocolError("bad_json", f"message is not valid JSON: {exc}") from None
    return _validate_message(msg, channel)


def encode_message(msg: Mapping[str, Any], *, channel: Channel | None = None) -> str:
    """Serialise ``msg`` to the JSON text sent on the wire.

    With ``channel`` the message is first validated exactly as the receiver will, so a bug
    on the sending side shows up where it happens.

    Returns compact JSON text. Raises ProtocolError: ``bad_field`` if ``msg`` is not
    JSON-serialisable (including NaN/inf) or lacks a string ``type``, ``too_large`` if
    the result exceeds :data:`MAX_MESSAGE_BYTES`, and any :func:`parse_message` code when
    ``channel`` is given and the message would be refused.
    """
    if not isinstance(msg, Mapping) or not isinstance(msg.get("type"), str):
        raise ProtocolError("bad_field", "message needs a string field 'type'", field="type")
    try:
        text = json.dumps(dict(msg), separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError, RecursionError) as exc:
        raise ProtocolError("bad_field", f"message is not JSON-serialisable: {exc}") from None
    # ensure_ascii (json's default) keeps the text ASCII, so characters == bytes.
    if len(text) > MAX_MESSAGE_BYTES:
        raise ProtocolError("too_large", f"message exceeds {MAX_MESSAGE_BYTES} bytes")
    if channel is not None:
        _validate_message(_loads(text), channel)
    return text


def error_message(code: str, message: str, *, seq: int | None = None) -> dict[str, Any]:
    """Build an ``error`` message (both the uplink and the control channel use this shape).

    ``seq`` names the command being answered, when there is one. Returns the dict; it
    raises nothing.
    """
    msg: dict[str, Any] = {"type": "error", "code": code, "message": message}
    if seq is not None:
        msg["seq"] = seq
    return msg


# --------------------------------------------------------------------------------------
# Command arguments
# --------------------------------------------------------------------------------------


def validate_command_args(spec: Mapping[str, Any], args: Mapping[str, Any]) -> dict[str, Any]:
    """Check a command's arguments against its declaration.

    ``spec`` is the ``args`` object of one command in the vehicle profile: argument name ->
    ``{type, min?, max?, default?, unit?}``. ``args`` is what the client sent.

    Returns a new dict with every declared argument: the sent value, or the declared
    default. Raises ProtocolError with code ``bad_args`` naming the argument when an
    argument is unknown, missing without a default, of the wrong type (a boolean is not a
    number, an integer argument refuses 1.5), NaN/infinite, or outside ``min``/``max``
    (inclusive).
    """
    if not isinstance(spec, Mapping):
        raise ProtocolError("bad_args", "command declaration 'args' must be an object")
    if not isinstance(args, Mapping):
        raise ProtocolError("bad_args", "args must be an object", field="args")
    for name in args:
        if name not in spec:
            raise _bad_arg(str(name), "is not declared for this command")
    out: dict[str, Any] = {}
    for name, arg_spec in spec.items():
        if not isinstance(arg_spec, Mapping):
            raise _bad_arg(str(name), "has a malformed declaration")
        if name in args:
            out[name] = _check_arg_value(arg_spec, args[name], name)
        elif "default" in arg_spec:
            out[name] = arg_spec["default"]
        else:
            raise _bad_arg(name, "is required")
    return out
