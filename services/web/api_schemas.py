"""The JSON API's request and response bodies as types (services.web.api serves them).

django-ninja derives the OpenAPI document from these classes, so what the document
says and what the API accepts and answers cannot drift apart. Request bodies are
closed (an unknown field is a 400 naming it, so a typo never passes silently) and
strict (``"40"`` is not a number, ``true`` is not 1). Response bodies are open, so that
fields can be added without breaking clients; the views return rows and these classes
read them (``resolve_*``).
"""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Annotated, Any, Literal

from ninja import Schema
from pydantic import (
    AfterValidator,
    ConfigDict,
    Field,
    PlainSerializer,
    Strict,
    StringConstraints,
    WithJsonSchema,
    field_validator,
)
from pydantic_core import PydanticCustomError

from fleet.attributes import CAMERAS, FEATURES
from fleet.models import Vehicle
from services import models
from services.sessions.log import session_log, session_log_verify
from services.sessions.selectors import session_delivery
from services.sessions.states import FINAL

BASE_PATH = "/api/v1"
MAX_BODY_BYTES = 64 * 1024
REASON_MAX = 300
# Free-form params are stored as JSON: deep nesting gains nothing and some databases'
# JSON functions refuse it.
PARAMS_MAX_DEPTH = 16


# --- field types ---------------------------------------------------------------------------


def _invalid(field: str, message: str) -> PydanticCustomError:
    """A validation error that names ``field`` (a dotted path deeper than pydantic's
    location, e.g. ``params.a[0]``); services.web.api puts it in the error envelope."""
    return PydanticCustomError("invalid_field", message, {"field": field})


def _storable(text: str) -> bool:
    """PostgreSQL stores neither NUL characters nor lone surrogates (which JSON's
    ``\\ud800`` escapes can produce); refuse them rather than fail on save."""
    if "\x00" in text:
        return False
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _storable_text(text: str) -> str:
    if not _storable(text):
        raise ValueError("must not contain NUL characters or lone surrogates")
    return text


def _check_json(value: Any, path: str, depth: int = 0) -> None:
    """Refuse text that cannot be stored (see _storable) and nesting deeper than
    PARAMS_MAX_DEPTH anywhere in the JSON ``value`` found at ``path``."""
    if depth > PARAMS_MAX_DEPTH:
        raise _invalid(path, f"nested more than {PARAMS_MAX_DEPTH} levels deep")
    if isinstance(value, str):
        if not _storable(value):
            raise _invalid(path, "must not contain NUL characters or lone surrogates")
    elif isinstance(value, dict):
        for key, item in value.items():
            if not _storable(key):
                raise _invalid(path, "keys must not contain NUL characters or lone surrogates")
            _check_json(item, f"{path}.{key}", depth + 1)
    elif isinstance(value, list):
        for index, item in enumerate(value):
            _check_json(item, f"{path}[{index}]", depth + 1)


#: Text a client sends: a JSON string that PostgreSQL can store. (Length and pattern
#: constraints go before the AfterValidator, or pydantic checks them on its result.)
Text = Annotated[str, Strict(), AfterValidator(_storable_text)]
Slug = Annotated[str, Strict(), StringConstraints(min_length=1), AfterValidator(_storable_text)]
Reason = Annotated[
    str,
    Strict(),
    StringConstraints(min_length=1, max_length=REASON_MAX, pattern=r"\S"),
    AfterValidator(_storable_text),
]


# Strict numbers: in JSON a bool is not a number, nor is "40"; integers are.
Latitude = Annotated[
    float, Strict(), Field(ge=-90, le=90, allow_inf_nan=False, description="Degrees, WGS 84.")
]
Longitude = Annotated[
    float, Strict(), Field(ge=-180, le=180, allow_inf_nan=False, description="Degrees, WGS 84.")
]
Percent = Annotated[float, Strict(), Field(ge=0, le=100, allow_inf_nan=False)]

#: A moment, as today's clients read it: ISO 8601 with microseconds and the offset.
Timestamp = Annotated[
    datetime,
    PlainSerializer(lambda value: value.isoformat(), return_type=str),
    WithJsonSchema({"type": "string", "format": "date-time"}),
]

Mode = Literal["sync", "async"]
Camera = Literal[CAMERAS]  # type: ignore[valid-type]  # the tuple is the vocabulary
Feature = Literal[FEATURES]  # type: ignore[valid-type]


