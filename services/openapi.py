"""The OpenAPI 3.1 document of the JSON API (services.api), built from small helpers.

Written by hand, next to the views it describes: the request schemas say exactly what
services.api accepts (unknown fields are refused), and the response schemas what it
returns. tests/services/test_api.py validates the document and fuzzes the live API
against it, so the two cannot drift apart silently.
"""

from __future__ import annotations

from typing import Any

from fleet.attributes import CAMERAS
from fleet.models import Vehicle
from services.models import Service, ServiceRole, Session

API_VERSION = "1.0.0"
BASE_PATH = "/api/v1"
MAX_BODY_BYTES = 64 * 1024
REASON_MAX = 300
# Free-form params are stored as JSON: deep nesting gains nothing and some databases'
# JSON functions refuse it.
PARAMS_MAX_DEPTH = 16

Schema = dict[str, Any]


# --- schema helpers ----------------------------------------------------------------------


def ref(name: str) -> Schema:
    return {"$ref": f"#/components/schemas/{name}"}


def nullable(schema: Schema) -> Schema:
    """``schema`` or JSON null (OpenAPI 3.1 is JSON Schema 2020-12: no ``nullable``)."""
    return {"anyOf": [schema, {"type": "null"}]}


def string(description: str = "", **kw: Any) -> Schema:
    return {"type": "string", **({"description": description} if description else {}), **kw}


def number(description: str = "", **kw: Any) -> Schema:
    return {"type": "number", **({"description": description} if description else {}), **kw}


def integer(description: str = "", **kw: Any) -> Schema:
    return {"type": "integer", **({"description": description} if description else {}), **kw}


def boolean(description: str = "") -> Schema:
    return {"type": "boolean", **({"description": description} if description else {})}


def array(items: Schema, description: str = "", **kw: Any) -> Schema:
    return {
        "type": "array",
        "items": items,
        **({"description": description} if description else {}),
        **kw,
    }


def timestamp(description: str = "") -> Schema:
    return string(description, format="date-time")


def obj(
    properties: dict[str, Schema],
    required: tuple[str, ...] | None = None,
    *,
    closed: bool = False,
    description: str = "",
) -> Schema:
    """An object; every property is required unless ``required`` says otherwise.

    ``closed`` refuses unknown properties: request bodies are closed (the API answers
    400 naming an unknown field, so a typo never passes silently), responses are open
    so that fields can be added without breaking clients.
    """
    schema: Schema = {
        "type": "object",
        "properties": properties,
        "required": list(properties if required is None else required),
    }
    if closed:
        schema["additionalProperties"] = False
    if description:
        schema["description"] = description
    return schema


def json_content(schema: Schema, example: Any = None) -> Schema:
    media: Schema = {"schema": schema}
    if example is not None:
        media["example"] = example
    return {"content": {"application/json": media}}


def response(description: str, schema: Schema | None = None, **extra: Any) -> Schema:
    body = json_content(schema) if schema is not None else {}
    return {"description": description, **body, **extra}


def error(description: str) -> Schema:
    return {"$ref": f"#/components/responses/{description}"}


# --- components ----------------------------------------------------------------------------

ERROR_CODES = {
    "invalid_json": (400, "the body is not a JSON object (or has NUL characters)"),
    "invalid_field": (400, "a field is missing, unknown, of the wrong type or out of range"),
    "not_authenticated": (401, "no bearer token was sent"),
    "invalid_token": (401, "the token is malformed, unknown, revoked or its user inactive"),
    "permission_denied": (403, "the token's user may not do this (role or service grant)"),
    "not_found": (404, "no such resource, or not visible to the token's user"),
    "method_not_allowed": (405, "the path exists but not with this method"),
    "session_state": (409, "the session is not in a state that allows this"),
    "session_limit": (409, "the user already holds as many live sessions as the service allows"),
    "payload_too_large": (413, f"the body is over {MAX_BODY_BYTES} bytes"),
    "unmet_requirement": (422, "no vehicle can meet the service's requirements now"),
    "invalid_task": (422, "the service's settings cannot make a valid vehicle task"),
    "internal_error": (500, "a bug: the platform logged it"),
}

ERROR = obj(
    {
        "error": obj(
            {
                "code": string("Stable, machine-readable.", enum=sorted(ERROR_CODES)),
                "message": string("For humans; names the field or the unmet requirement."),
                "field": string("The request field at fault (400), dotted: target.lat."),
                "session_id": string("The failed session recorded for a 422.", format="uuid"),
                "role": string("The service role that could not be filled (422)."),
            },
            required=("code", "message"),
        )
    },
    description="Every error has this shape, whatever the status.",
)

