"""The JSON API for third-party programs, on django-ninja (see docs/api.md).

The bodies are types (services.web.api_schemas); ninja validates requests against them,
renders responses through them and generates the OpenAPI document
(``/api/v1/openapi.json``) and its Swagger UI (``/api/v1/docs``) from them. The HTTP
plumbing (error envelope, bearer token, body limits) is services.web.api_kit. Views stay
thin: parse (ninja), call a service function, render (ninja).

Authentication is by ``Authorization: Bearer <token>`` only. The session cookie is
never consulted, so the endpoints are CSRF-exempt: a cross-site page can make a browser
send cookies, but it cannot make it send this header.
"""

# No `from __future__ import annotations`: ninja reads the views' annotations through
# api_kit.query's wrapper, whose globals are api_kit's, so they must be objects, not text.

from typing import Any
from uuid import UUID

from django.db import transaction
from django.http import Http404, HttpResponse
from django.http.response import HttpResponseBase
from ninja import Status, Swagger

from accounts.users import AuthenticatedHttpRequest
from fleet.models import Vehicle
from fleet.status import fleet_snapshot
from services.kinds import Request, RequestError
from services.models import Session
from services.sessions.deployment import (
    DeploymentError,
    InvalidTaskError,
    grant_issue,
    user_task_json,
)
from services.sessions.ending import session_end_by_user, session_revoke
from services.sessions.grants import service_usable_get, services_for_user
from services.sessions.matching import AssignmentError
from services.sessions.request import service_request
from services.sessions.states import SessionStateError
from services.web import api_schemas as schema
from services.web.api_kit import (
    ApiError,
    BearerToken,
    IouvApi,
    JsonObjectParser,
    document_view,
    field_error,
    not_found,
    query,
)
from services.web.api_schemas import BASE_PATH, MAX_BODY_BYTES, PARAMS_MAX_DEPTH, REASON_MAX
from services.web.record_views import EXPORTS, record_file, record_summary
from services.web.throttle import request_keys, throttle_check, throttle_count, throttle_peek

__all__ = ["MAX_BODY_BYTES", "PARAMS_MAX_DEPTH", "REASON_MAX", "ApiError", "api", "not_found"]

api = IouvApi(
    title="IoUV API",
    version="1.0.0",
    description="Request and follow IoUV sessions from your own programs. Authenticate "
    "with `Authorization: Bearer <token>` (an API token from your platform "
    "administrator). Every error is JSON: "
    '`{"error": {"code": ..., "message": ...}}`. See docs/api.md.',
    urls_namespace="api-v1",
    openapi_url="/openapi.json",
    docs_url="/docs",
    # Vendored assets only: no validator badge fetched from swagger.io.
    docs=Swagger(settings={"validatorUrl": None}),
    docs_decorator=document_view,
    servers=[{"url": BASE_PATH}],
    auth=BearerToken(),
    parser=JsonObjectParser(),
    openapi_extra={"info": {"license": {"name": "Apache-2.0", "identifier": "Apache-2.0"}}},
)


# --- documenting the answers ---------------------------------------------------------------

_STRING = {"schema": {"type": "string"}}
_CHALLENGE = {"WWW-Authenticate": {**_STRING, "description": 'Bearer realm="iouv" (+ error).'}}


def _doc(ok: dict[int, Any], *errors: int, **ok_extra: Any) -> dict[str, Any]:
    """An operation's answers for ninja: ``ok`` (status: schema) and the Error envelope
    for 400 (every operation refuses unknown query parameters), 401, 500, 503 (the
    database cannot be reached) and ``errors``; ``ok_extra`` (headers, links) joins the
    success's entry of the document."""
    (status,) = ok
    return {
        "response": {**ok, **dict.fromkeys(sorted({400, 401, *errors, 500, 503}), schema.Error)},
        "openapi_extra": {"responses": {401: {"headers": _CHALLENGE}, status: ok_extra}},
    }


def _link(operation_id: str) -> dict[str, Any]:
    # The created session's id feeds the session-id endpoints (stateful clients, and
    # schemathesis' state machine, follow these).
    return {"operationId": operation_id, "parameters": {"session_id": "$response.body#/session/id"}}


_LINKS = {
    "ReadSession": _link("session_read"),
    "GrantSession": _link("session_grant"),
    "EndSession": _link("session_end"),
    "StopSession": _link("session_stop"),
}

# --- lookups -------------------------------------------------------------------------------


def _visible_session(request: AuthenticatedHttpRequest, session_id: UUID) -> Session:
    """The session if the user owns it or may view every session; 404 otherwise, so
    that other users' sessions are not even confirmed to exist."""
    session = Session.objects.select_related("service", "user").filter(pk=session_id).first()
    user = request.user
    if session is None or (
        session.user_id != user.pk and not user.has_perm("services.view_session")
    ):
        raise ApiError(404, "not_found", "no such session")
    return session