class Closed(Schema):
    """A request body: unknown fields are refused."""

    model_config = ConfigDict(extra="forbid")


# --- requests ------------------------------------------------------------------------------


class Target(Closed):
    lat: Latitude
    lon: Longitude


class Preferences(Closed):
    """Narrow the service's requirements (never widen them)."""

    cameras: list[Camera] = Field(
        default_factory=list,
        description="Cameras the vehicle must carry too.",
        json_schema_extra={"uniqueItems": True},
    )
    min_battery: Percent = Field(
        default=0, description="A higher battery floor than the service's."
    )
    features: list[Feature] = Field(
        default_factory=list,
        description="Features the vehicle must have too (a car's camera_arm, say).",
        json_schema_extra={"uniqueItems": True},
    )

    @field_validator("cameras")
    @classmethod
    def _once_each(cls, cameras: list[str]) -> list[str]:
        if len(set(cameras)) != len(cameras):
            raise _invalid("preferences.cameras", "must not repeat a camera")
        return cameras

    @field_validator("features")
    @classmethod
    def _each_once(cls, features: list[str]) -> list[str]:
        if len(set(features)) != len(features):
            raise _invalid("preferences.features", "must not repeat a feature")
        return features


class SessionRequest(Closed):
    service: Slug = Field(description="The service's slug.")
    target: Target | None = None
    relay: Annotated[bool, Strict()] = Field(
        default=False, description="Control through the platform instead of point-to-point."
    )
    preferences: Preferences = Field(default_factory=lambda: Preferences())
    params: Annotated[dict[str, Any], Strict()] = Field(
        default_factory=dict,
        description="Free-form parameters kept with the session, at most "
        f"{PARAMS_MAX_DEPTH} levels deep, without NUL characters. `mission` is reserved "
        "for the service's workflow and refused here.",
        json_schema_extra={"not": {"required": ["mission"]}},
    )

    @field_validator("params")
    @classmethod
    def _free_form(cls, params: dict[str, Any]) -> dict[str, Any]:
        if "mission" in params:
            # A mission is signed into the vehicle task and flown autonomously: only the
            # service's workflow may set one, never the requester.
            raise _invalid("params.mission", "is set by the service's workflow, not by a request")
        _check_json(params, "params")
        return params


class EndRequest(Closed):
    # Optional but not nullable (_not_null refuses an explicit null), as documented.
    reason: Annotated[
        Reason | None,
        WithJsonSchema(
            {
                "type": "string",
                "minLength": 1,
                "maxLength": REASON_MAX,
                "pattern": r"\S",
                "description": "Recorded as the session's reason; not blank.",
            }
        ),
    ] = None

    @field_validator("reason", mode="before")
    @classmethod
    def _not_null(cls, reason: Any) -> Any:
        if reason is None:
            raise ValueError("must be a non-empty string")
        return reason


# --- responses -----------------------------------------------------------------------------


ErrorCode = Literal[
    "invalid_json",
    "invalid_field",
    "not_authenticated",
    "invalid_token",
    "permission_denied",
    "not_found",
    "method_not_allowed",
    "session_state",
    "session_limit",
    "payload_too_large",
    "unmet_requirement",
    "invalid_task",
    "rate_limited",
    "internal_error",
    "database_unavailable",
]


class ErrorDetail(Schema):
    """``code`` is stable and machine-readable: invalid_json and invalid_field (400),
    not_authenticated and invalid_token (401), permission_denied (403), not_found (404),
    method_not_allowed (405), session_state and session_limit (409), payload_too_large
    (413), unmet_requirement and invalid_task (422), rate_limited (429, with
    Retry-After), internal_error (500), database_unavailable (503, with Retry-After)."""

    code: ErrorCode
    message: str = Field(description="For humans; names the field or the unmet requirement.")
    field: str | None = Field(None, description="The request field at fault (400): target.lat.")
    session_id: uuid.UUID | None = Field(None, description="The failed session (422).")
    role: str | None = Field(None, description="The role no vehicle could fill (422).")


class Error(Schema):
    """Every error has this shape, whatever the status."""

    error: ErrorDetail


class Limits(Schema):
    """Signed into every vehicle task of the service; null means no limit."""

    max_altitude_m: float | None
    geofence_radius_m: float | None
    max_speed_mps: float | None
    link_loss_timeout_ms: int
    failsafe_action: models.Service.Failsafe
    session_time_limit_s: int | None
    latency_soft_ms: int | None
    latency_hard_ms: int | None


