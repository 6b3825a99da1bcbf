"""Wire protocol shared by the IoUV platform and the vehicle agent.

This module is the only code the Django platform and the vehicle agent have in common, so it
imports nothing but the standard library and ``cryptography``: the agent runs on small
companion computers without Django.

It provides:

* signed documents (the *vehicle task* and the *user grant*) in a compact token format,
  signed with the platform's Ed25519 private key and verified offline by the agent, which
  holds only the public key;
* :class:`ReplayGuard`, which makes each document nonce single-use;
* parsing and validation of the JSON messages of the four WebSocket channels;
* validation of command arguments against a vehicle's declared command vocabulary.

Every refusal is a :class:`ProtocolError` (or a subclass) carrying a short machine ``code``
and a message naming the offending field, so callers can answer the peer with
:func:`error_message` without inspecting exception types. ``docs/protocol.md`` describes the
protocol for people integrating vehicles and writing clients.
"""

from __future__ import annotations

import base64
import binascii
import heapq
import json
import math
import re
import secrets
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Final, Literal, TypeAlias

from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)

__all__ = [
    "ARG_TYPES",
    "CHANNELS",
    "CLOCK_SKEW_S",
    "DEFAULT_LINK_LOSS_TIMEOUT_MS",
    "FAILSAFE_ACTIONS",
    "KINDS",
    "MAX_MESSAGE_BYTES",
    "MESSAGE_TYPES",
    "PROTOCOL_VERSION",
    "REPLAY_GUARD_MAX_ENTRIES",
    "ROLES",
    "Channel",
    "ExpiredError",
    "Kind",
    "Limits",
    "ProtocolError",
    "ReplayError",
    "ReplayGuard",
    "SignatureError",
    "UserGrant",
    "VehicleTask",
    "WrongTargetError",
    "encode_message",
    "error_message",
    "generate_keypair",
    "load_private_key",
    "load_public_key",
    "new_nonce",
    "parse_message",
    "sign_document",
    "validate_command_args",
    "verify_document",
]

# --------------------------------------------------------------------------------------
# Constants
# --------------------------------------------------------------------------------------

#: Version of the wire protocol. It changes only for incompatible changes (see
#: docs/protocol.md, "Versioning"); both ends refuse a peer or a document of another version.
PROTOCOL_VERSION: Final = 1

#: Largest accepted WebSocket message (UTF-8 bytes). Bounds the work a peer can cause.
MAX_MESSAGE_BYTES: Final = 64 * 1024

#: Tolerated clock difference between platform and agent when checking document expiry.
#: Small on purpose: documents are short-lived and both ends are expected to run NTP.
CLOCK_SKEW_S: Final = 2.0

#: Default time without any message from the controlling user before the agent performs
#: the fail-safe action.
DEFAULT_LINK_LOSS_TIMEOUT_MS: Final = 500

#: Default bound on the number of nonces a :class:`ReplayGuard` remembers.
REPLAY_GUARD_MAX_ENTRIES: Final = 100_000

Kind: TypeAlias = Literal["vehicle_task", "user_grant"]
Channel: TypeAlias = Literal[
    "uplink_to_platform", "uplink_to_agent", "control_to_agent", "control_to_client"
]

KINDS: Final[frozenset[str]] = frozenset({"vehicle_task", "user_grant"})
CHANNELS: Final[tuple[str, ...]] = (
    "uplink_to_platform",
    "uplink_to_agent",
    "control_to_agent",
    "control_to_client",
)
FAILSAFE_ACTIONS: Final[frozenset[str]] = frozenset({"stop", "land", "return_to_home"})
ROLES: Final[frozenset[str]] = frozenset({"controller", "viewer"})
ARG_TYPES: Final[frozenset[str]] = frozenset({"number", "integer", "boolean", "string"})

# Ed25519 signatures are always 64 bytes; anything else cannot verify, so refuse it early.
_SIGNATURE_BYTES: Final = 64

# A token travels inside a message, so it can never legitimately be larger than one.
_MAX_TOKEN_CHARS: Final = MAX_MESSAGE_BYTES

_LINK_LOSS_RANGE_MS: Final = (50, 60_000)

# --------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------


class ProtocolError(Exception):
    """A message, document or argument was refused.

    ``code`` is a short machine-readable reason (``bad_json``, ``too_large``,
    ``unknown_type``, ``bad_field``, ``bad_version``, ``bad_token``, ``wrong_kind``,
    ``bad_args``, ``bad_key`` and the subclass codes); ``message`` is for humans and names
    the offending field; ``field`` is that field's path (``"limits.max_speed_mps"``,
    ``"commands[2].name"``) when one is to blame, else ``None``.
    """

    def __init__(self, code: str, message: str, *, field: str | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.field = field

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.code!r}, {self.message!r})"


class SignatureError(ProtocolError):
    """The document's signature is missing, malformed or not made by the platform key."""

    def __init__(self, message: str) -> None:
        super().__init__("bad_signature", message)


