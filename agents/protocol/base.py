"""Constants, errors and field checkers shared by the protocol's messages and documents."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any, Final, Literal, TypeAlias

# --------------------------------------------------------------------------------------
# Constants
# --------------------------------------------------------------------------------------

#: Version of the wire protocol. It changes only for incompatible changes (see
#: docs/protocol.md, "Versioning"); both ends refuse a peer or a document of another version.
PROTOCOL_VERSION: Final = 2

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
