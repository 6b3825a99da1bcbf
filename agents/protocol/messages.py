"""The JSON messages of the four WebSocket channels, as typed structs, and command arguments.

Every message type is a frozen :class:`msgspec.Struct` tagged by its ``type`` field; each
channel is the tagged union of the structs it accepts, decoded and validated in one pass
by a :class:`msgspec.json.Decoder` built once. Unknown fields are ignored, so a newer
peer can add optional fields without breaking an older one (docs/protocol.md,
"Versioning"). An optional field a peer left out is :data:`msgspec.UNSET` (falsy).
The JSON Schema of each channel is generated from these structs by
:mod:`agents.protocol.schema`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any, Final, Literal, TypeAlias, get_args

import msgspec
from msgspec import UNSET, Meta, UnsetType, field

from agents.protocol.base import (
    MAX_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    Channel,
    ProtocolError,
    _bad_arg,
    _check_arg_value,
)

# --------------------------------------------------------------------------------------
# Field types: the limits of every field, readable by msgspec and by JSON Schema.
# --------------------------------------------------------------------------------------

Id = Annotated[str, Meta(min_length=1)]
Uint = Annotated[int, Meta(ge=0)]
# msgspec refuses NaN/Infinity (not JSON) and numbers beyond the float range.
Number = float
PositiveNumber = Annotated[float, Meta(gt=0)]
Latitude = Annotated[float, Meta(ge=-90, le=90)]
Longitude = Annotated[float, Meta(ge=-180, le=180)]
Battery = Annotated[float, Meta(ge=0, le=100, description="Percent, 0..100")]
RateHz = Annotated[float, Meta(gt=0, le=50)]
if TYPE_CHECKING:
    Version = int
else:  # any other value is refused as bad_version
    Version = Literal[PROTOCOL_VERSION]
FailsafeAction = Literal["stop", "land", "return_to_home"]
Role = Literal["controller", "viewer"]
Object = dict[str, Any]
# Empty means the vehicle cannot be reached directly; clients must use the relay.
# (?![\s\S]) is "end of text" in both Python and ECMA regexes; $ would allow "\n".
ControlUrl = Annotated[str, Meta(pattern=r"^(?:wss?://|(?![\s\S]))")]

#: The longest description of a safe action a profile may carry (shown in a sentence).
_MAX_SAFE_ACTION_WORDS: Final = 160
_ACTIONS: Final = get_args(FailsafeAction)

# Checked in Profile.__post_init__ so a refusal names the action; the schema says the same.
SafeActions = Annotated[
    dict[str, Any],
    Meta(
        description="What each fail-safe action does to this vehicle, in words",
        extra_json_schema={
            "propertyNames": {"enum": list(_ACTIONS)},
            "additionalProperties": {
                "type": "string",
                "minLength": 1,
                "maxLength": _MAX_SAFE_ACTION_WORDS,
            },
        },
    ),
]


def _invalid(path: str, problem: str) -> ValueError:
    """A refusal raised inside ``__post_init__``: msgspec appends where the struct sits,
    :func:`_protocol_error` joins that with ``path`` (relative to the struct)."""
    return ValueError(f"<{path}> {problem}")


class Position(msgspec.Struct, frozen=True):
    """Where the vehicle is; ground and surface vehicles may not know their altitude."""

    lat: Latitude
    lon: Longitude
    alt: float | None = None


class ArgSpec(msgspec.Struct, frozen=True):
    """One command argument's declaration."""

    type: Literal["number", "integer", "boolean", "string"]
    min: float | UnsetType = UNSET
    max: float | UnsetType = UNSET
    default: bool | int | float | str | UnsetType = UNSET
    unit: str | UnsetType = UNSET
    description: str | UnsetType = UNSET

    def __post_init__(self) -> None:
        for bound in ("min", "max"):
            value = getattr(self, bound)
            if value is not UNSET and self.type not in ("number", "integer"):
                raise _invalid(bound, "is only allowed for number and integer arguments")
            if value is not UNSET and not math.isfinite(value):
                raise _invalid(bound, "must be a finite number")
        if self.min is not UNSET and self.max is not UNSET and self.min > self.max:
            raise _invalid("min", "must not exceed max")
        if self.default is not UNSET:
            try:
                _check_arg_value(msgspec.structs.asdict(self), self.default, "default")
            except ProtocolError as exc:
                raise _invalid("default", f"is invalid: {exc.message}") from None


