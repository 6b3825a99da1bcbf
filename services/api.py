"""The JSON API for third-party programs (described by services.openapi; see docs/api.md).

Views stay thin: :func:`api_view` authenticates, checks the method and turns every
failure into the JSON error envelope; each view parses, calls a service function and
renders. Authentication is by ``Authorization: Bearer <token>`` only. The session
cookie is never consulted, so the views are CSRF-exempt: a cross-site page can make a
browser send cookies, but it cannot make it send this header.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from collections.abc import Callable
from functools import wraps
from typing import Any

from django.core.exceptions import RequestDataTooBig
from django.http import HttpRequest, JsonResponse
from django.utils.cache import add_never_cache_headers
from django.views.decorators.csrf import csrf_exempt

from accounts.tokens import token_authenticate
from accounts.users import AuthenticatedHttpRequest, User
from fleet.attributes import CAMERAS
from fleet.models import Vehicle
from fleet.status import fleet_snapshot
from services.assignment import AssignmentError
from services.deployment import (
    DeploymentError,
    InvalidTaskError,
    grant_issue,
    session_end,
    session_revoke,
    user_task_json,
)
from services.eventlog import session_log_verify
from services.grants import services_for_user, user_can_use
from services.kinds import Request, RequestError
from services.models import Service, Session
from services.openapi import (
    BASE_PATH,
    MAX_BODY_BYTES,
    PARAMS_MAX_DEPTH,
    REASON_MAX,
    openapi_document,
)
from services.request import service_request
from services.selectors import session_delivery
from services.sessions import FINAL, SessionStateError

logger = logging.getLogger(__name__)

_REALM = 'Bearer realm="iouv"'


class ApiError(Exception):
    """An error answer: HTTP ``status``, a stable ``code``, a message for humans and
    optional extra members of the envelope (``field``, ``session_id``, ``role``)."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        *,
        headers: dict[str, str] | None = None,
        **extra: str | None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.headers = headers or {}
        self.extra = extra

    def response(self) -> JsonResponse:
        return error_response(
            self.status, self.code, self.message, headers=self.headers, **self.extra
        )


def error_response(
    status: int,
    code: str,
    message: str,
    *,
    headers: dict[str, str] | None = None,
    **extra: str | None,
) -> JsonResponse:
    """The error envelope ``{"error": {"code", "message", ...}}`` with ``status``."""
    response = JsonResponse({"error": {"code": code, "message": message, **extra}}, status=status)
    for name, value in (headers or {}).items():
        response[name] = value
    add_never_cache_headers(response)
    return response


def field_error(field: str, message: str) -> ApiError:
    return ApiError(400, "invalid_field", f"{field}: {message}", field=field)


def _authenticate(request: HttpRequest) -> User:
    header = request.headers.get("Authorization", "")
    scheme, _, raw = header.partition(" ")
    if not header:
        raise ApiError(
            401,
            "not_authenticated",
            "send an API token: Authorization: Bearer <token>",
            headers={"WWW-Authenticate": _REALM},
        )
    user = token_authenticate(raw.strip()) if scheme.lower() == "bearer" else None
    if user is None:
        raise ApiError(
            401,
            "invalid_token",
            "the token is malformed, unknown or revoked",
            headers={"WWW-Authenticate": f'{_REALM}, error="invalid_token"'},
        )
    return user


View = Callable[..., JsonResponse]


def _check_query(request: HttpRequest, allowed: tuple[str, ...]) -> None:
    """Refuse unknown and repeated query parameters: ``?stauts=idle`` silently
    returning every vehicle would be worse than a 400 naming it."""
    for name in sorted(request.GET):
        if name not in allowed:
            raise field_error(name, "unknown query parameter")
        if len(request.GET.getlist(name)) > 1:
            raise field_error(name, "give this query parameter once")