class ExpiredError(ProtocolError):
    """The document's ``exp`` is in the past (beyond :data:`CLOCK_SKEW_S`)."""

    def __init__(self, message: str) -> None:
        super().__init__("expired", message, field="exp")


class ReplayError(ProtocolError):
    """The document's nonce was already used while the document is still valid."""

    def __init__(self, message: str) -> None:
        super().__init__("replayed", message, field="nonce")


class WrongTargetError(ProtocolError):
    """The document is valid but addressed to another vehicle."""

    def __init__(self, message: str) -> None:
        super().__init__("wrong_vehicle", message, field="vehicle_id")


def _bad(path: str, problem: str, code: str = "bad_field") -> ProtocolError:
    return ProtocolError(code, f"field '{path}' {problem}", field=path)


# --------------------------------------------------------------------------------------
# Field checkers
#
# Each checker takes (value, path) and returns the (possibly normalised) value or raises
# ProtocolError naming ``path``. They are shared by the message table and the dataclasses
# so a rule is written once.
# --------------------------------------------------------------------------------------

Checker: TypeAlias = Callable[[Any, str], Any]


def _is_number(value: Any) -> bool:
    # bool is an int subclass in Python but never a number on the wire; ints need no
    # finiteness check (and math.isfinite would overflow on huge ones).
    if isinstance(value, bool):
        return False
    if isinstance(value, int):
        return True
    return isinstance(value, float) and math.isfinite(value)


def _check_str(value: Any, path: str) -> str:
    if not isinstance(value, str):
        raise _bad(path, "must be a string")
    return value


def _check_id(value: Any, path: str) -> str:
    if not isinstance(value, str) or not value:
        raise _bad(path, "must be a non-empty string")
    return value