_ARGS_SCHEMA: Final = {
    "propertyNames": {"minLength": 1},
    "additionalProperties": {"$ref": "#/$defs/ArgSpec"},
}


class CommandSpec(msgspec.Struct, frozen=True):
    """One command of the vehicle's vocabulary. ``args`` stays a dict of declarations
    (each checked as an :class:`ArgSpec`) for :func:`validate_command_args`."""

    name: Id
    # dict[str, Any]: each value is checked in __post_init__ (so a refusal names the
    # argument); the schema says what is checked.
    args: Annotated[dict[str, Any], Meta(extra_json_schema=_ARGS_SCHEMA)]
    description: str | UnsetType = UNSET
    group: str | UnsetType = UNSET
    # Moves the vehicle: repeated while a key is held, refused past the hard latency limit.
    motion: bool | UnsetType = UNSET
    key: str | UnsetType = UNSET  # default key binding for controllers, e.g. "ArrowUp"
    # control_to_client welcome only: whether this user's session may send it.
    allowed: bool | UnsetType = UNSET

    def __post_init__(self) -> None:
        for arg_name, spec in self.args.items():
            if not arg_name:
                raise _invalid("args", "has an argument with an empty name")
            try:
                msgspec.convert(spec, ArgSpec)
            except msgspec.ValidationError as exc:
                path, problem = _split(str(exc))
                raise _invalid(_join(f"args.{arg_name}", path), problem) from None


def _check_commands(commands: list[CommandSpec]) -> None:
    seen: set[str] = set()
    for i, command in enumerate(commands):
        if command.name in seen:
            raise _invalid(f"commands[{i}].name", f"repeats command '{command.name}'")
        seen.add(command.name)


# --------------------------------------------------------------------------------------
# Messages, by channel. A trailing ``| UnsetType = UNSET`` marks an optional field,
# ``| None`` allows JSON null.
# --------------------------------------------------------------------------------------


IceUrl = Annotated[str, Meta(pattern=r"^(?:stuns?|turns?):", max_length=300)]


class IceServer(msgspec.Struct, frozen=True):
    """A STUN/TURN server as WebRTC's ``RTCIceServer`` takes it; TURN carries the
    short-lived credentials the platform minted for the session."""

    urls: Annotated[list[IceUrl], Meta(min_length=1, max_length=8)]
    username: Annotated[str, Meta(max_length=300)] | UnsetType = UNSET
    credential: Annotated[str, Meta(max_length=300)] | UnsetType = UNSET

    def as_config(self) -> dict[str, Any]:
        """The server as the agent's configuration spells one (``agents.rtc``)."""
        return {
            "urls": list(self.urls),
            "username": self.username or None,
            "credential": self.credential or None,
        }


class Message(msgspec.Struct, frozen=True, tag_field="type"):
    """Base of every message struct (not itself a message)."""


# uplink_to_platform -------------------------------------------------------------------


class Hello(Message, frozen=True, tag="hello"):
    v: Version
    vehicle_id: Id
    credential: Id


