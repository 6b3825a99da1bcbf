"""Constants, errors and the checker of command arguments."""

from __future__ import annotations

import math
from collections.abc import Mapping
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
# Command arguments
#
# Checked against the vehicle's own declarations (known only at run time), so by hand;
# messages and signed documents are checked by their msgspec types.
# --------------------------------------------------------------------------------------


def _is_number(value: Any) -> bool:
    # bool is an int subclass in Python but never a number on the wire; ints need no
    # finiteness check (and math.isfinite would overflow on huge ones).
    if isinstance(value, bool):
        return False
    if isinstance(value, int):
        return True
    return isinstance(value, float) and math.isfinite(value)


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