LIMITS = obj(
    {
        "max_altitude_m": nullable(number()),
        "geofence_radius_m": nullable(number()),
        "max_speed_mps": nullable(number()),
        "link_loss_timeout_ms": integer(),
        "failsafe_action": string(enum=list(Service.Failsafe.values)),
        "session_time_limit_s": nullable(integer()),
        "latency_soft_ms": nullable(integer()),
        "latency_hard_ms": nullable(integer()),
    },
    description="Signed into every vehicle task of the service; null means no limit.",
)

SERVICE_ROLE = obj(
    {
        "name": string(),
        "required": boolean("Assigned at request time (else later, by the workflow)."),
        "kinds": array(string(), "Acceptable vehicle kinds; empty = any."),
        "adapters": array(string(), "Acceptable adapters; empty = any."),
        "cameras": array(string(), "Cameras the vehicle must all have."),
        "environments": array(string(), "The vehicle must operate in one; empty = any."),
        "features": array(string()),
        "min_attributes": {"type": "object", "additionalProperties": {"type": "number"}},
        "min_battery": number(minimum=0, maximum=100),
        "selection": string(enum=list(ServiceRole.Selection.values)),
    }
)

SERVICE = obj(
    {
        "slug": string(),
        "name": string(),
        "description": string(),
        "mode": string(
            "sync: the user controls live; async: a workflow runs it.", enum=["sync", "async"]
        ),
        "kind": string("The service's kind: the name of an installed kind (services.kinds)."),
        "commands": array(string(), "Commands a controller may send; empty = view only."),
        "roles": array(ref("ServiceRole")),
        "limits": ref("Limits"),
    }
)

TARGET = obj(
    {
        "lat": number("Degrees, WGS 84.", minimum=-90, maximum=90),
        "lon": number("Degrees, WGS 84.", minimum=-180, maximum=180),
    },
    closed=True,
)

SESSION_REQUEST = obj(
    {
        "service": string("The service's slug.", minLength=1),
        "target": nullable(ref("Target")),
        "relay": boolean("Control through the platform instead of point-to-point."),
        "preferences": obj(
            {
                "cameras": array(
                    string(enum=list(CAMERAS)),
                    "Cameras the vehicle must carry too.",
                    uniqueItems=True,
                ),
                "min_battery": number(
                    "A higher battery floor than the service's.", minimum=0, maximum=100
                ),
            },
            required=(),
            closed=True,
            description="Narrow the service's requirements (never widen them).",
        ),
        "params": {
            "type": "object",
            "description": "Free-form parameters kept with the session, at most "
            f"{PARAMS_MAX_DEPTH} levels deep, without NUL characters. `mission` is "
            "reserved for the service's workflow and refused here.",
            "not": {"required": ["mission"]},
        },
    },
    required=("service",),
    closed=True,
)

USER_TASK = obj(
    {
        "session_id": string(format="uuid"),
        "vehicle_id": string(format="uuid"),
        "vehicle_name": string(),
        "control_url": string(
            "WebSocket to open and send `auth` with the grant on: the agent's control "
            "socket, or the platform's relay when `relay` is true."
        ),
        "grant": string("Signed user grant (docs/protocol.md, User grant). Secret; short-lived."),
        "role": string(enum=["controller", "viewer"]),
        "expires_at": number("Unix seconds; use the grant before then, then ask for a new one."),
        "commands": array(
            {"type": "object"}, "Declarations of the commands this grant allows (protocol)."
        ),
        "telemetry": array(string(), "Telemetry topics to subscribe to."),
        "relay": boolean(),
    },
    description="What a client needs to control the session's vehicle.",
)

ASSIGNMENT = obj(
    {
        "role": string(),
        "vehicle": obj({"id": string(format="uuid"), "name": string()}),
        "active": boolean("False once released (the session ended)."),
        "distance_m": number("From the vehicle to the target when assigned."),
        "created_at": timestamp(),
        "released_at": nullable(timestamp()),
    }
)

SESSION_EVENT = obj(
    {
        "seq": integer(minimum=1),
        "kind": string("requested, assigned, state, task_deployed, grant_issued, agent events..."),
        "created_at": timestamp(),
        "data": {"type": "object"},
    }
)