class ServiceRole(Schema):
    name: str
    required: bool = Field(description="Assigned at request time (else later, by the workflow).")
    kinds: list[str] = Field(description="Acceptable vehicle kinds; empty = any.")
    adapters: list[str] = Field(description="Acceptable adapters; empty = any.")
    cameras: list[str] = Field(description="Cameras the vehicle must all have.")
    environments: list[str] = Field(description="The vehicle must operate in one; empty = any.")
    features: list[str]
    min_attributes: dict[str, float]
    min_battery: float = Field(ge=0, le=100)
    selection: models.ServiceRole.Selection


class Service(Schema):
    slug: str
    name: str
    description: str
    mode: Mode = Field(description="sync: the user controls live; async: a workflow runs it.")
    kind: str = Field(description="The name of an installed kind (services.kinds).")
    commands: list[str] = Field(description="Commands a controller may send; empty = view only.")
    roles: list[ServiceRole]
    limits: Limits

    @staticmethod
    def resolve_commands(service: models.Service) -> list[str]:
        return list(service.allowed_commands)

    @staticmethod
    def resolve_limits(service: models.Service) -> models.Service:
        return service  # the limits are the service's own columns


class Services(Schema):
    services: list[Service]


class VehicleRef(Schema):
    id: uuid.UUID
    name: str


class ServiceRef(Schema):
    slug: str
    name: str
    mode: Mode


class Assignment(Schema):
    role: str
    vehicle: VehicleRef
    active: bool = Field(description="False once released (the session ended).")
    distance_m: float = Field(description="From the vehicle to the target when assigned.")
    created_at: Timestamp
    released_at: Timestamp | None


class Delivery(Schema):
    """Whether the session's end (or a monitor's stop) has reached one vehicle."""

    vehicle: VehicleRef
    message: Literal["revoke", "end_task"]
    action: Literal["stop", "land", "return_to_home"] | None
    state: Literal["delivered", "sending", "vehicle_offline"] = Field(
        description="delivered: the vehicle's agent confirmed; sending: it is online and "
        "has not yet; vehicle_offline: its own fail-safe holds until it reconnects."
    )
    at: Timestamp | None
    text: str = Field(description="The same, for people.")


class SessionEvent(Schema):
    seq: int = Field(ge=1)
    kind: str = Field(description="requested, assigned, state, task_deployed, grant_issued…")
    created_at: Timestamp = Field(description="When it was written to the log.")
    occurred_at: Timestamp | None = Field(
        description="When it happened on the vehicle, by the vehicle's clock (events "
        "logged from an agent's report; null for the platform's own)."
    )
    data: dict[str, Any]


class SessionLog(Schema):
    chain_ok: bool = Field(description="The hash chain of the log verifies.")
    bad_seq: int | None = Field(description="First event that breaks the chain.")
    problem: str
    events: list[SessionEvent]


class Session(Schema):
    """A session with its assignments and its log, and whether the log's chain holds."""

    id: uuid.UUID
    service: ServiceRef
    user: str = Field(description="The username of the session's owner.")
    state: models.Session.State
    reason: str = Field(description="Why it is in this state; always set once final.")
    relay: bool
    control_path: models.Session.ControlPath | Literal[""] = Field(
        description="How the controller's messages reach the vehicle, as its agent last "
        "said: WebRTC direct or through TURN, the platform's relay, or the vehicle's own "
        "socket; empty before anyone connected."
    )
    target: Target | None
    params: dict[str, Any]
    created_at: Timestamp
    assigned_at: Timestamp | None
    started_at: Timestamp | None
    ended_at: Timestamp | None
    assignments: list[Assignment]
    delivery: list[Delivery] = Field(
        description="Once the session is over: whether its end has reached each vehicle "
        "that had its task."
    )
    log: SessionLog

    @staticmethod
    def resolve_user(session: models.Session) -> str:
        return session.user.get_username()

    @staticmethod
    def resolve_target(session: models.Session) -> dict[str, float] | None:
        target = session.target
        return {"lat": target[0], "lon": target[1]} if target else None

    @staticmethod
    def resolve_params(session: models.Session) -> dict[str, Any]:
        return session.params if isinstance(session.params, dict) else {}

    # The assignments and the log come from the function that just wrote them, when it
    # left them on the session (models.Session.known_*), else they are read.

    @staticmethod
    def resolve_assignments(session: models.Session) -> Any:
        if session.known_assignments is not None:
            return session.known_assignments
        return session.assignments.select_related("vehicle")

    @staticmethod
    def resolve_delivery(session: models.Session) -> list[dict[str, Any]]:
        return session_delivery(session) if session.state in FINAL else []

    @staticmethod
    def resolve_log(session: models.Session) -> dict[str, Any]:
        events = session.known_events
        if events is None:
            events = session_log(session=session)  # read once: checked and shown
        check = session_log_verify(session=session, events=events)
        return {
            "chain_ok": check.ok,
            "bad_seq": check.bad_seq,
            "problem": check.problem,
            "events": events,
        }