def _check_int(value: Any, path: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _bad(path, "must be an integer")
    return value


def _check_uint(value: Any, path: str) -> int:
    if _check_int(value, path) < 0:
        raise _bad(path, "must be an integer >= 0")
    return int(value)


def _check_number(value: Any, path: str) -> int | float:
    if not _is_number(value):
        raise _bad(path, "must be a finite number")
    return value  # type: ignore[no-any-return]


def _check_positive_number(value: Any, path: str) -> int | float:
    if _check_number(value, path) <= 0:
        raise _bad(path, "must be a number > 0")
    return value  # type: ignore[no-any-return]


def _check_bool(value: Any, path: str) -> bool:
    if not isinstance(value, bool):
        raise _bad(path, "must be a boolean")
    return value


def _check_object(value: Any, path: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise _bad(path, "must be an object")
    return value


def _check_id_list(value: Any, path: str) -> list[str]:
    if not isinstance(value, list):
        raise _bad(path, "must be a list of strings")
    for i, item in enumerate(value):
        _check_id(item, f"{path}[{i}]")
    return value


def _check_version(value: Any, path: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _bad(path, "must be an integer", code="bad_version")
    if value != PROTOCOL_VERSION:
        raise _bad(path, f"is {value}, this end speaks {PROTOCOL_VERSION}", code="bad_version")
    return value


# Unix seconds: anything beyond this is a bug, and it keeps float conversion from overflowing.
_MAX_TIMESTAMP: Final = 1e12


def _check_timestamp(value: Any, path: str) -> float:
    if not _is_number(value) or not -_MAX_TIMESTAMP <= value <= _MAX_TIMESTAMP:
        raise _bad(path, "must be a time in Unix seconds")
    return float(value)


def _check_lat(value: Any, path: str) -> float:
    if not _is_number(value) or not -90 <= value <= 90:
        raise _bad(path, "must be a latitude in degrees, -90..90")
    return float(value)


def _check_lon(value: Any, path: str) -> float:
    if not _is_number(value) or not -180 <= value <= 180:
        raise _bad(path, "must be a longitude in degrees, -180..180")
    return float(value)


def _check_position(value: Any, path: str) -> dict[str, Any]:
    obj = _check_object(value, path)
    for key in ("lat", "lon"):
        if key not in obj:
            raise _bad(f"{path}.{key}", "is missing")
    out = dict(obj)
    out["lat"] = _check_lat(obj["lat"], f"{path}.lat")
    out["lon"] = _check_lon(obj["lon"], f"{path}.lon")
    # Ground and surface vehicles may not know their altitude.
    if obj.get("alt") is not None:
        _check_number(obj["alt"], f"{path}.alt")
    return out


def _check_battery(value: Any, path: str) -> int | float:
    if not _is_number(value) or not 0 <= value <= 100:
        raise _bad(path, "must be a battery percentage, 0..100")
    return value  # type: ignore[no-any-return]


def _check_action(value: Any, path: str) -> str:
    if not isinstance(value, str) or value not in FAILSAFE_ACTIONS:
        raise _bad(path, f"must be one of {sorted(FAILSAFE_ACTIONS)}")
    return str(value)


#: The longest description of a safe action a profile may carry (shown in a sentence).
_MAX_SAFE_ACTION_WORDS: Final = 160


def _check_safe_actions(value: Any, path: str) -> dict[str, str]:
    """What each fail-safe action does to the vehicle, in words: ``{action: words}``."""
    if not isinstance(value, dict):
        raise _bad(path, "must be an object")
    for action, words in value.items():
        _check_action(action, f"{path}.{action}")
        if not isinstance(words, str) or not 0 < len(words) <= _MAX_SAFE_ACTION_WORDS:
            raise _bad(f"{path}.{action}", f"must be 1 to {_MAX_SAFE_ACTION_WORDS} characters")
    return value


def _check_role(value: Any, path: str) -> str:
    if not isinstance(value, str) or value not in ROLES:
        raise _bad(path, f"must be one of {sorted(ROLES)}")
    return str(value)


def _check_rate_hz(value: Any, path: str) -> int | float:
    if not _is_number(value) or not 0 < value <= 50:
        raise _bad(path, "must be a rate in Hz, 0 < rate <= 50")
    return value  # type: ignore[no-any-return]


def _check_control_url(value: Any, path: str) -> str:
    # Empty means the vehicle cannot be reached directly; clients must use the relay.
    if not isinstance(value, str) or not (value == "" or value.startswith(("ws://", "wss://"))):
        raise _bad(path, "must be a ws:// or wss:// URL, or empty for relay-only")
    return value


def _check_arg_spec(value: Any, path: str) -> dict[str, Any]:
    """Validate one argument declaration ``{type, min?, max?, default?, unit?}``."""
    spec = _check_object(value, path)
    arg_type = spec.get("type")
    if not isinstance(arg_type, str) or arg_type not in ARG_TYPES:
        raise _bad(f"{path}.type", f"must be one of {sorted(ARG_TYPES)}")
    for bound in ("min", "max"):
        if bound in spec:
            if arg_type not in ("number", "integer"):
                raise _bad(f"{path}.{bound}", "is only allowed for number and integer arguments")
            _check_number(spec[bound], f"{path}.{bound}")
    if "min" in spec and "max" in spec and spec["min"] > spec["max"]:
        raise _bad(f"{path}.min", "must not exceed max")
    if "unit" in spec:
        _check_str(spec["unit"], f"{path}.unit")
    if "description" in spec:
        _check_str(spec["description"], f"{path}.description")
    if "default" in spec:
        try:
            _check_arg_value(spec, spec["default"], "default")
        except ProtocolError as exc:
            raise _bad(f"{path}.default", f"is invalid: {exc.message}") from exc
    return spec


def _check_command_spec(value: Any, path: str) -> dict[str, Any]:
    """Validate one command declaration ``{name, args, description?, group?}``."""
    spec = _check_object(value, path)
    if "name" not in spec:
        raise _bad(f"{path}.name", "is missing")
    _check_id(spec["name"], f"{path}.name")
    if "args" not in spec:
        raise _bad(f"{path}.args", "is missing")
    args = _check_object(spec["args"], f"{path}.args")
    for arg_name, arg_spec in args.items():
        if not arg_name:
            raise _bad(f"{path}.args", "has an argument with an empty name")
        _check_arg_spec(arg_spec, f"{path}.args.{arg_name}")
    for key in ("description", "group"):
        if key in spec:
            _check_str(spec[key], f"{path}.{key}")
    return spec


def _check_commands(value: Any, path: str) -> list[dict[str, Any]]:
    if not isinstance(value, list):
        raise _bad(path, "must be a list of command declarations")
    seen: set[str] = set()
    for i, item in enumerate(value):
        spec = _check_command_spec(item, f"{path}[{i}]")
        if spec["name"] in seen:
            raise _bad(f"{path}[{i}].name", f"repeats command '{spec['name']}'")
        seen.add(spec["name"])
    return value


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


def _check_arg_value(arg_spec: Mapping[str, Any], value: Any, name: str) -> Any:
    arg_type = arg_spec.get("type")
    if arg_type == "number":
        if not _is_number(value):
            raise _bad_arg(name, "must be a finite number")
    elif arg_type == "integer":
        if isinstance(value, bool) or not isinstance(value, int):
            raise _bad_arg(name, "must be an integer")
    elif arg_type == "boolean":
        if not isinstance(value, bool):
            raise _bad_arg(name, "must be a boolean")
    elif arg_type == "string":
        if not isinstance(value, str):
            raise _bad_arg(name, "must be a string")
    else:
        raise _bad_arg(name, f"has an unknown declared type {arg_type!r}")
    if arg_type in ("number", "integer"):
        low, high = arg_spec.get("min"), arg_spec.get("max")
        if _is_number(low) and value < low:
            raise _bad_arg(name, f"must be >= {low}")
        if _is_number(high) and value > high:
            raise _bad_arg(name, f"must be <= {high}")
    return value


def _bad_arg(name: str, problem: str) -> ProtocolError:
    return ProtocolError("bad_args", f"argument '{name}' {problem}", field=f"args.{name}")


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


# --------------------------------------------------------------------------------------
# Keys
# --------------------------------------------------------------------------------------


def generate_keypair() -> tuple[str, str]:
    """Create a new platform signing key.

    Returns ``(private_pem, public_pem)``: PKCS#8 unencrypted private key and
    SubjectPublicKeyInfo public key, both PEM text. Raises nothing.
    """
    private_key = Ed25519PrivateKey.generate()
    private_pem = private_key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    ).decode("ascii")
    public_pem = (
        private_key.public_key()
        .public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
        .decode("ascii")
    )
    return private_pem, public_pem


def load_private_key(pem: str) -> Ed25519PrivateKey:
    """Load an unencrypted PEM private key.

    Returns the key. Raises ProtocolError ``bad_key`` if the text is not a PEM private key
    or the key is not Ed25519 (the only algorithm the agents accept).
    """
    try:
        key = serialization.load_pem_private_key(pem.encode("utf-8"), password=None)
    except (ValueError, TypeError, UnsupportedAlgorithm, AttributeError) as exc:
        raise ProtocolError("bad_key", f"not a usable PEM private key: {exc}") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise ProtocolError("bad_key", "private key is not an Ed25519 key")
    return key


def load_public_key(pem: str) -> Ed25519PublicKey:
    """Load a PEM public key.

    Returns the key. Raises ProtocolError ``bad_key`` if the text is not a PEM public key or
    the key is not Ed25519.
    """
    try:
        key = serialization.load_pem_public_key(pem.encode("utf-8"))
    except (ValueError, TypeError, UnsupportedAlgorithm, AttributeError) as exc:
        raise ProtocolError("bad_key", f"not a usable PEM public key: {exc}") from None
    if not isinstance(key, Ed25519PublicKey):
        raise ProtocolError("bad_key", "public key is not an Ed25519 key")
    return key


# --------------------------------------------------------------------------------------
# Signed documents
# --------------------------------------------------------------------------------------

_B64URL = re.compile(r"[A-Za-z0-9_-]*")


def _b64url_encode(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode("ascii")


def _b64url_decode(text: str, part: str) -> bytes:
    # Strict: Python's decoder silently skips foreign characters, which would give one
    # document many spellings. Require the alphabet and the canonical encoding.
    if not _B64URL.fullmatch(text) or len(text) % 4 == 1:
        raise ProtocolError("bad_token", f"token {part} is not unpadded base64url")
    try:
        data = base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))
    except (binascii.Error, ValueError):
        raise ProtocolError("bad_token", f"token {part} is not unpadded base64url") from None
    if _b64url_encode(data) != text:
        raise ProtocolError("bad_token", f"token {part} is not canonical base64url")
    return data


def _canonical_json(payload: Mapping[str, Any]) -> bytes:
    """Deterministic JSON so one payload always yields the same token."""
    return json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False).encode(
        "ascii"
    )