def api_view(
    *methods: str, auth: bool = True, query: tuple[str, ...] = ()
) -> Callable[[View], View]:
    """Make ``view`` an API endpoint answering only ``methods``, with only the query
    parameters in ``query``.

    With ``auth``, ``request.user`` is the bearer token's user (the session cookie is
    ignored, also when no token is sent). ApiError becomes its JSON answer; any other
    exception is logged and answered with a JSON 500, never an HTML page.
    """

    def decorate(view: View) -> View:
        @csrf_exempt
        @wraps(view)
        def wrapped(request: HttpRequest, *args: Any, **kwargs: Any) -> JsonResponse:
            try:
                if request.method not in methods:
                    raise ApiError(
                        405,
                        "method_not_allowed",
                        f"{request.method} is not allowed here; use {', '.join(methods)}",
                        headers={"Allow": ", ".join(methods)},
                    )
                if auth:
                    request.user = _authenticate(request)
                _check_query(request, query)
                response = view(request, *args, **kwargs)
            except ApiError as exc:
                return exc.response()
            except Exception:
                logger.exception("API error on %s %s", request.method, request.path)
                return error_response(
                    500, "internal_error", "the platform failed; the error was logged"
                )
            # Answers are per user and may carry grants: no cache may keep them.
            if not response.has_header("Cache-Control"):
                add_never_cache_headers(response)
            return response

        return wrapped

    return decorate


@csrf_exempt
def not_found(request: HttpRequest, *args: Any, **kwargs: Any) -> JsonResponse:
    """Every path under /api/ that no endpoint matches (JSON, never an HTML page)."""
    return error_response(404, "not_found", f"no API endpoint at {request.path}")


# --- parsing ---------------------------------------------------------------------------------


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


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


def _check_strings(value: Any, path: str, depth: int = 0) -> None:
    """Refuse text that cannot be stored (see _storable) and needless nesting."""
    if depth > PARAMS_MAX_DEPTH:
        raise field_error(path, f"nested more than {PARAMS_MAX_DEPTH} levels deep")
    if isinstance(value, str):
        if not _storable(value):
            raise field_error(path, "must not contain NUL characters or lone surrogates")
    elif isinstance(value, dict):
        for key, item in value.items():
            if not _storable(key):
                raise field_error(path, "keys must not contain NUL characters or lone surrogates")
            _check_strings(item, f"{path}.{key}", depth + 1)
    elif isinstance(value, list):
        for index, item in enumerate(value):
            _check_strings(item, f"{path}[{index}]", depth + 1)