class Profile(Message, frozen=True, tag="profile"):
    vehicle_type: Id
    adapter: Id
    attributes: Object
    commands: list[CommandSpec]
    telemetry: list[Id]
    control_url: ControlUrl
    video: bool
    position: Position | None
    battery: Battery | None
    # What each fail-safe action does to this vehicle, in words the platform shows
    # before a user ends a session or a monitor stops it.
    safe_actions: SafeActions | UnsetType = UNSET
    # What the agent is doing as it (re)registers, so the platform can converge it: the
    # session of the task it runs, whether a user controls it, its status word.
    session_id: Id | UnsetType | None = UNSET
    controller: bool | UnsetType = UNSET
    status: str | UnsetType = UNSET
    #: The agent can publish its camera to the platform's SFU (a vehicle task's ``sfu``
    #: section); older agents, which would refuse a task with that section, leave it out.
    sfu: bool | UnsetType = UNSET

    def __post_init__(self) -> None:
        _check_commands(self.commands)
        for action, words in (self.safe_actions or {}).items():
            if action not in _ACTIONS:
                raise _invalid(f"safe_actions.{action}", f"must be one of {sorted(_ACTIONS)}")
            if not isinstance(words, str) or not 0 < len(words) <= _MAX_SAFE_ACTION_WORDS:
                raise _invalid(
                    f"safe_actions.{action}", f"must be 1 to {_MAX_SAFE_ACTION_WORDS} characters"
                )


class Heartbeat(Message, frozen=True, tag="heartbeat"):
    seq: Uint
    position: Position | UnsetType | None = UNSET
    battery: Battery | UnsetType | None = UNSET
    status: str | UnsetType = UNSET
    telemetry: Object | UnsetType = UNSET


class TaskAccepted(Message, frozen=True, tag="task_accepted"):
    session_id: Id


class TaskRefused(Message, frozen=True, tag="task_refused"):
    code: Id
    reason: str
    session_id: Id | UnsetType | None = UNSET


class Ack(Message, frozen=True, tag="ack"):
    """The agent handled the platform message carrying this id (see "Delivery")."""

    id: Id
    ok: bool
    detail: str | UnsetType = UNSET


class Event(Message, frozen=True, tag="event"):
    """Something that happened on the vehicle (a report to the platform). ``at``: when,
    by the vehicle's clock (Unix seconds); a report queued while the platform was away,
    or written late, keeps the time it happened. Absent from agents before it."""

    session_id: Id | None
    event: Id
    data: Object
    at: (
        Annotated[
            float,
            Meta(gt=0, description="When it happened on the vehicle: Unix seconds, its clock"),
        ]
        | UnsetType
    ) = UNSET


#: The kinds of flight-record samples (docs/records.md).
RecordKind = Literal["telemetry", "command", "event", "tlog", "dropped"]
#: Samples in one ``record`` batch at most (the frame's byte limit binds first).
RECORD_SAMPLES_MAX: Final = 1000


class RecordSample(msgspec.Struct, frozen=True):
    """One numbered sample of a session's flight record: ``seq`` counts from 1 per
    session without a gap, ``t`` is when it happened by the vehicle's clock (Unix
    seconds)."""

    seq: Annotated[int, Meta(ge=1)]
    t: Annotated[float, Meta(gt=0, description="Unix seconds, the vehicle's clock")]
    kind: RecordKind
    data: Object


class Record(Message, frozen=True, tag="record"):
    """A batch of a session's flight record, samples ``first`` .. ``first + n - 1`` in
    order. The platform answers ``ack`` with ``id`` once it is stored (or was already);
    the agent keeps the batch on disk and sends it again until then."""

    id: Id
    session_id: Id
    first: Annotated[int, Meta(ge=1)]
    samples: Annotated[list[RecordSample], Meta(min_length=1, max_length=RECORD_SAMPLES_MAX)]

    def __post_init__(self) -> None:
        for offset, sample in enumerate(self.samples):
            if sample.seq != self.first + offset:
                raise _invalid(
                    f"samples[{offset}].seq", f"must be {self.first + offset} (no gap, in order)"
                )


