"""The HTTP plumbing of the JSON API (services.web.api) on django-ninja.

Every failure, ninja's own included, is answered with the error envelope
``{"error": {"code", "message", ...}}`` (:class:`ApiError`); :class:`BearerToken`
authenticates; :class:`JsonObjectParser` enforces the body limits; :class:`IouvApi`
ties them together and wraps ninja's URLs so that a wrong method or an unknown path
under the API is JSON too.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from functools import wraps
from typing import Any, TypeVar, cast

from django.core.exceptions import RequestDataTooBig
from django.http import Http404, HttpRequest, HttpResponse, HttpResponseNotAllowed, JsonResponse
from django.urls import URLPattern
from django.utils.cache import add_never_cache_headers, patch_cache_control
from ninja import NinjaAPI
from ninja.errors import AuthenticationError, HttpError, ValidationError
from ninja.parser import Parser
from ninja.security import HttpBearer

from accounts.tokens import token_authenticate
from accounts.users import User
from operations.outages import DATABASE_UNAVAILABLE, database_unavailable_response
from services.web.api_schemas import MAX_BODY_BYTES
from services.web.throttle import Throttled

# Under the API's name: the one operators know from the log lines of requests.
logger = logging.getLogger("services.web.api")

_REALM = 'Bearer realm="iouv"'


# --- the error envelope --------------------------------------------------------------------


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
        """The envelope ``{"error": {"code", "message", ...}}``, never cached."""
        body = {"code": self.code, "message": self.message, **self.extra}
        response = JsonResponse({"error": body}, status=self.status)
        for name, value in self.headers.items():
            response[name] = value
        add_never_cache_headers(response)
        return response


def field_error(field: str, message: str) -> ApiError:
    return ApiError(400, "invalid_field", f"{field}: {message}", field=field)


def _too_large() -> ApiError:
    return ApiError(413, "payload_too_large", f"the body must be at most {MAX_BODY_BYTES} bytes")


def _not_authenticated() -> ApiError:
    return ApiError(
        401,
        "not_authenticated",
        "send an API token: Authorization: Bearer <token>",
        headers={"WWW-Authenticate": _REALM},
    )


def _not_json(detail: str = "") -> ApiError:
    return ApiError(400, "invalid_json", detail or "the body must be a JSON object")


#: Pydantic's wording where ours says more.
_MESSAGES = {"missing": "is required", "extra_forbidden": "unknown field"}


def _validation_error(request: HttpRequest, exc: ValidationError) -> HttpResponse:
    """The first of ninja's validation errors as a 400 naming the field (dotted, down to
    the list that holds a bad item: ``preferences.cameras``)."""
    error = exc.errors[0]
    source, *loc = error["loc"]
    if source == "body":
        loc = loc[1:]  # the view's parameter name, not a field the client sent
        if not loc:  # the body as a whole: empty, or not an object
            return _not_json().response()
    names: list[str] = []
    for part in loc:
        if isinstance(part, int):
            break
        names.append(str(part))
    field = (error.get("ctx") or {}).get("field") or ".".join(names) or source
    if error["type"] == "value_error":  # our validators' words, without pydantic's prefix
        message = str(error["ctx"]["error"])
    else:
        message = _MESSAGES.get(error["type"], str(error["msg"]))
    return field_error(str(field), message).response()


def _http_error(request: HttpRequest, exc: HttpError) -> HttpResponse:
    if isinstance(exc.__cause__, ApiError):  # raised by the parser, wrapped by ninja
        return exc.__cause__.response()
    if exc.status_code == 400:  # ninja could not parse the body
        return _not_json().response()
    return ApiError(exc.status_code, "invalid_field", str(exc)).response()


def _throttled(request: HttpRequest, exc: Throttled) -> HttpResponse:
    retry = {"Retry-After": str(exc.retry_after_s)}
    return ApiError(429, "rate_limited", str(exc), headers=retry).response()


def _database_unavailable(request: HttpRequest, exc: Exception) -> HttpResponse:
    logger.warning("API: database unavailable on %s %s: %s", request.method, request.path, exc)
    return database_unavailable_response(request)


def _server_error(request: HttpRequest, exc: Exception) -> HttpResponse:
    logger.exception("API error on %s %s", request.method, request.path, exc_info=exc)
    # Details go to the log, never to the client.
    return ApiError(500, "internal_error", "the platform failed; the error was logged").response()


# --- authentication, parsing, query parameters -------------------------------------------


class BearerToken(HttpBearer):
    """``Authorization: Bearer <token>`` (accounts.tokens); the scheme is
    case-insensitive. Sets ``request.user`` to the token's user; answers 401
    ``not_authenticated`` without the header, ``invalid_token`` for a bad one."""

    openapi_description = "An API token: iouv_<prefix>_<secret>."

    def __call__(self, request: HttpRequest) -> User:
        header = request.headers.get("Authorization", "")
        if not header:
            raise _not_authenticated()
        scheme, _, raw = header.partition(" ")
        user = self.authenticate(request, raw.strip()) if scheme.lower() == "bearer" else None
        if user is None:
            raise ApiError(
                401,
                "invalid_token",
                "the token is malformed, unknown or revoked",
                headers={"WWW-Authenticate": f'{_REALM}, error="invalid_token"'},
            )
        # The token's user acts, whoever the session cookie (ignored) names.
        request.user = user
        return user

    def authenticate(self, request: HttpRequest, token: str) -> User | None:
        return token_authenticate(token)


class JsonObjectParser(Parser):
    """A body is one JSON object of at most MAX_BODY_BYTES (413 beyond, checked on the
    declared length first); anything else is a 400. NaN and Infinity are not JSON.
    A blank body parses to None: "no body", which only optional bodies accept."""

    def parse_body(self, request: HttpRequest) -> dict[str, Any]:
        try:
            declared = int(request.META.get("CONTENT_LENGTH") or 0)
        except ValueError:
            declared = 0
        if declared > MAX_BODY_BYTES:
            raise _too_large()
        raw = request.body
        if len(raw) > MAX_BODY_BYTES:  # a body sent without a (truthful) length
            raise _too_large()
        if not raw.strip():
            return cast(dict[str, Any], None)
        try:
            body = json.loads(raw, parse_constant=_reject_constant)
        except (ValueError, RecursionError) as exc:
            raise _not_json(f"the body is not valid JSON: {exc}") from None
        if not isinstance(body, dict):
            raise _not_json()
        return body


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


_View = TypeVar("_View", bound=Callable[..., Any])


def query(*allowed: str) -> Callable[[_View], _View]:
    """Refuse query parameters not in ``allowed``, and repeated ones: ``?stauts=idle``
    silently returning every vehicle would be worse than a 400 naming it."""

    def decorate(view: _View) -> _View:
        @wraps(view)
        def checked(request: HttpRequest, *args: Any, **kwargs: Any) -> Any:
            for name in sorted(request.GET):
                if name not in allowed:
                    raise field_error(name, "unknown query parameter")
                if len(request.GET.getlist(name)) > 1:
                    raise field_error(name, "give this query parameter once")
            return view(request, *args, **kwargs)

        return cast(_View, checked)

    return decorate


# --- the API -------------------------------------------------------------------------------


def _json_answers(view: Callable[..., HttpResponse]) -> Callable[..., HttpResponse]:
    """Wrap one of ninja's URL views so that what ninja answers outside an operation is
    the envelope too (a wrong method, the bare /api/v1/), and no answer is cached unless
    it says so."""

    @wraps(view)
    def wrapped(request: HttpRequest, *args: Any, **kwargs: Any) -> HttpResponse:
        try:
            response = view(request, *args, **kwargs)
        except Http404:
            response = ApiError(404, "not_found", f"no API endpoint at {request.path}").response()
        if isinstance(response, HttpResponseNotAllowed):
            allow = ", ".join(sorted(response["Allow"].split(", ")))
            response = ApiError(
                405,
                "method_not_allowed",
                f"{request.method} is not allowed here; use {allow}",
                headers={"Allow": allow},
            ).response()
        if not response.has_header("Cache-Control"):
            # Answers are per user and may carry grants: no cache may keep them.
            add_never_cache_headers(response)
        return response

    # No endpoint reads the session cookie (see the module docstring).
    wrapped.csrf_exempt = True  # type: ignore[attr-defined]
    return wrapped


def not_found(request: HttpRequest, *args: Any, **kwargs: Any) -> HttpResponse:
    """Every path under /api/ that no endpoint matches (JSON, never an HTML page)."""
    return ApiError(404, "not_found", f"no API endpoint at {request.path}").response()


not_found.csrf_exempt = True  # type: ignore[attr-defined]


def document_view(view: Callable[..., HttpResponse]) -> Callable[..., HttpResponse]:
    """The OpenAPI document and its Swagger UI page: GET only, no token needed, and the
    same for everyone until the next deploy."""

    @wraps(view)
    def wrapped(request: HttpRequest, *args: Any, **kwargs: Any) -> HttpResponse:
        if request.method != "GET":
            return HttpResponseNotAllowed(["GET"])
        response = view(request, *args, **kwargs)
        patch_cache_control(response, public=True, max_age=300)
        return response

    return wrapped


class IouvApi(NinjaAPI):
    """NinjaAPI answering every failure with the envelope, with the document's paths
    relative to its server (``/api/v1``, as generated clients expect) and JSON labelled
    plain application/json."""

    def set_default_exception_handlers(self) -> None:
        # Replaces ninja's {"detail": ...} answers. (Its handler type admits the
        # exception's class too, which it never passes: hence Any.)
        on = cast(Any, self.add_exception_handler)
        on(ApiError, lambda request, exc: exc.response())
        on(ValidationError, _validation_error)
        on(HttpError, _http_error)
        on(AuthenticationError, lambda request, exc: _not_authenticated().response())
        on(RequestDataTooBig, lambda request, exc: _too_large().response())
        on(Http404, lambda request, exc: ApiError(404, "not_found", "no such resource").response())
        on(Throttled, _throttled)
        for unavailable in DATABASE_UNAVAILABLE:
            on(unavailable, _database_unavailable)
        on(Exception, _server_error)

    def get_openapi_schema(
        self, *, path_prefix: str | None = None, path_params: dict[str, Any] | None = None
    ) -> Any:
        return super().get_openapi_schema(path_prefix=path_prefix or "", path_params=path_params)

    def get_content_type(self) -> str:
        return "application/json"  # JSON is UTF-8 by definition (RFC 8259): no charset

    def urlpatterns(self) -> tuple[list[URLPattern], str]:
        """The API's URL patterns (see _json_answers) and app name, for
        ``include(..., namespace=api.urls_namespace)``."""
        patterns, app_name, _namespace = self.urls
        wrapped = [
            URLPattern(p.pattern, _json_answers(p.callback), p.default_args, p.name)
            for p in patterns
            if isinstance(p, URLPattern)
        ]
        return wrapped, app_name