def _check_header(payload: Mapping[str, Any]) -> None:
    """Check the fields every signed document carries: v, kind, exp."""
    if "v" not in payload:
        raise _bad("v", "is missing", code="bad_version")
    _check_version(payload["v"], "v")
    kind = payload.get("kind")
    if not isinstance(kind, str) or kind not in KINDS:
        raise _bad("kind", f"must be one of {sorted(KINDS)}")
    if "exp" not in payload:
        raise _bad("exp", "is missing")
    _check_timestamp(payload["exp"], "exp")


def sign_document(payload: Mapping[str, Any], private_key: Ed25519PrivateKey) -> str:
    """Sign ``payload`` with the platform key.

    ``payload`` must carry ``v`` (= :data:`PROTOCOL_VERSION`), ``kind`` (one of
    :data:`KINDS`) and a finite ``exp`` (Unix seconds): a document that never expires or
    whose purpose is ambiguous is refused rather than signed.

    Returns the token ``base64url(canonical JSON) + "." + base64url(signature)`` (no
    padding). Raises ProtocolError (``bad_field``/``bad_version``) for a missing or bad
    header field or a payload that is not JSON-serialisable.
    """
    if not isinstance(payload, Mapping):
        raise ProtocolError("bad_field", "payload must be a mapping")
    _check_header(payload)
    try:
        body = _canonical_json(payload)
    except (TypeError, ValueError, RecursionError) as exc:
        raise ProtocolError("bad_field", f"payload is not JSON-serialisable: {exc}") from None
    signature = private_key.sign(body)
    return f"{_b64url_encode(body)}.{_b64url_encode(signature)}"