#: Raw bytes of a file in one ``artifact`` chunk (base64 makes it 4/3 bigger; the frame
#: stays well under MAX_MESSAGE_BYTES with its fields), and the largest file.
ARTIFACT_CHUNK_BYTES: Final = 32 * 1024
ARTIFACT_MAX_BYTES: Final = 16 * 1024 * 1024
ARTIFACT_MAX_CHUNKS: Final = ARTIFACT_MAX_BYTES // ARTIFACT_CHUNK_BYTES
#: What a mission's file may be called: a plain file name, no path.
ArtifactName = Annotated[str, Meta(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")]
MediaType = Annotated[str, Meta(pattern=r"^[a-z]+/[a-z0-9.+-]{1,60}$")]
Sha256 = Annotated[str, Meta(pattern=r"^[0-9a-f]{64}$")]


class Artifact(Message, frozen=True, tag="artifact"):
    """Chunk ``index`` of ``count`` of a file a mission made in a session (a photo), its
    bytes in ``b64``. Every chunk carries the whole file's ``size``, ``sha256``,
    ``media_type`` and ``meta`` (what it is: where a photo was taken), so any chunk
    may arrive first. The platform answers ``ack`` with ``id`` once the chunk is kept (or
    was already); the agent keeps the file until every chunk is acknowledged."""

    id: Id
    session_id: Id
    name: ArtifactName
    media_type: MediaType
    size: Annotated[int, Meta(ge=1, le=ARTIFACT_MAX_BYTES)]
    sha256: Sha256
    index: Annotated[int, Meta(ge=0)]
    count: Annotated[int, Meta(ge=1, le=ARTIFACT_MAX_CHUNKS)]
    meta: Object
    b64: Annotated[str, Meta(min_length=4, max_length=4 * ((ARTIFACT_CHUNK_BYTES + 2) // 3))]

    def __post_init__(self) -> None:
        if self.count != -(-self.size // ARTIFACT_CHUNK_BYTES):
            raise _invalid("count", f"must be the size in chunks of {ARTIFACT_CHUNK_BYTES} bytes")
        if self.index >= self.count:
            raise _invalid("index", "must be below count")

    def chunk_bytes(self) -> int:
        """How many bytes chunk ``index`` holds (the last one may be shorter)."""
        if self.index < self.count - 1:
            return ARTIFACT_CHUNK_BYTES
        return self.size - ARTIFACT_CHUNK_BYTES * (self.count - 1)


class RelayClose(Message, frozen=True, tag="relay_close"):
    """A relayed client went away or was dropped (both uplink directions)."""

    session_id: Id
    conn: Id
    code: Uint | UnsetType = UNSET
    reason: str | UnsetType = UNSET


# uplink_to_agent ----------------------------------------------------------------------


class Welcome(Message, frozen=True, tag="welcome"):
    v: Version
    heartbeat_interval_s: PositiveNumber
    platform_public_key: str | UnsetType = UNSET
    # The platform's signing keys as a JWKS (RFC 7517): during a key rotation it holds
    # both keys, so a task signed with either verifies on the agent.
    platform_jwks: Object | UnsetType = UNSET


# These three carry an id and are sent again until the agent acknowledges it.
class Task(Message, frozen=True, tag="task"):
    token: Id
    id: Id | UnsetType = UNSET


class Revoke(Message, frozen=True, tag="revoke"):
    session_id: Id
    reason: str
    action: FailsafeAction
    id: Id | UnsetType = UNSET


class EndTask(Message, frozen=True, tag="end_task"):
    session_id: Id
    reason: str
    id: Id | UnsetType = UNSET


class Error(Message, frozen=True, tag="error"):
    """A refusal (uplink_to_agent and control_to_client); ``seq`` names the command."""

    code: Id
    message: str
    seq: Uint | UnsetType = UNSET


# control_to_agent ---------------------------------------------------------------------


class Auth(Message, frozen=True, tag="auth"):
    grant: Id


class Command(Message, frozen=True, tag="command"):
    seq: Uint
    name: Id
    args: Object = field(default_factory=dict)
    #: When the user sent it, in milliseconds since the epoch on the user's clock; the
    #: agent (clocks aligned by the ping exchange) drops commands that arrive too late.
    t: Number | UnsetType = UNSET


class Subscribe(Message, frozen=True, tag="subscribe"):
    topics: list[Id]
    rate_hz: RateHz


class Unsubscribe(Message, frozen=True, tag="unsubscribe"):
    topics: list[Id]


class Ping(Message, frozen=True, tag="ping"):
    t: Number


class Pong(Message, frozen=True, tag="pong"):
    """Answer to the agent's ping: lets the agent measure latency for its limits and,
    with ``client_t`` (the user's clock, ms since the epoch), align the clocks."""

    t: Number
    client_t: Number | UnsetType = UNSET


class Keepalive(Message, frozen=True, tag="keepalive"):
    pass


class TakeControl(Message, frozen=True, tag="take_control"):
    pass


class ReleaseControl(Message, frozen=True, tag="release_control"):
    pass


class WebrtcOffer(Message, frozen=True, tag="webrtc_offer"):
    sdp: str


class WebrtcAnswer(Message, frozen=True, tag="webrtc_answer"):
    sdp: str


# control_to_client --------------------------------------------------------------------


class ClientWelcome(Message, frozen=True, tag="welcome"):
    role: Role
    vehicle: Object
    commands: list[CommandSpec]
    telemetry: list[Id]
    # How to show each topic: {topic: {label, unit?, decimals?, yes?, no?}}.
    telemetry_info: Object | UnsetType = UNSET

    def __post_init__(self) -> None:
        _check_commands(self.commands)


class CommandAck(Message, frozen=True, tag="ack"):
    seq: Uint
    ok: bool
    error: str | None
    code: str | UnsetType | None = UNSET


class Telemetry(Message, frozen=True, tag="telemetry"):
    t: Number
    data: Object


class ClientPong(Message, frozen=True, tag="pong"):
    t: Number
    server_t: Number


class ClientEvent(Message, frozen=True, tag="event"):
    event: Id
    data: Object


class RoleChange(Message, frozen=True, tag="role"):
    role: Role


class VideoStatus(Message, frozen=True, tag="video_status"):
    """What the vehicle's camera sends now (one stream for everyone; its bitrate
    follows the pilot's link): picture size, frame rate, target bitrate in bit/s."""

    width: Uint
    height: Uint
    fps: Uint
    bitrate: Uint


ControlToAgent: TypeAlias = (
    Auth
    | Command
    | Subscribe
    | Unsubscribe
    | Ping
    | Pong
    | Keepalive
    | TakeControl
    | ReleaseControl
    | WebrtcOffer
)
ControlToClient: TypeAlias = (
    ClientWelcome
    | CommandAck
    | Telemetry
    | ClientPong
    | Ping
    | ClientEvent
    | WebrtcAnswer
    | Error
    | RoleChange
    | VideoStatus
)


# A relayed payload is an ordinary control message of the matching channel, so the relay
# path cannot carry anything the direct path would refuse.
class RelayToPlatform(Message, frozen=True, tag="relay"):
    session_id: Id
    payload: ControlToClient
    conn: Id | UnsetType = UNSET


class RelayToAgent(Message, frozen=True, tag="relay"):
    session_id: Id
    payload: ControlToAgent
    conn: Id | UnsetType = UNSET
    #: With a relayed ``webrtc_offer``: the STUN/TURN servers (fresh TURN credentials
    #: for this session) the platform gives the agent for that connection.
    ice_servers: Annotated[list[IceServer], Meta(max_length=8)] | UnsetType = UNSET


UplinkToPlatform: TypeAlias = (
    Hello
    | Profile
    | Heartbeat
    | TaskAccepted
    | TaskRefused
    | Ack
    | Event
    | RelayToPlatform
    | RelayClose
    | Record
    | Artifact
)
# ``ack`` both ways: the platform acknowledges the agent's ``record`` batches and
# ``artifact`` chunks by their id.
UplinkToAgent: TypeAlias = (
    Welcome | Task | Revoke | EndTask | RelayToAgent | RelayClose | Error | Ack
)

#: channel -> the union of the message structs it accepts.
CHANNEL_TYPES: Final[dict[str, Any]] = {
    "uplink_to_platform": UplinkToPlatform,
    "uplink_to_agent": UplinkToAgent,
    "control_to_agent": ControlToAgent,
    "control_to_client": ControlToClient,
}


def message_type(msg: Message) -> str:
    """The ``type`` tag of a message struct (``"heartbeat"``)."""
    return str(msg.__struct_config__.tag)


#: channel -> the message types it accepts.
MESSAGE_TYPES: Final[dict[str, frozenset[str]]] = {
    channel: frozenset(str(cls.__struct_config__.tag) for cls in get_args(union))
    for channel, union in CHANNEL_TYPES.items()
}

_DECODERS: Final[dict[str, msgspec.json.Decoder[Any]]] = {
    channel: msgspec.json.Decoder(union) for channel, union in CHANNEL_TYPES.items()
}
# CommandSpec's check converts to ArgSpec: prepared at import, as the decoders are
# (agents.protocol.documents says why).
msgspec.json.Decoder(ArgSpec)
_ENCODER: Final = msgspec.json.Encoder()

# --------------------------------------------------------------------------------------
# Errors: msgspec's text -> ProtocolError(code, message, field)
# --------------------------------------------------------------------------------------

_WHERE = re.compile(r"^(?P<problem>.*?)(?: - at (?:`key` in )?`\$(?P<path>[^`]*)`)?$", re.S)
_MISSING = re.compile(r"^Object missing required field `(?P<name>[^`]*)`$")
_MARKED = re.compile(r"^<(?P<path>[^>]*)> (?P<problem>.*)$", re.S)
# Only structs that refuse unknown fields meet it (the signed documents); messages ignore them.
_UNKNOWN = re.compile(r"^Object contains unknown field `(?P<name>.*)`$", re.S)


def _join(outer: str, inner: str) -> str:
    if not inner:
        return outer
    if not outer or inner.startswith("["):
        return outer + inner
    return f"{outer}.{inner}"


def _split(text: str) -> tuple[str, str]:
    """msgspec's ``"problem - at `$.a.b`"`` -> ``("a.b", "problem")``, folding in the
    field a missing or unknown field error names and the path a :func:`_invalid`
    refusal carries."""
    where = _WHERE.match(text)
    assert where is not None  # the pattern matches any text
    problem, path = where["problem"], (where["path"] or "").removeprefix(".")
    if missing := _MISSING.match(problem):
        return _join(path, missing["name"]), "is missing"
    if unknown := _UNKNOWN.match(problem):
        return _join(path, unknown["name"]), "is not known"
    if marked := _MARKED.match(problem):
        return _join(path, marked["path"]), marked["problem"]
    return path, problem


def _protocol_error(exc: msgspec.ValidationError) -> ProtocolError:
    path, problem = _split(str(exc))
    if path in ("type", "payload.type"):
        return ProtocolError("unknown_type", f"message type: {problem}", field=path)
    if path == "":
        return ProtocolError("bad_json", f"message must be a JSON object: {problem}")
    if path == "v" and problem != "is missing":
        problem = f"{problem} (this end speaks version {PROTOCOL_VERSION})"
        return ProtocolError("bad_version", f"field 'v': {problem}", field="v")
    return ProtocolError("bad_field", f"field '{path}': {problem}", field=path)


# --------------------------------------------------------------------------------------
# Codec
# --------------------------------------------------------------------------------------


def parse_message(raw: str | bytes, *, channel: Channel) -> Any:
    """Decode and validate one WebSocket message received on ``channel``.

    Returns the message struct of its type (one of the channel's union, e.g.
    :class:`Heartbeat`); absent optional fields are :data:`msgspec.UNSET`, except
    ``command.args`` which defaults to ``{}``. Unknown fields are dropped. A relayed
    ``payload`` is a struct of the matching control channel.

    Raises ProtocolError with code ``too_large`` (over :data:`MAX_MESSAGE_BYTES`),
    ``bad_json`` (not UTF-8, not JSON, not an object), ``unknown_type`` (type not
    accepted on this channel), ``bad_field`` (missing or mistyped field, its path in
    ``field``) or ``bad_version`` (a ``hello``/``welcome`` of another protocol version).
    Raises KeyError only if ``channel`` itself is not one of the channels.
    """
    decoder = _DECODERS[channel]
    if isinstance(raw, str):
        # A character is at least one UTF-8 byte: cheap early refusal before encoding.
        if len(raw) > MAX_MESSAGE_BYTES:
            raise ProtocolError("too_large", f"message exceeds {MAX_MESSAGE_BYTES} bytes")
        try:
            raw = raw.encode("utf-8")
        except UnicodeEncodeError:  # lone surrogates
            raise ProtocolError("bad_json", "message is not valid UTF-8 text") from None
    elif not isinstance(raw, bytes):
        raise ProtocolError("bad_json", "message must be text or bytes")
    if len(raw) > MAX_MESSAGE_BYTES:
        raise ProtocolError("too_large", f"message exceeds {MAX_MESSAGE_BYTES} bytes")
    try:
        return decoder.decode(raw)
    except msgspec.ValidationError as exc:
        raise _protocol_error(exc) from None
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError) as exc:
        # RecursionError: deeply nested arrays fit easily in 64 KiB.
        raise ProtocolError("bad_json", f"message is not valid JSON: {exc}") from None


def encode_message(msg: Message, *, channel: Channel | None = None) -> str:
    """Serialise a message struct to the JSON text sent on the wire.

    Struct constructors do not check limits, so with ``channel`` the text is also
    validated exactly as the receiver will, and a bug on the sending side shows up where
    it happens. NaN and infinities encode as ``null`` (refused where a number is required).

    Returns compact JSON text. Raises ProtocolError: ``bad_field`` if ``msg`` is not a
    message struct or holds a value msgspec cannot encode, ``too_large`` if the result
    exceeds :data:`MAX_MESSAGE_BYTES`, and any :func:`parse_message` code when ``channel``
    is given and the message would be refused.
    """
    if not isinstance(msg, Message) or type(msg) is Message:
        raise ProtocolError("bad_field", "only message structs can be encoded", field="type")
    try:
        data = _ENCODER.encode(msg)
    except (TypeError, ValueError, OverflowError, RecursionError) as exc:
        raise ProtocolError("bad_field", f"message is not JSON-serialisable: {exc}") from None
    if len(data) > MAX_MESSAGE_BYTES:
        raise ProtocolError("too_large", f"message exceeds {MAX_MESSAGE_BYTES} bytes")
    if channel is not None:
        parse_message(data, channel=channel)
    return data.decode("utf-8")


def message_from_dict(data: Mapping[str, Any], *, channel: Channel) -> Any:
    """A message held as JSON data (a database row, a form's input) as the struct
    :func:`parse_message` would return for its text.

    Raises ProtocolError exactly as :func:`parse_message` does."""
    if not isinstance(data, Mapping):
        raise ProtocolError("bad_json", "message must be a JSON object")
    try:
        return msgspec.convert(data, CHANNEL_TYPES[channel], strict=True)
    except msgspec.ValidationError as exc:
        raise _protocol_error(exc) from None


def message_to_dict(msg: Message) -> dict[str, Any]:
    """The message as JSON data, to store it (a database row): a dict with its
    ``type``, absent optional fields left out."""
    out = msgspec.to_builtins(msg)
    assert isinstance(out, dict)
    return out


def error_message(code: str, message: str, *, seq: int | None = None) -> Error:
    """Build an ``error`` message (the uplink and the control channel share this shape).

    ``seq`` names the command being answered, when there is one. Raises nothing.
    """
    return Error(code=code, message=message, seq=UNSET if seq is None else seq)


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