def _owned_session(
    request: AuthenticatedHttpRequest, session_id: UUID, action: str, *, lock: bool = False
) -> Session:
    """The session if the user owns it; 403 if they may only view it, else 404.
    ``lock``: read it locked, in the caller's transaction (only one's own is locked)."""
    rows = Session.objects.select_related("service", "user")
    if lock:
        rows = rows.select_for_update(of=("self",), no_key=True)
    session = rows.filter(pk=session_id, user_id=request.user.pk).order_by("pk").first()
    if session is None:
        _visible_session(request, session_id)  # 404 unless the user may view it
        raise ApiError(403, "permission_denied", f"only the session's user may {action} it")
    return session


def _require_perm(request: AuthenticatedHttpRequest, perm: str, what: str) -> None:
    if not request.user.has_perm(perm):
        raise ApiError(403, "permission_denied", f"your account may not {what}")


def _reason(payload: schema.EndRequest | None, default: str) -> str:
    return payload.reason.strip() if payload is not None and payload.reason else default


# --- endpoints -----------------------------------------------------------------------------

_SESSION_PATH = "/sessions/{uuid:session_id}"


@api.get(
    "/services",
    **_doc({200: schema.Services}),
    operation_id="services_list",
    summary="Services the token's user may request",
)
@query()
def services_list(request: AuthenticatedHttpRequest) -> dict[str, Any]:
    """The services the token's user may request (empty without the client role)."""
    return {"services": services_for_user(request.user).prefetch_related("roles")}


@api.post(
    "/sessions",
    operation_id="session_create",
    summary="Request a session: reserve vehicles and deploy the task",
    **_doc(
        {201: schema.SessionCreated},
        403,
        409,
        413,
        422,
        429,
        headers={"Location": _STRING},
        links=_LINKS,
    ),
)
@query()
def session_create(
    request: AuthenticatedHttpRequest, payload: schema.SessionRequest, response: HttpResponse
) -> Status[dict[str, Any]]:
    """Request a session, as the portal does (services.sessions.request). A synchronous service
    is deployed at once: 201 with the user task (control URL and grant). An
    asynchronous one is left to its kind's workflow (task null), which reads its own
    `params` (docs/api.md lists them). 422 names the requirement no vehicle met; 409
    `session_limit` says the user already holds as many live sessions as it allows.
    429 `rate_limited` (with Retry-After): too many requests from the user or the
    address (docs/operations.md, "Rate limits")."""
    _require_perm(request, "services.use_services", "request services")
    throttle_check(action="session_request", **request_keys(request))
    service = service_usable_get(request.user, payload.service)
    if service is None:
        raise field_error("service", f"no service {payload.service!r}")
    # Whether the user may use it (read with it): service_request checks it first, and
    # a refusal is the same 403 as ever (AssignmentError without a session, below).
    target = payload.target
    wish = Request(
        target=(target.lat, target.lon) if target else None,
        relay=payload.relay,
        preferences=payload.preferences.model_dump(exclude_unset=True),
        params=payload.params,
    )
    try:
        opened = service_request(
            user=request.user, service=service, request=wish, usable=service.usable
        )
    except RequestError as exc:
        raise field_error(exc.field or "service", str(exc)) from None
    except AssignmentError as exc:
        if exc.over_cap:
            raise ApiError(409, "session_limit", str(exc)) from None
        if exc.session is None:  # the grant went away meanwhile
            raise ApiError(403, "permission_denied", str(exc)) from None
        raise ApiError(
            422, "unmet_requirement", str(exc), session_id=str(exc.session.pk), role=exc.role
        ) from None
    except InvalidTaskError as exc:
        failed = str(exc.session.pk) if exc.session is not None else None
        raise ApiError(422, "invalid_task", str(exc), session_id=failed) from None
    except DeploymentError as exc:
        raise ApiError(409, "session_state", str(exc)) from None
    task = user_task_json(opened.task, request=request) if opened.task is not None else None
    response["Location"] = f"{BASE_PATH}/sessions/{opened.session.pk}"
    return Status(201, {"session": opened.session, "task": task})


@api.get(
    _SESSION_PATH,
    operation_id="session_read",
    summary="A session, its vehicles and its log",
    **_doc({200: schema.Session}, 404),
)
@query()
def session_read(request: AuthenticatedHttpRequest, session_id: UUID) -> Session:
    """Visible to its owner and to monitors; 404 for anyone else."""
    return _visible_session(request, session_id)