def verify_document(
    token: str,
    public_key: Ed25519PublicKey,
    *,
    kind: Kind | None = None,
    now: float | None = None,
) -> dict[str, Any]:
    """Verify a token made by :func:`sign_document` and return its payload.

    Order: token shape, signature, JSON object, ``v``, ``kind``, ``exp``. The signature is
    checked before the payload is even parsed, so unauthenticated bytes never reach the
    JSON parser. With ``kind`` given, a document of the other kind is refused: a user
    grant is never accepted as a vehicle task or the reverse.

    ``now`` (Unix seconds, default ``time.time()``) is the verifier's clock; the document
    is expired when ``now > exp + CLOCK_SKEW_S``.

    Returns the payload dict. Raises only ProtocolError subclasses: SignatureError
    (``bad_signature``), ExpiredError (``expired``), or ProtocolError with ``bad_token``
    (malformed token), ``bad_version``, ``wrong_kind`` or ``bad_field``.
    """
    if not isinstance(token, str):
        raise ProtocolError("bad_token", "token must be a string")
    if len(token) > _MAX_TOKEN_CHARS:
        raise ProtocolError("bad_token", "token is too long")
    parts = token.split(".")
    if len(parts) != 2:
        raise ProtocolError("bad_token", "token must be two base64url parts joined by '.'")
    body = _b64url_decode(parts[0], "payload")
    signature = _b64url_decode(parts[1], "signature")
    if len(signature) != _SIGNATURE_BYTES:
        raise SignatureError("token signature has the wrong length")
    try:
        public_key.verify(signature, body)
    except InvalidSignature:
        raise SignatureError("token signature does not match the platform key") from None
    try:
        payload = _loads(body.decode("utf-8"))
    except (ValueError, RecursionError):
        # Only reachable with a validly signed bad payload: a platform bug.
        raise ProtocolError("bad_token", "token payload is not valid JSON") from None
    if not isinstance(payload, dict):
        raise ProtocolError("bad_token", "token payload must be a JSON object")
    _check_header(payload)
    if kind is not None and payload["kind"] != kind:
        raise ProtocolError(
            "wrong_kind",
            f"document is a {payload['kind']}, expected a {kind}",
            field="kind",
        )
    current = time.time() if now is None else now
    if current - CLOCK_SKEW_S > payload["exp"]:
        raise ExpiredError(f"document expired at {payload['exp']} (now {current:.3f})")
    return payload


def new_nonce() -> str:
    """Return a fresh random nonce (128 bits, URL-safe text) for a signed document."""
    return secrets.token_urlsafe(16)


# --------------------------------------------------------------------------------------
# Document dataclasses
# --------------------------------------------------------------------------------------


def _check_keys(payload: Mapping[str, Any], allowed: frozenset[str], prefix: str) -> None:
    # Signed documents fail closed: a field this end does not understand may be a limit it
    # would fail to enforce, so it is refused rather than ignored.
    for key in payload:
        if key not in allowed:
            path = f"{prefix}{key}"
            raise ProtocolError("bad_field", f"field '{path}' is not known", field=path)


def _require(payload: Mapping[str, Any], keys: tuple[str, ...], prefix: str = "") -> None:
    for key in keys:
        if key not in payload:
            raise _bad(f"{prefix}{key}", "is missing")


def _check_optional(value: Any, path: str, checker: Checker) -> Any:
    return None if value is None else checker(value, path)


def _check_positive_int(value: Any, path: str) -> int:
    if _check_int(value, path) <= 0:
        raise _bad(path, "must be an integer > 0")
    return int(value)


def _check_times(issued_at: Any, expires_at: Any) -> None:
    _check_timestamp(issued_at, "iat")
    _check_timestamp(expires_at, "exp")
    if expires_at < issued_at:
        raise _bad("exp", "must not be earlier than iat")


def _check_commands_tuple(value: Any, path: str) -> tuple[str, ...]:
    if not isinstance(value, (list, tuple)):
        raise _bad(path, "must be a list of strings")
    for i, item in enumerate(value):
        _check_id(item, f"{path}[{i}]")
    return tuple(value)