def json_body(request: HttpRequest, *, required: bool) -> dict[str, Any]:
    """The request body as a JSON object; ``{}`` for an empty optional body.

    Raises ApiError 413 over MAX_BODY_BYTES (checked on the declared length before
    reading), 400 for anything but a JSON object (NaN and Infinity are not JSON).
    """
    too_large = ApiError(
        413, "payload_too_large", f"the body must be at most {MAX_BODY_BYTES} bytes"
    )
    try:
        declared = int(request.META.get("CONTENT_LENGTH") or 0)
    except ValueError:
        declared = 0
    if declared > MAX_BODY_BYTES:
        raise too_large
    try:
        raw = request.body
    except RequestDataTooBig:
        raise too_large from None
    if len(raw) > MAX_BODY_BYTES:  # a body sent without a (truthful) length
        raise too_large
    if not raw.strip():
        if required:
            raise ApiError(400, "invalid_json", "the body must be a JSON object")
        return {}
    try:
        body = json.loads(raw, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as exc:
        raise ApiError(400, "invalid_json", f"the body is not valid JSON: {exc}") from None
    if not isinstance(body, dict):
        raise ApiError(400, "invalid_json", "the body must be a JSON object")
    return body


def _only(body: dict[str, Any], allowed: set[str], where: str = "") -> None:
    unknown = sorted(set(body) - allowed)
    if unknown:
        name = f"{where}.{unknown[0]}" if where else unknown[0]
        raise field_error(name, "unknown field")


def _number(value: Any, field: str, low: float, high: float) -> float:
    # bool is an int in Python; in JSON it is not a number.
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise field_error(field, f"must be a number from {low:g} to {high:g}")
    if not low <= value <= high:
        raise field_error(field, f"must be a number from {low:g} to {high:g}")
    return float(value)


def _target(value: Any) -> tuple[float, float] | None:
    if value is None:
        return None
    if not isinstance(value, dict):
        raise field_error("target", 'must be an object {"lat": ..., "lon": ...} or null')
    _only(value, {"lat", "lon"}, "target")
    for name in ("lat", "lon"):
        if name not in value:
            raise field_error(f"target.{name}", "is required")
    return (
        _number(value["lat"], "target.lat", -90, 90),
        _number(value["lon"], "target.lon", -180, 180),
    )


def _preferences(value: Any) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise field_error("preferences", "must be an object")
    _only(value, {"cameras", "min_battery"}, "preferences")
    prefs: dict[str, Any] = {}
    if "cameras" in value:
        cameras = value["cameras"]
        if not isinstance(cameras, list) or not all(c in CAMERAS for c in cameras):
            raise field_error("preferences.cameras", f"must be a list of {', '.join(CAMERAS)}")
        if len(set(cameras)) != len(cameras):
            raise field_error("preferences.cameras", "must not repeat a camera")
        prefs["cameras"] = cameras
    if "min_battery" in value:
        prefs["min_battery"] = _number(value["min_battery"], "preferences.min_battery", 0, 100)
    return prefs


@dataclasses.dataclass(frozen=True)
class SessionRequestData:
    service: str
    target: tuple[float, float] | None
    relay: bool
    preferences: dict[str, Any]
    params: dict[str, Any]


def parse_session_request(body: dict[str, Any]) -> SessionRequestData:
    """Validate a session request body (schema SessionRequest); ApiError 400 naming the
    field otherwise."""
    _only(body, {"service", "target", "relay", "preferences", "params"})
    service = body.get("service")
    if not isinstance(service, str) or not service:
        raise field_error("service", "is required: a service slug")
    _check_strings(service, "service")
    relay = body.get("relay", False)
    if not isinstance(relay, bool):
        raise field_error("relay", "must be true or false")
    params = body.get("params", {})
    if not isinstance(params, dict):
        raise field_error("params", "must be an object")
    if "mission" in params:
        # A mission is signed into the vehicle task and flown autonomously: only the
        # service's workflow may set one, never the requester.
        raise field_error("params.mission", "is set by the service's workflow, not by a request")
    _check_strings(params, "params")
    return SessionRequestData(
        service=service,
        target=_target(body.get("target")),
        relay=relay,
        preferences=_preferences(body["preferences"]) if "preferences" in body else {},
        params=params,
    )


def _reason(body: dict[str, Any], default: str) -> str:
    _only(body, {"reason"})
    if "reason" not in body:
        return default
    reason = body["reason"]
    if not isinstance(reason, str) or not reason.strip():
        raise field_error("reason", "must be a non-empty string")
    if len(reason) > REASON_MAX:
        raise field_error("reason", f"must be at most {REASON_MAX} characters")
    _check_strings(reason, "reason")
    return reason.strip()


# --- rendering -------------------------------------------------------------------------------


def _iso(value: Any) -> str | None:
    return value.isoformat() if value else None


def service_json(service: Service) -> dict[str, Any]:
    return {
        "slug": service.slug,
        "name": service.name,
        "description": service.description,
        "mode": service.mode,
        "kind": service.kind,
        "commands": list(service.allowed_commands),
        "roles": [
            {
                "name": role.name,
                "required": role.required,
                "kinds": role.kinds,
                "adapters": role.adapters,
                "cameras": role.cameras,
                "environments": role.environments,
                "features": role.features,
                "min_attributes": role.min_attributes,
                "min_battery": role.min_battery,
                "selection": role.selection,
            }
            for role in service.roles.all()
        ],
        "limits": {
            "max_altitude_m": service.max_altitude_m,
            "geofence_radius_m": service.geofence_radius_m,
            "max_speed_mps": service.max_speed_mps,
            "link_loss_timeout_ms": service.link_loss_timeout_ms,
            "failsafe_action": service.failsafe_action,
            "session_time_limit_s": service.session_time_limit_s,
            "latency_soft_ms": service.latency_soft_ms,
            "latency_hard_ms": service.latency_hard_ms,
        },
    }


def session_json(session: Session) -> dict[str, Any]:
    """A session with its assignments and its log, and whether the log's chain holds."""
    check = session_log_verify(session=session)
    target = session.target
    return {
        "id": str(session.pk),
        "service": {
            "slug": session.service.slug,
            "name": session.service.name,
            "mode": session.service.mode,
        },
        "user": session.user.get_username(),
        "state": session.state,
        "reason": session.reason,
        "relay": session.relay,
        "target": {"lat": target[0], "lon": target[1]} if target else None,
        "params": session.params if isinstance(session.params, dict) else {},
        "created_at": _iso(session.created_at),
        "assigned_at": _iso(session.assigned_at),
        "started_at": _iso(session.started_at),
        "ended_at": _iso(session.ended_at),
        "assignments": [
            {
                "role": a.role,
                "vehicle": {"id": str(a.vehicle_id), "name": a.vehicle.name},
                "active": a.active,
                "distance_m": a.distance_m,
                "created_at": _iso(a.created_at),
                "released_at": _iso(a.released_at),
            }
            for a in session.assignments.select_related("vehicle")
        ],
        "delivery": session_delivery(session) if session.state in FINAL else [],
        "log": {
            "chain_ok": check.ok,
            "bad_seq": check.bad_seq,
            "problem": check.problem,
            "events": [
                {"seq": e.seq, "kind": e.kind, "created_at": _iso(e.created_at), "data": e.data}
                for e in session.events.order_by("seq")
            ],
        },
    }


# --- lookups ---------------------------------------------------------------------------------


def _visible_session(request: AuthenticatedHttpRequest, session_id: Any) -> Session:
    """The session if the user owns it or may view every session; 404 otherwise, so
    that other users' sessions are not even confirmed to exist."""
    session = Session.objects.select_related("service", "user").filter(pk=session_id).first()
    user = request.user
    if session is None or (
        session.user_id != user.pk and not user.has_perm("services.view_session")
    ):
        raise ApiError(404, "not_found", "no such session")
    return session


def _owned_session(request: AuthenticatedHttpRequest, session_id: Any, action: str) -> Session:
    session = _visible_session(request, session_id)
    if session.user_id != request.user.pk:
        raise ApiError(403, "permission_denied", f"only the session's user may {action} it")
    return session


def _require_perm(request: AuthenticatedHttpRequest, perm: str, what: str) -> None:
    if not request.user.has_perm(perm):
        raise ApiError(403, "permission_denied", f"your account may not {what}")


# --- endpoints -------------------------------------------------------------------------------


@api_view("GET")
def services_list(request: AuthenticatedHttpRequest) -> JsonResponse:
    """The services the token's user may request (empty without the client role)."""
    services = services_for_user(request.user).prefetch_related("roles")
    return JsonResponse({"services": [service_json(s) for s in services]})


@api_view("POST")
def sessions_create(request: AuthenticatedHttpRequest) -> JsonResponse:
    """Request a session, as the portal does (services.request): a service its user
    drives is deployed at once (201 with the user task); one the platform runs is left
    to its kind's workflow (201, task null)."""
    _require_perm(request, "services.use_services", "request services")
    data = parse_session_request(json_body(request, required=True))
    service = Service.objects.filter(slug=data.service, is_active=True).first()
    if service is None:
        raise field_error("service", f"no service {data.service!r}")
    if not user_can_use(request.user, service):
        raise ApiError(403, "permission_denied", f"you may not use the service {service.name!r}")
    wish = Request(
        target=data.target, relay=data.relay, preferences=data.preferences, params=data.params
    )
    try:
        opened = service_request(user=request.user, service=service, request=wish)
    except RequestError as exc:
        raise field_error(exc.field or "service", str(exc)) from None
    except AssignmentError as exc:
        if exc.over_cap:
            raise ApiError(409, "session_limit", str(exc)) from None
        if exc.session is None:  # the grant went away meanwhile
            raise ApiError(403, "permission_denied", str(exc)) from None
        raise ApiError(
            422,
            "unmet_requirement",
            str(exc),
            session_id=str(exc.session.pk),
            role=exc.role,
        ) from None
    except InvalidTaskError as exc:
        failed = str(exc.session.pk) if exc.session is not None else None
        raise ApiError(422, "invalid_task", str(exc), session_id=failed) from None
    except DeploymentError as exc:
        raise ApiError(409, "session_state", str(exc)) from None
    task = user_task_json(opened.task, request=request) if opened.task is not None else None
    response = JsonResponse({"session": session_json(opened.session), "task": task}, status=201)
    response["Location"] = f"{BASE_PATH}/sessions/{opened.session.pk}"
    return response


@api_view("GET")
def session_read(request: AuthenticatedHttpRequest, session_id: Any) -> JsonResponse:
    """One session, for its owner or a monitor."""
    return JsonResponse(session_json(_visible_session(request, session_id)))


@api_view("POST")
def session_grant(request: AuthenticatedHttpRequest, session_id: Any) -> JsonResponse:
    """A fresh controller grant for the session's owner, e.g. to reconnect."""
    session = _owned_session(request, session_id, "control")
    if session.service.mode != "sync":
        raise ApiError(409, "session_state", "this session is run by the platform, not driven")
    try:
        task = grant_issue(session=session, user=request.user)
    except DeploymentError as exc:
        raise ApiError(409, "session_state", str(exc)) from None
    return JsonResponse({"task": user_task_json(task, request=request)})


@api_view("POST")
def session_finish(request: AuthenticatedHttpRequest, session_id: Any) -> JsonResponse:
    """The owner ends the session on purpose; the vehicles are released."""
    session = _owned_session(request, session_id, "end")
    reason = _reason(json_body(request, required=False), "ended by the user")
    try:
        session = session_end(session=session, reason=reason, by_user=True)
    except SessionStateError as exc:
        raise ApiError(409, "session_state", str(exc)) from None
    return JsonResponse(session_json(session))


@api_view("POST")
def session_stop(request: AuthenticatedHttpRequest, session_id: Any) -> JsonResponse:
    """A monitor's kill switch: the agent drops the user and performs the service's
    fail-safe action; the session is aborted."""
    session = _visible_session(request, session_id)
    _require_perm(request, "services.stop_session", "stop sessions")
    reason = _reason(
        json_body(request, required=False),
        f"stopped by a monitor ({request.user.get_username()})",
    )
    try:
        session = session_revoke(
            session=session, reason=reason, action=session.service.failsafe_action
        )
    except SessionStateError as exc:
        raise ApiError(409, "session_state", str(exc)) from None
    return JsonResponse(session_json(session))


@api_view("GET", query=("status", "station"))
def vehicles_list(request: AuthenticatedHttpRequest) -> JsonResponse:
    """The fleet for monitors, optionally by ``status`` and ``station`` (its name)."""
    _require_perm(request, "fleet.view_fleet", "watch the fleet")
    vehicles = Vehicle.objects.all()
    status = request.GET.get("status")
    if status is not None:
        if status not in Vehicle.Status.values:
            raise field_error("status", f"must be one of {', '.join(Vehicle.Status.values)}")
        vehicles = vehicles.filter(status=status)
    station = request.GET.get("station")
    if station is not None:
        _check_strings(station, "station")
        vehicles = vehicles.filter(station__name=station)
    return JsonResponse({"vehicles": fleet_snapshot(vehicles.values_list("pk", flat=True))})


@api_view("GET", auth=False)
def openapi(request: HttpRequest) -> JsonResponse:
    """The OpenAPI 3.1 document (no token needed)."""
    response = JsonResponse(openapi_document())
    # The same for everyone and changes only with a deploy.
    response["Cache-Control"] = "public, max-age=300"
    return response