SESSION = obj(
    {
        "id": string(format="uuid"),
        "service": obj(
            {"slug": string(), "name": string(), "mode": string(enum=["sync", "async"])}
        ),
        "user": string("The username of the session's owner."),
        "state": string(enum=list(Session.State.values)),
        "reason": string("Why it is in this state; always set once final."),
        "relay": boolean(),
        "target": nullable(ref("Target")),
        "params": {"type": "object"},
        "created_at": timestamp(),
        "assigned_at": nullable(timestamp()),
        "started_at": nullable(timestamp()),
        "ended_at": nullable(timestamp()),
        "assignments": array(ref("Assignment")),
        "delivery": array(
            obj(
                {
                    "vehicle": obj({"id": string(format="uuid"), "name": string()}),
                    "message": string(enum=["revoke", "end_task"]),
                    "action": nullable(string(enum=["stop", "land", "return_to_home"])),
                    "state": string(
                        "delivered: the vehicle's agent confirmed; sending: it is online "
                        "and has not yet; vehicle_offline: its own fail-safe holds until "
                        "it reconnects and is told.",
                        enum=["delivered", "sending", "vehicle_offline"],
                    ),
                    "at": nullable(timestamp()),
                    "text": string("The same, for people."),
                }
            ),
            description="Once the session is over: whether its end (or a monitor's stop) "
            "has reached each vehicle that had its task.",
        ),
        "log": obj(
            {
                "chain_ok": boolean("The hash chain of the log verifies."),
                "bad_seq": nullable(integer("First event that breaks the chain.")),
                "problem": string(),
                "events": array(ref("SessionEvent")),
            }
        ),
    }
)

VEHICLE = obj(
    {
        "id": string(format="uuid"),
        "name": string(),
        "type": string(),
        "kind": string(),
        "station": string(),
        "status": string(enum=list(Vehicle.Status.values)),
        "maintenance": boolean(),
        "battery": nullable(number(minimum=0, maximum=100)),
        "position": nullable(obj({"lat": number(), "lon": number(), "alt": nullable(number())})),
        "last_seen": nullable(timestamp()),
    }
)

END_REQUEST = obj(
    {
        "reason": string(
            "Recorded as the session's reason; not blank.",
            minLength=1,
            maxLength=REASON_MAX,
            pattern=r"\S",
        )
    },
    required=(),
    closed=True,
)

SCHEMAS: dict[str, Schema] = {
    "Error": ERROR,
    "Limits": LIMITS,
    "ServiceRole": SERVICE_ROLE,
    "Service": SERVICE,
    "Target": TARGET,
    "SessionRequest": SESSION_REQUEST,
    "UserTask": USER_TASK,
    "Assignment": ASSIGNMENT,
    "SessionEvent": SESSION_EVENT,
    "Session": SESSION,
    "Vehicle": VEHICLE,
    "EndRequest": END_REQUEST,
}

_UNAUTHORIZED_HEADERS = {
    "WWW-Authenticate": {
        "description": 'Bearer realm="iouv" (with error="invalid_token" for a bad token).',
        "schema": string(),
    }
}
_ALLOW_HEADERS = {"Allow": {"description": "The methods this path accepts.", "schema": string()}}

RESPONSES: dict[str, Schema] = {
    "BadRequest": response("Invalid JSON or an invalid field (named).", ref("Error")),
    "Unauthorized": response(
        "Missing or invalid bearer token.", ref("Error"), headers=_UNAUTHORIZED_HEADERS
    ),
    "Forbidden": response("The token's user may not do this.", ref("Error")),
    "NotFound": response("No such resource for this user.", ref("Error")),
    "MethodNotAllowed": response("Wrong method.", ref("Error"), headers=_ALLOW_HEADERS),
    "Conflict": response(
        "The session's state does not allow this, or the user is at the service's session limit.",
        ref("Error"),
    ),
    "PayloadTooLarge": response(f"Body over {MAX_BODY_BYTES} bytes.", ref("Error")),
    "Unprocessable": response("The fleet cannot meet the request now.", ref("Error")),
    "InternalError": response("A bug on the platform.", ref("Error")),
}


# --- paths ---------------------------------------------------------------------------------


def _errors(*names: str) -> dict[str, Schema]:
    status = {
        "BadRequest": "400",
        "Unauthorized": "401",
        "Forbidden": "403",
        "NotFound": "404",
        "MethodNotAllowed": "405",
        "Conflict": "409",
        "PayloadTooLarge": "413",
        "Unprocessable": "422",
        "InternalError": "500",
    }
    return {status[name]: error(name) for name in ("Unauthorized", *names, "InternalError")}


def operation(
    op_id: str,
    summary: str,
    ok: tuple[str, Schema],
    *,
    errors: tuple[str, ...] = (),
    body: Schema | None = None,
    body_required: bool = False,
    parameters: list[Schema] | None = None,
    description: str = "",
) -> Schema:
    """One authenticated operation; 401 and 500 are always listed."""
    op: Schema = {
        "operationId": op_id,
        "summary": summary,
        "responses": {ok[0]: ok[1], **_errors(*errors)},
    }
    if description:
        op["description"] = description
    if parameters:
        op["parameters"] = parameters
    if body is not None:
        op["requestBody"] = {"required": body_required, **json_content(body)}
        op["responses"].update(_errors("BadRequest", "PayloadTooLarge", *errors))
    return op