@dataclass(frozen=True, kw_only=True)
class Limits:
    """Safety limits the agent enforces for one session. ``None`` means "no limit".

    Construction validates every field and raises ProtocolError (``bad_field``, naming
    ``limits.<field>``) on a bad value, so an invalid Limits object cannot exist.
    """

    max_altitude_m: float | None = None
    #: (latitude, longitude) in degrees; set together with geofence_radius_m.
    geofence_center: tuple[float, float] | None = None
    geofence_radius_m: float | None = None
    max_speed_mps: float | None = None
    #: Silence from the controlling user after which the agent runs failsafe_action.
    link_loss_timeout_ms: int = DEFAULT_LINK_LOSS_TIMEOUT_MS
    failsafe_action: str = "stop"
    #: Past this round-trip latency the agent lowers the allowed speed.
    latency_soft_ms: int | None = None
    #: Past this round-trip latency only stop / land / return_to_home are accepted.
    latency_hard_ms: int | None = None
    session_time_limit_s: int | None = None

    _FIELDS: ClassVar[frozenset[str]] = frozenset(
        {
            "max_altitude_m",
            "geofence_center",
            "geofence_radius_m",
            "max_speed_mps",
            "link_loss_timeout_ms",
            "failsafe_action",
            "latency_soft_ms",
            "latency_hard_ms",
            "session_time_limit_s",
        }
    )

    def __post_init__(self) -> None:
        p = "limits."
        _check_optional(self.max_altitude_m, p + "max_altitude_m", _check_positive_number)
        _check_optional(self.geofence_radius_m, p + "geofence_radius_m", _check_positive_number)
        _check_optional(self.max_speed_mps, p + "max_speed_mps", _check_positive_number)
        center = self.geofence_center
        if center is not None:
            if not isinstance(center, (list, tuple)) or len(center) != 2:
                raise _bad(p + "geofence_center", "must be [latitude, longitude]")
            normalised = (
                _check_lat(center[0], p + "geofence_center[0]"),
                _check_lon(center[1], p + "geofence_center[1]"),
            )
            # Frozen dataclass: normalise a JSON list into the declared tuple type.
            object.__setattr__(self, "geofence_center", normalised)
        if (center is None) != (self.geofence_radius_m is None):
            raise _bad(
                p + "geofence_center",
                "and geofence_radius_m must be set together (a fence needs both)",
            )
        low, high = _LINK_LOSS_RANGE_MS
        timeout = _check_int(self.link_loss_timeout_ms, p + "link_loss_timeout_ms")
        if not low <= timeout <= high:
            raise _bad(p + "link_loss_timeout_ms", f"must be in {low}..{high}")
        _check_action(self.failsafe_action, p + "failsafe_action")
        _check_optional(self.latency_soft_ms, p + "latency_soft_ms", _check_positive_int)
        _check_optional(self.latency_hard_ms, p + "latency_hard_ms", _check_positive_int)
        if (
            self.latency_soft_ms is not None
            and self.latency_hard_ms is not None
            and self.latency_soft_ms > self.latency_hard_ms
        ):
            raise _bad(p + "latency_soft_ms", "must not exceed latency_hard_ms")
        _check_optional(self.session_time_limit_s, p + "session_time_limit_s", _check_positive_int)

    def to_payload(self) -> dict[str, Any]:
        """Return the JSON-ready dict (every field present, ``None`` as null)."""
        return {
            "max_altitude_m": self.max_altitude_m,
            "geofence_center": (
                list(self.geofence_center) if self.geofence_center is not None else None
            ),
            "geofence_radius_m": self.geofence_radius_m,
            "max_speed_mps": self.max_speed_mps,
            "link_loss_timeout_ms": self.link_loss_timeout_ms,
            "failsafe_action": self.failsafe_action,
            "latency_soft_ms": self.latency_soft_ms,
            "latency_hard_ms": self.latency_hard_ms,
            "session_time_limit_s": self.session_time_limit_s,
        }

    @classmethod
    def from_payload(cls, payload: Any) -> Limits:
        """Build Limits from a payload dict; absent fields take their defaults.

        Returns the Limits. Raises ProtocolError ``bad_field`` naming ``limits.<field>``
        for a non-object, an unknown field, or a bad value.
        """
        if not isinstance(payload, Mapping):
            raise _bad("limits", "must be an object")
        _check_keys(payload, cls._FIELDS, "limits.")
        return cls(**{str(k): v for k, v in payload.items()})


def _verify_common(
    token: str,
    public_key: Ed25519PublicKey,
    kind: Kind,
    vehicle_id: str,
    now: float | None,
) -> dict[str, Any]:
    if not isinstance(vehicle_id, str) or not vehicle_id:
        raise ValueError("vehicle_id must be the verifying agent's own non-empty id")
    return verify_document(token, public_key, kind=kind, now=now)


def _check_target(
    doc_vehicle: str,
    vehicle_id: str,
    nonce: str,
    expires_at: float,
    now: float | None,
    replay_guard: ReplayGuard | None,
) -> None:
    if doc_vehicle != vehicle_id:
        raise WrongTargetError(f"document is for vehicle {doc_vehicle!r}, this is {vehicle_id!r}")
    # Replay last: a document refused for another reason must not burn its nonce.
    if replay_guard is not None:
        replay_guard.check_and_remember(nonce, expires_at, now=now)