class IceServerOut(Schema):
    """A STUN/TURN server as the browser's ``RTCIceServer`` takes it."""

    urls: list[str]
    username: str | None = None
    credential: str | None = None


class SfuViewer(Schema):
    """Where a viewer subscribes to the vehicle's video (docs/video.md, "The SFU")."""

    url: str = Field(description="Janus's WebSocket API (subprotocol `janus-protocol`).")
    token: str = Field(description="Janus token for every request. Secret.")
    room: int
    feed: int = Field(description="The vehicle's publisher id in the room.")
    pin: str = Field(description="The room's pin, for `join`. Secret.")


class UserTask(Schema):
    """What a client needs to control the session's vehicle."""

    session_id: uuid.UUID
    vehicle_id: uuid.UUID
    vehicle_name: str
    control_url: str = Field(
        description="WebSocket to open and send `auth` with the grant on: the agent's "
        "control socket, or the platform's relay when `relay` is true."
    )
    grant: str = Field(description="Signed user grant (docs/protocol.md). Secret; short-lived.")
    role: Literal["controller", "viewer"]
    expires_at: float = Field(description="Unix seconds; ask for a new grant before then.")
    commands: list[dict[str, Any]] = Field(description="The commands this grant allows.")
    telemetry: list[str] = Field(description="Telemetry topics to subscribe to.")
    relay: bool
    relay_url: str = Field(
        description="The platform's relay socket for this session: always reachable, and "
        "where a WebRTC connection to the vehicle is signalled (`webrtc_offer`)."
    )
    ice_servers: list[IceServerOut] = Field(
        description="STUN/TURN servers for that WebRTC connection, as `RTCIceServer`; "
        "TURN credentials are short-lived and for this session only."
    )
    sfu: SfuViewer | None = Field(
        default=None,
        description="A viewer's: watch the vehicle's video at the platform's SFU (Janus "
        "VideoRoom) instead of the vehicle; null for the controller or without an SFU.",
    )


class SessionCreated(Schema):
    session: Session
    task: UserTask | None = Field(description="For a service its user drives; else null.")


class Grant(Schema):
    task: UserTask


class Position(Schema):
    lat: float
    lon: float
    alt: float | None


class FleetVehicle(Schema):
    id: uuid.UUID
    name: str
    type: str
    kind: str
    station: str
    status: Vehicle.Status
    maintenance: bool
    battery: float | None = Field(ge=0, le=100)
    position: Position | None
    last_seen: Timestamp | None


class Fleet(Schema):
    vehicles: list[FleetVehicle]


# --- flight records ----------------------------------------------------------------------

#: The exports of a flight record (docs/records.md).
RecordExport = Literal["gpx", "kml", "track.csv", "commands.csv", "events.csv", "tlog", "zip"]


class RecordCheck(Schema):
    """The record checked against the session's hash-chained log."""

    ok: bool
    batches: int
    samples: int
    videos: int = Field(description="The stretches of recorded video the session's log chains.")
    video_check: Literal["size", "sha256"] = Field(
        description="How far the video was checked against the log: its files' sizes (the "
        "record's summary), or their SHA-256 too (the zip's verification.json)."
    )
    problems: list[str] = Field(description="What does not hold, in words; empty when ok.")


class RecordSummary(Schema):
    """What a session's flight record holds, its check, and where its exports are."""

    session: uuid.UUID
    samples: dict[str, int] = Field(
        description="Samples by kind: telemetry, command, event, tlog, dropped."
    )
    verification: RecordCheck
    exports: dict[str, str] = Field(description="Export name -> its URL (tlog only if any).")