@api.post(
    f"{_SESSION_PATH}/grant",
    operation_id="session_grant",
    summary="A fresh controller grant for the session's owner (to reconnect)",
    **_doc({200: schema.Grant}, 403, 404, 409, 429),
)
@query()
def session_grant(request: AuthenticatedHttpRequest, session_id: UUID) -> dict[str, Any]:
    """A fresh controller grant for the session's owner, e.g. to reconnect. 429
    `rate_limited` (with Retry-After): too many grants for the user or the address;
    only grants given count."""
    keys = request_keys(request)
    throttle_peek(action="grant", **keys)
    session = _owned_session(request, session_id, "control")
    if session.service.mode != "sync":
        raise ApiError(409, "session_state", "this session is run by the platform, not driven")
    try:
        task = grant_issue(session=session, user=request.user)
    except DeploymentError as exc:
        raise ApiError(409, "session_state", str(exc)) from None
    throttle_count(action="grant", **keys)
    return {"task": user_task_json(task, request=request)}


@api.post(
    f"{_SESSION_PATH}/end",
    operation_id="session_end",
    summary="End the session on purpose (its owner)",
    **_doc({200: schema.Session}, 403, 404, 409, 413),
)
@query()
def session_finish(
    request: AuthenticatedHttpRequest, session_id: UUID, payload: schema.EndRequest | None = None
) -> Session:
    """The owner ends the session on purpose, in any live state: a request still
    waiting for a vehicle is withdrawn (nothing was sent), else the vehicles are
    released. The reason is the same as the portal's unless the body gives one."""
    # One transaction: the session is read locked, and what is ended is what was read.
    with transaction.atomic():
        session = _owned_session(request, session_id, "end", lock=True)
        try:
            return session_end_by_user(session=session, reason=_reason(payload, ""), locked=True)
        except SessionStateError as exc:
            raise ApiError(409, "session_state", str(exc)) from None


@api.post(
    f"{_SESSION_PATH}/stop",
    operation_id="session_stop",
    summary="Stop a session now (monitors): the vehicle performs the service's fail-safe",
    **_doc({200: schema.Session}, 403, 404, 409, 413),
)
@query()
def session_stop(
    request: AuthenticatedHttpRequest, session_id: UUID, payload: schema.EndRequest | None = None
) -> Session:
    """A monitor's kill switch: the agent drops the user and performs the service's
    fail-safe action; the session is aborted."""
    session = _visible_session(request, session_id)
    _require_perm(request, "services.stop_session", "stop sessions")
    reason = _reason(payload, f"stopped by a monitor ({request.user.get_username()})")
    try:
        return session_revoke(
            session=session, reason=reason, action=session.service.failsafe_action
        )
    except SessionStateError as exc:
        raise ApiError(409, "session_state", str(exc)) from None


@api.get(
    "/vehicles",
    operation_id="vehicles_list",
    summary="The fleet (monitors)",
    **_doc({200: schema.Fleet}, 403),
)
@query("status", "station")
def vehicles_list(
    request: AuthenticatedHttpRequest,
    status: Vehicle.Status | None = None,
    station: schema.Text | None = None,
) -> dict[str, Any]:
    """The fleet for monitors, optionally by ``status`` and ``station`` (its name)."""
    _require_perm(request, "fleet.view_fleet", "watch the fleet")
    vehicles = Vehicle.objects.all()
    if status is not None:
        vehicles = vehicles.filter(status=status)
    if station is not None:
        vehicles = vehicles.filter(station__name=station)
    return {"vehicles": fleet_snapshot(vehicles.values_list("pk", flat=True))}


# --- flight records --------------------------------------------------------------------------

_EXPORT_TYPES = sorted({content_type.split(";")[0] for _, content_type, _ in EXPORTS.values()})


@api.get(
    _SESSION_PATH + "/record",
    operation_id="session_record",
    summary="A session's flight record: what it holds, its check, its exports",
    **_doc({200: schema.RecordSummary}, 404),
)
@query()
def session_record(request: AuthenticatedHttpRequest, session_id: UUID) -> dict[str, Any]:
    """For the session's owner, monitors and admins; 404 for anyone else."""
    session = _visible_session(request, session_id)
    return record_summary(
        session, url_for=lambda name: f"{BASE_PATH}/sessions/{session.pk}/record/{name}"
    )


@api.get(
    _SESSION_PATH + "/record/{str:name}",
    operation_id="session_record_export",
    summary="One export of a session's flight record (GPX, KML, CSV, tlog, zip)",
    response={404: schema.Error, **dict.fromkeys((400, 401, 500, 503), schema.Error)},
    openapi_extra={
        "responses": {
            200: {
                "description": "The export as a download.",
                "content": {
                    t: {"schema": {"type": "string", "format": "binary"}} for t in _EXPORT_TYPES
                },
            },
            401: {"headers": _CHALLENGE},
        }
    },
)
@query()
def session_record_export(
    request: AuthenticatedHttpRequest, session_id: UUID, name: schema.RecordExport
) -> HttpResponseBase:
    """For the session's owner, monitors and admins; 404 for anyone else, and for a
    ``tlog`` the record does not have."""
    session = _visible_session(request, session_id)
    try:
        return record_file(request, session, name)
    except Http404 as exc:
        raise ApiError(404, "not_found", str(exc)) from None