@dataclass(frozen=True, kw_only=True)
class VehicleTask:
    """What the platform asks one vehicle to do for one session (signed, pushed on uplink).

    Construction validates every field and raises ProtocolError (``bad_field``) naming the
    field. ``issued_at``/``expires_at`` are Unix seconds and travel as ``iat``/``exp``.
    """

    KIND: ClassVar[Kind] = "vehicle_task"
    _FIELDS: ClassVar[frozenset[str]] = frozenset(
        {
            "v",
            "kind",
            "session_id",
            "vehicle_id",
            "user",
            "allowed_commands",
            "limits",
            "iat",
            "exp",
            "nonce",
            "mission",
        }
    )

    session_id: str
    vehicle_id: str
    user: str
    #: Command names (from the vehicle's vocabulary) this session may send.
    allowed_commands: tuple[str, ...]
    limits: Limits
    issued_at: float
    expires_at: float
    nonce: str = field(default_factory=new_nonce)
    #: Free-form plan for autonomous tasks (e.g. waypoints); any JSON object.
    mission: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        _check_id(self.session_id, "session_id")
        _check_id(self.vehicle_id, "vehicle_id")
        _check_id(self.user, "user")
        object.__setattr__(
            self,
            "allowed_commands",
            _check_commands_tuple(self.allowed_commands, "allowed_commands"),
        )
        if not isinstance(self.limits, Limits):
            raise _bad("limits", "must be a Limits object")
        _check_times(self.issued_at, self.expires_at)
        _check_id(self.nonce, "nonce")
        if self.mission is not None:
            _check_object(self.mission, "mission")
            try:
                _canonical_json(self.mission)
            except (TypeError, ValueError, RecursionError):
                raise _bad("mission", "must be JSON-serialisable (no NaN/inf)") from None

    def to_payload(self) -> dict[str, Any]:
        """Return the document payload (with ``v`` and ``kind``) ready for signing."""
        return {
            "v": PROTOCOL_VERSION,
            "kind": self.KIND,
            "session_id": self.session_id,
            "vehicle_id": self.vehicle_id,
            "user": self.user,
            "allowed_commands": list(self.allowed_commands),
            "limits": self.limits.to_payload(),
            "iat": self.issued_at,
            "exp": self.expires_at,
            "nonce": self.nonce,
            "mission": self.mission,
        }

    @classmethod
    def from_payload(cls, payload: Any) -> VehicleTask:
        """Build a VehicleTask from a (verified) payload.

        Returns the task. Raises ProtocolError naming the field for a missing, unknown or
        bad field, ``bad_version`` for another version and ``wrong_kind`` for a grant.
        """
        if not isinstance(payload, Mapping):
            raise ProtocolError("bad_field", "document payload must be an object")
        _check_keys(payload, cls._FIELDS, "")
        _require(
            payload,
            (
                "v",
                "kind",
                "session_id",
                "vehicle_id",
                "user",
                "allowed_commands",
                "limits",
                "iat",
                "exp",
                "nonce",
            ),
        )
        _check_version(payload["v"], "v")
        if payload["kind"] != cls.KIND:
            raise ProtocolError("wrong_kind", f"document kind must be {cls.KIND}", field="kind")
        return cls(
            session_id=payload["session_id"],
            vehicle_id=payload["vehicle_id"],
            user=payload["user"],
            allowed_commands=_check_commands_tuple(payload["allowed_commands"], "allowed_commands"),
            limits=Limits.from_payload(payload["limits"]),
            issued_at=payload["iat"],
            expires_at=payload["exp"],
            nonce=payload["nonce"],
            mission=payload.get("mission"),
        )

    def sign(self, private_key: Ed25519PrivateKey) -> str:
        """Return this task as a signed token (see :func:`sign_document`)."""
        return sign_document(self.to_payload(), private_key)

    @classmethod
    def verify(
        cls,
        token: str,
        public_key: Ed25519PublicKey,
        *,
        vehicle_id: str,
        now: float | None = None,
        replay_guard: ReplayGuard | None = None,
    ) -> VehicleTask:
        """Verify a task token on the agent whose id is ``vehicle_id``.

        Order: :func:`verify_document` (shape, signature, version, kind, expiry), fields,
        target vehicle, then, if ``replay_guard`` is given, the nonce.

        Returns the task. Raises SignatureError, ExpiredError, WrongTargetError,
        ReplayError or ProtocolError; ValueError only for an empty ``vehicle_id`` argument.
        """
        payload = _verify_common(token, public_key, cls.KIND, vehicle_id, now)
        task = cls.from_payload(payload)
        _check_target(task.vehicle_id, vehicle_id, task.nonce, task.expires_at, now, replay_guard)
        return task