SESSION_ID = {
    "name": "session_id",
    "in": "path",
    "required": True,
    "schema": string(format="uuid"),
}

PATHS: dict[str, Schema] = {
    "/services": {
        "get": operation(
            "services_list",
            "Services the token's user may request",
            ("200", response("The services.", obj({"services": array(ref("Service"))}))),
        )
    },
    "/sessions": {
        "post": operation(
            "session_create",
            "Request a session: reserve vehicles and deploy the task",
            (
                "201",
                response(
                    "The session; for a synchronous service also the user task.",
                    obj(
                        {
                            "session": ref("Session"),
                            "task": nullable(ref("UserTask")),
                        }
                    ),
                    headers={"Location": {"schema": string()}},
                ),
            ),
            errors=("Forbidden", "Conflict", "Unprocessable"),
            body=ref("SessionRequest"),
            body_required=True,
            description="A synchronous service is deployed at once: the response carries "
            "the user task (control URL and grant). An asynchronous service returns the "
            "session only; its workflow runs it, reading its kind's own `params` (docs/api.md "
            "lists them). 422 names the "
            "requirement no vehicle met; 409 `session_limit` says the user already holds "
            "as many live sessions of the service as it allows.",
        )
    },
    "/sessions/{session_id}": {
        "parameters": [SESSION_ID],
        "get": operation(
            "session_read",
            "A session, its vehicles and its log",
            ("200", response("The session.", ref("Session"))),
            errors=("NotFound",),
            description="Visible to its owner and to monitors; 404 for anyone else.",
        ),
    },
    "/sessions/{session_id}/grant": {
        "parameters": [SESSION_ID],
        "post": operation(
            "session_grant",
            "A fresh controller grant for the session's owner (to reconnect)",
            ("200", response("A new user task.", obj({"task": ref("UserTask")}))),
            errors=("Forbidden", "NotFound", "Conflict"),
        ),
    },
    "/sessions/{session_id}/end": {
        "parameters": [SESSION_ID],
        "post": operation(
            "session_end",
            "End the session on purpose (its owner)",
            ("200", response("The ended session.", ref("Session"))),
            errors=("Forbidden", "NotFound", "Conflict"),
            body=ref("EndRequest"),
        ),
    },
    "/sessions/{session_id}/stop": {
        "parameters": [SESSION_ID],
        "post": operation(
            "session_stop",
            "Stop a session now (monitors): the vehicle performs the service's fail-safe",
            ("200", response("The aborted session.", ref("Session"))),
            errors=("Forbidden", "NotFound", "Conflict"),
            body=ref("EndRequest"),
        ),
    },
    "/vehicles": {
        "get": operation(
            "vehicles_list",
            "The fleet (monitors)",
            ("200", response("Every vehicle.", obj({"vehicles": array(ref("Vehicle"))}))),
            errors=("BadRequest", "Forbidden"),
            parameters=[
                {
                    "name": "status",
                    "in": "query",
                    "required": False,
                    "schema": string(enum=list(Vehicle.Status.values)),
                },
                {
                    "name": "station",
                    "in": "query",
                    "required": False,
                    "description": "A station's name.",
                    "schema": string(),
                },
            ],
        )
    },
    "/openapi.json": {
        "get": {
            "operationId": "openapi",
            "summary": "This document",
            "security": [],
            "responses": {"200": response("OpenAPI 3.1.", {"type": "object"})},
        }
    },
}


def openapi_document() -> Schema:
    """The whole OpenAPI 3.1 document, JSON-ready."""
    return {
        "openapi": "3.1.0",
        "info": {
            "title": "IoUV API",
            "version": API_VERSION,
            "description": "Request and follow IoUV sessions from your own programs. "
            "Authenticate with `Authorization: Bearer <token>` (an API token from your "
            "platform administrator). Every error is JSON: "
            '`{"error": {"code": ..., "message": ...}}`. See docs/api.md.',
            "license": {"name": "Apache-2.0", "identifier": "Apache-2.0"},
        },
        "servers": [{"url": BASE_PATH}],
        "security": [{"bearer": []}],
        "paths": PATHS,
        "components": {
            "schemas": SCHEMAS,
            "responses": RESPONSES,
            "securitySchemes": {
                "bearer": {
                    "type": "http",
                    "scheme": "bearer",
                    "description": "An API token: iouv_<prefix>_<secret>.",
                }
            },
        },
    }