@dataclass(frozen=True, kw_only=True)
class UserGrant:
    """Permission for one user to connect to one vehicle's control socket (signed).

    The browser presents it in ``auth``. Construction validates every field and raises
    ProtocolError (``bad_field``) naming the field.
    """

    KIND: ClassVar[Kind] = "user_grant"
    _FIELDS: ClassVar[frozenset[str]] = frozenset(
        {
            "v",
            "kind",
            "session_id",
            "vehicle_id",
            "user",
            "role",
            "allowed_commands",
            "iat",
            "exp",
            "nonce",
        }
    )

    session_id: str
    vehicle_id: str
    user: str
    role: str
    #: Command names this user may send; a viewer normally gets an empty tuple.
    allowed_commands: tuple[str, ...]
    issued_at: float
    expires_at: float
    nonce: str = field(default_factory=new_nonce)

    def __post_init__(self) -> None:
        _check_id(self.session_id, "session_id")
        _check_id(self.vehicle_id, "vehicle_id")
        _check_id(self.user, "user")
        _check_role(self.role, "role")
        object.__setattr__(
            self,
            "allowed_commands",
            _check_commands_tuple(self.allowed_commands, "allowed_commands"),
        )
        _check_times(self.issued_at, self.expires_at)
        _check_id(self.nonce, "nonce")

    def to_payload(self) -> dict[str, Any]:
        """Return the document payload (with ``v`` and ``kind``) ready for signing."""
        return {
            "v": PROTOCOL_VERSION,
            "kind": self.KIND,
            "session_id": self.session_id,
            "vehicle_id": self.vehicle_id,
            "user": self.user,
            "role": self.role,
            "allowed_commands": list(self.allowed_commands),
            "iat": self.issued_at,
            "exp": self.expires_at,
            "nonce": self.nonce,
        }

    @classmethod
    def from_payload(cls, payload: Any) -> UserGrant:
        """Build a UserGrant from a (verified) payload.

        Returns the grant. Raises ProtocolError naming the field for a missing, unknown or
        bad field, ``bad_version`` for another version and ``wrong_kind`` for a task.
        """
        if not isinstance(payload, Mapping):
            raise ProtocolError("bad_field", "document payload must be an object")
        _check_keys(payload, cls._FIELDS, "")
        _require(
            payload,
            (
                "v",
                "kind",
                "session_id",
                "vehicle_id",
                "user",
                "role",
                "allowed_commands",
                "iat",
                "exp",
                "nonce",
            ),
        )
        _check_version(payload["v"], "v")
        if payload["kind"] != cls.KIND:
            raise ProtocolError("wrong_kind", f"document kind must be {cls.KIND}", field="kind")
        return cls(
            session_id=payload["session_id"],
            vehicle_id=payload["vehicle_id"],
            user=payload["user"],
            role=payload["role"],
            allowed_commands=_check_commands_tuple(payload["allowed_commands"], "allowed_commands"),
            issued_at=payload["iat"],
            expires_at=payload["exp"],
            nonce=payload["nonce"],
        )

    def sign(self, private_key: Ed25519PrivateKey) -> str:
        """Return this grant as a signed token (see :func:`sign_document`)."""
        return sign_document(self.to_payload(), private_key)

    @classmethod
    def verify(
        cls,
        token: str,
        public_key: Ed25519PublicKey,
        *,
        vehicle_id: str,
        now: float | None = None,
        replay_guard: ReplayGuard | None = None,
    ) -> UserGrant:
        """Verify a grant presented to the agent whose id is ``vehicle_id``.

        Same order and errors as :meth:`VehicleTask.verify`. With ``replay_guard`` the
        grant's nonce is consumed: a grant opens one connection, a reconnect needs a fresh
        grant from the platform.
        """
        payload = _verify_common(token, public_key, cls.KIND, vehicle_id, now)
        grant = cls.from_payload(payload)
        _check_target(
            grant.vehicle_id, vehicle_id, grant.nonce, grant.expires_at, now, replay_guard
        )
        return grant


# --------------------------------------------------------------------------------------
# Replay protection
# --------------------------------------------------------------------------------------


class ReplayGuard:
    """Remembers document nonces so each signed document is accepted at most once.

    A nonce is remembered until its document could no longer pass the expiry check
    (``expires_at + CLOCK_SKEW_S``); after that the document is refused as expired anyway,
    so forgetting it is safe and keeps memory bounded. ``max_entries`` is a hard cap on
    top: when full, the oldest remembered nonce is evicted. Not thread-safe: meant for one
    asyncio loop.
    """

    def __init__(self, *, max_entries: int = REPLAY_GUARD_MAX_ENTRIES) -> None:
        if max_entries < 1:
            raise ValueError("max_entries must be >= 1")
        self._max_entries = max_entries
        # nonce -> forget-after time; dict insertion order gives "oldest" for eviction.
        self._forget_at: dict[str, float] = {}
        # (forget-after time, nonce) min-heap, so pruning touches only expired entries.
        self._heap: list[tuple[float, str]] = []

    def __len__(self) -> int:
        return len(self._forget_at)

    def __contains__(self, nonce: object) -> bool:
        return nonce in self._forget_at

    def check_and_remember(
        self, nonce: str, expires_at: float, *, now: float | None = None
    ) -> None:
        """Accept ``nonce`` once.

        Returns None and remembers the nonce when it is new. Raises ReplayError if the
        nonce was seen and its document is still valid; ProtocolError ``bad_field`` for an
        empty nonce or a non-finite ``expires_at``.
        """
        _check_id(nonce, "nonce")
        _check_timestamp(expires_at, "exp")
        current = time.time() if now is None else now
        self._prune(current)
        if nonce in self._forget_at:
            raise ReplayError("document nonce was already used")
        while len(self._forget_at) >= self._max_entries:
            del self._forget_at[next(iter(self._forget_at))]
        forget_at = float(expires_at) + CLOCK_SKEW_S
        self._forget_at[nonce] = forget_at
        heapq.heappush(self._heap, (forget_at, nonce))
        if len(self._heap) > 2 * self._max_entries:
            # Evicted nonces leave stale heap entries; rebuild so the heap stays bounded.
            self._heap = [(t, n) for n, t in self._forget_at.items()]
            heapq.heapify(self._heap)

    def _prune(self, now: float) -> None:
        while self._heap and self._heap[0][0] < now:
            forget_at, nonce = heapq.heappop(self._heap)
            # The entry may be stale (evicted by the cap); only drop a matching one.
            if self._forget_at.get(nonce) == forget_at:
                del self._forget_at[nonce]
